"""On a coarse mesh (18 mm edges) an exertion point on the ROI's own triangles is on the surface: the serving
paths that have the ROI's triangles (a shard row, ``Preop.from_arrays``, the pyfunc, ``--shards``) measure the
point to them, not to a quadratic fit of the nearest nodes, which puts such points 4-14 mm off and refused the
project's own training rows. A point really off the surface is still refused, with its distance."""
from __future__ import annotations

import re

import numpy as np
import pytest

from liverforce.mesh.supports import closest_on_triangles
from liverforce.serve import Predictor, Preop
from liverforce.serve.checks import Limits, check_case, check_roi, nearest_on_roi
from liverforce.serve.errors import PredictionInputError


@pytest.fixture(scope="module")
def coarse():
    """The procedural liver meshed coarsely (about 400 nodes), as ``tests/mesh/test_exertion_facing.py`` does."""
    from liverforce.geometry.procedural import procedural_liver
    from liverforce.mesh.build import build_liver_mesh

    m = build_liver_mesh(procedural_liver(0), target_nodes=400, seed=0)
    return m.points, m.facets, np.flatnonzero(m.facet_visible)


def _rows(pred: Predictor, coarse, k: int = 3) -> dict:
    """Shard-like rows (no pre-operative surface, the ROI's triangles) of the first ``k`` visible facets' centres
    that the quadratic fit of the nearest ROI nodes puts more than the tolerance off the surface."""
    P, F, vis = coarse
    rows, fit_off = [], []
    for f in vis:
        pre = pred.preop_from_surface(P, F, P[F[f]].mean(axis=0))
        U_loc = (pre.roi_undeformed_mm - pre.exertion_point_mm) @ pre.rotation.T
        try:
            check_roi(U_loc, pred.scale, pred.limits, "", fit_height=True)
        except PredictionInputError as exc:
            if "off the undeformed surface" in str(exc):
                rows.append(pre.to_arrays(pre.roi_undeformed_mm))  # roi_deformed = undeformed: no push
                fit_off.append(float(re.search(r"is ([\d.]+) mm off", str(exc)).group(1)))
        if len(rows) == k:
            break
    assert len(rows) == k and min(fit_off) > 2 * Limits().surface_tol_mm
    out = {key: [r[key][0] for r in rows] if isinstance(rows[0][key], list) else np.concatenate([r[key] for r in rows])
           for key in rows[0]}
    out["case_id"] = np.array([f"coarse-{i}" for i in range(k)])
    for i in range(k):  # on its own triangles, to rounding
        d = closest_on_triangles(out["roi_undeformed_mm"][i][out["roi_triangles"][i]],
                                 np.asarray(out["exertion_point_mm"][i])[None])[1][0]
        assert d < 1e-6
    return out


def _pyfunc(pred: Predictor, arrays: dict, **params):
    from liverforce.tracking.model import ForceModelPyfunc, arrays_to_frame

    pf = ForceModelPyfunc()
    pf.model = pred.model
    return pf.predict(None, arrays_to_frame(arrays, list(arrays)), params={"on_refused": "row", **params})


