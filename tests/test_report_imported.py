"""The report says what a lab's imported liver is: its file, the conversion, its own supports and exertion points;
a run with no imported liver has no such block and the same sentences as before."""

import json
import re
from html import unescape

import test_report
from test_report import _write

stage_outputs = test_report.stage_outputs  # the hand-made stage outputs (fixture)

SETUP = {"main_variant": "pca_sv", "validate": {"material_scale": 1.4, "livers": 3, "n_cases": 4},
         "boundary": {"ligament_total_n_per_mm": 56.3, "visceral_total_n_per_mm": 42.6, "tangential_ratio": 1.0},
         "sweep": {"design": "sobol", "force": {"min_n": 0.0, "max_n": 5.0, "cone_deg": 30.0},
                   "exertion": {"n_points": 8, "min_spacing_mm": 15.0},
                   "scenarios": {"II": {"n_cases": 200, "geometries": 1, "exertion": "varies", "material": "fixed"}}},
         "dataset": {"roi_fraction": 0.18}, "mesh": {"target_nodes": 400},
         "population": {"training": ["imp-lab01", "proc-0000"], "unseen": ["val-1000", "val-1001", "val-1002"]}}

SPEC = {"kind": "imported", "name": "lab01", "path": "/data/lab/lab_liver_lps_m.stl", "units": "m", "frame": "LPS",
        "label": None, "mesh": "auto", "exertion_points": {"path": "/data/lab/tools_lps_m.csv"},
        "supports": {"mode": "replace", "list": [
            {"name": "cava", "kind": "fixed", "file": {"path": "/data/lab/cava_lps_m.csv"}},
            {"name": "diaphragm", "kind": "foundation", "region": "ligament",
             "file": {"path": "/data/lab/ligament_lps_m.csv"},
             "stiffness": {"total_n_per_mm": 56.3, "tangential_ratio": 1.0}},
            {"name": "floor", "kind": "foundation", "region": "visceral",
             "sphere": {"center_mm": [0.0, 0.01, -0.1], "radius_mm": 30.0},
             "stiffness": {"normal_n_per_mm3": 0.002}}]}}
CONVERSION = {"units": "m", "frame": "LPS", "scale_to_mm": 1000.0, "rigid": True, "winding_reversed": False,
              "summary": "units m (x1000 to mm); frame LPS: x and y negated to RAS (a 180 degree rotation about "
                         "the superior axis; winding kept)"}
FEATURES = {"volume_mm3": 1.45e6, "extent_mm": [234.0, 165.0, 109.0], "n_nodes": 380, "n_tets": 1169,
            "exertion_given": True, "exertion_candidates_mm": [[-49.0, 79.0, -157.0], [-13.2, 98.0, -165.4],
                                                               [-23.6, 85.5, -148.7]],
            "exertion_snap_mm": [1.05e-05, 0.000289, 0.000166],
            "supports": [{"name": "cava", "kind": "fixed", "selector": "file", "n_facets": 164, "n_mesh_facets": 31,
                          "snap_mm": {"max": 0.000627, "mean": 0.0002, "n_points": 94}},
                         {"name": "diaphragm", "kind": "foundation", "selector": "file", "n_facets": 2840,
                          "snap_mm": {"max": 0.00075, "mean": 0.0002, "n_points": 1471}},
                         {"name": "floor", "kind": "foundation", "selector": "sphere", "n_facets": 12815}],
            "support_boundary": {"ligament_kn": 0.0092984, "ligament_kt": 0.0092984, "visceral_kn": 0.002,
                                 "visceral_kt": 0.002},
            "provenance": {"empty_regions": ["rib"]}}


def _report(out, setup=SETUP):
    from liverforce.report.html import collect, write_report

    data = collect(out["metrics"], [out["manifest"]], out["validation"], out["features"], out["studies"])
    return write_report(data, [], "x", out["root"] / "report" / "index.html", setup=setup).read_text()


def _plain(html: str) -> str:
    """The text of ``html``: table cells apart by a space, other tags dropped."""
    return re.sub(r"\s+", " ", re.sub(r"<[^>]+>", "", re.sub(r"</t[dh]>", " ", html)))


def _with_lab_liver(out):
    root = out["root"]
    _write(root / "geometry" / "imp-lab01.json", {"source": SPEC["path"], "format": "trimesh-stl", "units": "m",
                                                   "frame": "LPS", "spec": SPEC, "conversion": CONVERSION,
                                                   "repairs": [], "mesh_mode": "remesh", "sha256": "58e254d015e4ab"})
    _write(root / "geometry" / "proc-0000.json", {"source": "procedural", "spec": {"kind": "procedural", "seed": 0}})
    out["features"] = [_write(root / "mesh" / "imp-lab01.features.json", FEATURES), *out["features"]]
    return out


