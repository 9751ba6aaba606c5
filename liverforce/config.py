"""Compose and validate the liverforce configuration (the only Hydra import).

The Hydra config groups under ``config/`` are the single source of truth. This
module composes them once (``compose``), checks every key's type against the
dataclass schema below and every value's range, and returns a plain ``dict``
(no ``DictConfig`` ever leaves this module). A wrong key or value raises
:class:`ConfigError` with the key's dotted path, before any compute.

Example
-------
>>> from liverforce.config import compose
>>> cfg = compose(["experiment=smoke", "sweep.force.max_n=4.0"])
>>> cfg["sweep"]["force"]["max_n"]
4.0
"""

from __future__ import annotations

import hashlib
import importlib
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

PROJECT_ROOT = Path(__file__).resolve().parent.parent
CONFIG_DIR = PROJECT_ROOT / "config"

SCENARIOS = ("I", "II", "III", "IV")


#: omegaconf.MISSING (a mandatory value), spelled here so that importing this module does not import omegaconf
MISSING = "???"


class ConfigError(ValueError):
    """A configuration key is unknown, mistyped or out of range."""


# --------------------------------------------------------------------------
# Schema: types (checked by OmegaConf) — ranges are checked in _check_ranges.
#
# No defaults here: every value comes from config/*.yaml (MISSING marks a field
# the YAML must give; tests/test_config.py checks that no field has a default).
# The one exception is ImportedGeometry, the schema of each entry of the
# user's geometry.imported list: no YAML file can hold defaults for list
# entries, so an entry's optional keys default here (and only here).
# --------------------------------------------------------------------------


@dataclass
class ProceduralGeometry:
    count: int = MISSING
    seed: int = MISSING
    shape: dict[str, Any] = MISSING  # LiverShapeParams fields


@dataclass
class CubeGeometry:
    enabled: bool = MISSING
    edge_mm: float = MISSING


@dataclass
class ImportedGeometry:
    name: str = "???"
    path: str = "???"
    units: str = "mm"  # mm | cm | m | auto | a number (scale to mm)
    label: Optional[Any] = None  # a label volume's liver label value, or a 3D Slicer segment's name or ID
    # RAS | LPS (3D Slicer models, DICOM) | a 4x4 [[...],...,[0,0,0,1]]: file mm (after units) -> RAS mm
    frame: Any = "RAS"
    # own supports, in the file's frame (liverforce.mesh.supports): {mode: replace|add, list: [{name, kind:
    # fixed|foundation|sliding, sphere|box|file: {...} | group: name|tag|{array, value}, region:
    # ligament|visceral, stiffness: {...}}]}
    supports: Optional[Any] = None
    # own exertion points, in the file's frame: {coordinates_mm: [[x,y,z],...]} | {vertex_ids: [...]}
    # | {path: pts.npy|txt|csv, units: ...}; the sweep uses all of them instead of sampled ones
    exertion_points: Optional[Any] = None
    # auto (a file holding tetrahedra: as_given; anything else: remesh) | as_given (the file's tets and node
    # numbering, linear tets raised to P2 by the solver) | remesh (tetrahedralise its surface, as for an STL)
    mesh: str = "auto"
    # the liver's own material (the run's material.model): {E_pa: ...} | {E_mpa: ...} (neo_hookean, the run's nu)
    # | {params_mpa: {C10: ...}} | {scale: s} (the run's constants x s); none: the run's material. Held out
    # (validate.imported): its cases take these constants as given (validate.material_scale is not applied);
    # a training liver: the constants its scenarios draw around (material.vary_rel). See liver_material.
    material: Optional[Any] = None


@dataclass
class GeometryConfig:
    procedural: ProceduralGeometry = field(default_factory=ProceduralGeometry)
    cube: CubeGeometry = field(default_factory=CubeGeometry)
    imported: list[ImportedGeometry] = MISSING


@dataclass
class MeshConfig:
    target_nodes: int = MISSING
    mesher: str = MISSING
    refine_radius_mm: float = MISSING
    refine_edge_mm: float = MISSING
    refine_growth: float = MISSING
    refine_ivc_edge_mm: float = MISSING
    regions: dict[str, Any] = MISSING
    regions_check: str = MISSING  # warn | strict | off: anatomical plausibility of the tagged regions


@dataclass
class MaterialConfig:
    model: str = MISSING
    params_mpa: dict[str, float] = MISSING
    # neo_hookean from a paper's Young's modulus, in Pa or in MPa (give one): params_mpa is then derived,
    # C10 = mu / 2 with mu = E / (2 (1 + nu)) (liverforce.fem.materials.neo_hookean_from_young)
    E_pa: Optional[float] = MISSING
    E_mpa: Optional[float] = MISSING
    nu: float = MISSING
    vary_rel: float = MISSING
    stability_stretch: list[float] = MISSING
    on_unstable: str = MISSING


@dataclass
class GravityConfig:
    enabled: bool = MISSING
    density_kg_per_m3: float = MISSING
    direction: list[float] = MISSING  # in the mesh frame (RAS for procedural livers), normalised


@dataclass
class BoundaryConfig:
    ligament_total_n_per_mm: float = MISSING
    visceral_total_n_per_mm: float = MISSING
    tangential_ratio: float = MISSING
    rib_normal_n_per_mm3: float = MISSING
    rib_contact: str = MISSING  # bilateral | unilateral
    gravity: GravityConfig = field(default_factory=GravityConfig)


@dataclass
class ForceRange:
    min_n: float = MISSING
    max_n: float = MISSING
    cone_deg: float = MISSING


@dataclass
class ExertionConfig:
    n_points: int = MISSING
    min_spacing_mm: float = MISSING


@dataclass
class ScenarioSweep:
    n_cases: int = MISSING
    geometries: str = MISSING  # "1" (first liver) or "all"
    exertion: str = MISSING  # fixed | varies
    material: str = MISSING  # fixed | varies


@dataclass
class SweepConfig:
    design: str = MISSING
    seed: int = MISSING
    cases_per_shard: int = MISSING
    force: ForceRange = field(default_factory=ForceRange)
    exertion: ExertionConfig = field(default_factory=ExertionConfig)
    scenarios: dict[str, ScenarioSweep] = MISSING


@dataclass
class SimulateConfig:
    formulation: str = MISSING
    tool_radius_mm: float = MISSING
    tol: float = MISSING
    max_iter: int = MISSING
    max_total_iter: int = MISSING  # Newton iterations per case: the deterministic budget (time_limit_s: a safety net)
    initial_step: float = MISSING
    min_step: float = MISSING
    max_steps: int = MISSING
    time_limit_s: float = MISSING
    warm_start: bool = MISSING
    modified_newton: bool = MISSING
    linear_solver: str = MISSING
    tool_model: str = MISSING
    tool_tip_radius_mm: float = MISSING
    tool_penalty_n_per_mm3: float = MISSING
    tool_force_rtol: float = MISSING
    tool_force_atol_n: float = MISSING
    tool_max_slide_mm: float = MISSING
    tool_control: str = MISSING  # magnitude | vector: what the sphere case prescribes (simulate.tool_model: sphere)


@dataclass
class DatasetConfig:
    roi_fraction: float = MISSING
    store_full_surface: bool = MISSING
    compression: str = MISSING


@dataclass
class IntervalConfig:
    coverage: float = MISSING  # nominal coverage of the per-component interval (split conformal)
    calibration_fraction: float = MISSING  # of the training split, held out to calibrate it
    folds: int = MISSING  # > 1: cross-conformal over the training split (by liver in IV); 1: one held-out split
    scale: str = MISSING  # none | stiffness (x the case's stiffness factor) | force (x a + b |predicted force|)
    # | force_bins (a width per bin of the predicted |force|)
    bins: int = MISSING  # scale: force_bins: bins at the quantiles of the calibration cases' predicted |force|
    widen: str = MISSING  # outside the calibration's stiffness range: proportional (x k / k_hi) | fitted (x (k /
    # k_hi)^g, g the calibration residuals' growth with the stiffness)
    spread: Optional[float] = MISSING  # beta > 0: widths x (the GP ensemble members' sd + beta x its calibration
    # median); null: not scaled by the members' spread (liverforce.learn.interval)
    distance_quantile: Optional[float] = MISSING  # a GP model's prediction warns when its inputs lie farther from
    # every training row than this quantile of the training cases' from the other livers' rows
    # (liverforce.learn.interval); null: no such flag
    far_widths: bool = MISSING  # with distance_quantile: the cases beyond it get a width of their own, the others
    # theirs (Mondrian conformal on the flag; liverforce.learn.interval)


@dataclass
class OcclusionConfig:
    radius_mm: float = MISSING
    mode: str = MISSING


@dataclass
class CameraConfig:
    observation: dict[str, Any] = MISSING  # ObservationConfig fields (liverforce.learn.observation)
    grid: dict[str, Any] = MISSING  # CloudGridSpec fields other than grid_size and half_width_mm
    tip_noise_mm: float = MISSING  # Gaussian noise of the tool tip position (robot kinematics), per coordinate
    tip_noise_normal_mm: Optional[float] = MISSING  # null: isotropic; else the sd along the normal (tip_noise_mm: tangential)
    views: int = MISSING  # observed views per training case (camera pose, density, noise drawn again)


@dataclass
class GPConfig:
    max_points: int = MISSING  # training rows of the exact GP; above it a seeded subset of this size
    iterations: int = MISSING  # L-BFGS iterations on the marginal likelihood
    code_members: Optional[list[int]] = MISSING  # PCA code sizes of a GP ensemble (mean of one GP per size); null: one GP
    kernel: str = MISSING  # rational_quadratic | squared_exponential (liverforce.learn.gp)
    shape: Optional[float] = MISSING  # the rational quadratic's a; null: fitted by the marginal likelihood
    per_output: bool = MISSING  # one kernel per force component (own length scales and variances)
    noise_floor: float = MISSING  # the least noise variance (standardised targets), in the likelihood and posterior


