"""The report's block per imported liver: what the lab's liver is and how it is held and pushed.

Read from the geometry stage's record (``geometry/<id>.json``: the source file, the declared units and frame,
the conversion applied, the config entry under ``spec``) and the mesh stage's features
(``mesh/<id>.features.json``: the facets each support holds, its own foundation stiffness under
``support_boundary``, a file of points' frame check (``frame_check``: its fit as read and mirrored, flagged with
what to state when it looks read in the other of RAS and LPS), the exertion points given and how far they were
snapped).
"""

from __future__ import annotations

import html
import json
from pathlib import Path

from liverforce.layout import surface_meta_of_mesh
from liverforce.mesh.supports import (FRAME_FIT_MARGIN_MM, FRAME_FIT_RATIO, SPHERE_OFF_SURFACE_MM,
                                      SPHERE_ON_SURFACE_MM)

#: how each support kind holds its facets (liverforce.mesh.supports)
KIND_TEXT = {"fixed": "clamped", "foundation": "elastic foundation", "sliding": "no normal motion, free sliding"}
SELECTORS = ("sphere", "box", "file", "group")


def geometry_record(features_path: str | Path) -> dict | None:
    """The geometry stage's record of the liver of ``mesh/<id>.features.json``: ``geometry/<id>.json`` of the
    same results directory, or None when there is none."""
    try:
        rec = surface_meta_of_mesh(features_path)  # a mesh folder's file -> its liver's geometry record
    except ValueError:  # not in a results layout's mesh/ folder
        return None
    if not rec.is_file():
        return None
    try:
        return json.loads(rec.read_text())
    except (OSError, ValueError):
        return None


def is_imported(g: dict) -> bool:
    """True for a liver whose geometry record says it was imported (``spec.kind: imported``)."""
    rec = g.get("geometry_record") or {}
    return (rec.get("spec") or {}).get("kind") == "imported"


def _name(path) -> str:
    return Path(str(path)).name


def _selector(s: dict) -> str:
    """A support's selector in words: ``file cava.csv`` or the sphere / box / group as given."""
    for key in SELECTORS:
        if key not in s:
            continue
        val = s[key]
        if key == "file" and isinstance(val, dict):
            extra = "".join(f", {k} {v}" for k, v in val.items() if k != "path")
            return f"file <code>{html.escape(_name(val.get('path', '?')))}</code>{html.escape(extra)}"
        if key == "file":
            return f"file <code>{html.escape(_name(val))}</code>"
        text = json.dumps(val, separators=(", ", ": ")) if isinstance(val, (dict, list)) else str(val)
        return f"{key} <code>{html.escape(text)}</code>"
    return "–"


def _g(v) -> str:
    return f"{float(v):.3g}"


def _stiffness(s: dict, own: dict) -> str:
    """A foundation's stiffness as given, and the springs it gives on this mesh (N/mm³)."""
    if s.get("kind") != "foundation":
        return "–"
    st = s.get("stiffness") or {}
    region = s.get("region", "ligament")
    given = []
    if "total_n_per_mm" in st:
        given.append(f"total {_g(st['total_n_per_mm'])} N/mm")
        if "tangential_ratio" in st:
            given.append(f"k<sub>t</sub>/k<sub>n</sub> {_g(st['tangential_ratio'])}")
    for k, label in (("normal_n_per_mm3", "k<sub>n</sub>"), ("tangential_n_per_mm3", "k<sub>t</sub>")):
        if k in st:
            given.append(f"{label} {_g(st[k])} N/mm³")
    kn, kt = own.get(f"{region}_kn"), own.get(f"{region}_kt")
    slot = f"{html.escape(str(region))} slot"
    got = (f"; on this mesh k<sub>n</sub> {_g(kn)}, k<sub>t</sub> {_g(kt)} N/mm³ ({slot})"
           if kn is not None and kt is not None else f" ({slot})")
    return (", ".join(given) or "as the built-in boundary") + got


