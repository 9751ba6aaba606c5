"""Where every stage output lives, and the names of the MLflow experiments: spelled here only.

The Snakemake rules, the CLI, the report, the progress display and the stage
adapters take paths and names from this module (the workflow through
:attr:`liverforce.pipeline.plan.Plan.paths` and
:meth:`~liverforce.pipeline.plan.Plan.experiment_name`); none joins a folder
name of its own. Standard library only, so every layer may use it.

Files under ``<results_dir>/<experiment>/`` (the layout users see)::

    geometry/<gid>.ply, <gid>.json              surface, its metadata
    mesh/<gid>.vtu, .features.json, .regions.png
    sweep/<scenario>/cases.parquet, sweep.json
    shards/<scenario>/shard-<NNNN>.parquet, manifest.json
    progress/<scenario>-<NNNN>.json             a running simulate job's progress
    models/<scenario>/<variant>/metrics.json, model/
    validate/metrics.json
    validate/physics.json, physics/<NN>/shard-0000.parquet, manifest.json   the physics study's choices
    studies/<study>.json, <study>.png
    report/index.html
    cases/<case id>.png                         ``liverforce show-case``
    logs/<stage>/<name>.log

Every path method's arguments default to the Snakemake wildcard of the same
name, so ``Layout(root).mesh()`` is the rule pattern
``<root>/mesh/{gid}.vtu`` and ``Layout(root).mesh("proc-0000")`` one file.
Module-level functions read the names back from a path
(:func:`gid_of`, :func:`scenario_of_manifest`, :func:`root_of_manifest`, :func:`model_of_metrics`) or
name a file beside another (:func:`features_of_mesh`, :func:`progress_of_shard`).

MLflow experiments (:func:`experiment_name`): ``<prefix>-<experiment>-<scenario>``
(trained models, Ax trials nested), ``<prefix>-<experiment>-validation`` and
``<prefix>-<experiment>-studies``.
"""

from __future__ import annotations

from pathlib import Path

__all__ = [
    "Layout", "experiment_name", "shard_id", "case_id", "scenario_of_case", "gid_of", "scenario_of_manifest",
    "root_of_manifest",
    "model_of_metrics", "features_of_mesh", "surface_meta_of", "surface_meta_of_mesh", "progress_of_shard",
    "study_picture_of",
    "physics_variant_files",
]

# file names and suffixes (one place)
_SURFACE, _SURFACE_META = ".ply", ".json"
_MESH, _FEATURES, _REGIONS_PNG = ".vtu", ".features.json", ".regions.png"
_GID_SUFFIXES = (_FEATURES, _REGIONS_PNG, _MESH, _SURFACE, _SURFACE_META)  # longest first
_SHARD_PREFIX, _SHARD_SUFFIX = "shard-", ".parquet"
_MANIFEST = "manifest.json"
_METRICS = "metrics.json"


def experiment_name(prefix: str, experiment: str, kind: str) -> str:
    """MLflow experiment name: ``<prefix>-<experiment>-<kind>`` (kind: a scenario, ``validation`` or ``studies``)."""
    return f"{prefix}-{experiment}-{kind}"


def shard_id(index) -> str:
    """Shard id of shard ``index`` (``"0003"``); a string (e.g. the ``{shard}`` wildcard) is kept as it is."""
    return index if isinstance(index, str) else f"{int(index):04d}"


def case_id(scenario: str, index: int) -> str:
    """Case id of case ``index`` of a scenario's case table: ``<scenario>-<index:06d>``."""
    return f"{scenario}-{int(index):06d}"


def scenario_of_case(case: str) -> str:
    """The scenario of a case id (:func:`case_id`)."""
    return str(case).rsplit("-", 1)[0]


class Layout:
    """Paths of every stage output under ``root`` (``<results_dir>/<experiment>``, as given: relative or absolute)."""

    def __init__(self, root: str | Path):
        self.root = str(root)

    def _p(self, *parts: str) -> str:
        return "/".join((self.root, *parts))

    # geometry and mesh: one file set per geometry id
    def surface(self, gid: str = "{gid}") -> str:
        return self._p("geometry", gid + _SURFACE)

    def surface_meta(self, gid: str = "{gid}") -> str:
        return self._p("geometry", gid + _SURFACE_META)

    def mesh(self, gid: str = "{gid}") -> str:
        return self._p("mesh", gid + _MESH)

    def features(self, gid: str = "{gid}") -> str:
        return self._p("mesh", gid + _FEATURES)

    def regions_picture(self, gid: str = "{gid}") -> str:
        return self._p("mesh", gid + _REGIONS_PNG)

    # sweep and shards: per scenario
    def cases(self, scenario: str = "{scenario}") -> str:
        return self._p("sweep", scenario, "cases.parquet")

    def sweep_report(self, scenario: str = "{scenario}") -> str:
        return self._p("sweep", scenario, "sweep.json")

    def shard_dir(self, scenario: str = "{scenario}") -> str:
        return self._p("shards", scenario)

    def shard(self, scenario: str = "{scenario}", shard="{shard}") -> str:
        """``shard``: an index or a shard id (:func:`shard_id`)."""
        return self._p("shards", scenario, _SHARD_PREFIX + shard_id(shard) + _SHARD_SUFFIX)

    def manifest(self, scenario: str = "{scenario}") -> str:
        return self._p("shards", scenario, _MANIFEST)

    def progress(self, scenario: str = "{scenario}", shard="{shard}") -> str:
        """The progress file a simulate job rewrites after every case."""
        return self._p("progress", f"{scenario}-{shard_id(shard)}.json")

    # models, validation, studies, report
    def model_metrics(self, scenario: str = "{scenario}", variant: str = "{variant}") -> str:
        return self._p("models", scenario, variant, _METRICS)

    def model_dir(self, scenario: str = "{scenario}", variant: str = "{variant}") -> str:
        return self._p("models", scenario, variant, "model")

    def validation_metrics(self) -> str:
        return self._p("validate", _METRICS)

    def physics(self) -> str:
        """The physics study (liverforce.pipeline.physics); its shards in ``physics_shards()``."""
        return self._p("validate", "physics.json")

    def physics_shards(self) -> str:
        return self._p("validate", "physics")

    def study(self, study: str = "{study}") -> str:
        return self._p("studies", f"{study}.json")

    def study_picture(self, study: str = "{study}") -> str:
        return self._p("studies", f"{study}.png")

    def report(self) -> str:
        return self._p("report", "index.html")

    def case_picture(self, case: str) -> str:
        return self._p("cases", f"{case}.png")

    def log(self, stage: str, name: str) -> str:
        """A job's log: ``logs/<stage>/<name>.log`` (``name`` may hold wildcards, e.g. ``{scenario}-{shard}``)."""
        return self._p("logs", stage, f"{name}.log")