@dataclass
class ModelConfig:
    encoder: str = MISSING
    code_size: int = MISSING
    state_vector: bool = MISSING
    grid_size: int = MISSING
    regressor: str = MISSING  # gp | mlp (liverforce.learn.regressor)
    gp: GPConfig = field(default_factory=GPConfig)
    hidden: list[int] = MISSING
    dropout: float = MISSING
    occlusion: OcclusionConfig = field(default_factory=OcclusionConfig)
    noise_mm: float = MISSING
    roi_features: str = MISSING
    grid_half_width_mm: float = MISSING
    dae_input_noise: float = MISSING
    roi_fraction: Optional[float] = MISSING  # None: the shards' dataset.roi_fraction
    force_scaling: str = MISSING  # linear | stiffness | none (state-vector models; liverforce.learn.model)
    probe_force_radius_mm: float = MISSING  # Gaussian radius of the linear force estimate C^-1 u_w (0 = off)
    indentation_strain: bool = MISSING  # with the linear force estimate: also u_w,n / h (tissue thickness h)
    rigid_motion: str = MISSING  # keep | remove (the ROI's best rigid motion undone; displacement features)
    rigid_motion_radius_mm: float = MISSING  # remove: fitted to the ROI nodes at least this far from the tool, mm
    interpolation: str = MISSING  # surface | points: node displacements on the ROI patch's top sheet or the points'
    #                               Delaunay interpolant (liverforce.learn.representation)
    camera: CameraConfig = field(default_factory=CameraConfig)  # roi_features: cloud (liverforce.learn.camera)


@dataclass
class HeldoutPointsConfig:
    scenarios: list[str] = MISSING  # scenarios split by case whose models are also scored on unseen exertion points
    folds: int = MISSING  # groups of whole exertion points, each predicted by a model fitted on the others


@dataclass
class TrainConfig:
    scenarios: list[str] = MISSING
    variants: list[dict[str, Any]] = MISSING  # each: name + model overrides
    test_fraction: float = MISSING
    epochs: int = MISSING
    batch_size: int = MISSING
    lr: float = MISSING
    weight_decay: float = MISSING
    seed: int = MISSING
    repeats: int = MISSING  # seeded train/test splits per model (the first is the main split): mean +- sd
    final_fit: bool = MISSING  # the saved model is refitted on every case of the scenario (else the main split's)
    interval: IntervalConfig = field(default_factory=IntervalConfig)
    heldout_points: HeldoutPointsConfig = field(default_factory=HeldoutPointsConfig)


@dataclass
class TuneConfig:
    enabled: bool = MISSING
    trials: int = MISSING
    folds: int = MISSING
    sobol_trials: int = MISSING
    epochs: int = MISSING
    space: dict[str, Any] = MISSING


@dataclass
class TrackingConfig:
    uri: Optional[str] = MISSING
    experiment_prefix: str = MISSING


@dataclass
class PhysicsConfig:
    enabled: bool = MISSING  # the physics study (liverforce.pipeline.physics): off -> no rule, no report section
    liver: int = MISSING  # which unseen liver (index among the procedural ones, then validate.imported)
    n_cases: int = MISSING  # its first cases, simulated again under each changed choice
    foundation_scale: list[float] = MISSING  # both foundations' stiffness x each
    tangential_ratio: list[float] = MISSING  # k_t / k_n values
    rib_contact: list[str] = MISSING  # unilateral | bilateral | off
    gravity: list[list[float]] = MISSING  # gravity directions (RAS), each a variant
    tool: str = MISSING  # none | sphere: the tool as a rigid sphere (simulate.tool_model: sphere)
    tool_cases: int = MISSING  # the sphere runs the first tool_cases cases (a contact case costs ~30 traction cases)
    tool_max_force_n: float = MISSING  # ... of at most this force (a 5 mm tip sinks > 7 mm beyond ~1 N)


@dataclass
class ValidateConfig:
    seed: int = MISSING  # unseen liver i has the procedural seed seed + i
    livers: int = MISSING  # unseen procedural livers
    imported: list[str] = MISSING  # names of geometry.imported livers held out of training: unseen livers too
    n_cases: int = MISSING  # cases per unseen liver
    material_scale: float = MISSING
    variant: str = MISSING  # auto: lowest CV MAE (N) on the training livers | main: the first variant | a name
    input: str = MISSING  # camera: auto chooses among the camera-cloud variants (what surgery has) | any
    camera_sensitivity: dict[str, Any] = MISSING  # setting -> values re-observed for the camera-cloud model
    shape_changes: list[Any] = MISSING  # [amplitude_mm, wavelength_mm] pairs: each unseen liver's shape changed
    registration_errors: list[Any] = MISSING  # [shift_mm, turn_deg] pairs: the camera's registration that far off
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)


@dataclass
class ReportConfig:
    format: str = MISSING


@dataclass
class StudyValues:
    enabled: bool = MISSING
    scenarios: list[str] = MISSING
    values: list[Any] = MISSING


@dataclass
class StateVectorStudy:
    enabled: bool = MISSING
    scenarios: list[str] = MISSING
    values: list[bool] = MISSING
    encoder: str = MISSING


@dataclass
class OcclusionStudy:
    enabled: bool = MISSING
    scenarios: list[str] = MISSING
    radii_mm: list[float] = MISSING
    encoders: list[str] = MISSING
    modes: list[str] = MISSING


@dataclass
class StudyConfig:
    """Comparison studies on existing shards (liverforce.learn.study)."""

    enabled: bool = MISSING
    epochs: int = MISSING
    hyper_parameters: str = MISSING  # main | config
    roi_fraction: StudyValues = field(default_factory=StudyValues)
    encoder: StudyValues = field(default_factory=StudyValues)
    state_vector: StateVectorStudy = field(default_factory=StateVectorStudy)
    occlusion: OcclusionStudy = field(default_factory=OcclusionStudy)
    noise: StudyValues = field(default_factory=StudyValues)
    train_size: StudyValues = field(default_factory=StudyValues)
    train_livers: StudyValues = field(default_factory=StudyValues)


@dataclass
class RootConfig:
    experiment: str = MISSING
    results_dir: str = MISSING
    seed: int = MISSING
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    material: MaterialConfig = field(default_factory=MaterialConfig)
    boundary: BoundaryConfig = field(default_factory=BoundaryConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)
    simulate: SimulateConfig = field(default_factory=SimulateConfig)
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    tune: TuneConfig = field(default_factory=TuneConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    validate: ValidateConfig = field(default_factory=ValidateConfig)
    report: ReportConfig = field(default_factory=ReportConfig)
    study: StudyConfig = field(default_factory=StudyConfig)


# --------------------------------------------------------------------------
# compose
# --------------------------------------------------------------------------


def variant_model(model: dict, variant: dict) -> dict:
    """The model config of one ``train.variants`` entry: the ``model`` group with the variant's overrides (its keys
    but ``name``). A group the variant overrides with a mapping (``gp: {kernel: squared_exponential}``,
    ``camera: {observation: {noise_sd_mm: 1.0}}``) is updated key by key at every depth, so the variant names only
    what differs; any other value replaces the model's."""
    return merge_mapping(model, {k: v for k, v in variant.items() if k != "name"})


def merge_mapping(base: dict, over: dict) -> dict:
    """``base`` with ``over``'s values: a mapping over a mapping is merged key by key at every depth, any other value
    replaces (the variants here, the studies' model overrides in :mod:`liverforce.learn.study`)."""
    out = dict(base)
    for k, val in over.items():
        out[k] = merge_mapping(base[k], val) if isinstance(base.get(k), dict) and isinstance(val, dict) else val
    return out


def _unknown_keys(base: dict, over: dict, prefix: str = "") -> list[str]:
    """Dotted names of the keys of ``over`` that ``base`` does not have, at every depth of the mappings both have."""
    out = []
    for k, val in over.items():
        if k not in base:
            out.append(prefix + k)
        elif isinstance(base[k], dict) and isinstance(val, dict):
            out += _unknown_keys(base[k], val, f"{prefix}{k}.")
    return sorted(out)


def compose(overrides: list[str] | tuple[str, ...] | None = None, *, run: bool = True) -> dict:
    """Compose ``config/`` with Hydra overrides, validate, return a plain dict.

    Parameters
    ----------
    overrides : list of str
        Hydra override strings, e.g. ``["experiment=smoke", "sweep.seed=3"]``.
    run : bool
        Also check what only a run of the pipeline needs (:func:`check_run`: scenario IV's two training livers).
        True (the default) for the Snakefile (``workflow/rules/common.smk``) and ``liverforce run``, which
        validate the config once before any job; False for commands that do not run the pipeline
        (``liverforce config``, ``ui``, ``progress``, ``show-case``, ``benchmarks/bench_mesh.py``).

    Returns
    -------
    dict
        The validated configuration as plain Python containers.

    Raises
    ------
    ConfigError
        On an unknown key, a wrong type or an out-of-range value; the message
        names the key's dotted path and what to do.
    """
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    overrides = list(overrides or [])
    if GlobalHydra.instance().is_initialized():
        GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            # with Hydra's own record of the run: the command-line overrides (hydra.overrides.task) and the
            # group choices (hydra.runtime.choices) tell a preset's value from the user's (_young_given_once)
            raw = hydra_compose(config_name="config", overrides=overrides, return_hydra_config=True)
    except (HydraException, OmegaConfBaseException) as exc:
        raise ConfigError(
            f"could not compose the configuration with overrides {overrides}: {exc}. "
            "Check the override keys against config/ (e.g. `liverforce config show`)."
        ) from exc
    finally:
        GlobalHydra.instance().clear()

    OmegaConf.set_struct(raw, False)
    hydra_cfg = raw.pop("hydra", None)
    provenance = _provenance(hydra_cfg)
    try:
        typed = OmegaConf.merge(OmegaConf.structured(RootConfig), raw)
        cfg = OmegaConf.to_container(typed, resolve=True, throw_on_missing=True)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None) or "?"
        msg = str(exc).splitlines()[0]
        raise ConfigError(f"config key '{key}': {msg}") from exc
    _young_given_once(cfg["material"], provenance)
    _check_ranges(cfg, run=run)
    return cfg