def test_an_imported_liver_gets_its_file_conversion_supports_and_points(stage_outputs):
    html = _report(_with_lab_liver(stage_outputs))
    assert html.count("<div class='imported'") == 1  # the procedural liver (with a record too) gets none
    block = html[html.index("<div class='imported'"):]
    block = _plain(block[:block.index("</div>")])
    assert "imp-lab01: the lab's liver lab01" in block
    assert "Source file lab_liver_lps_m.stl (trimesh-stl)" in block and "/data/lab" not in block
    assert ("Declared units m, frame LPS; conversion applied: units m (x1000 to mm); frame LPS: x and y negated "
            "to RAS") in block
    assert "Supports: its own, mode replace: they replace the built-in regions" in block
    assert "built-in regions left empty: rib" in block
    # one row per support: name, kind, selector (file basename or the sphere as given), facets held on the input
    # surface and on the mesh (the VTU's support array; a features JSON written before has none: –), stiffness
    assert "cava fixed (clamped) file cava_lps_m.csv 164 31 0.000627 –" in block
    assert ("diaphragm foundation (elastic foundation) file ligament_lps_m.csv 2840 – 0.00075 total 56.3 N/mm, "
            "kt/kn 1; on this mesh kn 0.0093, kt 0.0093 N/mm³ (ligament slot)") in block
    assert 'floor foundation (elastic foundation) sphere {"center_mm": [0.0, 0.01, -0.1], "radius_mm": 30.0}' \
        in block.replace("&quot;", '"')
    assert "kn 0.002 N/mm³; on this mesh kn 0.002, kt 0.002 N/mm³ (visceral slot)" in block
    assert ("Exertion points: 3 given by the lab from tools_lps_m.csv (used instead of sweep.exertion.n_points "
            "for this liver); each snapped to its closest surface point, at most 0.000289 mm away.") in block
    text = _plain(html)
    # the sweep sentence counts the lab's points for its liver, the sampled count for the others
    assert ("8 candidate exertion points per sampled liver (sweep.exertion.n_points); livers with their own: "
            "imp-lab01: 3 given by the lab;") in text
    # the boundary line is the built-in regions', and says which liver holds itself
    assert ("Boundary (the built-in regions): ligament_total_n_per_mm = 56.3, visceral_total_n_per_mm = 42.6, "
            "tangential_ratio = 1; imp-lab01 held by its own supports (see Imported livers)") in text


def test_the_default_report_has_no_imported_block(stage_outputs):
    html = _report(stage_outputs)
    assert "class='imported'" not in html and "Imported livers" not in html
    text = _plain(html)
    assert "8 candidate exertion points per liver; sobol design." in text
    assert ("Boundary: ligament_total_n_per_mm = 56.3, visceral_total_n_per_mm = 42.6, tangential_ratio = 1"
            in text) and "the built-in regions" not in text


def test_a_lab_liver_without_its_own_supports_or_points_says_so(stage_outputs):
    out = _with_lab_liver(stage_outputs)
    rec = json.loads((out["root"] / "geometry" / "imp-lab01.json").read_text())
    rec["spec"] = {**SPEC, "supports": None, "exertion_points": None, "units": "mm", "frame": "RAS"}
    (out["root"] / "geometry" / "imp-lab01.json").write_text(json.dumps(rec))
    feats = {**FEATURES, "exertion_given": False, "exertion_snap_mm": None, "supports": None, "support_boundary": {},
             "exertion_candidates_mm": [[0.0, 0.0, 0.0]] * 8}
    out["features"][0].write_text(json.dumps(feats))
    text = _plain(_report(out))
    assert "Supports: none of its own; the built-in regions are tagged on it" in text
    assert "Exertion points: none of its own; 8 sampled on its visible surface" in text
    assert "8 candidate exertion points per liver;" in text and "Boundary: ligament" in text


#: the frame check of a support's file of points (liverforce.mesh.supports), as the features JSON records it
WRONG_FRAME = {"read_in": "RAS", "as_given_mm": {"mean": 2.91, "max": 4.62},
               "mirrored_mm": {"mean": 0.213, "max": 0.74}, "likely_mix_up": True, "refused_under_strict": True,
               "warning": "support 'cava' (/data/lab/cava_lps_m.csv) looks read in the wrong frame: ...",
               "advice": "The file states no frame, so its points are read in the geometry's: if the file is in LPS, "
                         "state geometry.imported[lab01].supports.list[0].file.frame: LPS (changing "
                         "geometry.imported[].frame would turn the liver and these points alike)"}
