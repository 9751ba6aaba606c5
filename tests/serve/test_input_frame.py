"""Point inputs in a lab's own frame and units (LPS, a registration's 4x4, metres): converted to the model's frame
(RAS mm) on the way in, the force given back in the inputs' frame (``liverforce.serve.input_frame``)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from liverforce.serve import Predictor, Preop
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.files import read_context
from liverforce.serve.input_frame import InputFrame

from tests.serve.test_predict_cli import context_doc, run, write_ply


def rigid(reflect: bool, seed: int = 3) -> np.ndarray:
    """A 4x4 input mm -> RAS mm: a random rotation (times a reflection), a translation in mm."""
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    M = np.eye(4)
    M[:3, :3] = q @ np.diag([1.0, 1.0, -1.0 if reflect else 1.0])
    M[:3, 3] = [120.0, -35.0, 410.0]  # a scanner's origin far from the liver
    return M


def to_inputs(M: np.ndarray, scale: float, x_mm: np.ndarray) -> np.ndarray:
    """RAS mm -> the inputs' frame and units (the inverse of the map the model applies)."""
    return (np.asarray(x_mm) - M[:3, 3]) @ M[:3, :3] / scale


@pytest.mark.parametrize("reflect", [False, True])
def test_points_round_trip_and_forces_come_back_rotated(reflect):
    M = rigid(reflect)
    fr = InputFrame.resolve(M.tolist(), "m")
    x = np.random.default_rng(0).normal(size=(50, 3)) * 80
    np.testing.assert_allclose(fr.points(to_inputs(M, 1000.0, x)), x, atol=1e-9)
    F = np.array([0.3, -1.2, 2.5])
    F_in = fr.vectors_out(F)
    np.testing.assert_allclose(np.linalg.norm(F_in), np.linalg.norm(F), rtol=1e-12)  # a force keeps its length
    np.testing.assert_allclose(F_in @ M[:3, :3].T, F, atol=1e-12)  # and maps back by the frame's own rotation
    assert fr.reflects == reflect and not fr.identity
    # the second moment of volume transforms as a tensor: that of the converted points is the converted one
    J_in = np.einsum("ni,nj->ij", to_inputs(M, 1000.0, x) - to_inputs(M, 1000.0, x).mean(0),
                     to_inputs(M, 1000.0, x) - to_inputs(M, 1000.0, x).mean(0))
    J = np.einsum("ni,nj->ij", x - x.mean(0), x - x.mean(0))
    np.testing.assert_allclose(fr.inertia(J_in) / 1000.0**3, J, rtol=1e-9)  # points weigh mm^2, not mm^5
    # a triangle outward (+z) in RAS is outward in the inputs' frame with its winding reversed if the frame
    # reflects (as a file in that frame holds it): converted, it is outward (+z) again
    tri = np.array([[0, 1, 2]])
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]) * 10
    Vm, tm = fr.surface(to_inputs(M, 1000.0, V), tri[:, ::-1] if reflect else tri)
    n = np.cross(Vm[tm[0, 1]] - Vm[tm[0, 0]], Vm[tm[0, 2]] - Vm[tm[0, 0]])
    np.testing.assert_allclose(n / np.linalg.norm(n), [0, 0, 1], atol=1e-9)


