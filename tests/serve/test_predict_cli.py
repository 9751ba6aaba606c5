"""``liverforce predict`` (registered on a parser as the main CLI will): files in, force out, exit codes."""
from __future__ import annotations

import argparse
import json

import numpy as np
import pandas as pd
import pytest

from liverforce.serve import Predictor, Preop
from liverforce.cli import register_predict as register
from liverforce.serve.files import read_points, read_surface


def run(argv, capsys) -> tuple[int, str, str]:
    parser = argparse.ArgumentParser(prog="liverforce")
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    args = parser.parse_args(["predict", *map(str, argv)])
    rc = args.func(args)
    out, err = capsys.readouterr()
    return rc, out, err


def write_ply(path, pts, faces=None, binary=False):
    head = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0", "comment test",
            f"element vertex {len(pts)}", "property double x", "property double y", "property double z",
            "property uchar red"]
    if faces is not None:
        head += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    head.append("end_header")
    with open(path, "wb") as fh:
        fh.write(("\n".join(head) + "\n").encode())
        if binary:
            v = np.zeros(len(pts), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "u1")])
            v["x"], v["y"], v["z"] = pts.T
            fh.write(v.tobytes())
            if faces is not None:
                f = np.zeros(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
                f["n"], f["v"] = 3, faces
                fh.write(f.tobytes())
        else:
            fh.write("".join(f"{x!r} {y!r} {z!r} 7\n" for x, y, z in np.asarray(pts).tolist()).encode())
            if faces is not None:
                fh.write("".join(f"3 {a} {b} {c}\n" for a, b, c in np.asarray(faces).tolist()).encode())


def context_doc(ctx: Preop, roi_file: str, with_state=True) -> dict:
    doc = {"exertion_point_mm": ctx.exertion_point_mm.tolist(), "roi_undeformed": roi_file,
           "frame": {"normal": ctx.frame[2].tolist(), "t1": ctx.frame[0].tolist(), "t2": ctx.frame[1].tolist()}}
    if with_state:
        doc.update(material_params_mpa=ctx.material_params_mpa.tolist(),
                   liver_centroid_mm=ctx.liver_centroid_mm.tolist(),
                   inertia_mm5=ctx.inertia_mm5.tolist(), tool_thickness_mm=ctx.tool_thickness_mm,
                   probe_compliance_mm_per_n=ctx.probe_compliance_mm_per_n.tolist())
    return doc


@pytest.mark.parametrize("fmt", ["ply-ascii", "ply-binary", "csv", "npy"])
def test_cloud_file_formats(trained, test_cases, tmp_path, capsys, fmt):
    model = trained("deformed")
    ctx = Preop.from_arrays(test_cases, 1)
    D = np.asarray(test_cases["roi_deformed_mm"][1])
    np.save(tmp_path / "roi.npy", ctx.roi_undeformed_mm)
    (tmp_path / "ctx.json").write_text(json.dumps(context_doc(ctx, "roi.npy", with_state=False)))
    if fmt.startswith("ply"):
        cloud = tmp_path / "cloud.ply"
        write_ply(cloud, D, binary=fmt.endswith("binary"))
    elif fmt == "csv":
        cloud = tmp_path / "cloud.csv"
        cloud.write_text("x,y,z\n" + "".join(f"{x!r},{y!r},{z!r}\n" for x, y, z in D.tolist()))
    else:
        cloud = tmp_path / "cloud.npy"
        np.save(cloud, D)
    np.testing.assert_array_equal(read_points(cloud), D)
    rc, out, err = run(["-m", model, cloud, "--context", tmp_path / "ctx.json"], capsys)
    assert rc == 0, err
    doc = json.loads(out)
    expect = Predictor.load(model).predict_cloud(D, ctx)
    np.testing.assert_allclose(doc["force_n"], expect, atol=1e-12)
    assert doc["mode"] == "exact" and doc["points_used"] == len(D)


def test_nodes_mode_yaml_context_and_outputs(trained, test_cases, tmp_path, capsys):
    import yaml

    model = trained("disp")
    ctx = Preop.from_arrays(test_cases, 2)
    D = np.asarray(test_cases["roi_deformed_mm"][2])
    (tmp_path / "roi.csv").write_text("".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in ctx.roi_undeformed_mm.tolist()))
    (tmp_path / "ctx.yaml").write_text(yaml.safe_dump(context_doc(ctx, "roi.csv")))
    np.save(tmp_path / "nodes.npy", D)
    expect = Predictor.load(model).predict(D, ctx)
    rc, out, err = run(["-m", model, tmp_path / "nodes.npy", "--mode", "nodes", "--context", tmp_path / "ctx.yaml",
                        "--out", tmp_path / "f.json"], capsys)
    assert rc == 0, err
    doc = json.loads((tmp_path / "f.json").read_text())
    np.testing.assert_allclose(doc["force_n"], expect, atol=1e-12)
    # the calibrated interval per local component (t1, t2, n) comes with the force
    iv, m = doc["interval"], Predictor.load(model).model
    np.testing.assert_allclose(iv["frame"], ctx.frame, atol=1e-12)
    np.testing.assert_allclose(iv["force_local_n"], ctx.frame @ expect, atol=1e-9)
    k = 1.0 if m.pre.material_ref is None else ctx.material_params_mpa[0] / m.pre.material_ref
    np.testing.assert_allclose(iv["half_width_local_n"], k * np.asarray(m.interval.half_width_n), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(iv["upper_local_n"]) - iv["lower_local_n"],
                               2 * np.asarray(iv["half_width_local_n"]), rtol=1e-12)
    assert iv["coverage"] == 0.9 and m.interval.n_calibration >= 9 and min(iv["half_width_local_n"]) > 0
    rc, out, err = run(["-m", model, tmp_path / "nodes.npy", "--mode", "nodes", "--context", tmp_path / "ctx.yaml",
                        "--out", tmp_path / "f.csv"], capsys)
    assert rc == 0
    np.testing.assert_allclose(pd.read_csv(tmp_path / "f.csv").to_numpy()[0], expect, atol=1e-12)
    # a force beyond the training forces is said: the same model with its recorded largest force below this one's
    assert not any(w.startswith("the predicted force") for w in doc["warnings"])
    import shutil

    capped = tmp_path / "capped"
    shutil.copytree(model, capped)
    bundle = json.loads((capped / "model.json").read_text())
    bundle["meta"]["training_scale"]["force_magnitude_n"][1] = 0.5 * float(np.linalg.norm(expect))
    (capped / "model.json").write_text(json.dumps(bundle))
    rc, out, err = run(["-m", capped, tmp_path / "nodes.npy", "--mode", "nodes", "--context", tmp_path / "ctx.yaml"],
                       capsys)
    assert rc == 0, err
    warned = json.loads(out)["warnings"]
    assert warned[:-1] == doc["warnings"] and warned[-1].startswith("the predicted force") and "ROI nodes" in warned[-1]
    # the same in metres: --units m scales every point input (and the inertia)
    in_m = Preop.from_dict({**ctx.to_dict(), "exertion_point_mm": ctx.exertion_point_mm / 1000})
    doc = context_doc(in_m, "roi_m.npy")
    doc["liver_centroid_mm"] = (ctx.liver_centroid_mm / 1000).tolist()
    doc["inertia_mm5"] = (ctx.inertia_mm5 / 1e15).tolist()
    doc["tool_thickness_mm"] = ctx.tool_thickness_mm / 1000
    doc["probe_compliance_mm_per_n"] = (ctx.probe_compliance_mm_per_n / 1000).tolist()  # m/N
    np.save(tmp_path / "roi_m.npy", ctx.roi_undeformed_mm / 1000)
    np.save(tmp_path / "nodes_m.npy", D / 1000)
    (tmp_path / "ctx_m.json").write_text(json.dumps(doc))
    rc, out, err = run(["-m", model, tmp_path / "nodes_m.npy", "--mode", "nodes", "--context", tmp_path / "ctx_m.json",
                        "--units", "m"], capsys)
    assert rc == 0, err
    np.testing.assert_allclose(json.loads(out)["force_n"], expect, atol=1e-5)
    # ... and without --units the metre inputs are refused, naming the units
    rc, out, err = run(["-m", model, tmp_path / "nodes_m.npy", "--mode", "nodes", "--context", tmp_path / "ctx_m.json"],
                       capsys)
    assert rc == 2 and "in mm" in err