def check_run(cfg: dict) -> None:
    """Refuse, with :class:`ConfigError`, a composed config that validates but cannot be run by the pipeline:
    a scenario split by liver (IV) with fewer than two training livers. :func:`compose` calls it unless
    ``run=False``, so the Snakefile and ``liverforce run`` refuse such a run before any job, while commands
    that only read the config (``liverforce config``, ``progress``, ``show-case``, ``ui``) or mesh livers
    (``benchmarks/bench_mesh.py --livers 1``) take it."""
    _check_grouped_livers(cfg)


def _provenance(hydra_cfg) -> dict:
    """The dotted keys the command line set (Hydra's ``hydra.overrides.task``, parsed by Hydra's own override
    parser) and the config group chosen for each group (``hydra.runtime.choices``)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    if hydra_cfg is None:
        return {"overridden": {}, "choices": {}, "dirs": [str(CONFIG_DIR)]}
    task = [str(o) for o in hydra_cfg.overrides.task]
    overridden = {o.key_or_group: o for o in OverridesParser.create().parse_overrides(task)}
    choices = {str(k): (None if v is None else str(v)) for k, v in hydra_cfg.runtime.choices.items()}
    # the config folders in Hydra's search order (config/, then any hydra.searchpath=[file://...])
    dirs = [str(src.path) for src in hydra_cfg.runtime.config_sources if src.schema == "file"]
    return {"overridden": overridden, "choices": choices, "dirs": dirs or [str(CONFIG_DIR)]}


def _group_file(group: str, name: str | None, dirs) -> Path | None:
    """The file Hydra read for ``<group>=<name>``: the first of the config folders (search order) that has it."""
    if not name:
        return None
    for d in dirs:
        path = Path(d) / group / f"{name}.yaml"
        if path.is_file():
            return path
    return None


def _shown(path: Path) -> str:
    """``path`` relative to the project folder when it is in it (config/experiment/lab.yaml), else absolute."""
    try:
        return str(path.resolve().relative_to(PROJECT_ROOT))
    except ValueError:
        return str(path)


#: who set a value, weakest first: a later one overrides an earlier one (config/config.yaml's defaults list puts
#: the experiment after the material preset, and the command line is applied last)
_RANKS = ("files", "preset", "experiment", "command line")


def _young_source(key: str, provenance: dict) -> tuple[int, str, Path | None]:
    """Who set ``material.<key>`` last: ``(rank in _RANKS, description, the file or None)``.

    The command line (a ``material.<key>=`` override), else the experiment's file when it sets the key (so an
    experiment changing the preset's value is named, not the preset), else the material preset's file.
    """
    from omegaconf import OmegaConf

    over = provenance["overridden"]
    if f"material.{key}" in over and not over[f"material.{key}"].is_delete():
        return 3, "the command line", None
    choices, dirs = provenance["choices"], provenance.get("dirs") or [str(CONFIG_DIR)]
    exp = choices.get("experiment")
    path = _group_file("experiment", exp, dirs)
    if path is not None:
        material = OmegaConf.load(path).get("material")
        if material is not None and hasattr(material, "keys") and material.get(key) is not None:
            return 2, f"the experiment experiment={exp} ({_shown(path)})", path
    preset = choices.get("material")
    path = _group_file("material", preset, dirs)
    if path is not None and OmegaConf.load(path).get(key) is not None:
        return 1, f"the preset material={preset} ({_shown(path)})", path
    return 0, "the config files", None


def _young_given_once(mat: dict, provenance: dict) -> None:
    """``material.E_pa`` and ``E_mpa`` both set: the one set by the stronger source wins, with a logged note —
    the command line over the experiment's file over the material preset's file, as for any other key
    (``material=neo_hookean_from_e material.E_mpa=0.0149``, or an experiment file with ``material: {E_mpa:
    0.0149}`` over that preset: the preset's ``E_pa: 14900`` is dropped). Both set by the same source (both on
    the command line, both in the experiment's file, both in the preset's) are refused naming that source and
    the exact fix there."""
    import logging

    keys = ("E_pa", "E_mpa")
    if any(mat.get(k) is None for k in keys):
        return
    src = {k: _young_source(k, provenance) for k in keys}
    if src["E_pa"][0] != src["E_mpa"][0]:
        mine, other = sorted(keys, key=lambda k: -src[k][0])
        how = "given on" if src[mine][0] == 3 else "set by"
        logging.getLogger("liverforce").info(
            "material: material.%s=%s %s %s replaces material.%s %s of %s (Young's modulus is given once)",
            mine, mat[mine], how, src[mine][1], other, mat[other], src[other][1])
        mat[other] = None
        return
    e_pa, e_mpa = mat["E_pa"], mat["E_mpa"]
    rank, where, path = src["E_pa"]
    problem = f"Young's modulus is given twice, E_pa {e_pa} (Pa) and E_mpa {e_mpa} (MPa)"
    if rank == 3:
        _fail("material.E_pa", f"{problem}: both on the command line (material.E_pa={e_pa} and material.E_mpa={e_mpa})",
              f"give it once: material.E_pa={e_pa} material.E_mpa=null, or material.E_pa=null material.E_mpa={e_mpa}")
    if path is not None:
        _fail("material.E_pa", f"{problem}: both by {where}",
              f"give it once in {_shown(path)}: under material:, E_pa: null (to keep E_mpa {e_mpa}) or E_mpa: null "
              f"(to keep E_pa {e_pa}); or once on the command line, which replaces the file's: material.E_pa=null "
              f"material.E_mpa={e_mpa}, or material.E_pa={e_pa} material.E_mpa=null")
    _fail("material.E_pa", f"{problem}: both by {where}",
          f"give it once: material.E_pa={e_pa} material.E_mpa=null, or material.E_pa=null material.E_mpa={e_mpa}")


def _fail(key: str, problem: str, fix: str = "") -> None:
    raise ConfigError(f"config key '{key}': {problem}" + (f" — {fix}" if fix else ""))


def _check_choice(key: str, value: Any, choices, what: str = "") -> None:
    """Refuse ``value`` unless it is one of ``choices``; the error names the key, the value and the choices."""
    choices = tuple(choices)
    if value not in choices:
        _fail(key, f"unknown {what + ' ' if what else ''}'{value}'", f"choose one of {', '.join(map(str, choices))}")


# --------------------------------------------------------------------------
# Choice registries: each choice key is checked against the names exported by the module that implements
# it (read at check time, so a name added to a registry is valid here without touching this module).
# Imported inside the functions: importing this module stays light.
# --------------------------------------------------------------------------


def material_models() -> tuple[str, ...]:
    """``material.model``: the models :func:`liverforce.fem.materials.make_material` builds."""
    from liverforce.fem.materials import available_models

    return tuple(available_models())


def formulations() -> tuple[str, ...]:
    """``simulate.formulation``: :data:`liverforce.fem.assembly.FORMULATIONS` (``formulation_spec``)."""
    from liverforce.fem.assembly import FORMULATIONS

    return tuple(FORMULATIONS)


def linear_solvers() -> tuple[str, ...]:
    """``simulate.linear_solver``: the methods :class:`liverforce.fem.linsolve.LinearSolver` accepts."""
    from liverforce.fem import linsolve

    return tuple(linsolve.METHODS)


def tool_models() -> tuple[str, ...]:
    """``simulate.tool_model``: :data:`liverforce.pipeline.simulate.TOOL_MODELS`."""
    from liverforce.pipeline.simulate import TOOL_MODELS

    return tuple(TOOL_MODELS)


def interval_widenings() -> tuple[str, ...]:
    """``train.interval.widen``: :data:`liverforce.learn.interval.WIDENINGS`."""
    from liverforce.learn.interval import WIDENINGS

    return tuple(WIDENINGS)


def interval_scales() -> tuple[str, ...]:
    """``train.interval.scale``: :data:`liverforce.learn.interval.SCALES`."""
    from liverforce.learn.interval import SCALES

    return tuple(SCALES)


def sweep_designs() -> tuple[str, ...]:
    """``sweep.design``: the samplers of :data:`liverforce.sweep.design.DESIGNS`."""
    from liverforce.sweep.design import design_names

    return design_names()


#: ``mesh.mesher`` (liverforce.mesh.tetra.tetrahedralise_with_info checks the same two)
MESHERS = ("gmsh", "tetgen")
#: ``report.format`` (liverforce.report writes HTML only)
REPORT_FORMATS = ("html",)


def _learn_names():
    """:mod:`liverforce.learn.names` (encoders, ROI features, occlusion modes); it and the package's
    ``__init__`` import nothing heavy (no torch)."""
    return importlib.import_module("liverforce.learn.names")


def encoders() -> tuple[str, ...]:
    """``model.encoder`` and the study's encoder lists: :data:`liverforce.learn.names.ENCODERS`."""
    return tuple(_learn_names().ENCODERS)


def roi_features() -> tuple[str, ...]:
    """``model.roi_features``: :data:`liverforce.learn.names.ROI_FEATURE_CHANNELS` (the representation's)."""
    return tuple(_learn_names().ROI_FEATURE_CHANNELS)


def force_scalings() -> tuple[str, ...]:
    """``model.force_scaling``: :data:`liverforce.learn.names.FORCE_SCALINGS`."""
    return tuple(_learn_names().FORCE_SCALINGS)


def occlusion_modes() -> tuple[str, ...]:
    """``model.occlusion.mode`` and ``study.occlusion.modes``: :data:`liverforce.learn.names.OCCLUSION_MODES`."""
    return tuple(_learn_names().OCCLUSION_MODES)


