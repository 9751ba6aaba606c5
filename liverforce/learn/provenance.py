"""A model's training provenance in words: one line per liver, and the MLflow tags and params of its run.

The record (``ForceModel.meta["provenance"]``, the run's artifact ``training_provenance.json``) is assembled
by the train stage from the results layout (:func:`liverforce.pipeline.provenance.training_provenance`):
``livers``, one dict per geometry id (``kind`` imported, procedural, cube or unknown), and the ``material``
as configured. A model trained before liverforce recorded it has none (:func:`provenance_lines` says so).
"""

from __future__ import annotations

#: the run's artifact holding the whole record
ARTIFACT = "training_provenance.json"
#: longest tag or param value written (MLflow takes 8000 characters per tag value, 6000 per param value)
MAX_VALUE_CHARS = 5000


def _num(v) -> str:
    try:
        return f"{float(v):.12g}"
    except (TypeError, ValueError):
        return str(v)


def units_and_frame(rec: dict) -> tuple[str, str]:
    """``(units, frame)`` of a liver's source file as given: an imported file's, ``("mm", "RAS")`` for a liver
    the pipeline generated, ``("unknown", "unknown")`` for a liver without a record."""
    if rec.get("kind") == "imported":
        return str(rec.get("units") or "unknown"), str(rec.get("frame") or "unknown")
    if rec.get("kind") in ("procedural", "cube"):
        return "mm", "RAS"
    return "unknown", "unknown"


def liver_line(rec: dict) -> str:
    """One line saying where a training liver came from (a record of ``provenance["livers"]``)."""
    gid, kind = rec.get("geometry_id", "?"), rec.get("kind")
    if kind == "imported":
        sha = str(rec.get("sha256") or "unknown")[:12]
        units, frame = units_and_frame(rec)
        declared = rec.get("units_declared")
        guessed = f", declared {declared}" if declared is not None and str(declared) != units else ""
        scale = rec.get("scale_to_mm")
        return (f"{gid}: imported {rec.get('file') or 'file unknown'} (sha256 {sha}), units {units} "
                f"({'scale unknown' if scale is None else f'x{_num(scale)}'} to mm{guessed}), frame {frame}"
                + ("" if frame == "RAS" else " -> RAS"))
    if kind == "procedural":
        return f"{gid}: procedural ({rec.get('generator', 'generator unknown')}, seed {rec.get('seed', '?')})"
    if kind == "cube":
        edge = (rec.get("params") or {}).get("edge_mm")
        return f"{gid}: cube phantom (edge {_num(edge)} mm)"
    return f"{gid}: origin unknown ({rec.get('reason', 'no record')})"


def material_line(mat: dict | None) -> str:
    """One line: the material as configured, in MPa, and as the user entered it."""
    mat = mat or {}
    if mat.get("source") not in ("config", "shards"):
        return f"material: unknown ({mat.get('reason', 'not recorded')})"
    params = ", ".join(f"{k} {_num(v)}" for k, v in (mat.get("params_mpa") or {}).items())
    line = f"material: {mat.get('model')} {params} MPa"
    if mat.get("nu") is not None:
        line += f", nu {_num(mat['nu'])}"
    entered = mat.get("entered")
    if isinstance(entered, dict):
        line += " (entered as " + ", ".join(f"{k} {_num(v)}" for k, v in entered.items()) + ")"
    elif entered == "unknown":
        line += " (how it was entered is not recorded)"
    return line


def provenance_lines(prov: dict | None) -> list[str]:
    """One line per training liver, then the material's (:meth:`liverforce.serve.predictor.Predictor.describe`)."""
    if not prov:
        return ["unknown: the model records no training livers (trained before liverforce recorded them, or "
                "outside the pipeline)"]
    line = material_line(prov.get("material"))
    if run_material_unused(prov):
        line = line.replace("material: ", "material: not used (every training liver has its own, below); the run's ",
                            1)
    return [liver_line(r) for r in prov.get("livers") or []] + [line] + own_material_lines(prov.get("material"))