def test_named_frames_records_and_refusals(tmp_path):
    lps = InputFrame.resolve("lps", "cm")
    np.testing.assert_allclose(lps.points([1.0, 2.0, 3.0]), [-10.0, -20.0, 30.0])
    np.testing.assert_allclose(lps.vectors_out([1.0, 2.0, 3.0]), [-1.0, -2.0, 3.0])
    assert "LPS" in lps.describe() and "x10 to mm" in lps.describe()
    assert InputFrame.resolve(None).identity and "nothing converted" in InputFrame.resolve("RAS").describe()
    # the geometry stage's record of an imported liver: its units and frame, stated once
    rec = {"frame": "LPS", "conversion": {"units": "m", "scale_to_mm": 1000.0, "frame": "LPS",
                                          "frame_matrix": np.diag([-1.0, -1.0, 1.0, 1.0]).tolist()}}
    (tmp_path / "imp-lab.json").write_text(json.dumps(rec))
    fr = InputFrame.resolve("imp-lab.json", base=tmp_path)
    assert (fr.label, fr.units, fr.scale) == ("LPS", "m", 1000.0) and "imp-lab.json" in fr.describe()
    assert InputFrame.resolve(tmp_path / "imp-lab.json", "m").scale == 1000.0
    with pytest.raises(PredictionInputError, match="imported in m .* said to be in mm"):
        InputFrame.resolve(tmp_path / "imp-lab.json", "mm")
    np.save(tmp_path / "shear.npy", np.diag([1.0, 1.0, 2.0, 1.0]))
    with pytest.raises(PredictionInputError, match="scales or shears"):
        InputFrame.resolve(tmp_path / "shear.npy")
    np.save(tmp_path / "flat.npy", np.diag([1.0, 1.0, 0.0, 1.0]))
    with pytest.raises(PredictionInputError, match="singular"):
        InputFrame.resolve(tmp_path / "flat.npy")
    with pytest.raises(PredictionInputError, match="no such file.*RAS, LPS"):
        InputFrame.resolve("RSA")
    (tmp_path / "other.json").write_text(json.dumps({"something": 1}))
    with pytest.raises(PredictionInputError, match="neither a 4x4"):
        InputFrame.resolve(tmp_path / "other.json")
    (tmp_path / "old.json").write_text(json.dumps({"conversion": {"units": "m"}}))
    with pytest.raises(PredictionInputError, match="geometry stage again"):
        InputFrame.resolve(tmp_path / "old.json")
    (tmp_path / "m.yaml").write_text(f"matrix: {rigid(False).tolist()}\nunits: m\n")
    assert InputFrame.resolve(tmp_path / "m.yaml").scale == 1000.0


def _rotated_context(ctx: Preop, M: np.ndarray, s: float, roi_file: str) -> dict:
    """``context_doc`` of ``ctx`` with every point, direction and tensor in the inputs' frame and units."""
    A = M[:3, :3]
    doc = context_doc(ctx, roi_file)
    doc["exertion_point_mm"] = to_inputs(M, s, ctx.exertion_point_mm).tolist()
    doc["frame"] = {"t1": (ctx.frame[0] @ A).tolist(), "t2": (ctx.frame[1] @ A).tolist(),
                    "normal": (ctx.frame[2] @ A).tolist()}
    doc["liver_centroid_mm"] = to_inputs(M, s, ctx.liver_centroid_mm).tolist()
    doc["inertia_mm5"] = (A.T @ ctx.inertia_mm5 @ A / s**5).tolist()
    doc["tool_thickness_mm"] = ctx.tool_thickness_mm / s
    doc["probe_compliance_mm_per_n"] = (ctx.probe_compliance_mm_per_n / s).tolist()  # local frame: units only
    return doc


def test_nodes_and_context_in_a_registration_frame(trained, test_cases, tmp_path, capsys):
    """ROI nodes, the local frame, the liver features and the exertion point in a rotated, shifted frame in
    metres: the same force as in RAS mm, given back rotated; the interval's local components unchanged."""
    model = trained("disp")
    ctx = Preop.from_arrays(test_cases, 2)
    D = np.asarray(test_cases["roi_deformed_mm"][2])
    pred = Predictor.load(model)
    iv = pred.interval(D, ctx)
    M = rigid(False)
    np.save(tmp_path / "M.npy", M)
    np.save(tmp_path / "roi.npy", to_inputs(M, 1000.0, ctx.roi_undeformed_mm))
    np.save(tmp_path / "nodes.npy", to_inputs(M, 1000.0, D))
    (tmp_path / "ctx.json").write_text(json.dumps({**_rotated_context(ctx, M, 1000.0, "roi.npy"),
                                                   "input_frame": "M.npy", "units": "m"}))
    rc, out, err = run(["-m", model, tmp_path / "nodes.npy", "--mode", "nodes", "--context", tmp_path / "ctx.json"],
                       capsys)
    assert rc == 0, err
    doc = json.loads(out)
    np.testing.assert_allclose(doc["force_n_model"], iv["force_n"], atol=1e-6)
    np.testing.assert_allclose(doc["force_n"], np.asarray(iv["force_n"]) @ M[:3, :3], atol=1e-6)
    np.testing.assert_allclose(doc["interval"]["force_local_n"], iv["force_local_n"], atol=1e-6)
    np.testing.assert_allclose(doc["interval"]["frame"], ctx.frame @ M[:3, :3], atol=1e-9)  # axes, inputs' frame
    assert "frame matrix" in doc["input_frame"] and "inputs in m" in doc["input_frame"]
    # without the frame, the same files give the same force in their frame: the model reads the liver in its
    # local frame, so a rigid motion of every input leaves it unchanged (the frame matters for the mesh stage's
    # tet mesh, which is in RAS mm, and for a reflection: the smoke workflow's test and the test below)
    (tmp_path / "ctx_nf.json").write_text(json.dumps({**_rotated_context(ctx, M, 1000.0, "roi.npy"), "units": "m"}))
    rc, out, err = run(["-m", model, tmp_path / "nodes.npy", "--mode", "nodes", "--context", tmp_path / "ctx_nf.json"],
                       capsys)
    assert rc == 0 and "force_n_model" not in json.loads(out)
    np.testing.assert_allclose(json.loads(out)["force_n"], doc["force_n"], atol=1e-6)
    # a reflecting frame would make the given local frame left-handed: refused, saying what to give instead
    np.save(tmp_path / "R.npy", rigid(True))
    rc, out, err = run(["-m", model, tmp_path / "nodes.npy", "--mode", "nodes", "--context", tmp_path / "ctx.json",
                        "--frame", tmp_path / "R.npy"], capsys)
    assert rc == 2 and "left-handed" in err and "surface" in err
    rc, out, err = run(["-m", model, "--shards", tmp_path, "--frame", "LPS"], capsys)
    assert rc == 2 and "model's frame" in err