def _check_ranges(cfg: dict, run: bool = True) -> None:
    """Range and consistency checks; each failure names the dotted key."""
    g = cfg["geometry"]
    if g["procedural"]["count"] < 1 and not g["imported"]:
        _fail("geometry.procedural.count", "needs at least one geometry", "set count >= 1 or list imported livers")
    _check_held_out(cfg)
    try:
        from liverforce.geometry.procedural import LiverShapeParams

        LiverShapeParams(**g["procedural"]["shape"])
    except (TypeError, ValueError) as exc:
        _fail("geometry.procedural.shape", str(exc))
    first: dict[str, int] = {}
    for i, imp in enumerate(g["imported"]):
        name = imp["name"]
        if not name or not all(c.isalnum() or c in "-_" for c in name):
            _fail(f"geometry.imported[{i}].name", f"'{name}' must be letters, digits, '-' or '_' (it names output files)")
        if name in first:  # imp-<name> would name both livers' files: the second dropped, the first trained twice
            _fail(f"geometry.imported[{i}].name", f"'{name}' is already the name of geometry.imported[{first[name]}] "
                  f"({g['imported'][first[name]]['path']})", "give each imported liver its own name (it names the "
                  f"liver's files, imp-{name}.*, and validate.imported refers to it)")
        first[name] = i
        _check_units(f"geometry.imported[{i}].units", imp["units"])
        _check_mesh_mode(f"geometry.imported[{i}]", imp)
        _check_frame(f"geometry.imported[{i}].frame", imp["frame"])
        _check_user_scene(f"geometry.imported[{i}]", imp)
    if g["cube"]["edge_mm"] <= 0:
        _fail("geometry.cube.edge_mm", "must be > 0 mm")

    m = cfg["mesh"]
    if not 100 <= m["target_nodes"] <= 200_000:
        _fail("mesh.target_nodes", f"must be in [100, 200000] (got {m['target_nodes']})")
    _check_choice("mesh.mesher", m["mesher"], MESHERS, "mesher")
    if m["refine_radius_mm"] < 0 or m["refine_edge_mm"] <= 0:
        _fail("mesh.refine_radius_mm", "refine radius must be >= 0 and refine_edge_mm > 0")
    if not m["refine_growth"] > 0:
        _fail("mesh.refine_growth", "must be > 0 (mm of size per mm of distance)")
    if m["refine_ivc_edge_mm"] < 0:
        _fail("mesh.refine_ivc_edge_mm", "must be >= 0 mm (0 = no refinement at the IVC)")
    _check_choice("mesh.regions_check", m["regions_check"], ("warn", "strict", "off"))

    mat = cfg["material"]
    _check_choice("material.model", mat["model"], material_models(), "material")
    if not 0.0 < mat["nu"] < 0.5:
        _fail("material.nu", f"Poisson ratio must be in (0, 0.5) (got {mat['nu']})")
    if mat["nu"] > NU_MAX:
        _fail("material.nu", f"Poisson ratio {mat['nu']} makes the bulk modulus {_k_over_mu(mat['nu']):.3g} times the "
              "shear modulus: the nearly incompressible solver spends its Newton budget there (at 0.4999999 three "
              "of four small cases failed, at 0.4999 they converged)",
              f"give at most {NU_MAX} (liver models use 0.45-0.499; 0.5, incompressible, is approached, not reached)")
    young = "E_pa" if mat.get("E_pa") is not None else "E_mpa" if mat.get("E_mpa") is not None else None
    _material_from_young(mat)
    if not mat["params_mpa"]:
        _fail("material.params_mpa", "no material constants given", "give params_mpa (MPa), or E_pa / E_mpa "
              "for a neo_hookean material")
    _check_material_scale(mat, f"material.{young}" if young else "material.params_mpa")
    if not 0.0 <= mat["vary_rel"] < 1.0:
        _fail("material.vary_rel", f"must be in [0, 1) (got {mat['vary_rel']})")
    lo_hi = mat["stability_stretch"]
    if len(lo_hi) != 2 or not 0 < lo_hi[0] < 1 < lo_hi[1]:
        _fail("material.stability_stretch", f"must be [lo, hi] with 0 < lo < 1 < hi (got {lo_hi})")
    _check_choice("material.on_unstable", mat["on_unstable"], ("refuse", "clip"))
    for i, imp in enumerate(g["imported"]):
        if imp.get("material") is not None:
            liver_material(imp["material"], mat, f"geometry.imported[{i}].material")

    b = cfg["boundary"]
    for k in ("ligament_total_n_per_mm", "visceral_total_n_per_mm", "tangential_ratio", "rib_normal_n_per_mm3"):
        if b[k] < 0:
            _fail(f"boundary.{k}", f"stiffness must be >= 0 (got {b[k]})")
    _check_choice("boundary.rib_contact", b["rib_contact"], ("bilateral", "unilateral"), "rib contact")
    grav = b["gravity"]
    if not 100 <= grav["density_kg_per_m3"] <= 5000:
        _fail("boundary.gravity.density_kg_per_m3", f"must be in [100, 5000] kg/m^3 (got {grav['density_kg_per_m3']})",
              "liver tissue is about 1060 kg/m^3; units are kg/m^3, not g/cm^3")
    d = grav["direction"]
    if len(d) != 3 or not sum(x * x for x in d) > 0:
        _fail("boundary.gravity.direction", f"must be a non-zero 3-vector (got {d})")

    s = cfg["sweep"]
    _check_choice("sweep.design", s["design"], sweep_designs(), "design")
    if s["cases_per_shard"] < 1:
        _fail("sweep.cases_per_shard", "must be >= 1")
    f = s["force"]
    if f["min_n"] < 0:
        _fail("sweep.force.min_n", f"force magnitude must be >= 0 N (got {f['min_n']})")
    if f["max_n"] <= f["min_n"]:
        _fail("sweep.force.max_n", f"must exceed sweep.force.min_n (got {f['max_n']} <= {f['min_n']})")
    if f["max_n"] > 50:
        _fail("sweep.force.max_n", f"{f['max_n']} N is far beyond surgical forces (0-5 N); units are newtons")
    if not 0 <= f["cone_deg"] < 90:
        _fail("sweep.force.cone_deg", f"must be in [0, 90) degrees (got {f['cone_deg']})")
    if s["exertion"]["n_points"] < 1:
        _fail("sweep.exertion.n_points", "must be >= 1")
    if s["exertion"]["min_spacing_mm"] < 0:
        _fail("sweep.exertion.min_spacing_mm", "must be >= 0 mm")
    if not s["scenarios"]:
        _fail("sweep.scenarios", "no scenario defined")
    for name, sc in s["scenarios"].items():
        key = f"sweep.scenarios.{name}"
        if name not in SCENARIOS:
            _fail(key, f"unknown scenario '{name}'", f"use {', '.join(SCENARIOS)}")
        if sc["n_cases"] < 1:
            _fail(f"{key}.n_cases", f"must be >= 1 (got {sc['n_cases']})")
        _check_choice(f"{key}.geometries", str(sc["geometries"]), ("1", "all"))
        _check_choice(f"{key}.exertion", sc["exertion"], ("fixed", "varies"))
        _check_choice(f"{key}.material", sc["material"], ("fixed", "varies"))

    sim = cfg["simulate"]
    _check_choice("simulate.formulation", sim["formulation"], formulations(), "formulation")
    if sim["tool_radius_mm"] <= 0:
        _fail("simulate.tool_radius_mm", "must be > 0 mm")
    if not 0 < sim["tol"] < 1:
        _fail("simulate.tol", "must be in (0, 1)")
    if sim["max_iter"] < 1 or sim["max_steps"] < 1:
        _fail("simulate.max_iter", "max_iter and max_steps must be >= 1")
    if sim["max_total_iter"] < sim["max_iter"]:
        _fail("simulate.max_total_iter", f"must be >= simulate.max_iter ({sim['max_iter']}): it is the case's "
              "budget of Newton iterations over all its load steps")
    if not 0 < sim["min_step"] <= sim["initial_step"] <= 1:
        _fail("simulate.initial_step", "need 0 < min_step <= initial_step <= 1")
    if sim["time_limit_s"] <= 0:
        _fail("simulate.time_limit_s", "must be > 0 s")
    _check_choice("simulate.linear_solver", sim["linear_solver"], linear_solvers(), "linear solver")
    _check_choice("simulate.tool_model", sim["tool_model"], tool_models(), "tool model")
    if sim["tool_tip_radius_mm"] <= 0:
        _fail("simulate.tool_tip_radius_mm", "must be > 0 mm")
    if sim["tool_penalty_n_per_mm3"] < 0:
        _fail("simulate.tool_penalty_n_per_mm3", "must be >= 0 N/mm^3 (0 = automatic)")
    if not 0 < sim["tool_force_rtol"] < 1:
        _fail("simulate.tool_force_rtol", "must be in (0, 1)")
    if sim["tool_force_atol_n"] <= 0:
        _fail("simulate.tool_force_atol_n", "must be > 0 N")
    _check_choice("simulate.tool_control", sim["tool_control"], ("magnitude", "vector"), "sphere control")
    if sim["tool_max_slide_mm"] <= 0:
        _fail("simulate.tool_max_slide_mm", "must be > 0 mm")
    if sim["tool_model"] == "sphere" and cfg["boundary"]["gravity"]["enabled"]:
        _fail("simulate.tool_model", "the sphere tool does not support gravity yet",
              "set boundary.gravity.enabled=false or simulate.tool_model=traction")

    d = cfg["dataset"]
    if not 0 < d["roi_fraction"] <= 1:
        _fail("dataset.roi_fraction", f"must be in (0, 1] (got {d['roi_fraction']})")
    names = [v.get("name") for v in cfg["train"]["variants"]] or ["default"]
    # main | auto | a name of train.variants
    _check_choice("validate.variant", cfg["validate"]["variant"], ["main", "auto", *names], "variant")
    _check_choice("validate.input", cfg["validate"]["input"], ["camera", "any"], "validation input")
    for k in cfg["validate"]["camera_sensitivity"]:
        _check_choice("validate.camera_sensitivity", k, ["n_points", "noise_sd_mm", "cone_half_angle_deg",
                                                        "tip_noise_mm", "instrument_in_cloud", "tool_tilt_deg",
                                                        "outlier_fraction"],
                      "camera setting")
    for f in cfg["validate"]["camera_sensitivity"].get("outlier_fraction") or []:
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 <= f <= 0.5:
            _fail("validate.camera_sensitivity.outlier_fraction",
                  f"each value is the share of the points at a gross depth error, in [0, 0.5] (got {f!r})",
                  "e.g. [0.0, 0.01, 0.03, 0.1] for 0, 1, 3 and 10 %")
    for e in cfg["validate"]["registration_errors"]:
        if (not isinstance(e, (list, tuple)) or len(e) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v for v in e)):
            _fail("validate.registration_errors",
                  f"each entry is a pair [shift_mm, turn_deg] of numbers >= 0 (got {e!r})",
                  "e.g. [[0, 0], [1, 0], [2, 2]]")
    for e in cfg["validate"]["shape_changes"]:
        if (not isinstance(e, (list, tuple)) or len(e) != 2
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in e)
                or not (e[0] >= 0 and e[1] > 0)):
            _fail("validate.shape_changes",
                  f"each entry is a pair [amplitude_mm >= 0, wavelength_mm > 0] (got {e!r})",
                  "e.g. [[2, 150], [5, 300]]")
    obs = cfg["model"]["camera"]["observation"]
    if obs.get("cone_axis") is None and float(obs.get("tool_radius_mm") or 0) > 0:
        # the shaft runs along the normal, the cone's axis: a camera within the tool's radius plus the clearance of
        # it would sit inside the instrument, so no pose of a narrower cone is ever valid
        reach = float(obs["tool_radius_mm"]) + float(obs.get("camera_tool_clearance_mm") or 0)
        far = float(max(obs["camera_distance_mm"]))
        for a in cfg["validate"]["camera_sensitivity"].get("cone_half_angle_deg") or []:
            if far * math.sin(math.radians(float(a))) <= reach:
                _fail("validate.camera_sensitivity.cone_half_angle_deg",
                      f"{a} deg puts every camera within {reach:g} mm of the tool's shaft (it runs along the "
                      f"normal; the camera is at most {far:g} mm away): no valid view exists",
                      f"use angles above {math.degrees(math.asin(min(1.0, reach / far))):.2g} deg")
    mf = cfg["model"]["roi_fraction"]
    if mf is not None:
        if not 0 < mf <= 1:
            _fail("model.roi_fraction", f"must be in (0, 1] or null (got {mf})")
        if not d["store_full_surface"]:
            _fail("model.roi_fraction", "re-selecting the ROI at training time needs the full surface in the shards",
                  "set dataset.store_full_surface=true, or change dataset.roi_fraction (re-simulates)")
    _check_choice("dataset.compression", d["compression"], ("zstd", "snappy", "gzip", "none"), "compression")

    mo = cfg["model"]
    _check_model(mo, "model")
    t = cfg["train"]
    for sc in t["scenarios"]:
        if sc not in s["scenarios"]:
            _fail("train.scenarios", f"scenario '{sc}' has no sweep (sweep.scenarios)", "add it or remove it")
    names = [v.get("name") for v in t["variants"]]
    if len(set(names)) != len(names) or not all(isinstance(n, str) and n for n in names):
        _fail("train.variants", f"every variant needs a unique name (got {names})")
    for v in t["variants"]:
        vname = v["name"]
        over = {k: val for k, val in v.items() if k != "name"}
        unknown = _unknown_keys(mo, over)
        if unknown:
            _fail(f"train.variants.{vname}", f"unknown model keys {unknown}")
        _check_model(variant_model(mo, v), f"train.variants.{vname}")
    if not 0 < t["test_fraction"] < 1:
        _fail("train.test_fraction", "must be in (0, 1)")
    if t["repeats"] < 1:
        _fail("train.repeats", "must be >= 1 (the number of seeded train/test splits per model)")
    if not 0.0 < t["interval"]["coverage"] < 1.0:
        _fail("train.interval.coverage", f"must be in (0, 1), got {t['interval']['coverage']}", "e.g. 0.9")
    if not 0.0 < t["interval"]["calibration_fraction"] < 1.0:
        _fail("train.interval.calibration_fraction",
              f"must be in (0, 1), got {t['interval']['calibration_fraction']}", "e.g. 0.2")
    if t["interval"]["folds"] < 1:
        _fail("train.interval.folds", f"must be >= 1 (got {t['interval']['folds']})", "e.g. 4 (1: one held-out split)")
    _check_choice("train.interval.scale", t["interval"]["scale"], interval_scales(), "interval scale")
    _check_choice("train.interval.widen", t["interval"]["widen"], interval_widenings(), "interval widening")
    spread = t["interval"].get("spread")
    if spread is not None and not (isinstance(spread, (int, float)) and not isinstance(spread, bool)
                                   and math.isfinite(spread) and spread > 0):
        _fail("train.interval.spread", f"must be a positive number or null, got {spread!r}",
              "e.g. 4 (the members' median sd x 4 added to each case's), or null for no spread")
    dq = t["interval"].get("distance_quantile")
    if dq is not None and not (isinstance(dq, (int, float)) and not isinstance(dq, bool) and 0.5 <= dq < 1.0):
        _fail("train.interval.distance_quantile", f"must be a quantile in [0.5, 1) or null, got {dq!r}",
              "e.g. 0.9 (a prediction farther from training than 90 % of the calibration cases warns)")
    if not isinstance(t["interval"].get("far_widths"), bool):
        _fail("train.interval.far_widths", f"must be true or false, got {t['interval'].get('far_widths')!r}")
    if t["interval"]["bins"] < 1:
        _fail("train.interval.bins", f"must be >= 1 (got {t['interval']['bins']})", "e.g. 4 (with scale: force_bins)")
    if t["heldout_points"]["folds"] < 2:
        _fail("train.heldout_points.folds", f"must be >= 2 (got {t['heldout_points']['folds']})")
    for sc in t["heldout_points"]["scenarios"]:
        _check_choice("train.heldout_points.scenarios", sc, ("I", "II", "III"), "scenario split by case")
    if t["epochs"] < 1 or t["batch_size"] < 1 or t["lr"] <= 0:
        _fail("train.epochs", "epochs, batch_size must be >= 1 and lr > 0")
    tu = cfg["tune"]
    if tu["trials"] < 1 or tu["folds"] < 2 or tu["epochs"] < 1:
        _fail("tune.folds", "need trials >= 1, folds >= 2, epochs >= 1")
    v = cfg["validate"]
    if v["n_cases"] < 1:
        _fail("validate.n_cases", "must be >= 1")
    n_unseen = v["livers"] + len(v["imported"])
    if v["livers"] < 0 or n_unseen < 1:
        _fail("validate.livers", f"needs at least one unseen liver (got validate.livers={v['livers']} and "
              f"{len(v['imported'])} imported livers held out)",
              "set validate.livers >= 1, or hold out an imported liver: validate.imported=[<its name>]")
    ph = v["physics"]
    if not 0 <= ph["liver"] < n_unseen:
        _fail("validate.physics.liver", f"must index an unseen liver, 0 .. {n_unseen - 1} (the {v['livers']} "
              f"procedural ones, then validate.imported) (got {ph['liver']})")
    if ph["n_cases"] < 1 or ph["n_cases"] > v["n_cases"]:
        _fail("validate.physics.n_cases", f"must be 1 .. validate.n_cases ({v['n_cases']}) (got {ph['n_cases']})")
    if any(not f > 0 for f in ph["foundation_scale"]) or any(r < 0 for r in ph["tangential_ratio"]):
        _fail("validate.physics.foundation_scale", "foundation scales must be > 0 and tangential ratios >= 0")
    for rib in ph["rib_contact"]:
        _check_choice("validate.physics.rib_contact", rib, ("unilateral", "bilateral", "off"), "rib model")
    for d in ph["gravity"]:
        if len(d) != 3 or not sum(float(x) ** 2 for x in d) > 0:
            _fail("validate.physics.gravity", f"each gravity direction is a non-zero 3-vector (got {d})")
    _check_choice("validate.physics.tool", ph["tool"], ("none", "sphere"), "tool model")
    if not 1 <= ph["tool_cases"] <= v["n_cases"]:
        _fail("validate.physics.tool_cases", f"must be 1 .. validate.n_cases ({v['n_cases']})")
    if not ph["tool_max_force_n"] > 0:
        _fail("validate.physics.tool_max_force_n", "must be > 0 N")
    from liverforce.seeds import liver_seeds

    for key, value in (("seed", cfg["seed"]), ("sweep.seed", s["seed"]), ("train.seed", t["seed"]),
                       ("geometry.procedural.seed", g["procedural"]["seed"]), ("validate.seed", v["seed"])):
        if value < 0:
            _fail(key, f"seeds are integers >= 0 (got {value})")
    train_seeds = liver_seeds(g["procedural"]["seed"], g["procedural"]["count"])
    shared = sorted(set(train_seeds) & set(liver_seeds(v["seed"], v["livers"])))
    if shared:
        _fail("validate.seed", f"seeds {shared} of the unseen livers are training livers' seeds",
              f"pick validate.seed outside [{train_seeds.start}, {train_seeds.stop}) minus validate.livers")
    _check_choice("report.format", cfg["report"]["format"], REPORT_FORMATS, "report format")
    if run:
        check_run(cfg)  # the run-level check (compose(run=False) leaves it out)
    _check_study(cfg)


