"""Bad inputs are repaired (and say so) or refused with a GeometryError naming the file."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import trimesh

from liverforce.geometry import GeometryError, load_surface
from liverforce.geometry.procedural import cube_phantom

EDGE = 200.0


def save(tmp_path, name, vertices, faces):
    path = tmp_path / name
    trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces), process=False).export(path)
    return path


def cube(edge=EDGE, div=2, centre=(0.0, 0.0, 0.0)):
    c = cube_phantom(edge, divisions=div, centre_mm=centre)
    return c.vertices, c.faces


def load(path, **kw):
    kw.setdefault("max_edge_mm", None)
    return load_surface(path, **kw)


def test_empty_file(tmp_path):
    path = tmp_path / "empty.stl"
    path.write_bytes(b"")
    with pytest.raises(GeometryError, match=r"empty\.stl: the file is empty \(0 bytes\)\. Export"):
        load(path)


@pytest.mark.parametrize("name", ["garbage.stl", "garbage.obj", "garbage.ply", "garbage.vtk", "garbage.vtu", "garbage.msh"])
def test_garbage_bytes(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(GeometryError, match=name.replace(".", r"\.")):
        load(path)


def test_unsupported_suffix(tmp_path):
    path = tmp_path / "liver.xyz"
    path.write_text("1 2 3\n")
    with pytest.raises(GeometryError, match=r"liver\.xyz: unsupported file type '\.xyz'\. Use one of"):
        load(path)


def test_meshio_sys_exit_becomes_geometry_error(tmp_path):
    # a legacy VTK dataset meshio 5.3.5 does not support makes it call sys.exit(1)
    path = tmp_path / "grid.vtk"
    path.write_text("# vtk DataFile Version 3.0\nx\nASCII\nDATASET RECTILINEAR_GRID\nDIMENSIONS 2 2 2\n")
    with pytest.raises(GeometryError, match=r"grid\.vtk: meshio could not read"):
        load(path)


def test_open_box_holes_are_filled(tmp_path):
    v, f = cube(div=2)
    top = v[f].mean(axis=1)[:, 2] > EDGE / 2 - 1e-9
    path = save(tmp_path, "open_box.ply", v, f[~top])
    s, msgs = load(path)
    assert any(m.startswith("holes filled (1 holes") for m in msgs), msgs
    m = s.to_trimesh()
    assert m.is_watertight and m.is_winding_consistent and s.volume_mm3 > 0
    # the fan over the 8-edge square loop closes the box exactly (planar hole)
    assert s.volume_mm3 == pytest.approx(EDGE**3, rel=1e-9)


def test_too_open_surface_is_refused(tmp_path):
    v, f = cube(div=2)
    keep = v[f].mean(axis=1)[:, 2] < -EDGE / 2 + 1e-9  # only the bottom face
    keep |= np.abs(v[f].mean(axis=1)[:, 0]) > EDGE / 2 - 1e-9  # plus two side faces
    path = save(tmp_path, "sheet.ply", v, f[keep])
    with pytest.raises(GeometryError, match=r"sheet\.ply: open surface.*(too large|touch)"):
        load(path)


def test_small_second_component_is_dropped(tmp_path):
    v1, f1 = cube()
    v2, f2 = cube(edge=20.0, centre=(400.0, 0.0, 0.0))
    path = save(tmp_path, "two.stl", np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)]))
    s, msgs = load(path)
    assert any("largest component kept (1 smaller components dropped" in m for m in msgs), msgs
    assert s.volume_mm3 == pytest.approx(EDGE**3, rel=1e-9)


def test_two_comparable_components_are_refused(tmp_path):
    v1, f1 = cube()
    v2, f2 = cube(centre=(400.0, 0.0, 0.0))
    path = save(tmp_path, "two_livers.stl", np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)]))
    with pytest.raises(GeometryError, match=r"two_livers\.stl: 2 disconnected components.*Keep only the liver"):
        load(path)


def test_inverted_normals_are_flipped(tmp_path):
    v, f = cube()
    path = save(tmp_path, "inside_out.ply", v, f[:, ::-1])
    s, msgs = load(path)
    assert any(m.startswith("normals flipped") for m in msgs), msgs
    assert s.volume_mm3 == pytest.approx(EDGE**3, rel=1e-9)


def test_inconsistent_winding_is_fixed(tmp_path):
    v, f = cube()
    f = f.copy()
    f[::3] = f[::3, ::-1]
    path = save(tmp_path, "mixed.ply", v, f)
    s, msgs = load(path)
    assert any(m.startswith("winding made consistent") for m in msgs), msgs
    assert s.volume_mm3 == pytest.approx(EDGE**3, rel=1e-9)


def test_degenerate_triangles_are_removed(tmp_path):
    v, f = cube()
    bad = np.array([[0, 0, 1], [2, 3, 3], [5, 5, 5]])
    path = save(tmp_path, "degenerate.ply", v, np.vstack([f, bad]))
    s, msgs = load(path)
    assert any(m.startswith("degenerate triangles removed (3") for m in msgs), msgs
    assert s.volume_mm3 == pytest.approx(EDGE**3, rel=1e-9) and len(s.faces) == len(f)


def test_duplicate_vertices_and_triangles_are_merged(tmp_path):
    v, f = cube()
    v2 = np.vstack([v, v])  # every vertex twice; second copy used by a duplicate of every face
    f2 = np.vstack([f, f + len(v)])
    path = save(tmp_path, "dup.ply", v2, f2)
    s, msgs = load(path)
    assert any("duplicate vertices" in m for m in msgs) and any("duplicate triangles" in m for m in msgs), msgs
    assert s.volume_mm3 == pytest.approx(EDGE**3, rel=1e-9)


def test_isolated_collinear_triangle_is_dropped(tmp_path):
    v, f = cube()
    extra = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [20.0, 0.0, 0.0]]) + 500.0
    path = save(tmp_path, "sliver.ply", np.vstack([v, extra]), np.vstack([f, [[len(v), len(v) + 1, len(v) + 2]]]))
    s, msgs = load(path)
    assert any(m.startswith("zero-area triangles repaired (1 with three collinear") and "1 dropped" in m
               for m in msgs), msgs
    assert s.volume_mm3 == pytest.approx(EDGE**3, rel=1e-9) and len(s.faces) == len(f)


def test_collinear_triangle_in_the_surface_is_removed_by_a_split(tmp_path):
    """A zero-area triangle (a, b, m), m the midpoint of ab, closing a split of one side of ab."""
    v, f = cube()
    a, b, c = f[0]
    m = len(v)
    v = np.vstack([v, 0.5 * (v[a] + v[b])])
    f = np.vstack([f[1:], [[a, m, c], [m, b, c], [a, b, m]]])  # the other side of ab stays unsplit
    path = save(tmp_path, "cap.ply", v, f)
    s, msgs = load(path)
    assert any(m.startswith("zero-area triangles repaired (1 ") and "1 removed by splitting" in m for m in msgs), msgs
    mesh = s.to_trimesh()
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert s.volume_mm3 == pytest.approx(EDGE**3, rel=1e-9) and s.area_mm2 == pytest.approx(6 * EDGE**2, rel=1e-9)


def test_non_manifold_fin_is_removed(tmp_path):
    v, f = cube()
    a, b = f[0][:2]  # a fin: a third triangle on an existing edge
    fin = np.vstack([v, [[0.0, 0.0, 500.0]]])
    path = save(tmp_path, "fin.ply", fin, np.vstack([f, [[a, b, len(v)]]]))
    s, msgs = load(path)
    assert any(m.startswith("non-manifold edges repaired (1 edges shared by more than two triangles: "
                            "1 dangling triangles removed") for m in msgs), msgs
    assert s.volume_mm3 == pytest.approx(EDGE**3, rel=1e-9) and len(s.faces) == len(f)


def test_boxes_glued_on_a_face_are_refused(tmp_path):
    """Two boxes sharing a face: the shared wall makes its whole rim non-manifold; cutting it out is too much."""
    v1, f1 = cube()
    v2, f2 = cube(centre=(EDGE, 0.0, 0.0))
    path = save(tmp_path, "glued.stl", np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)]))
    with pytest.raises(GeometryError, match=r"glued\.stl: non-manifold surface: \d+ edges are shared by more "
                                            r"than two triangles.*(too much|too many).*MeshLab"):
        load(path)


def sphere(radius=120.0, subdivisions=3):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices), np.asarray(s.faces)


def folded_sphere():
    v, f = sphere()
    v = v.copy()
    i = int(np.argmax(v[:, 2]))
    v[i] = [3.0, 2.0, -150.0]  # the north pole dives through the body and out of the south cap
    return v, f, i


def test_local_self_intersection_is_repaired_locally(tmp_path):
    """Only the triangles round the fold change: every other vertex and triangle is the file's, exactly."""
    from liverforce.geometry.repair import self_intersections

    v, f, pole = folded_sphere()
    v = v.astype(np.float32).astype(np.float64)  # as the PLY file holds them
    assert len(self_intersections(v, f)) > 0
    path = save(tmp_path, "folded.ply", v, f)
    s, msgs = load(path)
    assert any(m.startswith("self-intersections removed locally (8 intersecting triangle pairs")
               and "(MeshFix), every other triangle kept as given" in m for m in msgs), msgs
    m = s.to_trimesh()
    assert m.is_watertight and len(self_intersections(s.vertices, s.faces)) == 0
    # the spike is gone: the sphere less its polar cap (a pentagon of the icosphere's 3rd subdivision)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=120.0).volume
    assert s.volume_mm3 == pytest.approx(ball, rel=1e-3) and s.volume_mm3 < ball
    others = np.delete(v, pole, axis=0)
    assert len(s.vertices) == len(others)
    assert {tuple(x) for x in s.vertices.tolist()} == {tuple(x) for x in others.tolist()}  # bit for bit
    given = {frozenset(map(tuple, v[t].tolist())) for t in f}
    same = sum(frozenset(map(tuple, s.vertices[t].tolist())) in given for t in s.faces)
    assert same == len(f) - 6  # the pole's five triangles and one more replaced, by four