def test_a_surface_in_a_reflected_frame_in_metres(trained, tmp_path, capsys, ellipsoid):
    """The undeformed surface and the deformed one through a reflecting 4x4 in metres: the triangles are turned
    back outward, so the ROI, its normal and the force are those of the RAS mm inputs."""
    model = trained("deformed")
    pts, tri = ellipsoid()
    p = pts[123]
    pred = Predictor.load(model)
    ctx = Preop.from_surface(pts, tri, p, None, roi_fraction=pred.roi_fraction)
    dent = pts.copy()
    dent[ctx.roi_point_ids] -= 2.0 * ctx.frame[2] * np.exp(-np.sum((pts[ctx.roi_point_ids] - p) ** 2, 1) / 200)[:, None]
    expect = pred.predict(ctx.roi_of_surface(dent), ctx)
    M = rigid(True, seed=5)
    write_ply(tmp_path / "liver.ply", to_inputs(M, 1000.0, pts), tri[:, ::-1])  # outward in the reflected frame
    np.save(tmp_path / "dent.npy", to_inputs(M, 1000.0, dent))
    np.save(tmp_path / "M.npy", M)
    flags = ["-m", model, tmp_path / "dent.npy", "--mode", "surface", "--surface", tmp_path / "liver.ply",
             "--exertion-point", *to_inputs(M, 1000.0, p), "--units", "m", "--frame", tmp_path / "M.npy"]
    rc, out, err = run(flags, capsys)
    assert rc == 0, err
    doc = json.loads(out)
    np.testing.assert_allclose(doc["force_n_model"], expect, atol=1e-6)
    np.testing.assert_allclose(doc["force_n"], expect @ M[:3, :3], atol=1e-6)
    assert "reflection" in doc["input_frame"]
    preop, fr = read_context({"surface": str(tmp_path / "liver.ply"), "exertion_point_mm": to_inputs(M, 1000.0, p),
                              "units": "m", "input_frame": str(tmp_path / "M.npy")}, pred)
    np.testing.assert_allclose(preop.frame[2], ctx.frame[2], atol=1e-9)  # the outward normal, as in RAS
    assert fr.reflects