def _supports_block(spec_supports, features: dict) -> str:
    if not spec_supports:
        return ("<p>Supports: none of its own; the built-in regions are tagged on it (vena cava patch fixed, "
                "ligament and visceral foundations, rib contact) with the <code>boundary</code> stiffnesses."
                "</p>")
    if isinstance(spec_supports, list):
        mode, items = "replace", spec_supports
    else:
        mode, items = spec_supports.get("mode", "replace"), spec_supports.get("list") or []
    held = {s.get("name"): s for s in features.get("supports") or []}
    own = features.get("support_boundary") or {}
    rows, checked = [], set()  # the kinds of frame check shown: "points" (a file's), "centre" (a sphere's)
    for i, s in enumerate(items):
        name = s.get("name") or f"support{i}"
        h = held.get(name) or {}
        snap = (h.get("snap_mm") or {}).get("max")
        fit, flag = _frame_fit(h.get("frame_check"), name)
        if fit:
            checked.add((h.get("frame_check") or {}).get("of", "points"))
        rows.append(f"<tr><td>{html.escape(str(name))}</td><td>{html.escape(str(s.get('kind', '?')))} "
                    f"<small>({html.escape(KIND_TEXT.get(s.get('kind'), ''))})</small></td><td>{_selector(s)}</td>"
                    f"<td>{h['n_facets'] if 'n_facets' in h else '–'}</td>"
                    f"<td>{h['n_mesh_facets'] if 'n_mesh_facets' in h else '–'}</td>"
                    f"<td>{'–' if snap is None else f'{float(snap):.3g}'}{fit}</td><td>{_stiffness(s, own)}</td></tr>"
                    + flag)
    how = ("replace: they replace the built-in regions (vena cava patch, ligament, visceral face, rib contact)"
           if mode == "replace" else "add: they lie over the built-in regions, which hold the rest of the surface")
    empty = ((features.get("provenance") or {}).get("empty_regions") or [])
    return (f"<p>Supports: its own, mode {html.escape(how)}"
            + (f"; built-in regions left empty: {html.escape(', '.join(map(str, empty)))}" if empty else "")
            + ". Its foundations use their own stiffness, not <code>boundary</code>'s.</p>"
            "<table class='supports'><thead><tr><th>support</th><th>kind</th><th>selector (file frame)</th>"
            "<th>facets held (input surface)</th><th>mesh facets (VTU <code>support</code>)</th>"
            "<th>max snap (mm)</th><th>stiffness</th></tr></thead><tbody>"
            + "".join(rows) + "</tbody></table>"
            + ("<p><small>" + " ".join(FRAME_FIT_NOTES[k] for k in ("points", "centre") if k in checked)
               + "</small></p>" if checked else ""))


#: under the supports table, per kind of frame check shown: a support's file of points, a sphere's centre
FRAME_FIT_NOTES = {
    "points": ("Frame check of a file of points (<code>frame_check</code> in the features JSON): under its max snap, "
               "the points' mean distance to the surface (mm) as read and mirrored in x and y (as if read in the "
               "other of RAS and LPS). Points marked on the liver's surface fit it within a fraction of a mm; a "
               f"mirrored fit clearly closer (at most {FRAME_FIT_RATIO:g} times as far and {FRAME_FIT_MARGIN_MM:g} "
               "mm closer) means the file was likely read in the wrong frame and the support put on the wrong side "
               "of the liver (⚠, with what to state)."),
    "centre": ("Frame check of a sphere (<code>frame_check</code>, of its centre): its centre's distance to the "
               "surface (mm) as read and mirrored in x and y. A centre picked on the liver's surface and read in "
               "the wrong frame lies on it only mirrored (flagged within "
               f"{SPHERE_ON_SURFACE_MM:g} mm mirrored and {SPHERE_OFF_SURFACE_MM:g} mm or more off it as read, ⚠); a "
               "centre off the surface (the middle of a vessel) tells nothing."),
}


def _frame_fit(check: dict | None, name) -> tuple[str, str]:
    """A support's frame check (``frame_check``, :func:`liverforce.mesh.supports.check_support_frame`) for the
    supports table:
    its fits as read and mirrored (mean mm) under the max snap, and, when the file looks read in the wrong
    frame, a flag there and a row under the support's with the warning's advice; for a sphere
    (:func:`liverforce.mesh.supports.check_sphere_frame`, ``of: centre``) its centre's distance as read and
    mirrored; ``("", "")`` unchecked (a box, group or vertex ids; ``mesh.regions_check: off``)."""
    if not check:
        return "", ""
    g, m = (check.get(k) or {} for k in ("as_given_mm", "mirrored_mm"))
    if g.get("mean") is None or m.get("mean") is None:
        return "", ""
    centre = check.get("of") == "centre"  # a sphere's centre: one distance, not a mean over points
    fit = f"<br><small>{'centre' if centre else 'mean'} {_g(g['mean'])} as read, {_g(m['mean'])} mirrored</small>"
    if not check.get("likely_mix_up"):
        return fit, ""
    advice = str(check.get("advice") or check.get("warning") or "check the file's frame").rstrip(".")
    read_in = str(check.get("read_in", "?"))
    read_in = read_in if read_in in ("RAS", "LPS") else f"{read_in} frame"  # a 4x4, the markups file's own
    flag = (f"<tr class='frame-flag'><td colspan='7'><b class='flag'>⚠ {html.escape(str(name))}: likely read in "
            f"the wrong frame</b> (read in {html.escape(read_in)}; mirrored, "
            + (f"its centre lies {_g(m['mean'])} mm from the surface, {_g(g['mean'])} as read" if centre else
               f"its points fit the surface {_g(m['mean'])} mm on average, {_g(g['mean'])} as read")
            + f"). {html.escape(advice)}.</td></tr>")
    return fit + " <b class='flag'>⚠ frame</b>", flag