def test_surface_mode_with_flags(trained, tmp_path, capsys, ellipsoid):
    model = trained("disp")
    pts, tri = ellipsoid()
    write_ply(tmp_path / "liver.ply", pts, tri, binary=True)
    p2, t2 = read_surface(tmp_path / "liver.ply")
    np.testing.assert_array_equal(p2, pts)
    np.testing.assert_array_equal(t2, tri)
    p = pts[123]
    pred = Predictor.load(model)
    C = np.diag([0.8, 0.8, 1.5])  # the synthetic training data's probe compliance, mm/N
    ctx = Preop.from_surface(pts, tri, p, [0.0016, 0.0125], roi_fraction=pred.roi_fraction).with_compliance(C)
    dent = pts.copy()
    dent[ctx.roi_point_ids] -= 2.0 * ctx.frame[2] * np.exp(-np.sum((pts[ctx.roi_point_ids] - p) ** 2, 1) / 200)[:, None]
    np.save(tmp_path / "deformed_surface.npy", dent)
    flags = ["-m", model, tmp_path / "deformed_surface.npy", "--mode", "surface", "--surface", tmp_path / "liver.ply",
             "--exertion-point", *p, "--material", 0.0016, 0.0125]
    rc, out, err = run(flags, capsys)  # a state-vector model without the stiffness probe: refused, naming --mesh
    assert rc == 2 and "probe_compliance_mm_per_n" in err and "--mesh" in err
    (tmp_path / "probe.yaml").write_text(f"probe_compliance_mm_per_n: {C.tolist()}\n")
    rc, out, err = run(flags + ["--context", tmp_path / "probe.yaml"], capsys)
    assert rc == 0, err
    np.testing.assert_allclose(json.loads(out)["force_n"], pred.predict(ctx.roi_of_surface(dent), ctx), atol=1e-9)