@pytest.mark.parametrize("frame", ["LPS", "matrix"])
def test_the_geometry_stages_record_maps_the_files_points_onto_the_meshed_liver(tmp_path, frame):
    """The record the geometry stage writes for an imported liver (units m; LPS or a rotated, shifted 4x4):
    InputFrame maps the file's own vertices onto the stage's RAS mm surface; a procedural liver's record is RAS mm."""
    import meshio

    from liverforce.geometry.procedural import procedural_liver
    from liverforce.pipeline.geometry import make_geometry

    liver = procedural_liver(0)
    M = np.diag([-1.0, -1.0, 1.0, 1.0]) if frame == "LPS" else rigid(False, seed=11)
    file_m = to_inputs(M, 1000.0, liver.vertices)
    path = tmp_path / "lab.ply"
    meshio.write(path, meshio.Mesh(file_m, [("triangle", liver.faces)]), binary=True)
    spec = {"kind": "imported", "name": "lab", "path": str(path), "units": "m", "label": None,
            "frame": "LPS" if frame == "LPS" else M.tolist()}
    make_geometry(spec, tmp_path / "out" / "imp-lab.ply", tmp_path / "out" / "imp-lab.json")
    fr = InputFrame.resolve(tmp_path / "out" / "imp-lab.json")
    assert (fr.units, fr.scale, fr.label) == ("m", 1000.0, frame)
    ras = meshio.read(tmp_path / "out" / "imp-lab.ply").points
    np.testing.assert_allclose(fr.points(file_m), ras, atol=1e-6)
    make_geometry({"kind": "procedural", "seed": 0}, tmp_path / "out" / "proc-0000.ply",
                  tmp_path / "out" / "proc-0000.json")
    assert InputFrame.resolve(tmp_path / "out" / "proc-0000.json").identity


def test_bad_frames_and_context_values_are_refused_by_name_not_by_traceback(trained, test_cases, tmp_path, capsys,
                                                                         monkeypatch):
    model = trained("disp")
    pred = Predictor.load(model)
    ctx = Preop.from_arrays(test_cases, 2)
    good = {"conversion": {"units": "m", "scale_to_mm": 1000.0, "frame": "LPS",
                           "frame_matrix": np.diag([-1.0, -1.0, 1.0, 1.0]).tolist()}}
    bad_records = {
        "null_scale": {"conversion": {**good["conversion"], "scale_to_mm": None}},
        "not_a_dict": {"conversion": 5},
        "ragged": {"conversion": {**good["conversion"], "frame": "matrix", "frame_matrix": [[1, 0], [0, 1, 0, 0]]}},
        "label_volume": {"label": 1, "conversion": {**good["conversion"], "frame": "RAS",
                                                     "frame_matrix": np.eye(4).tolist(), "summary": (
            "units mm (x1 to mm); frame RAS: ...; label volume: header frame converted to RAS first")}},
        "label_volume_moved": {"label": 1, "conversion": {**good["conversion"], "frame": "matrix",
                                                           "frame_matrix": [[1, 0, 0, 4.0], [0, 1, 0, 0],
                                                                            [0, 0, 1, 0], [0, 0, 0, 1]]}},
    }
    expect = {"label_volume": r"label volume.*--frame LPS or --frame RAS \(and --units\) for them$",
              "label_volume_moved": r"label volume.*--frame LPS.*also moved by its import frame.*diag\(-1, -1, 1, 1\)"}
    for name, rec in bad_records.items():
        (tmp_path / f"{name}.json").write_text(json.dumps(rec))
        with pytest.raises(PredictionInputError, match=expect.get(name, "geometry stage again")):
            InputFrame.resolve(tmp_path / f"{name}.json")
    (tmp_path / "num.yaml").write_text(f"matrix: {np.eye(4).tolist()}\nunits: 1000\n")
    with pytest.raises(PredictionInputError, match="units 1000"):
        InputFrame.resolve(tmp_path / "num.yaml")
    doc = context_doc(ctx, "roi.npy")
    np.save(tmp_path / "roi.npy", ctx.roi_undeformed_mm)
    flat = {**doc, "inertia_mm5": np.ravel(doc["inertia_mm5"]).tolist()}  # 9 numbers, as Preop takes them
    np.testing.assert_allclose(read_context(flat | {"roi_undeformed": ctx.roi_undeformed_mm.tolist()}, pred)[0]
                               .inertia_mm5, ctx.inertia_mm5)
    for key, value in [("exertion_point_mm", [1.0, 2.0]), ("inertia_mm5", [1.0, 2.0, 3.0]), ("units", 40)]:
        with pytest.raises(PredictionInputError, match=key.split("_")[0] if key != "exertion_point_mm" else "point"):
            read_context({**doc, "roi_undeformed": ctx.roi_undeformed_mm.tolist(), "input_frame": "LPS",
                          key: value}, pred)
    # a relative --frame is taken from the working directory, a context file's own paths from its folder
    (tmp_path / "lab").mkdir()
    (tmp_path / "lab" / "ctx.json").write_text(json.dumps({**doc, "roi_undeformed": "../roi.npy"}))
    np.save(tmp_path / "nodes.npy", np.asarray(test_cases["roi_deformed_mm"][2]))
    (tmp_path / "rec.json").write_text(json.dumps({"conversion": {**good["conversion"], "units": "mm",
                                                                  "scale_to_mm": 1.0, "frame": "RAS",
                                                                  "frame_matrix": np.eye(4).tolist()}}))
    monkeypatch.chdir(tmp_path)
    rc, out, err = run(["-m", model, "nodes.npy", "--mode", "nodes", "--context", "lab/ctx.json", "--frame",
                        "rec.json"], capsys)
    assert rc == 0, err
    np.testing.assert_allclose(json.loads(out)["force_n"], pred.predict(test_cases["roi_deformed_mm"][2], ctx),
                               atol=1e-9)