def _check_model(mo: dict, key: str) -> None:
    _check_choice(f"{key}.encoder", mo["encoder"], encoders(), "encoder")
    if mo["code_size"] < 1 or mo["grid_size"] < 3:
        _fail(f"{key}.code_size", "code_size must be >= 1 and grid_size >= 3")
    if not 0 <= mo["dropout"] < 1:
        _fail(f"{key}.dropout", "must be in [0, 1)")
    occ = mo["occlusion"]
    if occ["radius_mm"] < 0:
        _fail(f"{key}.occlusion.radius_mm", f"must be >= 0 mm (got {occ['radius_mm']})")
    _check_choice(f"{key}.occlusion.mode", occ["mode"], occlusion_modes(), "occlusion mode")
    if mo["noise_mm"] < 0:
        _fail(f"{key}.noise_mm", "must be >= 0 mm")
    _check_choice(f"{key}.roi_features", mo["roi_features"], roi_features(), "ROI features")
    if mo["grid_half_width_mm"] < 0:
        _fail(f"{key}.grid_half_width_mm", "must be >= 0 mm (0 = fitted)")
    if mo["dae_input_noise"] < 0:
        _fail(f"{key}.dae_input_noise", "must be >= 0")
    _check_choice(f"{key}.force_scaling", mo["force_scaling"], force_scalings())
    _check_choice(f"{key}.regressor", mo["regressor"], ("gp", "mlp"))
    if mo["gp"]["max_points"] < 2 or mo["gp"]["iterations"] < 1:
        _fail(f"{key}.gp", f"max_points must be >= 2 and iterations >= 1 (got {mo['gp']['max_points']}, "
              f"{mo['gp']['iterations']})")
    try:
        _learn_names().gp_code_members(mo["gp"].get("code_members"))
    except ValueError as exc:
        _fail(f"{key}.gp.code_members", str(exc), "for example [8, 12, 16, 24, 32], or null for one GP")
    _check_choice(f"{key}.gp.kernel", mo["gp"]["kernel"], tuple(_learn_names().GP_KERNELS), "GP kernel")
    if mo["gp"]["shape"] is not None and not (math.isfinite(mo["gp"]["shape"]) and mo["gp"]["shape"] > 0):
        _fail(f"{key}.gp.shape",
              f"the rational quadratic's shape must be a finite number > 0 (got {mo['gp']['shape']})",
              "or null to fit it by the marginal likelihood")
    nf = mo["gp"]["noise_floor"]  # a variant's entries are not type-checked by the structured config: a string or
    # a bool (YAML's true, which float() would read as 1, the targets' whole variance) is refused here too
    if isinstance(nf, bool) or not isinstance(nf, (int, float)) or not (math.isfinite(nf) and nf >= 0):
        _fail(f"{key}.gp.noise_floor", f"must be a finite variance >= 0 (got {nf!r})",
              "0 leaves the noise variance to the marginal likelihood alone")
    if mo["gp"]["per_output"] and mo["gp"]["kernel"] == "rational_quadratic" and mo["gp"]["shape"] is None:
        _fail(f"{key}.gp.per_output", "one kernel per force component needs a fixed rational-quadratic shape "
              "(gp.shape null: fitted)", "set model.gp.shape to a number (2 is the default) or per_output false")
    _check_choice(f"{key}.rigid_motion", mo["rigid_motion"], ("keep", "remove"))
    _check_choice(f"{key}.interpolation", mo["interpolation"], ("surface", "points"))
    if mo["rigid_motion_radius_mm"] < 0:
        _fail(f"{key}.rigid_motion_radius_mm", f"must be >= 0 mm (got {mo['rigid_motion_radius_mm']})")
    if mo["rigid_motion"] == "remove" and mo["roi_features"] not in ("displacement", "both"):
        _fail(f"{key}.rigid_motion", f"remove needs node displacements (roi_features: displacement or both), "
              f"not '{mo['roi_features']}'", "set rigid_motion: keep for this model")
    cam = mo["camera"]
    if cam["views"] < 1:
        _fail(f"{key}.camera.views", f"must be >= 1 (got {cam['views']})")
    if cam["tip_noise_mm"] < 0:
        _fail(f"{key}.camera.tip_noise_mm", f"must be >= 0 mm (got {cam['tip_noise_mm']})")
    tn = cam.get("tip_noise_normal_mm")
    if tn is not None and not (isinstance(tn, (int, float)) and not isinstance(tn, bool) and math.isfinite(tn)
                               and tn >= 0):
        _fail(f"{key}.camera.tip_noise_normal_mm", f"must be null (isotropic) or >= 0 mm (got {tn})")
    from liverforce.learn.cloud_features import CloudGridSpec
    from liverforce.learn.observation import ObservationConfig

    try:
        ObservationConfig.from_dict({k: v for k, v in cam["observation"].items() if v is not None})
    except (TypeError, ValueError) as exc:
        _fail(f"{key}.camera.observation", str(exc))
    try:
        CloudGridSpec(grid_size=3, half_width_mm=1.0, **cam["grid"])
    except (TypeError, ValueError) as exc:
        _fail(f"{key}.camera.grid", str(exc))
    r_fit = float(cam["grid"].get("instrument_radius_mm") or 0.0)
    obs_cfg = ObservationConfig.from_dict({k: v for k, v in cam["observation"].items() if v is not None})
    if obs_cfg.instrument_in_cloud and obs_cfg.tool_radius_mm <= 0:
        _fail(f"{key}.camera.observation.instrument_in_cloud", "there is no instrument to see: tool_radius_mm is 0",
              "give the tool's radius, or set instrument_in_cloud: false")
    if r_fit > 0 and r_fit != obs_cfg.tool_radius_mm:
        _fail(f"{key}.camera.grid.instrument_radius_mm",
              f"the instrument fit's radius ({r_fit} mm) is not the observed tool's "
              f"(camera.observation.tool_radius_mm: {obs_cfg.tool_radius_mm} mm)", "give both the instrument's radius")
    if r_fit > 0 and not obs_cfg.instrument_in_cloud:
        _fail(f"{key}.camera.grid.instrument_radius_mm",
              "a model that fits the instrument must be trained on clouds that show it (its tip would otherwise be "
              "the kinematic one in training and the instrument's axis in surgery)",
              "set camera.observation.instrument_in_cloud: true, or instrument_radius_mm: 0")
    if float(cam["grid"].get("outlier_mm") or 0.0) > 0 and obs_cfg.instrument_in_cloud and r_fit <= 0:
        _fail(f"{key}.camera.grid.outlier_mm",
              "the clouds show the instrument and nothing removes its points: they would be dropped, and counted, "
              "as gross depth errors", "fit the instrument (grid.instrument_radius_mm: the tool's radius), or set "
              "outlier_mm: 0")
    if mo["roi_features"] == "cloud" and (mo["occlusion"]["radius_mm"] > 0 or mo["noise_mm"] > 0):
        _fail(f"{key}.roi_features", "a camera-cloud model (cloud) observes the surface with model.camera; "
              "model.occlusion.radius_mm and model.noise_mm apply to node features only", "set them to 0")


