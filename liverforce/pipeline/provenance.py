"""What a model was trained on: each training liver's origin and the material, read from the results layout.

The train stage (:func:`liverforce.pipeline.train.train_model`) reads these facts from files the earlier stages
wrote already, none of them a declared input of the train rule (a new input would re-train every existing
model after a pull; these files change only when the shards do):

- each liver's geometry record ``geometry/<gid>.json`` (:func:`liverforce.pipeline.geometry.make_geometry`):
  for an imported liver the source file, its SHA-256, the units and scale to mm, the frame as given and the
  conversion to RAS mm; for a procedural liver its generator, seed and shape parameters;
- the material as configured: the ``material`` slice in the scenario's case table metadata
  (``sweep/<scenario>/cases.parquet``, ``liverforce.sweep``), with Young's modulus as the user entered it
  (``E_pa`` or ``E_mpa``); without a case table, the shards' stiffness-probe reference (the configured model
  and constants in MPa, not how they were entered).

A record that is missing (a run made before, or shards outside a results layout) is recorded as unknown with
its reason; it never stops training. :mod:`liverforce.learn.provenance` words the record (one line per liver,
MLflow tags and params).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from liverforce.dataset import io as dio
from liverforce.layout import Layout, root_of_manifest, scenario_of_manifest

log = logging.getLogger("liverforce")

#: version of the record's layout (``meta["provenance"]["version"]``)
PROVENANCE_VERSION = 1


def training_provenance(manifest_path: str | Path, geometry_ids, shard_meta: dict | None = None) -> dict:
    """The provenance record of a model trained on the shards of ``manifest_path``.

    Parameters
    ----------
    manifest_path : str or Path
        ``<root>/shards/<scenario>/manifest.json`` of a results layout (:mod:`liverforce.layout`).
    geometry_ids : iterable of str
        The livers in the training data (each recorded once, in sorted order).
    shard_meta : dict, optional
        A shard's ``liverforce.*`` metadata (:func:`liverforce.dataset.io.read_metadata`): the material's
        fallback (``probe``) when the case table is missing.

    Returns
    -------
    dict
        ``version``, ``livers`` (one dict per geometry id, :func:`liver_record`) and ``material``
        (:func:`material_record`).
    """
    root, why = None, None
    try:
        root = root_of_manifest(manifest_path)
    except ValueError:
        why = (f"the shards' manifest ({Path(manifest_path).name}) lies outside a results layout's "
               "shards/<scenario>/ folder")
    paths = Layout(root) if root is not None else None
    livers = []
    for gid in sorted({str(g) for g in geometry_ids}):
        if paths is None:
            livers.append(_unknown(gid, f"no geometry record: {why}"))
        else:
            livers.append(liver_record(gid, paths.surface_meta(gid)))
    if paths is None:
        material = material_record(None, shard_meta, why)
    else:
        material = material_record(paths.cases(scenario_of_manifest(manifest_path)), shard_meta)
    if material.get("per_liver"):  # only the livers this model was fitted on
        material["per_liver"] = {g: m for g, m in material["per_liver"].items() if g in {str(x) for x in geometry_ids}}
        if not material["per_liver"]:
            del material["per_liver"]
    for rec in livers:
        if rec["kind"] == "unknown":
            log.warning("training liver %s: origin unknown (%s); recorded as unknown in the model", rec["geometry_id"],
                        rec["reason"])
    return {"version": PROVENANCE_VERSION, "livers": livers, "material": material}


def liver_record(gid: str, record_path: str | Path) -> dict:
    """Where one liver came from, from the geometry stage's record ``record_path`` (``geometry/<gid>.json``).

    ``kind`` is ``imported`` (``name``, ``file`` (its name: no folder leaves the lab), ``sha256`` of the file,
    ``format``,
    ``units`` (as read; ``units_declared``: as configured, e.g. ``auto``), ``scale_to_mm``, ``frame`` (as
    given: ``RAS``, ``LPS`` or ``matrix``), ``converted`` (the conversion to RAS mm in words), ``conversion``
    (the record's, matrices included), ``mesh_mode``, ``label`` / ``segment`` of a label volume),
    ``procedural`` (``generator``, ``seed``, ``params``), ``cube`` (``generator``, ``params``) or ``unknown``
    (``reason``: the record is missing or unreadable).
    """
    record_path = Path(record_path)
    shown = _shown(record_path, 2)  # geometry/<gid>.json: the lab's folders stay on its machine
    if not record_path.is_file():
        return _unknown(gid, f"no geometry record at {shown} (a run made before, or its geometry folder "
                             "removed)")
    try:
        rec = json.loads(record_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        return _unknown(gid, f"geometry record {shown} unreadable ({_error(exc, record_path, shown)})")
    if not isinstance(rec, dict):
        return _unknown(gid, f"geometry record {shown} is not a JSON object")
    spec = rec.get("spec") if isinstance(rec.get("spec"), dict) else {}
    kind = spec.get("kind") or {"procedural": "procedural", "cube_phantom": "cube"}.get(rec.get("source"))
    # the record by its place in the results layout, and an imported file by its name and hash: a model travels,
    # and the lab's folder names (a patient's name in them, say) stay on its machine
    out = {"geometry_id": gid, "kind": kind or "unknown", "record": f"{record_path.parent.name}/{record_path.name}"}
    if kind == "imported":
        source = rec.get("source")
        conversion = rec.get("conversion") or {}
        out.update(
            name=spec.get("name"), file=Path(source).name if source else None,
            sha256=rec.get("sha256"), format=rec.get("format"), units=rec.get("units"),
            units_declared=spec.get("units"), scale_to_mm=rec.get("scale_to_mm"), frame=rec.get("frame"),
            converted=conversion.get("summary"), conversion=conversion or None, mesh_mode=rec.get("mesh_mode"),
        )
        out.update({k: rec[k] for k in ("label", "segment") if rec.get(k) is not None})
    elif kind in ("procedural", "cube"):
        out.update({k: rec[k] for k in ("generator", "seed", "params") if k in rec})
    else:
        out["reason"] = f"geometry record {shown} names no known kind of liver"
    return out


def material_record(cases_path: str | Path | None, shard_meta: dict | None = None,
                    why_no_cases: str | None = None) -> dict:
    """The material as configured for the training cases.

    From the case table's metadata (``cases_path``: ``source: config``): ``model``, ``params_mpa``, ``nu``,
    ``vary_rel``, ``entered`` (``{"E_pa": ...}`` or ``{"E_mpa": ...}`` when Young's modulus was given, else
    None: the constants were given in MPa), ``conversion`` (the derivation in words) and, when imported livers
    bring their own material (``geometry.imported[].material``), ``per_liver``: geometry id -> ``params_mpa``,
    ``entered``. Without a readable
    case table, from the shards' stiffness-probe reference (``source: shards``; ``entered`` unknown), else
    ``source: unknown`` with the ``reason``.
    """
    reason = why_no_cases
    if cases_path is not None:
        cases_path = Path(cases_path)
        if cases_path.is_file():
            try:
                mat = (dio.read_metadata(cases_path).get("sweep") or {}).get("material")
            except Exception as exc:  # noqa: BLE001 - an unreadable table: the record says so, training goes on
                shown = _shown(cases_path, 3)
                mat, reason = None, f"case table {shown} unreadable ({_error(exc, cases_path, shown)})"
            else:
                reason = None if mat else f"case table {_shown(cases_path, 3)} records no material"
            if isinstance(mat, dict):
                entered = {k: mat[k] for k in ("E_pa", "E_mpa") if mat.get(k) is not None}
                out = {"source": "config", "model": mat.get("model"), "params_mpa": mat.get("params_mpa"),
                       "nu": mat.get("nu"), "vary_rel": mat.get("vary_rel"), "entered": entered or None,
                       "conversion": mat.get("conversion")}
                if mat.get("per_liver"):  # imported livers' own constants (geometry.imported[].material)
                    out["per_liver"] = {str(g): {k: m.get(k) for k in ("params_mpa", "entered")}
                                        for g, m in mat["per_liver"].items()}
                return out
        else:
            reason = f"no case table at {_shown(cases_path, 3)}"
    probe = (shard_meta or {}).get("probe")
    if isinstance(probe, dict) and probe.get("model"):
        return {"source": "shards", "model": probe["model"], "params_mpa": probe.get("params_mpa"),
                "bulk_mpa": probe.get("bulk_mpa"), "entered": "unknown",
                "note": f"{reason}: the shards' stiffness-probe reference (the configured constants in MPa); how "
                        "they were entered is not recorded"}
    return {"source": "unknown", "reason": reason or "no case table and no material in the shards' metadata"}


def _shown(path: Path, parts: int) -> str:
    """A file of the results layout by its last ``parts`` path components (``sweep/IV/cases.parquet``): a model
    travels, and a lab's folder names (a patient's name in them, say) stay on its machine."""
    return "/".join(Path(path).parts[-parts:])


def _error(exc: Exception, path: Path, shown: str) -> str:
    """An error in words without the file's full path (an OSError's message names it; a reader's may)."""
    if isinstance(exc, OSError) and exc.strerror:
        return f"{type(exc).__name__}: {exc.strerror}"
    return f"{type(exc).__name__}: {str(exc).replace(str(path), shown)}"


def _unknown(gid: str, reason: str) -> dict:
    return {"geometry_id": gid, "kind": "unknown", "reason": reason}
