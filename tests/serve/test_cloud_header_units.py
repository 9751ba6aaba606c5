"""``liverforce predict``'s point files whose header names a unit (``x_mm,y_mm,z_mm``, ``X [m]``) are read in that
unit or refused, as the mesh stage refuses its tool-position files: a cloud headed in mm and declared ``--units m``
was read a thousand times too large and refused, if at all, by the units heuristics, without a word about the
header that said so."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from liverforce.mesh.supports import SupportError, read_point_file
from liverforce.serve import Predictor, Preop
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.files import read_points
from liverforce.serve.input_frame import InputFrame
from liverforce.serve.sequence import read_sequence, read_tips

from tests.serve.test_predict_cli import context_doc, run


def _csv(path, header: str | None, pts) -> str:
    rows = "".join(f"{x!r},{y!r},{z!r}\n" for x, y, z in np.asarray(pts, dtype=np.float64).reshape(-1, 3).tolist())
    path.write_text(("" if header is None else header + "\n") + rows)
    return str(path)


@pytest.fixture
def in_metres(trained, test_cases, tmp_path):
    """The ``deformed`` model, case 1's context in metres (``ctx_m.json``, its ROI in ``roi_m.npy``), the context in
    mm, the deformed ROI (mm) and its force."""
    model = trained("deformed")
    ctx = Preop.from_arrays(test_cases, 1)
    np.save(tmp_path / "roi_m.npy", ctx.roi_undeformed_mm / 1000.0)
    doc = context_doc(ctx, "roi_m.npy", with_state=False)
    doc["exertion_point_mm"] = (ctx.exertion_point_mm / 1000.0).tolist()
    (tmp_path / "ctx_m.json").write_text(json.dumps(doc))
    D = np.asarray(test_cases["roi_deformed_mm"][1], dtype=np.float64)
    return model, ctx, D, Predictor.load(model).predict_cloud(D, ctx)


def test_a_cloud_headed_in_another_unit_than_declared_is_refused_naming_the_header(in_metres, tmp_path, capsys):
    model, ctx, D, expect = in_metres
    cloud = _csv(tmp_path / "cloud_mm.csv", "x_mm,y_mm,z_mm", D)
    rc, _, err = run(["-m", model, cloud, "--context", tmp_path / "ctx_m.json", "--units", "m"], capsys)
    said = (f"{cloud}: its header 'x_mm,y_mm,z_mm' says the coordinates are in mm, but they are read in m (1000 mm "
            "each)")
    assert rc == 2 and said in err
    assert "declare --units mm (units: mm in a context file) if every point input is in mm, else convert this file " \
           "to m (or correct its header)" in err
    # the mesh stage's words for the same file read in the same unit
    with pytest.raises(SupportError) as exc:
        read_point_file(cloud, "m", 1000.0)
    assert str(exc.value).startswith(said + ": declare units: mm")
    # a header that agrees, and one that names no unit: read as declared, the same force
    for header in ("X [m], Y [m], Z [m]", "x,y,z", None):
        cloud = _csv(tmp_path / "cloud_m.csv", header, D / 1000.0)
        rc, out, err = run(["-m", model, cloud, "--context", tmp_path / "ctx_m.json", "--units", "m"], capsys)
        assert rc == 0, err
        np.testing.assert_allclose(json.loads(out)["force_n"], expect, atol=1e-9)
    # headed in metres, read in mm (no units said anywhere): refused, the fix named
    np.save(tmp_path / "roi.npy", ctx.roi_undeformed_mm)
    (tmp_path / "ctx.json").write_text(json.dumps(context_doc(ctx, "roi.npy", with_state=False)))
    cloud = _csv(tmp_path / "cloud.txt", "x_m y_m z_m", D)
    rc, _, err = run(["-m", model, cloud, "--context", tmp_path / "ctx.json"], capsys)
    assert rc == 2 and f"{cloud}: its header 'x_m y_m z_m' says the coordinates are in m, but they are read in mm " \
                       "(1 mm each): declare --units m" in err
    _csv(tmp_path / "cloud.txt", "x_mm y_mm z_mm", D)
    rc, out, err = run(["-m", model, cloud, "--context", tmp_path / "ctx.json"], capsys)
    assert rc == 0, err
    np.testing.assert_allclose(json.loads(out)["force_n"], expect, atol=1e-9)


def test_the_contexts_roi_file_is_checked_against_the_contexts_units(in_metres, tmp_path, capsys):
    model, ctx, D, expect = in_metres
    np.save(tmp_path / "cloud_m.npy", D / 1000.0)
    doc = json.loads((tmp_path / "ctx_m.json").read_text())
    roi = _csv(tmp_path / "roi_mm.csv", "x_mm,y_mm,z_mm", ctx.roi_undeformed_mm)
    (tmp_path / "ctx_m.json").write_text(json.dumps({**doc, "roi_undeformed": "roi_mm.csv", "units": "m"}))
    rc, _, err = run(["-m", model, tmp_path / "cloud_m.npy", "--context", tmp_path / "ctx_m.json"], capsys)
    assert rc == 2 and f"{roi}: its header 'x_mm,y_mm,z_mm' says the coordinates are in mm, but they are read in " \
                       "m (1000 mm each)" in err
    _csv(tmp_path / "roi_mm.csv", "x_m,y_m,z_m", ctx.roi_undeformed_mm / 1000.0)
    rc, out, err = run(["-m", model, tmp_path / "cloud_m.npy", "--context", tmp_path / "ctx_m.json"], capsys)
    assert rc == 0, err
    np.testing.assert_allclose(json.loads(out)["force_n"], expect, atol=1e-9)


def test_sequences_tips_and_frames_of_a_record(tmp_path):
    """A sequence's clouds (a folder or files) and its --tool-tips file are read in the inputs' units; an import
    record's units (m) are the units a header is checked against; a unit predict cannot be told (um) is said as
    a conversion."""
    metres = InputFrame.resolve(None, "m")
    folder = tmp_path / "frames"
    folder.mkdir()
    pts = np.random.default_rng(0).normal(size=(6, 3)) / 100.0
    _csv(folder / "f1.csv", "x_m,y_m,z_m", pts)
    bad = _csv(folder / "f2.csv", "x_mm,y_mm,z_mm", pts * 1000.0)
    said = r"its header 'x_mm,y_mm,z_mm' says the coordinates are in mm, but they are read in m \(1000 mm each\)"
    with pytest.raises(PredictionInputError, match=f"{re.escape(bad)}: {said}"):
        read_sequence([folder], frame=metres)
    with pytest.raises(PredictionInputError, match="its header 'x_mm,y_mm,z_mm'"):
        read_sequence([folder / "f1.csv", bad], frame=metres)
    names, clouds = read_sequence([folder / "f1.csv"], frame=metres)
    np.testing.assert_allclose(clouds[0], pts, rtol=1e-15)
    tips = _csv(tmp_path / "tips.csv", "tip_x [mm]; tip_y [mm]; tip_z [mm]", pts[:2] * 1000.0)
    with pytest.raises(PredictionInputError, match=r"--tool-tips: .*tips\.csv: its header .* says the coordinates "
                                                   r"are in mm, but they are read in m"):
        read_tips(tips, 2, metres)
    np.testing.assert_allclose(read_tips(tips, 2, InputFrame.resolve(None, None)), pts[:2] * 1000.0)
    record = {"matrix": np.eye(4).tolist(), "units": "m"}  # a frame that sets the units (as an import record)
    with pytest.raises(PredictionInputError, match="are in mm, but they are read in m"):
        read_points(tips, frame=InputFrame.resolve(record))
    micro = _csv(tmp_path / "um.csv", "x_um,y_um,z_um", pts)
    with pytest.raises(PredictionInputError, match=r"read in mm \(1 mm each\): convert this file to mm \(or correct"):
        read_points(micro)
    # .npy files name no unit: read as declared
    np.save(tmp_path / "c.npy", pts)
    np.testing.assert_array_equal(read_points(tmp_path / "c.npy", frame=metres), pts)