def run_material_unused(prov: dict | None) -> bool:
    """Whether every training liver of the record has its own material (``per_liver``), so that no training case
    took the run's constants."""
    livers = [r.get("geometry_id") for r in (prov or {}).get("livers") or []]
    own = ((prov or {}).get("material") or {}).get("per_liver") or {}
    return bool(livers) and all(g in own for g in livers)


def own_material_lines(mat: dict | None) -> list[str]:
    """One line per training liver with its own material (``geometry.imported[].material``): its constants in
    MPa, the centre of its cases' constants in place of the run's, and as the lab entered them."""
    lines = []
    for gid, own in sorted(((mat or {}).get("per_liver") or {}).items()):
        params = ", ".join(f"{k} {_num(v)}" for k, v in (own.get("params_mpa") or {}).items())
        entered = own.get("entered")
        shown = (" (entered as " + ", ".join(
            f"{k} " + (", ".join(f"{n} {_num(x)}" for n, x in v.items()) if isinstance(v, dict) else _num(v))
            for k, v in entered.items()) + ")" if isinstance(entered, dict) else "")
        lines.append(f"material of {gid}: its own, {params} MPa{shown}")
    return lines


def _clip(text: str) -> str:
    if len(text) <= MAX_VALUE_CHARS:
        return text
    tail = f" ... (clipped: the run's {ARTIFACT} has all)"
    return text[: MAX_VALUE_CHARS - len(tail)] + tail


def _distinct(values) -> str:
    return ", ".join(sorted(set(values)))


def provenance_tags(prov: dict | None) -> dict[str, str]:
    """Searchable run tags: ``training.livers`` (geometry ids), ``training.kinds``, ``training.units``,
    ``training.frames`` (as given, distinct values) and, with imported livers, ``training.files`` and
    ``training.sha256`` (``<file>:<first 12 hex digits>``). Empty without a record."""
    if not prov:
        return {}
    livers = prov.get("livers") or []
    tags = {
        "training.livers": ", ".join(str(r.get("geometry_id")) for r in livers),
        "training.kinds": _distinct(str(r.get("kind")) for r in livers),
        "training.units": _distinct(units_and_frame(r)[0] for r in livers),
        "training.frames": _distinct(units_and_frame(r)[1] for r in livers),
    }
    imported = [r for r in livers if r.get("kind") == "imported"]
    if imported:
        tags["training.files"] = ", ".join(str(r.get("file")) for r in imported)
        tags["training.sha256"] = ", ".join(f"{r.get('file')}:{str(r.get('sha256') or 'unknown')[:12]}"
                                            for r in imported)
    return {k: _clip(v) for k, v in tags.items()}


def provenance_params(prov: dict | None) -> dict[str, str]:
    """Run params of the material as configured: ``material.source`` (config, shards or unknown),
    ``material.model``, ``material.params_mpa.<name>``, ``material.nu`` and what the user entered
    (``material.E_pa`` or ``material.E_mpa``); the run's constants are left out, and ``material.run_constants``
    is ``unused``, when every training liver has its own; each liver's own constants as
    ``material.<gid>.params_mpa.<name>``. Empty without a record."""
    if not prov:
        return {}
    mat = prov.get("material") or {}
    out = {"material.source": str(mat.get("source", "unknown"))}
    if mat.get("model") is not None:
        out["material.model"] = str(mat["model"])
    if run_material_unused(prov):  # no training case took the run's constants: a search by them must not find it
        out["material.run_constants"] = "unused"
    else:
        out.update({f"material.params_mpa.{k}": _num(v) for k, v in (mat.get("params_mpa") or {}).items()})
        entered = mat.get("entered")
        if isinstance(entered, dict):
            out.update({f"material.{k}": _num(v) for k, v in entered.items()})
    if mat.get("nu") is not None:
        out["material.nu"] = _num(mat["nu"])
    for gid, own in sorted((mat.get("per_liver") or {}).items()):  # a liver's own constants
        out.update({f"material.{gid}.params_mpa.{k}": _num(v) for k, v in (own.get("params_mpa") or {}).items()})
    return {k: _clip(v) for k, v in out.items()}