def test_self_intersection_falls_back_to_a_voxel_remesh(tmp_path, monkeypatch):
    """Where the local repair fails, the whole surface is rebuilt from its inside, and the message says so."""
    import liverforce.geometry.repair as repair

    monkeypatch.setattr(repair, "local_self_intersection_repair", lambda v, f: None)
    v, f, _ = folded_sphere()
    s, msgs = load(save(tmp_path, "folded.ply", v, f))
    assert any(m.startswith("self-intersections removed by voxel remeshing") and "local repair failed" in m
               for m in msgs), msgs
    m = s.to_trimesh()
    assert m.is_watertight and s.volume_mm3 > 0 and len(s.vertices) > 10 * len(v)


def test_a_fold_far_from_the_origin_is_repaired_locally_too():
    """MeshFix hands its points back rounded to float32: a liver in scanner coordinates, a metre and more from the
    origin, keeps its local repair (the surface is centred for it) and every vertex but the fold's, bit for bit."""
    from liverforce.geometry.repair import local_self_intersection_repair

    v, f, pole = folded_sphere()
    v = v + np.array([1.0e5, -2.5e4, 3.0e3])
    fixed = local_self_intersection_repair(v, f)
    assert fixed is not None
    v2, f2, removed, added = fixed
    assert (removed, added) == (6, 4)
    assert {tuple(x) for x in v2.tolist()} == {tuple(x) for x in np.delete(v, pole, axis=0).tolist()}


