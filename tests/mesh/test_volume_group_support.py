"""A support's ``group:`` naming a group of tetrahedra (audit 96, defect 3).

A Gmsh physical volume holding every tet (``group: liver``) used to become the whole liver surface
as a support, silently. It is refused naming the group, that it is a 3-D group of N tets whose boundary
is the whole surface, and the surface groups to give instead; a sub-volume (the tets next to the cava)
still gives its faces on the boundary.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_byo_volume_files import shuffled_box, write_volume

from liverforce.mesh.boundary import boundary_facets
from liverforce.mesh.groups import read_file_groups
from liverforce.mesh.supports import SupportError, parse_supports, select_facets


def _supports(*entries):
    _, parsed = parse_supports({"mode": "replace", "list": list(entries)})
    return parsed


def _top(points, tets):
    f = boundary_facets(tets)
    return f[np.isclose(points[f][:, :, 2], 20.0).all(axis=1)]


@pytest.mark.parametrize("fmt", ["msh41", "msh22"])
def test_the_gmsh_volume_of_the_whole_liver_is_refused_as_a_support(tmp_path, fmt):
    points, tets, _ = shuffled_box(seed=3)
    path = tmp_path / "liver.msh"
    write_volume(path, fmt, points, tets, {"top": (3, _top(points, tets))})  # + physical volume 'liver' (tag 1)
    groups = read_file_groups(path)
    floor, = _supports({"name": "floor", "kind": "foundation", "stiffness": {"total_n_per_mm": 40.0}, "group": "liver"})
    with pytest.raises(SupportError) as err:
        select_facets(points, boundary_facets(tets), floor, file_groups=lambda: groups)
    msg = str(err.value)
    assert "support 'floor'" in msg and "'liver' is a 3-D (volume) group" in msg
    assert f"holding all {len(tets)} tetrahedra" in msg and "its boundary is the whole liver surface" in msg
    assert "more than 90 % of the surface's area" in msg
    assert "surface (2-D) group instead (its surface groups: ['top'])" in msg
    # the surface group still works
    top, = _supports({"name": "top", "kind": "fixed", "group": "top"})
    mask, _ = select_facets(points, boundary_facets(tets), top, file_groups=lambda: groups)
    assert mask.sum() == len(_top(points, tets))


def _with_region(tmp_path, points, tets, region):
    import meshio

    path = tmp_path / "liver.vtu"
    meshio.write(path, meshio.Mesh(points, [("tetra", tets)], cell_data={"region": [region.astype(np.int32)]}))
    return read_file_groups(path)


def test_a_material_array_tagging_every_tet_is_refused(tmp_path):
    points, tets, _ = shuffled_box(seed=4)
    groups = _with_region(tmp_path, points, tets, np.full(len(tets), 7))
    s, = _supports({"name": "floor", "kind": "foundation", "stiffness": {"total_n_per_mm": 40.0}, "group": 7})
    with pytest.raises(SupportError, match=rf"is a 3-D \(volume\) group .* holding all {len(tets)} tetrahedra, "
                                           r"and its boundary is the whole liver surface"):
        select_facets(points, boundary_facets(tets), s, file_groups=lambda: groups)


def test_a_sub_volume_still_gives_its_faces_on_the_surface(tmp_path):
    """The tets at one end (next to a vessel, say): their boundary faces are the support, as documented."""
    points, tets, _ = shuffled_box(seed=5, shape=(6, 2, 2))
    end = points[tets].mean(axis=1)[:, 0] < 5.0
    groups = _with_region(tmp_path, points, tets, np.where(end, 2, 1))
    facets = boundary_facets(tets)
    s, = _supports({"name": "cava", "kind": "fixed", "group": {"array": "region", "value": 2}})
    mask, _ = select_facets(points, facets, s, file_groups=lambda: groups)
    expected = (points[facets][:, :, 0] <= 5.0 + 1e-9).all(axis=1)
    np.testing.assert_array_equal(mask, expected)
    assert 0 < mask.sum() < len(facets) / 2


def test_a_group_of_most_of_the_tets_is_refused_by_its_share_of_the_surface(tmp_path):
    """All but the tets at one end: not every tet, but more than 90 % of the surface's area."""
    points, tets, _ = shuffled_box(seed=6, shape=(24, 2, 2), size=(120.0, 20.0, 20.0))
    body = points[tets].mean(axis=1)[:, 0] > 5.0
    groups = _with_region(tmp_path, points, tets, np.where(body, 1, 2))
    s, = _supports({"name": "floor", "kind": "foundation", "stiffness": {"total_n_per_mm": 40.0},
                    "group": {"array": "region", "value": 1}})
    with pytest.raises(SupportError, match=rf"holding {int(body.sum())} of the file's {len(tets)} tetrahedra, "
                                           r"and its boundary is 9\d\.\d % of the liver surface"):
        select_facets(points, boundary_facets(tets), s, file_groups=lambda: groups)


def test_face_matching_holds_for_node_ids_beyond_int64_keys():
    """The boundary faces a group of tets owns are matched by whole sorted rows: node ids above 2.1 M (where the
    old key n^2 a + n b + c overflowed int64) give the same faces as the small mesh they are offset from."""
    from liverforce.mesh.groups import faces_among

    points, tets, _ = shuffled_box(seed=7, shape=(6, 2, 2))
    facets = boundary_facets(tets)
    end = tets[points[tets].mean(axis=1)[:, 0] < 5.0]
    own_faces = end[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3)
    expected = np.array([frozenset(f) in {frozenset(g) for g in own_faces.tolist()} for f in facets.tolist()])
    assert 0 < expected.sum() < len(facets)
    np.testing.assert_array_equal(faces_among(facets, own_faces), expected)
    big = 3_000_000
    np.testing.assert_array_equal(faces_among(facets + big, own_faces[:, ::-1] + big), expected)
    # two faces the old key mixed up at 3.1 M nodes (it wraps around): told apart here
    n = 3_100_000
    a, b = np.array([[n - 3, n - 2, n - 1]]), np.array([[n - 4, n - 2, n - 1]])
    with np.errstate(over="ignore"):
        key = lambda f: np.sort(f, axis=1) @ np.array([n * n, n, 1], dtype=np.int64)  # noqa: E731
        assert np.any(key(np.concatenate([a, b])) < 0)  # the old key overflowed here
    assert faces_among(a, b).tolist() == [False] and faces_among(a, np.concatenate([b, a[:, ::-1]])).tolist() == [True]