def test_a_point_on_the_triangles_of_a_coarse_roi_is_accepted_on_every_path(trained, coarse, tmp_path, monkeypatch):
    """Rows whose exertion point lies on their ROI's triangles, which the node fit puts > 4 mm off: predicted by
    predict_arrays (one row at a time and as a batch), predict_cloud with Preop.from_arrays of the row, the pyfunc
    and predict_shards, all alike."""
    pred = Predictor.from_dir(trained("deformed"))
    arrays = _rows(pred, coarse)
    force = pred.predict_arrays(arrays)
    assert force.shape == (3, 3) and np.isfinite(force).all()
    for i in range(3):
        ctx = Preop.from_arrays(arrays, i)
        assert ctx.surface_point_mm is None and ctx.roi_triangles is not None  # as a shard row gives it
        np.testing.assert_allclose(pred.predict_cloud(ctx.roi_undeformed_mm, ctx), force[i], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(_pyfunc(pred, arrays)[["fx_n", "fy_n", "fz_n"]].to_numpy(), force, rtol=1e-5,
                               atol=1e-6)
    import liverforce.serve.batch as batch

    monkeypatch.setattr(batch, "shard_paths", lambda inputs: [])
    monkeypatch.setattr(batch, "load_shards", lambda paths: ({**arrays, "geometry_id": ["coarse"] * 3}, 0))
    got = batch.predict_shards(pred, [], tmp_path / "preds.csv")
    assert got["rows"] == 3
    np.testing.assert_allclose(got["frame"][["fx_n", "fy_n", "fz_n"]].to_numpy(), force, rtol=1e-5, atol=1e-6)


def test_the_same_point_moved_off_the_surface_is_refused_with_its_distance(trained, coarse):
    """The same row with its exertion point moved 10 mm out along the normal: refused by predict_arrays, the
    pyfunc (the whole request with ``on_refused="request"``, else the row: NaN and the reason) and predict_cloud,
    with its distance to the ROI's triangles."""
    pred = Predictor.from_dir(trained("deformed"))
    arrays = _rows(pred, coarse, k=1)
    p = np.asarray(arrays["exertion_point_mm"], dtype=np.float64) + 10.0 * np.asarray(arrays["frame_normal"])
    moved = {**arrays, "exertion_point_mm": p}
    d = closest_on_triangles(arrays["roi_undeformed_mm"][0][arrays["roi_triangles"][0]], p)[1][0]
    assert d > 2 * Limits().surface_tol_mm
    said = f"case coarse-0: the exertion point is {d:.3g} mm off the undeformed surface"
    for call in (lambda: pred.predict_arrays(moved), lambda: _pyfunc(pred, moved, on_refused="request")):
        with pytest.raises(PredictionInputError) as exc:
            call()
        assert str(exc.value).startswith(said) and "ROI's triangles" in str(exc.value)
    row = _pyfunc(pred, moved)
    assert list(row["refused"]) == [str(exc.value)] and row[["fx_n", "fy_n", "fz_n"]].isna().all().all()
    with pytest.raises(PredictionInputError, match=f"the exertion point is {d:.3g} mm off the undeformed surface"):
        pred.predict_cloud(arrays["roi_undeformed_mm"][0], Preop.from_arrays(moved, 0))


def test_without_triangles_the_node_fit_still_judges(trained, coarse):
    """A row without ``roi_triangles`` keeps the quadratic fit of the nearest nodes (nothing better is known)."""
    pred = Predictor.from_dir(trained("deformed"))
    arrays = {k: v for k, v in _rows(pred, coarse, k=1).items() if k != "roi_triangles"}
    with pytest.raises(PredictionInputError, match="off the undeformed surface \\(along its normal"):
        pred.predict_arrays(arrays)



def test_a_point_over_a_large_triangle_with_far_centroid_is_measured_to_it():
    """A point 1 mm over a large triangle whose centroid is far, with 16 small triangles 5 mm away nearer by
    centroid (a search of the nearest centroids' triangles would refuse it): measured to every triangle, it is
    1 mm from the large one."""
    big = np.array([[[-500.0, -500.0, 0.0], [1500.0, -500.0, 0.0], [-500.0, 1500.0, 0.0]]])
    small = np.array([[[x, y, 6.0], [x + 1.0, y, 6.0], [x, y + 1.0, 6.0]] for x in range(-2, 2) for y in range(-2, 2)])
    tri = np.concatenate([big, small])
    p = np.array([0.2, 0.2, 1.0])
    assert closest_on_triangles(tri, p[None])[1][0] > 4.0  # the 16 nearest centroids are the small ones
    near, d = nearest_on_roi(p, tri)
    assert d == pytest.approx(1.0) and np.allclose(near, [0.2, 0.2, 0.0])


def test_the_refusal_gives_the_point_in_the_declared_units_and_frame(trained, coarse):
    """The same refusal with the inputs declared in LPS metres (converted to the model's RAS mm already, as
    ``InputFrame.arrays`` does): the point and the nearest point of the ROI come back in m LPS, with what was
    declared."""
    from liverforce.serve.input_frame import InputFrame, as_given

    pred = Predictor.from_dir(trained("deformed"))
    arrays = _rows(pred, coarse, k=1)
    p = np.asarray(arrays["exertion_point_mm"], dtype=np.float64) + 10.0 * np.asarray(arrays["frame_normal"])
    moved = {**arrays, "exertion_point_mm": p}
    fr = InputFrame.resolve("LPS", "m")
    with pytest.raises(PredictionInputError) as exc:
        check_case(moved, 0, pred.model, pred.scale, pred.limits, input_frame=fr)
    msg = str(exc.value)
    assert msg.startswith("case coarse-0: the exertion point is ") and "off the undeformed surface" in msg, msg
    assert f"it was given as {as_given(fr, p[0])} (declared in m, LPS" in msg, msg
    assert "] m LPS" in msg.split("the nearest point of the surface is ")[1], msg
    with pytest.raises(PredictionInputError) as plain:  # no frame declared: RAS mm, said so
        check_case(moved, 0, pred.model, pred.scale, pred.limits)
    assert "no units or frame were declared" in str(plain.value) and "] mm RAS" in str(plain.value)