def to_input_arrays(M: np.ndarray, scale: float, arrays: dict) -> dict:
    """Input-contract arrays in RAS mm -> the inputs' frame and units, key by key (the inverse map, written out
    here apart from :meth:`InputFrame.arrays`)."""
    A = M[:3, :3]
    out = {}
    for k, v in arrays.items():
        if k in ("roi_undeformed_mm", "roi_deformed_mm", "camera_cloud_mm"):
            out[k] = [to_inputs(M, scale, c) for c in v]
        elif k.endswith("_mm") and k not in ("tool_thickness_mm",):
            out[k] = to_inputs(M, scale, v)
        elif k.startswith("frame_"):
            out[k] = np.asarray(v) @ A
        elif k == "inertia_mm5":
            J = np.asarray(v).reshape(-1, 3, 3)
            out[k] = (A.T @ J @ A).reshape(-1, 9) / scale**5
        elif k in ("tool_thickness_mm", "probe_compliance_mm_per_n"):
            out[k] = np.asarray(v) / scale
        elif k == "roi_triangles":
            out[k] = [t[:, ::-1] if np.linalg.det(A) < 0 else t for t in v]
        else:
            out[k] = v
    return out


@pytest.mark.parametrize("reflect", [False, True])
def test_input_contract_arrays_in_a_registration_frame_come_back_to_ras_mm(reflect):
    """What the MLflow pyfunc's ``input_frame``/``units`` params do to its columns: every point, axis, length,
    inertia and compliance back to RAS mm; the material and ids untouched; a column it cannot convert, and a
    given local frame under a reflection, refused by name."""
    rng = np.random.default_rng(1)
    n = 4
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    J = np.einsum("nij,nkj->nik", rng.normal(size=(n, 3, 3)), rng.normal(size=(n, 3, 3)))
    tri = [np.array([[0, 1, 2], [1, 2, 3]])] * n
    ras = {"case_id": np.array(["a", "b", "c", "d"], dtype=object), "exertion_point_mm": rng.normal(size=(n, 3)) * 50,
           "frame_normal": q[None, 2].repeat(n, 0), "frame_t1": q[None, 0].repeat(n, 0),
           "frame_t2": q[None, 1].repeat(n, 0), "roi_undeformed_mm": [rng.normal(size=(7, 3)) * 20] * n,
           "camera_cloud_mm": [rng.normal(size=(k, 3)) * 20 for k in (5, 9, 11, 3)],
           "tool_tip_mm": rng.normal(size=(n, 3)), "liver_centroid_mm": rng.normal(size=(n, 3)),
           "roi_centroid_undeformed_mm": rng.normal(size=(n, 3)),
           "inertia_mm5": (J + J.transpose(0, 2, 1)).reshape(n, 9),
           "tool_thickness_mm": rng.uniform(20, 60, size=n), "probe_compliance_mm_per_n": rng.normal(size=(n, 9)),
           "material_params_mpa": rng.uniform(size=(n, 2)), "roi_triangles": tri}
    M = rigid(reflect)
    fr = InputFrame.resolve(M.tolist(), "m")
    given = to_input_arrays(M, 1000.0, ras)
    if reflect:  # the given axes would turn left-handed
        with pytest.raises(PredictionInputError, match="left-handed"):
            fr.arrays(given)
        ras = {k: v for k, v in ras.items() if not k.startswith("frame_")}
        given = {k: v for k, v in given.items() if not k.startswith("frame_")}
    got = fr.arrays(given)
    assert set(got) == set(ras)
    for k, v in ras.items():
        if k == "case_id":
            assert list(got[k]) == list(v)
        elif isinstance(v, list):
            for g, w in zip(got[k], v):
                np.testing.assert_allclose(g, w, atol=1e-9, err_msg=k)
        else:
            np.testing.assert_allclose(got[k], v, rtol=1e-9, atol=1e-9, err_msg=k)
    assert InputFrame.resolve("RAS").arrays(given) is given  # nothing converted, nothing copied
    with pytest.raises(PredictionInputError, match="roi_deformed_mm_extra"):
        fr.arrays({**given, "roi_deformed_mm_extra": given["tool_tip_mm"]})
    for key, value in [("exertion_point_mm", given["exertion_point_mm"][:, :2]), ("tool_tip_mm", [["a", 1, 2]]),
                       ("inertia_mm5", np.zeros((n, 8))), ("camera_cloud_mm", [np.zeros((4, 2))] * n)]:
        with pytest.raises(PredictionInputError, match=key):  # refused by name, never reshaped into other rows
            fr.arrays({**given, key: value})
    with pytest.raises(PredictionInputError, match="exertion_point_mm"):  # (n, 0): not read as zero cases
        fr.arrays({**given, "exertion_point_mm": np.zeros((n, 0))})
    with pytest.raises(PredictionInputError, match="camera_cloud_mm: expected one entry per case"):
        fr.arrays({**given, "camera_cloud_mm": 5})
    if reflect:  # the triangles are rewound: whole vertex indices only
        with pytest.raises(PredictionInputError, match=r"roi_triangles\[0\]: expected whole vertex indices"):
            fr.arrays({**given, "roi_triangles": [np.array([[0, 1, 2.5]])] * n})
    none = fr.arrays({k: (v[:0] if isinstance(v, np.ndarray) else v[:0]) for k, v in given.items()})
    assert none["inertia_mm5"].shape == (0, 9) and none["exertion_point_mm"].shape == (0, 3)