def _exertion_text(spec_points, features: dict, n_sampled) -> str:
    snaps = features.get("exertion_snap_mm") or []
    n = len(features.get("exertion_candidates_mm") or snaps)
    if not features.get("exertion_given"):
        return (f"<p>Exertion points: none of its own; {n or n_sampled} sampled on its visible surface "
                "(<code>sweep.exertion.n_points</code>).</p>")
    src = ""
    if isinstance(spec_points, dict):
        if "path" in spec_points:
            src = f" from <code>{html.escape(_name(spec_points['path']))}</code>"
        elif "coordinates_mm" in spec_points:
            src = " as coordinates in its config entry"
        elif "vertex_ids" in spec_points:
            src = " as vertex ids of its file"
    off = features.get("exertion_not_visible") or []
    text = (f"<p>Exertion points: <b>{n} given by the lab</b>{src} (used instead of "
            "<code>sweep.exertion.n_points</code> for this liver)")
    if snaps:
        text += f"; each snapped to its closest surface point, at most {max(snaps):.3g} mm away"
    if off:
        text += f"; {len(off)} not on the visible area"
    return text + ".</p>"


def imported_block(g: dict, n_sampled=None) -> str:
    """The block of one imported liver ``g`` (a ``data["geometries"]`` entry with its ``geometry_record``)."""
    rec = g.get("geometry_record") or {}
    spec = rec.get("spec") or {}
    conv = rec.get("conversion") or {}
    units, frame = spec.get("units", rec.get("units")), spec.get("frame", rec.get("frame"))
    frame_text = frame if isinstance(frame, str) else "a 4×4 matrix to RAS"
    src = rec.get("source") or spec.get("path") or "?"
    parts = [f"<div class='imported' id='imported-{html.escape(g['id'])}'>",
             f"<h4><code>{html.escape(g['id'])}</code>: the lab's liver <code>{html.escape(str(spec.get('name')))}"
             f"</code></h4>",
             f"<p>Source file <code>{html.escape(_name(src))}</code>"
             + (f" ({html.escape(str(rec['format']))})" if rec.get("format") else "")
             + (f", sha256 <code>{html.escape(str(rec['sha256'])[:12])}…</code>" if rec.get("sha256") else "")
             + (f", label {html.escape(str(spec['label']))}" if spec.get("label") is not None else "")
             + f". Declared units <b>{html.escape(str(units))}</b>, frame <b>{html.escape(str(frame_text))}</b>; "
             f"conversion applied: {html.escape(str(conv.get('summary') or 'none recorded'))}"
             + (f"; repairs: {html.escape('; '.join(map(str, rec['repairs'])))}" if rec.get("repairs") else "")
             + (f"; mesh {html.escape(str(rec['mesh_mode']))}" if rec.get("mesh_mode") else "") + ".</p>",
             _supports_block(spec.get("supports"), g),
             _exertion_text(spec.get("exertion_points"), g, n_sampled), "</div>"]
    return "".join(parts)


def imported_section(geometries: list[dict], n_sampled=None) -> str:
    """Every imported liver's block under one heading, or ``""`` when no liver is imported."""
    livers = [g for g in geometries if is_imported(g)]
    if not livers:
        return ""
    return ("<h3 id='imported'>Imported livers</h3><p>Livers a lab brought (<code>geometry.imported</code>): "
            "where each comes from, how it was converted to RAS millimetres, and the supports and exertion "
            "points it gives itself.</p>" + "".join(imported_block(g, n_sampled) for g in livers))


def given_points(geometries: list[dict]) -> dict[str, int]:
    """Per liver that gives its own exertion points: how many."""
    return {g["id"]: len(g.get("exertion_candidates_mm") or g.get("exertion_snap_mm") or [])
            for g in geometries if g.get("exertion_given")}