def test_local_repair_refuses_what_is_not_local():
    """The local repair hands back None (the caller's fallback) when it would replace too much."""
    from liverforce.geometry.repair import local_self_intersection_repair

    v, f, _ = folded_sphere()
    assert local_self_intersection_repair(v, f) is not None
    assert local_self_intersection_repair(v, f, max_replaced=5 / len(f)) is None  # 6 triangles replaced


def test_many_self_intersections_are_refused(tmp_path):
    v, f = sphere()
    v = v.copy()
    v[::3] *= -0.9  # a third of the vertices thrown through the centre
    path = save(tmp_path, "crumpled.ply", v, f)
    with pytest.raises(GeometryError, match=r"crumpled\.ply: the surface intersects itself .*too many"):
        load(path)


def test_liver_with_wrong_units_is_refused(tmp_path):
    from liverforce.geometry.procedural import procedural_liver

    s = procedural_liver(0)
    path = save(tmp_path, "tiny_liver.stl", s.vertices / 40.0, s.faces)  # ~6 mm across
    with pytest.raises(GeometryError, match=r"tiny_liver\.stl: with units mm .* 6\.\d+ mm across.*units are probably wrong"):
        load(path, units="mm")
    with pytest.raises(GeometryError, match=r"tiny_liver\.stl: with units m .*6\d{3}(\.\d+)? mm across"):
        load(path, units="m")
    with pytest.raises(GeometryError, match=r"tiny_liver\.stl: cannot guess the units"):
        load(path, units="auto")
    ok, _ = load(path, units=40)
    assert 240 < ok.extent_mm.max() < 280