def _fmt_list(items) -> str:
    return "[" + ",".join(items) + "]"


def held_out(cfg: dict) -> list[str]:
    """The names of the imported livers held out of training (``validate.imported``): unseen livers, validated
    beside the procedural ones (an old config without the key: none)."""
    return [str(n) for n in (cfg["validate"].get("imported") or [])]


def _check_held_out(cfg: dict) -> None:
    """``validate.imported`` names imported livers, each once, and leaves at least one liver to train on."""
    g = cfg["geometry"]
    names = [imp["name"] for imp in g["imported"]]
    held = held_out(cfg)
    for i, name in enumerate(held):
        if name not in names:
            _fail(f"validate.imported[{i}]", f"'{name}' names no liver of geometry.imported "
                  f"({', '.join(names) if names else 'none is imported'})",
                  "give the name of an imported liver to hold it out of training as an unseen liver")
        if name in held[:i]:
            _fail(f"validate.imported[{i}]", f"'{name}' is listed twice", "list each held-out liver once")
    if g["procedural"]["count"] < 1 and not g["cube"]["enabled"] and len(held) == len(names):
        _fail("validate.imported", f"holds out every imported liver ({', '.join(names)}) and no procedural liver is "
              "left to train on (geometry.procedural.count=0)",
              "keep at least one imported liver for training, or set geometry.procedural.count >= 1")