RIGHT_FRAME = {"read_in": "LPS", "as_given_mm": {"mean": 0.000201, "max": 0.00075},
               "mirrored_mm": {"mean": 3.4, "max": 9.8}, "likely_mix_up": False, "refused_under_strict": False,
               "warning": None, "advice": None}


def _supports_rows(html: str) -> str:
    block = html[html.index("<div class='imported'"):]
    return block[block.index("<table class='supports'"):block.index("<p>Exertion points")]


def test_the_supports_table_shows_the_frame_check_and_flags_a_likely_mix_up(stage_outputs):
    """A support given by a file of points shows its fit as read and mirrored (mean mm) under its max snap; one that
    looks read in the wrong frame is flagged there, with a row under it giving the advice (what to state), never the
    lab's full path; a support with no check (the sphere) shows what it showed before."""
    out = _with_lab_liver(stage_outputs)
    before = unescape(_plain(_supports_rows(_report(out))))
    feats = json.loads(out["features"][0].read_text())
    feats["supports"][0].update(frame_check=WRONG_FRAME, snap_mm={"max": 4.62, "mean": 2.91, "n_points": 94})
    feats["supports"][1]["frame_check"] = RIGHT_FRAME
    out["features"][0].write_text(json.dumps(feats))
    html = _supports_rows(_report(out))
    rows = unescape(_plain(html))
    assert "cava fixed (clamped) file cava_lps_m.csv 164 31 4.62mean 2.91 as read, 0.213 mirrored ⚠ frame –" in rows
    assert ("⚠ cava: likely read in the wrong frame (read in RAS; mirrored, its points fit the surface 0.213 mm on "
            "average, 2.91 as read). The file states no frame, so its points are read in the geometry's: if the file "
            "is in LPS, state geometry.imported[lab01].supports.list[0].file.frame: LPS (changing") in rows
    assert html.count("<tr class='frame-flag'><td colspan='7'>") == 1 and "/data/lab" not in html
    assert "diaphragm foundation (elastic foundation) file ligament_lps_m.csv 2840 – 0.00075mean 0.000201 as read, " \
           "3.4 mirrored total 56.3 N/mm" in rows
    assert "Frame check of a file of points" in rows and "at most 0.5 times as far and 0.5 mm closer" in rows
    # the sphere's row is as before; without any check, the table is as before (no note)
    floor = before[before.index("floor "):before.index("(visceral slot)")]
    assert floor in rows and "Frame check" not in before and "mirrored" not in before


#: the frame check of a sphere support (liverforce.mesh.supports.check_sphere_frame): its centre's distances
SPHERE_WRONG = {"of": "centre", "read_in": "LPS", "as_given_mm": {"mean": 11.2, "max": 11.2},
                "mirrored_mm": {"mean": 0.0004, "max": 0.0004}, "likely_mix_up": True, "refused_under_strict": True,
                "warning": "support 'floor' (sphere r 30 mm) looks read in the wrong frame: ...",
                "advice": "The sphere states no frame, so its coordinates are read in the geometry's: if the "
                          "sphere's coordinates are in RAS, state geometry.imported[lab01].supports.list[2].sphere."
                          "frame: RAS (changing geometry.imported[].frame would turn the liver and the sphere alike)"}


def test_the_supports_table_shows_a_sphere_centres_frame_check(stage_outputs):
    """A sphere's check shows its centre's distance as read and mirrored (not a mean over points), flagged with the
    advice when the centre lies on the surface only mirrored; the note under the table says the sphere's rule."""
    out = _with_lab_liver(stage_outputs)
    feats = json.loads(out["features"][0].read_text())
    feats["supports"][2]["frame_check"] = SPHERE_WRONG
    out["features"][0].write_text(json.dumps(feats))
    html = _supports_rows(_report(out))
    rows = unescape(_plain(html))
    assert "12815 – –centre 11.2 as read, 0.0004 mirrored ⚠ frame" in rows
    assert ("⚠ floor: likely read in the wrong frame (read in LPS; mirrored, its centre lies 0.0004 mm from the "
            "surface, 11.2 as read). The sphere states no frame") in rows
    assert html.count("<tr class='frame-flag'><td colspan='7'>") == 1
    assert "Frame check of a sphere" in rows and "flagged within 1 mm mirrored and 5 mm or more" in rows
    assert "Frame check of a file of points" not in rows