def test_a_frame_given_inline_as_the_pyfunc_reads_its_json():
    """A record or {matrix, units} already read (a dict): the same frame as from a file; an empty matrix and
    units said twice differently are refused, naming what is wrong."""
    M = rigid(False)
    fr = InputFrame.resolve({"matrix": M.tolist(), "units": "m"})
    assert fr.scale == 1000.0 and np.array_equal(fr.matrix, M) and fr.source is None
    rec = {"conversion": {"units": "m", "scale_to_mm": 1000.0, "frame": "LPS",
                          "frame_matrix": np.diag([-1.0, -1.0, 1.0, 1.0]).tolist()}}
    lps = InputFrame.resolve(rec)
    assert lps.label == "LPS" and lps.scale == 1000.0
    with pytest.raises(PredictionInputError, match="'matrix' is empty"):
        InputFrame.resolve({"matrix": None, "units": "m"})
    with pytest.raises(PredictionInputError, match=r"its units \(m\) contradict the units said apart \(cm\)"):
        InputFrame.resolve({"matrix": M.tolist(), "units": "m"}, "cm")


def test_every_input_contract_column_has_a_conversion():
    """A column added to the input contract must be given a conversion, or the pyfunc refuses it in any frame
    but RAS mm (instead of passing it on unconverted)."""
    from liverforce.learn.camera import CLOUD_KEY, TIP_KEY
    from liverforce.learn.cloud_features import ROI_TRIANGLES_KEY
    from liverforce.learn.model import ROI_INPUTS
    from liverforce.learn.state import STATE_INPUTS
    from liverforce.serve import input_frame as f

    known = set(f.POINT_KEYS) | set(f.DIRECTION_KEYS) | set(f.LENGTH_KEYS) | set(f.PASS_KEYS) | {"inertia_mm5",
                                                                                                  "roi_triangles"}
    assert set(ROI_INPUTS) | set(STATE_INPUTS) | {CLOUD_KEY, TIP_KEY, ROI_TRIANGLES_KEY} <= known
    assert set(f.RAGGED_POINT_KEYS) <= set(f.POINT_KEYS)