def test_errors_exit_2_with_a_message(trained, test_cases, tmp_path, capsys):
    model = trained("deformed")
    ctx = Preop.from_arrays(test_cases, 1)
    np.save(tmp_path / "roi.npy", ctx.roi_undeformed_mm)
    (tmp_path / "ctx.json").write_text(json.dumps(context_doc(ctx, "roi.npy", with_state=False)))
    (tmp_path / "nan.csv").write_text("1,2,3\nnan,2,3\n")
    rc, _, err = run(["-m", model, tmp_path / "nan.csv", "--context", tmp_path / "ctx.json"], capsys)
    assert rc == 2 and "NaN or inf" in err and err.startswith("liverforce predict: error:")
    (tmp_path / "four.csv").write_text("1,2,3,4\n")
    rc, _, err = run(["-m", model, tmp_path / "four.csv", "--context", tmp_path / "ctx.json"], capsys)
    assert rc == 2 and "exactly x, y, z" in err
    np.save(tmp_path / "c.npy", np.asarray(test_cases["roi_deformed_mm"][1]))
    rc, _, err = run(["-m", model, tmp_path / "c.npy"], capsys)
    assert rc == 2 and "exertion_point_mm is required" in err
    rc, _, err = run(["-m", tmp_path / "nope", tmp_path / "c.npy", "--context", tmp_path / "ctx.json",
                      "--tracking-uri", f"sqlite:///{tmp_path / 'empty.db'}"], capsys)
    assert rc == 2 and "cannot fetch it from MLflow" in err
    (tmp_path / "bad.json").write_text("{not json")
    rc, _, err = run(["-m", model, tmp_path / "c.npy", "--context", tmp_path / "bad.json"], capsys)
    assert rc == 2 and "not valid JSON" in err


def test_describe_and_shards(trained, test_cases, tmp_path, capsys, make_shard_rows):
    from liverforce.dataset import io as dio

    model = trained("disp")
    rc, out, _ = run(["-m", model, "--describe"], capsys)
    assert rc == 0 and json.loads(out)["uses_state_vector"] is True
    dio.write_shard(make_shard_rows(test_cases, range(6)), tmp_path / "shard-0000.parquet")
    rc, out, err = run(["-m", model, "--shards", tmp_path, "--out", tmp_path / "p.parquet"], capsys)
    assert rc == 0, err
    assert json.loads(out)["rows"] == 6 and len(pd.read_parquet(tmp_path / "p.parquet")) == 6