# --------------------------------------------------------------------------
# names read back from paths, files beside files
# --------------------------------------------------------------------------


def gid_of(path: str | Path) -> str:
    """The geometry id of a per-geometry file (surface, its metadata, mesh, features, regions picture)."""
    name = Path(path).name
    for suffix in _GID_SUFFIXES:
        if name.endswith(suffix):
            return name[: -len(suffix)]
    raise ValueError(f"{path}: not a geometry or mesh file of the results layout")


def scenario_of_manifest(path: str | Path) -> str:
    """The scenario of a shard manifest or a shard (``shards/<scenario>/...``)."""
    return Path(path).parent.name


def root_of_manifest(path: str | Path) -> Path:
    """The results root (``<results_dir>/<experiment>``) of a shard manifest
    (``<root>/shards/<scenario>/manifest.json``) or a shard beside it; ``ValueError`` for a file outside a results
    layout's ``shards/`` folder."""
    p = Path(path)
    if p.parent.parent.name != "shards":
        raise ValueError(f"{path}: not in a results layout's shards/<scenario>/ folder")
    return p.parent.parent.parent


def model_of_metrics(path: str | Path) -> tuple[str, str]:
    """``(scenario, variant)`` of a model's ``models/<scenario>/<variant>/metrics.json`` (or its model folder)."""
    p = Path(path)
    return p.parent.parent.name, p.parent.name


def features_of_mesh(mesh_path: str | Path) -> Path:
    """The features JSON written beside a mesh (``mesh/<gid>.features.json``)."""
    p = Path(mesh_path)
    return p.with_name(gid_of(p) + _FEATURES)


def surface_meta_of(surface_path: str | Path) -> Path:
    """The metadata JSON written beside a geometry's surface (``geometry/<gid>.json``)."""
    p = Path(surface_path)
    return p.with_name(gid_of(p) + _SURFACE_META)


def surface_meta_of_mesh(mesh_path: str | Path) -> Path:
    """The geometry stage's record of a mesh's liver (``<root>/geometry/<gid>.json`` for ``<root>/mesh/<gid>.vtu``);
    ``ValueError`` for a file outside a results layout's ``mesh/`` folder."""
    p = Path(mesh_path).resolve()
    if p.parent.name != "mesh":
        raise ValueError(f"{mesh_path}: not in a results layout's mesh/ folder")
    return Path(Layout(p.parent.parent).surface_meta(gid_of(p)))


def physics_variant_files(folder: str | Path, k: int) -> tuple[Path, Path]:
    """The shard and manifest of the physics study's ``k``-th choice: ``validate/physics/<k>/shard-0000.parquet``
    and its ``manifest.json`` (:meth:`Layout.physics_shards`)."""
    d = Path(folder) / f"{int(k):02d}"
    return d / f"{_SHARD_PREFIX}{shard_id(0)}{_SHARD_SUFFIX}", d / _MANIFEST


def shards_in(folder: str | Path) -> list[Path]:
    """The shard files of a scenario's folder (``shard-<NNNN>.parquet``), sorted."""
    return sorted(Path(folder).glob(f"{_SHARD_PREFIX}*{_SHARD_SUFFIX}"))


def progress_of_shard(shard_path: str | Path) -> Path:
    """The progress file of the job writing ``shards/<scenario>/shard-<NNNN>.parquet``.

    That is ``progress/<scenario>-<NNNN>.json`` beside ``shards/`` (:meth:`Layout.progress`).
    """
    p = Path(shard_path)
    sid = p.name.removeprefix(_SHARD_PREFIX).removesuffix(_SHARD_SUFFIX)
    return p.parent.parent.parent / "progress" / f"{scenario_of_manifest(p)}-{sid}.json"


def study_picture_of(study_json: str | Path) -> Path:
    """The figure written beside a study's JSON (``studies/<study>.png``)."""
    return Path(study_json).with_suffix(".png")