def test_auto_units_name_inches_where_they_would_fit(tmp_path, caplog):
    """``units: auto`` never picks inches (a SOFA liver of arbitrary units would pass as one), but says so where
    inches too would make the liver liver-sized, and what to state: in the note (a warning; the report's repairs) of a
    257 mm liver written in inches (10.1 units across, taken as cm: 101 mm), and in the refusal of one 9 units
    across (no unit fits; in inches 229 mm)."""
    from liverforce.geometry.procedural import procedural_liver

    s = procedural_liver(0)
    extent = float(np.ptp(s.vertices, axis=0).max())
    path = save(tmp_path, "liver_in.stl", s.vertices / 25.4, s.faces)
    with caplog.at_level(logging.WARNING):
        surface, msgs = load(path, units="auto")
    note = (f"units guessed as 'cm' (largest extent {extent / 25.4:.4g} file units -> {extent / 2.54:.4g} mm); in "
            f"inches it would be {extent:.4g} mm across, liver-sized too: if the file is in inches, state units: 25.4")
    assert surface.meta["conversion"]["units"] == "cm" and note in msgs
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING] == [f"{path}: {note}"]
    ok, _ = load(path, units=25.4)
    assert ok.extent_mm.max() == pytest.approx(extent, rel=1e-6)
    path = save(tmp_path, "liver_9.stl", s.vertices * (9.0 / extent), s.faces)
    with pytest.raises(GeometryError, match=r"liver_9\.stl: cannot guess the units: .* none is liver-sized "
                                            r"\(100-450 mm\); in inches it would be 229 mm: if the file is "
                                            r"in inches, state units: 25\.4"):
        load(path, units="auto")
    path = save(tmp_path, "liver_m.stl", s.vertices / 1000.0, s.faces)  # metres: inches would be 6.5 mm
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        surface, msgs = load(path, units="auto")
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert surface.meta["conversion"]["units"] == "m" and not any("inches" in m for m in msgs)


@pytest.mark.parametrize("units", ["inch", -2.0, 0, "", True])
def test_invalid_units_are_refused(tmp_path, units):
    v, f = cube()
    path = save(tmp_path, "cube.stl", v, f)
    with pytest.raises(GeometryError, match=r"cube\.stl: invalid units"):
        load(path, units=units)


def test_nifti_without_the_label(tmp_path):
    import nibabel as nib

    data = np.zeros((20, 20, 20), dtype=np.int16)
    data[5:15, 5:15, 5:15] = 1
    path = tmp_path / "seg_no_liver.nii.gz"
    nib.save(nib.Nifti1Image(data, np.diag([12.0, 12.0, 12.0, 1.0])), path)
    with pytest.raises(GeometryError, match=r"seg_no_liver\.nii\.gz: label 6 is not present .*\[1\].*label="):
        load_surface(path, label=6)
    empty = tmp_path / "seg_empty.nii"
    nib.save(nib.Nifti1Image(np.zeros((8, 8, 8), dtype=np.uint8), np.eye(4)), empty)
    with pytest.raises(GeometryError, match=r"seg_empty\.nii: the volume holds no non-zero label"):
        load_surface(empty)


def test_auto_units_of_a_label_volume_whose_header_states_none_are_guessed_from_its_size(tmp_path):
    """An affine in metres with no unit in the header: units auto guesses m, as for a mesh (not mm, then refused
    as 0.24 mm across, with 'auto' among the fixes the message named)."""
    import nibabel as nib

    data = np.zeros((30, 20, 20), dtype=np.int16)
    data[5:25, 5:15, 5:15] = 1  # 20 x 10 x 10 voxels of 12 mm: 240 mm across (marching cubes, half-voxel rims)
    path = tmp_path / "liver_m.nii.gz"
    nib.save(nib.Nifti1Image(data, np.diag([0.012, 0.012, 0.012, 1.0])), path)  # xyzt_units: unknown
    surface, msgs = load_surface(path, units="auto")
    assert surface.meta["conversion"]["units"] == "m" and surface.meta["scale_to_mm"] == 1000.0
    assert 200 < float(np.ptp(surface.vertices, axis=0).max()) < 260
    assert msgs[1:3] == ["the image header states no units: guessed from the liver's size",
                         "units guessed as 'm' (largest extent 0.24 file units -> 240 mm)"]


def test_missing_file(tmp_path):
    with pytest.raises(GeometryError, match=r"nowhere\.stl: file not found"):
        load(tmp_path / "nowhere.stl")


def test_auto_units_of_a_volume_mesh_name_inches_too(tmp_path, caplog):
    """A tetrahedral mesh taken as given guesses its units as a surface does, with the same note on inches."""
    from liverforce.geometry.volume_mesh import load_volume_mesh
    from tests.test_byo_volume_files import shuffled_box, write_volume

    points, tets, _ = shuffled_box(seed=1, size=(254.0, 150.0, 120.0))  # mm
    write_volume(tmp_path / "box_in.vtu", "vtu", points / 25.4, tets)  # in inches: 10 units across
    with caplog.at_level(logging.WARNING):
        vm, msgs = load_volume_mesh(tmp_path / "box_in.vtu", units="auto")
    note = ("units guessed as 'cm' (largest extent 10 file units -> 100 mm); in inches it would be 254 mm across, "
            "liver-sized too: if the file is in inches, state units: 25.4")
    assert note in msgs and vm.meta["conversion"]["units"] == "cm"
    assert any(r.levelno == logging.WARNING and note in r.getMessage() for r in caplog.records)