def test_shards_with_refused_cases_go_on_and_exit_2_only_when_every_row_is_refused(trained, test_cases, tmp_path,
                                                                                  capsys, make_shard_rows):
    """--shards: refused cases get NaN and their reason, the rest are predicted (exit 0); stderr says how many and
    the first reasons; a batch of refused cases only exits 2, its file still written with every reason."""
    from liverforce.dataset import io as dio

    model = trained("disp")
    rows = make_shard_rows(test_cases, range(8))
    for k in (2, 5, 6, 7):  # pushed 60x further than in training: refused
        rows[k] = make_shard_rows(test_cases, [k], scale=60.0)[0]
    (tmp_path / "s").mkdir()
    dio.write_shard(rows, tmp_path / "s" / "shard-0000.parquet")
    rc, out, err = run(["-m", model, "--shards", tmp_path / "s", "--out", tmp_path / "p.parquet"], capsys)
    assert rc == 0, err
    summary, df = json.loads(out), pd.read_parquet(tmp_path / "p.parquet")
    assert summary["rows"] == 8 and summary["refused"] == 4 and summary["predicted"] == 4
    bad = df["refused"] != ""
    assert sorted(df["case_id"][bad]) == sorted(str(test_cases["case_id"][k]) for k in (2, 5, 6, 7))
    F = df[["fx_n", "fy_n", "fz_n"]].to_numpy()
    assert np.isnan(F[bad]).all() and np.isfinite(F[~bad]).all()
    reasons = list(df["refused"][bad])
    assert all("the ROI moved by up to" in r for r in reasons)
    assert err.startswith("liverforce predict: 4 of 8 rows refused, their forces NaN (the other rows were predicted; "
                          f"each reason in the 'refused' column of {tmp_path / 'p.parquet'}). The first: "
                          + "; ".join(reasons[:3]) + " (and 1 more)")
    dio.write_shard([rows[k] for k in (2, 5)], tmp_path / "s" / "shard-0000.parquet")
    rc, out, err = run(["-m", model, "--shards", tmp_path / "s", "--out", tmp_path / "all.csv"], capsys)
    assert rc == 2 and json.loads(out)["predicted"] == 0
    assert err.startswith("liverforce predict: error: 2 of 2 rows refused, their forces NaN (every row;")
    assert list(pd.read_csv(tmp_path / "all.csv")["refused"]) == reasons[:2]


@pytest.mark.parametrize("ext", ["stl", "obj", "vtu-tets"])
def test_surface_files(tmp_path, ext, ellipsoid):
    import meshio
    from scipy.spatial import Delaunay

    from liverforce.serve.preop import boundary_edges, surface_moments

    pts, tri = ellipsoid(n=600)
    vol, cen, inertia = surface_moments(pts, tri)
    if ext == "vtu-tets":
        tets = Delaunay(pts).simplices
        tets[::2] = tets[::2][:, [1, 0, 2, 3]]  # mixed orientation, as some meshers write
        path = tmp_path / "liver.vtu"
        meshio.write(path, meshio.Mesh(pts, [("tetra", tets)]))
    else:
        path = tmp_path / f"liver.{ext}"
        meshio.write(path, meshio.Mesh(pts, [("triangle", tri)]))
    p2, t2 = read_surface(path)
    assert boundary_edges(t2) == 0 and len(t2) == len(tri)
    v2, c2, i2 = surface_moments(p2, t2)
    assert v2 == pytest.approx(vol, rel=1e-6)  # outward: positive volume
    np.testing.assert_allclose(c2, cen, atol=1e-6)
    np.testing.assert_allclose(i2, inertia, rtol=1e-6, atol=1e-6 * np.abs(inertia).max())
    p3, _ = read_surface(path, units="cm")
    np.testing.assert_allclose(p3, p2 * 10)


def test_coordinates_in_scientific_notation_parse_as_numbers():
    """Metres give small coordinates; a script prints them as -5e-05: they are numbers, not options."""
    parser = argparse.ArgumentParser(prog="liverforce")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["predict", "-m", "model", "cloud.npy", "--exertion-point", "-5e-05", "0.02", "-1.5E-3",
                              "--tool-tip", "-.5", "-2", "-3.", "--material", "-1e-3"])
    assert args.exertion_point == [-5e-05, 0.02, -1.5e-3] and args.tool_tip == [-0.5, -2.0, -3.0]
    assert args.material == [-1e-3]
    with pytest.raises(SystemExit):  # a real unknown option is still refused
        parser.parse_args(["predict", "-m", "model", "--exertion-pt", "1", "2", "3"])


def test_a_model_whose_interval_cannot_be_given_is_refused_in_words(trained, test_cases, tmp_path, capsys):
    """A bundle edited by hand (an interval scaled by the GP ensemble members' spread on an MLP): predict of one
    cloud says what is wrong with the model and exits 2, not a traceback."""
    from liverforce.learn.model import ForceModel

    model = ForceModel.load(trained("deformed"))
    model.meta["interval"] = {**model.meta["interval"], "spread_beta": 4.0, "spread_median_n": [0.1, 0.1, 0.1]}
    path = model.save(tmp_path / "edited")
    ctx = Preop.from_arrays(test_cases, 1)
    np.save(tmp_path / "roi.npy", ctx.roi_undeformed_mm)
    (tmp_path / "ctx.json").write_text(json.dumps(context_doc(ctx, "roi.npy", with_state=False)))
    np.save(tmp_path / "cloud.npy", np.asarray(test_cases["roi_deformed_mm"][1]))
    rc, out, err = run(["-m", path, tmp_path / "cloud.npy", "--context", tmp_path / "ctx.json"], capsys)
    assert rc == 2 and out == ""
    assert f"model {path}: the model's interval" in err and "its regressor is an MLP" in err
    assert "Traceback" not in err