def _check_grouped_livers(cfg: dict) -> None:
    """A scenario split by liver (IV, :data:`liverforce.learn.splits.GROUPED_SCENARIOS`) needs 2 training livers.

    Refused here, before any job: scenario IV's models are trained for ``train.scenarios`` and, whatever that
    lists, for the validation on the unseen livers, the physics study and the report (the default target), so
    with one liver the run simulated every scenario and then stopped at training IV.
    """
    from liverforce.learn.splits import GROUPED_SCENARIOS

    g, s, t = cfg["geometry"], cfg["sweep"], cfg["train"]
    held = held_out(cfg)
    training = [imp for imp in g["imported"] if imp["name"] not in held]  # the held-out ones are unseen livers
    n_proc, n_imp, cube = g["procedural"]["count"], len(training), bool(g["cube"]["enabled"])
    n_train = n_proc + n_imp + int(cube)
    for sc in GROUPED_SCENARIOS:
        spec = s["scenarios"].get(sc)
        if spec is None:
            continue
        key = f"sweep.scenarios.{sc}"
        if str(spec["geometries"]) != "all":
            if n_train >= 2:
                _fail(f"{key}.geometries", f"scenario {sc} splits its data by liver (no liver in both its training "
                      f"and test split), so it needs more than one liver (got geometries: {spec['geometries']})",
                      f"set {key}.geometries=all (its {n_train} training livers)")
            n_livers = 1
        else:
            n_livers = n_train
        if n_livers >= 2:
            continue
        have = [f"geometry.procedural.count={n_proc}",
                f"geometry.imported: {n_imp} liver{'s' * (n_imp != 1)}" + (" to train on" if held else "")
                + (f" ({', '.join('imp-' + imp['name'] for imp in training)})" if n_imp else "")
                + (f" and {len(held)} held out as unseen (validate.imported: {', '.join(held)})" if held else "")]
        if cube:
            have.append("geometry.cube.enabled=true")
        needed_by = ["the validation on the unseen livers (target validate)"]
        if cfg["validate"]["physics"]["enabled"]:
            needed_by.append("the physics study (validate.physics)")
        needed_by.append("the report (the default target: `snakemake` with no target)")
        if sc in t["scenarios"]:
            needed_by.insert(0, f"train.scenarios (which lists {sc})")
        more = max(1, 2 - n_imp - int(cube))
        fixes = [f"add a second liver: geometry.procedural.count={more}"
                 + (f" (beside the {n_imp} imported liver{'s' * (n_imp != 1)})" if n_imp else "")
                 + " or a second entry in geometry.imported"
                 + (f", and {key}.geometries=all" if str(spec["geometries"]) != "all" else "")]
        others = [x for x in t["scenarios"] if x not in GROUPED_SCENARIOS] or \
            [x for x in SCENARIOS if x not in GROUPED_SCENARIOS and x in s["scenarios"]]
        subset = f"train.scenarios={_fmt_list(others)} ~{key}"  # unquoted: Snakemake's --config keeps quotes
        st = cfg["study"]
        studies = [n for n in ("roi_fraction", "encoder", "state_vector", "occlusion", "noise", "train_size",
                               "train_livers") if st[n]["enabled"] and sc in st[n]["scenarios"]]
        if st["enabled"] and studies:
            subset += " study.enabled=false"
        fixes.append(f"or, to train {', '.join(others)} on this one liver only, leave {sc} out of the run with "
                     f"{subset}" + (f" (the studies {', '.join(studies)} use {sc})" if st["enabled"] and studies
                                    else "")
                     + f" and run the target models: `snakemake --cores 2 models --config overrides=\"... "
                     f"{subset}\"` (the default target, validate, physics and report need scenario {sc}: "
                     "they cannot run on one liver)")
        _fail(key, f"scenario {sc} splits its data by liver (no liver in both its training and test split), so "
              f"it needs at least 2 training livers, and this config gives it {n_livers} "
              f"({', '.join(have)}); scenario {sc}'s models are needed by {', '.join(needed_by[:-1])} and "
              f"{needed_by[-1]}, so the run would simulate every scenario and then stop at training {sc}",
              "; ".join(fixes))


def _check_study(cfg: dict) -> None:
    """Ranges of the ``study`` group; study scenarios need shards and (for tuned values) a main model."""
    st = cfg["study"]
    if st["epochs"] < 1:
        _fail("study.epochs", f"must be >= 1 (got {st['epochs']})")
    _check_choice("study.hyper_parameters", st["hyper_parameters"], ("main", "config"))
    if not st["enabled"]:
        return
    for name in ("roi_fraction", "encoder", "state_vector", "occlusion", "noise", "train_size", "train_livers"):
        sub = st[name]
        if not sub["enabled"]:
            continue
        for sc in sub["scenarios"]:
            if sc not in cfg["train"]["scenarios"]:
                _fail(f"study.{name}.scenarios", f"scenario '{sc}' is not trained (train.scenarios)",
                      "the study reuses the scenario's shards and main model; add it to train.scenarios")
    for f in st["roi_fraction"]["values"]:
        if not isinstance(f, (int, float)) or not 0 < f <= 1:
            _fail("study.roi_fraction.values", f"ROI fractions must be in (0, 1] (got {f})")
    if st["roi_fraction"]["enabled"] and st["roi_fraction"]["scenarios"] and st["roi_fraction"]["values"] \
            and not cfg["dataset"]["store_full_surface"]:
        _fail("study.roi_fraction", "needs the full surface in the shards",
              "set dataset.store_full_surface=true or study.roi_fraction.enabled=false")
    for f in st["train_size"]["values"]:
        if not isinstance(f, (int, float)) or not 0 < f <= 1:
            _fail("study.train_size.values", f"training-set fractions must be in (0, 1] (got {f})")
    for k in st["train_livers"]["values"]:
        if not isinstance(k, int) or isinstance(k, bool) or k < 1:
            _fail("study.train_livers.values", f"numbers of training livers must be integers >= 1 (got {k})")
    if st["train_livers"]["enabled"] and any(sc != "IV" for sc in st["train_livers"]["scenarios"]):
        _fail("study.train_livers.scenarios", "the livers learning curve applies to scenario IV only "
              "(I-III train on one liver)")
    for e in st["encoder"]["values"]:
        _check_choice("study.encoder.values", e, encoders(), "encoder")
    _check_choice("study.state_vector.encoder", st["state_vector"]["encoder"], encoders(), "encoder")
    occ = st["occlusion"]
    if any(r < 0 for r in occ["radii_mm"]):
        _fail("study.occlusion.radii_mm", f"radii must be >= 0 mm (got {occ['radii_mm']})")
    for e in occ["encoders"]:
        _check_choice("study.occlusion.encoders", e, encoders(), "encoder")
    for mode in occ["modes"]:
        _check_choice("study.occlusion.modes", mode, occlusion_modes(), "occlusion mode")
    for v in st["noise"]["values"]:
        if not isinstance(v, (int, float)) or v < 0 or v > 20:
            _fail("study.noise.values", f"noise must be in [0, 20] mm (got {v}); units are mm")


def _material_from_young(mat: dict) -> None:
    """``material.E_pa`` / ``E_mpa`` + ``nu`` → ``params_mpa`` (neo-Hookean), logged and kept in
    ``material.conversion``; the two keys are dropped when unset (the slice is then as before)."""
    import logging

    e_pa, e_mpa = mat.pop("E_pa", None), mat.pop("E_mpa", None)
    if e_pa is None and e_mpa is None:
        return
    if e_pa is not None and e_mpa is not None:  # compose settles a preset's against an override first
        _fail("material.E_pa", f"both E_pa {e_pa} and E_mpa {e_mpa} are given",
              f"give Young's modulus once: material.E_pa={e_pa} material.E_mpa=null, or material.E_pa=null "
              f"material.E_mpa={e_mpa}")
    key, value = ("material.E_pa", e_pa) if e_pa is not None else ("material.E_mpa", e_mpa)
    if mat["model"] != "neo_hookean":
        _fail(key, f"Young's modulus defines a neo_hookean material, not '{mat['model']}'",
              "set material.model=neo_hookean (e.g. material=neo_hookean_from_e), or give params_mpa")
    from liverforce.fem.materials import neo_hookean_from_young

    try:
        params, note = neo_hookean_from_young(value, mat["nu"], unit="Pa" if e_pa is not None else "MPa")
    except ValueError as exc:
        _fail(key, str(exc))
    given = mat["params_mpa"]
    if given and not (set(given) == {"C10"} and abs(float(given["C10"]) - params["C10"]) <= 1e-12 + 1e-9 * params["C10"]):
        _fail("material.params_mpa", f"{given} given beside {key.split('.')[1]} {value} (which gives {params})",
              "give Young's modulus or params_mpa, not both (material.params_mpa={} clears it)")
    mat["params_mpa"] = params
    if e_pa is not None:
        mat["E_pa"] = float(e_pa)
    else:
        mat["E_mpa"] = float(e_mpa)
    mat["conversion"] = note
    logging.getLogger("liverforce").info("material: %s", note)


#: largest Poisson ratio taken (bulk modulus 5000 times the shear modulus)
NU_MAX = 0.4999


def _k_over_mu(nu: float) -> float:
    return 2.0 * (1.0 + nu) / (3.0 * (1.0 - 2.0 * nu))


#: initial shear modulus (MPa) of any liver or liver phantom, and then some: 10 Pa (E about 30 Pa) to 1 MPa
#: (E about 3 MPa; livers are 1-50 kPa, silicone and PVA phantoms up to about 1 MPa)
MU0_PLAUSIBLE_MPA = (1e-5, 1.0)


#: the forms of ``geometry.imported[].material`` (one key each)
LIVER_MATERIAL_KEYS = ("E_pa", "E_mpa", "params_mpa", "scale")


