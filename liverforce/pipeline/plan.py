"""What the workflow will build for a composed config: ids, paths, names, seeds, slices.

Pure bookkeeping (no I/O) shared by the Snakemake rules, the CLI and the
progress display, so the same names are used everywhere:

- paths: :attr:`Plan.paths`, a :class:`liverforce.layout.Layout` of
  ``<results_dir>/<experiment>`` (the only place file names are spelled);
- MLflow experiment names: :meth:`Plan.experiment_name`;
- seeds: :meth:`Plan.seed` (``liverforce.seeds.derive`` from the master
  ``seed``); no rule or stage does arithmetic on a seed.

Geometry ids
------------
``proc-<seed:04d>``  procedural training liver
``cube``             the cube phantom (``geometry.cube.enabled``)
``imp-<name>``       an imported liver
``val-<seed:04d>``   an unseen validation liver (procedural, held-out seeds ``validate.seed + i``)

An imported liver named in ``validate.imported`` is held out of training: it is
an unseen liver of the validation (after the procedural ones), not a training one.

Scenarios I–III (``sweep.scenarios.<s>.geometries: 1``) use one liver
(:attr:`Plan.single_geometry`): the first imported liver when the lab brings
any (``geometry.imported[0]``), else the first training geometry (``proc-0000``
of the embedded default). IV (``geometries: all``) uses every training geometry,
and the validation scenario ``V`` the unseen livers
(``validate.livers`` of them and the held-out imported ones, ``validate.n_cases`` cases each).
:meth:`Plan.scenario_livers` says which livers each scenario uses; the sweep
params and the case table's metadata record them (``geometries``).
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

from liverforce import layout
from liverforce.config import SCENARIOS, ConfigError, held_out, liver_material, results_root, variant_model
from liverforce.seeds import derive, liver_seeds
from liverforce.sweep.design import n_shards

VALIDATION = "V"
log = logging.getLogger("liverforce.plan")
_SAFE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]*")


def _safe_name(key: str, name) -> str:
    """A name that becomes a path component under results/: no separators, no '..'."""
    if not isinstance(name, str) or not _SAFE_NAME.fullmatch(name):
        raise ConfigError(f"config key '{key}': '{name}' must be letters, digits, '-' or '_' "
                          "(it names folders under the results directory)")
    return name


class Plan:
    """Targets and per-job config slices for one composed config."""

    def __init__(self, cfg: dict):
        self.cfg = cfg
        _safe_name("experiment", cfg["experiment"])
        for i, imp in enumerate(cfg["geometry"]["imported"]):
            _safe_name(f"geometry.imported[{i}].name", imp["name"])
        for v in cfg["train"]["variants"]:
            _safe_name("train.variants.name", v.get("name"))
        self.root = str(Path(cfg["results_dir"]) / cfg["experiment"])
        self.abs_root = results_root(cfg)
        #: every output path of the run (relative to the working directory when ``results_dir`` is)
        self.paths = layout.Layout(self.root)
        g = cfg["geometry"]
        self.train_geometries: list[str] = [
            f"proc-{s:04d}" for s in liver_seeds(g["procedural"]["seed"], g["procedural"]["count"])
        ]
        #: the imported livers held out of training (``validate.imported``): unseen livers of the validation
        self.held_out: list[str] = [f"imp-{name}" for name in held_out(cfg)]
        imported = [f"imp-{imp['name']}" for imp in g["imported"]]
        self.train_geometries += [gid for gid in imported if gid not in self.held_out]
        if g["cube"]["enabled"]:
            self.train_geometries.append("cube")
        #: the liver of the single-liver scenarios (I-III): a lab's own (training) liver when it brings one, for
        #: the procedural ones come first in :attr:`train_geometries` (whose order IV and the seeds keep)
        self.single_geometry: str = next((gid for gid in imported if gid not in self.held_out),
                                         self.train_geometries[0])
        v = cfg["validate"]
        #: the unseen livers: the procedural ones (held-out seeds), then the held-out imported ones
        self.validation_geometries: list[str] = [f"val-{s:04d}" for s in liver_seeds(v["seed"], v["livers"])]
        self.validation_geometries += self.held_out
        self.scenarios = [s for s in SCENARIOS if s in cfg["sweep"]["scenarios"]]
        if g["imported"]:
            first = ("the first imported liver" if self.single_geometry.startswith("imp-")
                     else "the first procedural liver: every imported one is held out")
            log.info("livers per scenario (I-III on %s, %s): %s", first, self.single_geometry,
                     "; ".join(f"{s} {', '.join(ids) if len(ids) <= 3 else f'{len(ids)} livers'}"
                               for s, ids in self.scenario_livers().items()))

    # ------------------------------------------------------------ names, seeds
    def experiment_name(self, kind: str) -> str:
        """MLflow experiment of this run: ``kind`` a scenario (its trained models), ``validation`` or ``studies``."""
        return layout.experiment_name(self.cfg["tracking"]["experiment_prefix"], self.cfg["experiment"], kind)

    def seed(self, stage: str, *keys) -> int:
        """The seed of one stochastic stage of this run: :func:`liverforce.seeds.derive` of the master ``seed``.

        Stages the workflow uses: ``("mesh", gid)`` (mesher and exertion
        candidates of one geometry), ``("sweep", sweep.seed, scenario)`` (a
        scenario's case table, :meth:`sweep_params`), ``("train",
        train.seed)`` (the split seed every training and study job shares,
        :meth:`train_seed`).
        """
        return derive(self.cfg["seed"], stage, *keys)

    def train_seed(self) -> int:
        """The split seed of every training and comparison-study job (all variants and scenarios share it,
        so the variants are compared on the same splits and the studies reuse the main model's)."""
        return self.seed("train", self.cfg["train"]["seed"])

    # ---------------------------------------------------------------- geometry
    @property
    def all_geometries(self) -> list[str]:
        return self.train_geometries + self.validation_geometries

    def geometry_spec(self, gid: str) -> dict:
        """Everything that defines one geometry (a rule's params)."""
        g = self.cfg["geometry"]
        if gid.startswith("proc-") or gid.startswith("val-"):
            return {"kind": "procedural", "seed": int(gid.split("-")[1]), "shape": dict(g["procedural"]["shape"])}
        if gid == "cube":
            return {"kind": "cube", "edge_mm": g["cube"]["edge_mm"]}
        if gid.startswith("imp-"):
            name = gid[4:]
            for imp in g["imported"]:
                if imp["name"] == name:  # its material is the sweep's (a new one re-simulates, never re-meshes)
                    return {"kind": "imported", **{k: v for k, v in imp.items() if k != "material"}}
        raise KeyError(f"unknown geometry id '{gid}'")

    def geometry_files(self, gid: str, stage: str = "mesh") -> list[str]:
        """The user's files one geometry is built from, as absolute paths (a rule's ``input:``).

        An imported geometry reads its own file (``path``) at the geometry stage;
        the mesh stage reads it again (a mesh taken as given, vertex ids, tagged
        groups) and the point files of its supports (``supports.list[].file.path``)
        and exertion points (``exertion_points.path``). ``stage="geometry"`` gives
        the first, ``stage="mesh"`` all of them, each once, in that order.
        Procedural livers and the cube read no file (an empty list).

        Declared as inputs, an edited file re-runs the stage that reads it and
        everything after it, and a missing one stops Snakemake before any job.
        A relative path is taken from the working directory, as the stages
        (which run there) open it.
        """
        if stage not in ("geometry", "mesh"):
            raise ValueError(f"stage must be 'geometry' or 'mesh', got '{stage}'")
        spec = self.geometry_spec(gid)
        if spec["kind"] != "imported":
            return []
        paths = [spec["path"]]
        if stage == "mesh":
            supports = spec.get("supports") or {}
            for s in supports.get("list") or []:
                selector = s.get("file")
                if selector is not None and selector.get("path") is not None:
                    paths.append(selector["path"])
            points = spec.get("exertion_points") or {}
            if points.get("path") is not None:
                paths.append(points["path"])
        cwd = Path(os.getcwd())
        out: list[str] = []
        for p in paths:
            full = str(cwd / str(p))  # an absolute path stays itself
            if full not in out:
                out.append(full)
        return out

    def scenario_geometries(self, scenario: str) -> list[str]:
        if scenario == VALIDATION:
            return list(self.validation_geometries)
        spec = self.cfg["sweep"]["scenarios"][scenario]
        return list(self.train_geometries) if str(spec["geometries"]) == "all" else [self.single_geometry]

    def scenario_livers(self) -> dict[str, list[str]]:
        """The geometry ids each scenario of this run simulates (the training scenarios, then ``V``).

        With an imported liver the single-liver scenarios (I-III) are on the lab's
        liver (the first of ``geometry.imported`` not held out), not on ``proc-0000``; the
        procedural livers serve IV and the unseen livers (with ``validate.imported``) the validation.
        """
        return {s: self.scenario_geometries(s) for s in self.all_scenarios()}

    # ------------------------------------------------------------------- sweep
    def scenario_spec(self, scenario: str) -> dict:
        if scenario == VALIDATION:
            v = self.cfg["validate"]
            return {"n_cases": v["n_cases"] * len(self.validation_geometries), "geometries": "all",
                    "exertion": "varies", "material": "fixed"}
        return dict(self.cfg["sweep"]["scenarios"][scenario])

    def sweep_params(self, scenario: str) -> dict:
        """The config slice the sweep rule of one scenario uses."""
        s = self.cfg["sweep"]
        material = dict(self.cfg["material"])
        if scenario == VALIDATION:
            scale = self.cfg["validate"]["material_scale"]
            material["params_mpa"] = {k: v * scale for k, v in material["params_mpa"].items()}
        own = {gid: m for gid, m in self.liver_materials().items() if gid in self.scenario_geometries(scenario)}
        if own:  # absent otherwise: a run without such livers keeps its sweep params (and its results)
            material["per_liver"] = own
        return {
            "scenario": scenario,
            "spec": self.scenario_spec(scenario),
            "geometries": self.scenario_geometries(scenario),
            "design": s["design"],
            "seed": self.seed("sweep", s["seed"], scenario),
            "cases_per_shard": s["cases_per_shard"],
            "force": dict(s["force"]),
            "exertion": dict(s["exertion"]),
            "material": material,
            "tool_radius_mm": self.cfg["simulate"]["tool_radius_mm"],
        }

    def liver_materials(self) -> dict[str, dict]:
        """The imported livers' own materials (``geometry.imported[].material``), by geometry id:
        ``{"params_mpa": {...} (MPa), "entered": <as given>}`` (no derived words: these are rule params, and a
        rewording must not re-run a sweep).

        A held-out liver's cases take these constants as they are (``validate.material_scale`` scales the
        others); a training liver's scenarios draw around them (``material.vary_rel``) where the material
        varies (:func:`liverforce.sweep.design.build_cases`).
        """
        out = {}
        for i, imp in enumerate(self.cfg["geometry"]["imported"]):
            if imp.get("material") is not None:
                params, _ = liver_material(imp["material"], self.cfg["material"], f"geometry.imported[{i}].material")
                out[f"imp-{imp['name']}"] = {"params_mpa": params, "entered": dict(imp["material"])}
        return out

    def physics_spec(self) -> dict:
        """``validate.physics`` as the physics rule takes it, and where its liver is a held-out liver with its own
        material (``geometry.imported[].material``), ``tool_force_scale``: that liver's initial shear modulus
        ``mu0`` over the procedural unseen livers' (the run's constants x ``validate.material_scale``), which
        ``tool_max_force_n`` is set for. The sphere's force cap takes it: a softer liver sinks deeper at the same
        force (Hertz: the depth follows F / E), beyond what the mesh resolves under a 2.5 mm tip. ``mu0`` is the
        model's (``2 C10`` for neo_hookean and yeoh, ``2 (C10 + C01)`` for Mooney-Rivlin, where the first
        constant alone may be small, zero or negative). Absent otherwise, and without the sphere
        (``tool: none``), so a run without such a liver or sphere keeps its params (and its results)."""
        from liverforce.fem.materials import make_material

        spec = dict(self.cfg["validate"]["physics"])
        gids = self.scenario_geometries(VALIDATION)
        if not 0 <= int(spec["liver"]) < len(gids):
            return spec  # refused where the rule's input indexes it (the config check names the range)
        own = self.liver_materials().get(gids[int(spec["liver"])])
        if own is not None and spec.get("tool") == "sphere":
            mat, scale = self.cfg["material"], self.cfg["validate"]["material_scale"]

            def mu0(params: dict) -> float:
                return make_material(mat["model"], params, nu=mat["nu"]).mu0

            unseen = {k: v * scale for k, v in mat["params_mpa"].items()}  # as the sweep's V scenario takes them
            spec["tool_force_scale"] = float(mu0(own["params_mpa"]) / mu0(unseen))
        return spec

    def all_scenarios(self) -> list[str]:
        return self.scenarios + [VALIDATION]

    def shard_ids(self, scenario: str) -> list[str]:
        spec = self.scenario_spec(scenario)
        return [layout.shard_id(i) for i in range(n_shards(spec["n_cases"], self.cfg["sweep"]["cases_per_shard"]))]

    # ------------------------------------------------------------------- train
    def variants(self) -> dict[str, dict]:
        """Model config per variant (model group merged with the variant's overrides, :func:`variant_model`)."""
        base = self.cfg["model"]
        out = {}
        for v in self.cfg["train"]["variants"]:
            out[v["name"]] = variant_model(base, v)
        if not out:
            out["default"] = dict(base)
        return out

    def train_scenarios(self) -> list[str]:
        return list(self.cfg["train"]["scenarios"])

    def require_iv(self, what: str) -> None:
        """Refuse, naming the fix, a target that needs scenario IV's models (``what``: the validation on the
        unseen livers, the physics check, the report that shows them) in a run that trains none (a lab's one-liver
        run: ``train.scenarios=[II] ~sweep.scenarios.IV``), where Snakemake would only say that
        ``models/IV/...`` is missing."""
        if "IV" in self.train_scenarios():
            return
        raise ConfigError(
            f"{what} needs scenario IV's models (a model trained on several livers, tested on livers it never "
            f"saw), and this run trains scenarios {', '.join(self.train_scenarios()) or 'none'} only "
            "(train.scenarios without IV). Ask for the models target instead (snakemake --cores 2 models "
            "--config ...), or, for the validation and the report, keep scenario IV (drop both overrides, "
            "train.scenarios=[...] and ~sweep.scenarios.IV) with at least two training livers, procedural and "
            "imported together (geometry.procedural.count, geometry.imported)")

    def train_settings(self) -> dict:
        """The ``train`` settings every training job shares: the group without ``variants`` and ``scenarios``.

        A training job's params carry these and its own variant's model config
        only, so adding or changing one variant (or scenario) re-runs that
        variant's jobs and what depends on them, not every training.
        """
        return {k: v for k, v in self.cfg["train"].items() if k not in ("variants", "scenarios")}

    def wildcard_patterns(self) -> dict[str, str]:
        """Regular expressions of every wildcard: exactly the values this plan knows."""
        def alt(values):
            return "|".join(re.escape(v) for v in values)

        return {"scenario": alt(self.all_scenarios()), "variant": alt(self.variants()),
                "gid": alt(self.all_geometries), "shard": r"\d{4}"}

    def chosen_variant(self) -> str:
        """The main variant (the first listed): the studies' starting point and the report's main column."""
        return next(iter(self.variants()))
