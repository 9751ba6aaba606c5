"""A lab's own liver surfaces with the defects real exports have, beyond tests/geometry/test_bad_inputs.py."""

from __future__ import annotations

import tracemalloc

import numpy as np
import trimesh

from liverforce.geometry.repair import self_intersections


def spiked_sphere(subdivisions=4, radius=100.0):
    """A fine sphere whose pole vertex is pulled 1.5 diameters inwards: its five long triangles pierce the far
    side (a segmentation spike), every other triangle is small."""
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    v, f = np.array(s.vertices), np.array(s.faces)
    pole = int(np.argmax(v[:, 2]))
    v[pole] = [0.13 * radius, 0.07 * radius, -1.5 * radius]  # off the axis: no edge coplanar with the far pole's
    return v, f, pole


def test_a_few_long_triangles_do_not_make_the_self_intersection_search_quadratic():
    """One spike across a dense surface made every triangle search the spike's reach (2x the longest triangle's
    radius): n^2/2 candidate pairs, which on a 600k-triangle liver killed the geometry job for memory with no
    message. Only the spike's own neighbourhood is searched now, and the crossing is found where it is."""
    v, f, pole = spiked_sphere()
    tracemalloc.start()
    try:
        pairs = self_intersections(v, f)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 40e6, f"{peak / 1e6:.0f} MB for {len(f)} triangles"
    spike = np.flatnonzero((f == pole).any(axis=1))
    assert len(pairs) and np.isin(pairs, spike).any(axis=1).all()  # every pair has a spike triangle
    other = np.where(np.isin(pairs[:, 0], spike), pairs[:, 1], pairs[:, 0])
    hit = v[f[other]].mean(axis=1)
    np.testing.assert_allclose(hit[:, 2], -100.0, atol=5.0)  # where the spike leaves: near the far pole
    assert np.abs(hit[:, :2]).max() < 20.0


def test_a_liver_in_metres_labelled_mm_is_told_which_units_fit(tmp_path):
    """The refusal named a Python argument (size_range_mm=None) as the way out, which no config key reaches; it
    now names the config key and the unit that makes the liver liver-sized."""
    import pytest

    from liverforce.geometry import GeometryError, load_surface
    from liverforce.geometry.procedural import procedural_liver

    s = procedural_liver(0)
    path = tmp_path / "ct_liver.stl"
    trimesh.Trimesh(s.vertices / 1000.0, s.faces, process=False).export(path)
    extent = float(np.ptp(s.vertices, axis=0).max())
    for units in ("mm", "cm"):
        with pytest.raises(GeometryError, match=rf"ct_liver\.stl: with units {units} .*the units are probably wrong\. "
                                                rf"Give the right units \(geometry\.imported\[\]\.units: .*'m' gives "
                                                rf"{extent:.4g} mm\)\. The workflow takes human-liver-sized"):
            load_surface(path, units=units)
    assert load_surface(path, units="m")[0].extent_mm.max() == pytest.approx(extent, rel=1e-6)


def test_a_repair_names_the_place_in_the_files_own_units_and_frame(tmp_path):
    """A CT liver in LPS metres with a scanner origin: the place of a self-intersection was given only in RAS mm
    as converted ([208.986, 129.375, 1105.276] mm), numbers the lab's file holds nowhere; the file's own
    coordinates follow now."""
    import re

    from liverforce.geometry import GeometryError, load_surface

    v, f, _ = spiked_sphere()
    origin = np.array([-0.15, -0.2, 1.2])
    path = tmp_path / "ct_spike.stl"
    trimesh.Trimesh(v * [-1, -1, 1] / 1000.0 + origin, f, process=False).export(path)
    try:
        _, msgs = load_surface(path, units="m", frame="LPS")
        text = next(m for m in msgs if "self-intersections" in m)
    except GeometryError as exc:
        text = str(exc)
    got = re.search(r"near \[([^\]]+)\] mm \(in the file: \[([^\]]+)\] m, LPS\)", text)
    assert got, text
    ras, file = (np.array([float(x) for x in g.split(",")]) for g in got.groups())
    np.testing.assert_allclose(file, ras * [-1, -1, 1] / 1000.0, atol=2e-6)
    assert np.linalg.norm(file - origin) < 0.3  # near the scanner's origin, where the file has the liver