def liver_material(spec: Any, mat: dict, key: str) -> tuple[dict[str, float], str]:
    """An imported liver's own constants (MPa) from ``geometry.imported[].material`` and the run's ``material``.

    ``spec`` is one of ``{E_pa: E}`` / ``{E_mpa: E}`` (a neo_hookean run; the run's ``nu``,
    :func:`liverforce.fem.materials.neo_hookean_from_young`), ``{params_mpa: {...}}`` (the run's model and
    constant names) or ``{scale: s}`` (the run's constants x ``s``). Returns ``(params_mpa, note)``, ``note``
    saying what was converted. Refuses (:class:`ConfigError` naming ``key``) another form, another model's
    constants, a non-positive scale, and constants no liver has (:func:`_check_material_scale`). ``mat`` is
    the run's resolved slice (``params_mpa`` set).
    """
    if not isinstance(spec, dict) or len(spec) != 1 or next(iter(spec)) not in LIVER_MATERIAL_KEYS:
        got = sorted(spec) if isinstance(spec, dict) else repr(spec)
        _fail(key, f"give one of {', '.join(LIVER_MATERIAL_KEYS)} (got {got})",
              f"e.g. {key}={{E_pa: 9000}} (a neo_hookean run), {{params_mpa: {{C10: 0.004}}}} or {{scale: 1.5}} "
              "(the run's constants x 1.5)")
    (form, value), = spec.items()
    run = {k: float(v) for k, v in mat["params_mpa"].items()}
    if form in ("E_pa", "E_mpa"):
        if mat["model"] != "neo_hookean":
            _fail(f"{key}.{form}", f"Young's modulus defines a neo_hookean material; this run's is "
                  f"'{mat['model']}'", f"give the liver's {mat['model']} constants: {key}.params_mpa={{...}} "
                  f"({', '.join(sorted(run))}), or {key}.scale")
        from liverforce.fem.materials import neo_hookean_from_young

        try:
            params, note = neo_hookean_from_young(float(value), mat["nu"], unit="Pa" if form == "E_pa" else "MPa")
        except (TypeError, ValueError) as exc:
            _fail(f"{key}.{form}", str(exc))
        _check_material_scale({"model": mat["model"], "params_mpa": params, form: float(value)}, f"material.{form}",
                              shown=f"{key}.{form}")
        return params, note
    if form == "scale":
        try:
            s = float("nan") if isinstance(value, bool) else float(value)
        except (TypeError, ValueError):
            s = float("nan")
        if not 0 < s < float("inf"):
            _fail(f"{key}.scale", f"must be a number > 0 (got {value!r})")
        params = {k: v * s for k, v in run.items()}
        _check_material_scale({"model": mat["model"], "params_mpa": params}, "material.params_mpa",
                              shown=f"{key}.scale")
        return params, f"the run's constants x {s:g}: " + ", ".join(f"{k} {v:.4g} MPa" for k, v in params.items())
    if not isinstance(value, dict) or set(value) != set(run):
        got = sorted(value) if isinstance(value, dict) else repr(value)
        _fail(f"{key}.params_mpa", f"must give the run's {mat['model']} constants {sorted(run)} (got {got})",
              "a liver's own material is the run's model with its own constants (material.model is one per run)")
    try:
        if any(isinstance(value[k], bool) for k in run):
            raise TypeError("true/false is no constant")
        params = {k: float(value[k]) for k in sorted(run)}
    except (TypeError, ValueError) as exc:
        _fail(f"{key}.params_mpa", f"constants must be numbers in MPa ({exc})")
    _check_material_scale({"model": mat["model"], "params_mpa": params}, "material.params_mpa",
                          shown=f"{key}.params_mpa")
    return params, ", ".join(f"{k} {v:.4g} MPa" for k, v in params.items()) + " (given)"


def _check_material_scale(mat: dict, key: str, shown: str | None = None) -> None:
    """Refuse constants whose initial shear modulus is no tissue's: Pa or kPa given as MPa (``E_mpa=14900``,
    ``params_mpa.C10=2500``) make a liver a million times too stiff, kPa given as Pa one a thousand times too
    soft, and both are stable, so nothing later would say it. Non-positive moduli are left to the stability
    check (which names them unstable); Ogden constants are not judged here."""
    from liverforce.fem.materials import _MODELS, _canonical

    try:
        mu0 = float(_MODELS[_canonical(mat["model"])].mu0(mat["params_mpa"]))
    except (KeyError, TypeError, ValueError):
        return  # a missing constant or an unknown model: refused with its own message elsewhere
    lo, hi = MU0_PLAUSIBLE_MPA
    if not mu0 > 0 or lo <= mu0 <= hi:
        return
    given = {k: v for k, v in mat.items() if k in ("E_pa", "E_mpa")} or mat["params_mpa"]
    if key in ("material.E_pa", "material.E_mpa"):
        name = key.split(".")[1]
        e = float(mat[name])
        e_pa = e if name == "E_pa" else e * 1e6  # what the value means as given, in Pa
        # the units under which the number is a plausible modulus (mu0 is proportional to E)
        reads = [(unit, e * pa) for unit, pa in (("Pa", 1.0), ("kPa", 1e3), ("MPa", 1e6))
                 if lo <= mu0 * e * pa / e_pa <= hi]
        typical = "about 5000-50000 Pa" if name == "E_pa" else "about 0.005-0.05 MPa"
        hint = f"{name} is in {'Pa' if name == 'E_pa' else 'MPa'}: a liver's E is {typical}"
        if reads:
            hint += "; " + " or ".join(f"if {e:g} is in {unit}, give E_pa={v:g} (E_mpa={v * 1e-6:g})"
                                       for unit, v in reads)
    elif mu0 > hi:
        hint = (f"params_mpa is in MPa, a liver's C10 about 0.001-0.01 MPa: if these constants are in Pa, divide them "
                f"by 1e6 (mu0 {mu0 * 1e-6:.3g} MPa), if in kPa by 1e3 (mu0 {mu0 * 1e-3:.3g} MPa)")
    else:  # too soft: no unit makes a plausible liver by a factor of 1e3 or 1e6 downwards
        hint = "params_mpa is in MPa, a liver's C10 about 0.001-0.01 MPa"
    _fail(shown or key, f"{given} gives an initial shear modulus mu0 = {mu0:.3g} MPa ({mu0 * 1e6:.3g} Pa), outside the "
               f"{lo:g}-{hi:g} MPa of any liver or liver phantom", hint)


def _check_mesh_mode(key: str, imp: dict) -> None:
    mode = imp.get("mesh", "auto")
    _check_choice(f"{key}.mesh", mode, ("auto", "as_given", "remesh"), "mesh mode")
    if mode == "as_given":
        from liverforce.geometry.volume_mesh import VOLUME_MESH_SUFFIXES

        if not str(imp["path"]).lower().endswith(VOLUME_MESH_SUFFIXES):
            _fail(f"{key}.mesh", f"as_given needs a tetrahedral mesh file ({', '.join(VOLUME_MESH_SUFFIXES)}), "
                                 f"got {imp['path']}", "use remesh (or auto) for surfaces and label volumes")
        if imp.get("label") is not None:
            _fail(f"{key}.label", "a label value is for label volumes, not a mesh taken as given")
    label = imp.get("label")
    if label is not None and (isinstance(label, bool) or not isinstance(label, (int, str)) or not str(label).strip()):
        _fail(f"{key}.label", f"got {label!r}", "give the liver's label value (an integer) or, for a 3D Slicer "
                                                "segmentation, a segment's name or ID")


def _check_frame(key: str, frame: Any) -> None:
    from liverforce.geometry.frames import frame_matrix

    try:
        frame_matrix(frame)
    except ValueError as exc:
        _fail(key, str(exc))


def _check_user_scene(key: str, imp: dict) -> None:
    """Syntax of an imported geometry's own supports and exertion points (files are read at the mesh stage)."""
    from liverforce.mesh.supports import (SupportError, check_point_file_units, coordinate_list, parse_supports,
                                          vertex_id_list)

    try:
        parse_supports(imp.get("supports"), where=f"{key}.supports")
    except SupportError as exc:
        _fail(str(exc).split(":")[0], str(exc).split(":", 1)[1].strip())
    ep = imp.get("exertion_points")
    if ep is None:
        return
    if isinstance(ep, (str, bytes)) or not hasattr(ep, "keys"):
        _fail(f"{key}.exertion_points", f"give a mapping, got {ep!r}", "e.g. {coordinates_mm: [[x, y, z], ...]}, "
              "{vertex_ids: [245, 184]} or {path: points.csv, units: m}")
    ep = dict(ep)
    keys = set(ep) - {"units", "frame"}
    if keys not in ({"coordinates_mm"}, {"vertex_ids"}, {"path"}):
        _fail(f"{key}.exertion_points", f"give one of coordinates_mm, vertex_ids or path, got {sorted(ep)}")
    if ep.get("frame") is not None:
        if "vertex_ids" in ep:
            _fail(f"{key}.exertion_points.frame", "vertex ids have no frame (they index the file's vertices)")
        _check_frame(f"{key}.exertion_points.frame", ep["frame"])
    if "path" in ep:
        from liverforce.mesh.supports import check_markups_spec, is_markups

        if is_markups(ep["path"]):
            try:
                check_markups_spec(ep, f"{key}.exertion_points")
            except SupportError as exc:
                _fail(f"{key}.exertion_points", str(exc).split(": ", 1)[1])
    try:
        if "coordinates_mm" in ep:
            coordinate_list(ep["coordinates_mm"], f"{key}.exertion_points.coordinates_mm")
        if "vertex_ids" in ep:
            vertex_id_list(ep["vertex_ids"], f"{key}.exertion_points.vertex_ids")
    except SupportError as exc:
        _fail(*str(exc).split(": ", 1))
    if ep.get("units") is not None:
        if "path" not in ep:  # coordinates_mm are mm; vertex ids have none (it was ignored)
            _fail(f"{key}.exertion_points.units", f"{next(iter(keys))} take no units (coordinates_mm are mm; vertex "
                  "ids index the file's vertices)", "units applies to a point file (path); drop it")
        try:
            check_point_file_units(ep["units"], f"{key}.exertion_points.units")
        except SupportError as exc:
            _fail(*str(exc).split(": ", 1))


def _check_units(key: str, units: str) -> None:
    if units in ("mm", "cm", "m", "auto"):
        return
    try:
        scale = float(units)
    except ValueError:
        _fail(key, f"unknown units '{units}'", "use mm, cm, m, auto or a number (scale to mm)")
    if not 0 < scale < float("inf"):  # nan and inf too: no scale to mm
        _fail(key, f"scale must be a number > 0 (got {units})")


# --------------------------------------------------------------------------
# helpers used by the workflow and the CLI
# --------------------------------------------------------------------------


def config_hash(obj: Any) -> str:
    """Short stable hash of a JSON-serialisable config slice (for run tags)."""
    blob = json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def results_root(cfg: dict) -> Path:
    """``<results_dir>/<experiment>`` as an absolute path."""
    base = Path(cfg["results_dir"])
    if not base.is_absolute():
        base = Path(os.getcwd()) / base
    return base / cfg["experiment"]


def tracking_uri(cfg: dict) -> str:
    """MLflow tracking URI: config value, else the embedded SQLite store."""
    if cfg["tracking"]["uri"]:
        return cfg["tracking"]["uri"]
    base = Path(cfg["results_dir"])
    if not base.is_absolute():
        base = Path(os.getcwd()) / base
    return f"sqlite:///{base / 'mlflow.db'}"
