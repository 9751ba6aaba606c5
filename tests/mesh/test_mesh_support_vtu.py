"""The mesh VTU carries which of the lab's supports holds each facet (cell data ``support``), and the features
JSON's ``supports`` say which index is which support. Before, ``write_mesh`` wrote ``region`` and ``visible``
only: a mesh read back (by later stages, or a lab opening ``mesh/<id>.vtu`` in ParaView to check its boundary
conditions) could not tell two fixed supports apart; only the mesh stage's ``regions.png`` showed them."""

from __future__ import annotations

import json
import re

import meshio
import numpy as np
import pytest

from liverforce.mesh.given import build_given_mesh
from liverforce.mesh.io import MeshFileError, read_mesh, support_records, write_mesh
from liverforce.mesh.supports import parse_supports
from tests.mesh.lab_stage import mesh_stage


@pytest.fixture(scope="module")
def lab_supports(liver_surface):
    """Two fixed supports (one region code, told apart only by ``facet_support``) and a foundation floor, on the
    procedural liver (mesh frame = RAS, mm)."""
    V, F = liver_surface.vertices, liver_surface.faces
    cent = V[F].mean(axis=1)
    cava = cent[np.argmin(cent[:, 1])]  # the most posterior point
    left = cent[np.argmin(cent[:, 0] - 0.5 * cent[:, 2])]  # far left, up
    return [
        {"name": "cava", "kind": "fixed", "sphere": {"center_mm": cava.round(3).tolist(), "radius_mm": 20.0}},
        {"name": "left vein", "kind": "fixed", "sphere": {"center_mm": left.round(3).tolist(), "radius_mm": 15.0}},
        {"name": "floor", "kind": "foundation", "region": "visceral", "stiffness": {"total_n_per_mm": 40.0},
         "box": {"min_mm": [-1e3, -1e3, -1e3], "max_mm": [1e3, 1e3, float(cent[:, 2].min() + 15)]}},
    ]


@pytest.fixture(scope="module")
def held(liver_mesh, lab_supports):
    """The liver mesh as given with the lab's supports, ``mode: replace`` (every tagged facet is a lab's)."""
    return build_given_mesh(liver_mesh.points, liver_mesh.tets,
                            supports=parse_supports({"mode": "replace", "list": lab_supports}))


def _tamper(src, dst, values):
    """Rewrite the VTU ``src`` as ``dst`` with the triangles' ``support`` values replaced."""
    raw = meshio.read(src)
    raw.cell_data["support"] = [raw.cell_data["support"][0], np.asarray(values)]
    meshio.write(dst, raw, file_format="vtu")


@pytest.mark.parametrize("mode", ["replace", "add"])
def test_a_mesh_with_facet_support_keeps_it_exactly_and_one_without_reads_none(tmp_path, liver_mesh, lab_supports,
                                                                              mode):
    mesh = build_given_mesh(liver_mesh.points, liver_mesh.tets,
                            supports=parse_supports({"mode": mode, "list": lab_supports[:2]}))
    assert set(np.unique(mesh.facet_support)) == {-1, 0, 1}
    if mode == "add":  # the auto-tagged regions beneath the lab's supports: tagged, held by none
        assert ((mesh.facet_support == -1) & (mesh.facet_region != 0)).any()
    write_mesh(tmp_path / "lab.vtu", mesh)
    back = read_mesh(tmp_path / "lab.vtu")
    assert back.facet_support.dtype == np.int64
    np.testing.assert_array_equal(back.facet_support, mesh.facet_support)
    back.validate()
    raw = meshio.read(tmp_path / "lab.vtu")
    assert set(raw.cell_data) == {"region", "visible", "support"}
    assert (raw.cell_data["support"][0] == -1).all()  # none on the tets
    # a built-in liver: no support array in its file, None read back (as every mesh written before)
    write_mesh(tmp_path / "built_in.vtu", liver_mesh)
    assert set(meshio.read(tmp_path / "built_in.vtu").cell_data) == {"region", "visible"}
    assert read_mesh(tmp_path / "built_in.vtu").facet_support is None


def _edit_cell_data(src, dst, edit, name="support"):
    """``src`` written as ASCII VTU to ``dst`` with the values of its cell-data array ``name`` (as text: the tets',
    then the facets') replaced by ``edit(values)``, as a hand edit of the file would."""
    meshio.write(dst, meshio.read(src), file_format="vtu", binary=False)
    text = dst.read_text()
    head = re.search(rf'<DataArray[^>]*Name="{name}"[^>]*>', text)
    end = text.index("</DataArray>", head.end())
    values = text[head.end():end].split()
    dst.write_text(text[:head.end()] + "\n" + "\n".join(edit(values)) + "\n" + text[end:])


@pytest.mark.parametrize("how, message", [
    ("free", r"free facets \(region 0, e\.g\. facet \d+\) are held by a support \(cell data 'support' = 1\)"),
    ("below", r"cell data 'support' holds -2 on facet \d+; values are a support's index \(0, 1, \.\.\.\) or -1"),
    ("fraction", r"cell data 'support' holds non-integer values \(dtype float64\)"),
    ("two codes", r"support 0 holds facets of region codes \[1, 3\]; a support sets one code"),
])
def test_a_tampered_support_array_is_refused_naming_the_file_and_what_to_do(tmp_path, held, how, message):
    write_mesh(tmp_path / "lab.vtu", held)
    bad = tmp_path / "bad.vtu"
    s = held.facet_support.copy()
    if how == "free":
        s[np.flatnonzero(held.facet_region == 0)[0]] = 1
    elif how == "below":
        s[0] = -2
    elif how == "two codes":
        s[held.facet_support == 2] = 0  # the floor's facets (visceral) given to the cava (fixed)
    _tamper(tmp_path / "lab.vtu", bad, s + 0.5 * (s == 0) if how == "fraction" else s)
    with pytest.raises(MeshFileError, match=r"bad\.vtu: .*" + message + r".*snakemake --forcerun mesh"):
        read_mesh(bad)


def _paraview_vtu(src, dst, support=None):
    """``src`` written to ``dst`` as ParaView saves a VTU by default (appended raw binary, uncompressed, UInt64
    headers), the facets' ``support`` replaced by ``support`` when given (of any length)."""
    raw = meshio.read(src)
    tets, tris = (np.asarray(b.data, dtype=np.int64) for b in raw.cells)
    cell = {k: np.concatenate([np.asarray(a) for a in v]) for k, v in raw.cell_data.items()}
    if support is not None:
        cell["support"] = np.concatenate([cell["support"][:len(tets)], np.asarray(support, dtype=np.int32)])
    arrays = {"Points": [("Points", np.asarray(raw.points, dtype=np.float64), 3)],
              "Cells": [("connectivity", np.concatenate([tets.ravel(), tris.ravel()]), 1),
                        ("offsets", np.cumsum([4] * len(tets) + [3] * len(tris)).astype(np.int64), 1),
                        ("types", np.array([10] * len(tets) + [5] * len(tris), dtype=np.uint8), 1)],
              "CellData": [(k, v, 1) for k, v in cell.items()]}
    kinds = {np.dtype(t): n for t, n in ((np.float64, "Float64"), (np.int64, "Int64"), (np.int32, "Int32"),
                                         (np.int8, "Int8"), (np.uint8, "UInt8"))}
    xml, blob = [], b""
    for section, items in arrays.items():
        xml.append(f"<{section}>")
        for name, a, nc in items:
            comps = f' NumberOfComponents="{nc}"' if nc > 1 else ""  # as VTK writes it: only when more than 1
            xml.append(f'<DataArray type="{kinds[a.dtype]}" Name="{name}"{comps} format="appended" '
                       f'offset="{len(blob)}"/>')
            blob += np.uint64(a.nbytes).tobytes() + np.ascontiguousarray(a).tobytes()
        xml.append(f"</{section}>")
    head = ('<?xml version="1.0"?>\n<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" '
            f'header_type="UInt64">\n<UnstructuredGrid>\n<Piece NumberOfPoints="{len(raw.points)}" '
            f'NumberOfCells="{len(tets) + len(tris)}">\n' + "\n".join(xml) + "\n</Piece>\n</UnstructuredGrid>\n"
            '<AppendedData encoding="raw">\n_')
    dst.write_bytes(head.encode() + blob + b"\n</AppendedData>\n</VTKFile>\n")


@pytest.mark.parametrize("how", ["appended", "inserted", "binary", "paraview", "short", "region"])
def test_a_cell_data_array_not_one_value_per_cell_is_refused_naming_it_and_the_counts(tmp_path, held, how):
    """A ``support`` array with more values than the cells (two appended, one inserted before the first facet's,
    which shifts every facet's support by one; in the compressed binary write_mesh writes; in ParaView's appended
    raw binary) is refused naming the file, the array, both counts and what to do. Before, meshio kept the first
    values without a word and the mesh read back with plausible, wrong supports. One value short is refused so
    too (before: meshio's words, which named no array), and so is a ``region`` array too long."""
    write_mesh(tmp_path / "lab.vtu", held)
    bad = tmp_path / "bad.vtu"
    tets, facets = len(held.tets), len(held.facets)
    cells, name = tets + facets, "region" if how == "region" else "support"
    if how == "appended":
        _edit_cell_data(tmp_path / "lab.vtu", bad, lambda v: [*v, "0", "1"])
    elif how == "inserted":
        _edit_cell_data(tmp_path / "lab.vtu", bad, lambda v: [*v[:tets], "-1", *v[tets:]])
    elif how == "short":
        _edit_cell_data(tmp_path / "lab.vtu", bad, lambda v: v[:-1])
    elif how == "region":
        _edit_cell_data(tmp_path / "lab.vtu", bad, lambda v: [*v, "0"], name="region")
    elif how == "paraview":  # saved in ParaView with a value inserted before the first facet's
        _paraview_vtu(tmp_path / "lab.vtu", tmp_path / "saved.vtu")  # saved as it was: read back the same
        assert b'encoding="raw"' in (tmp_path / "saved.vtu").read_bytes()
        back = read_mesh(tmp_path / "saved.vtu")
        for k in ("facets", "facet_region", "facet_support"):
            np.testing.assert_array_equal(getattr(back, k), getattr(held, k))
        _paraview_vtu(tmp_path / "lab.vtu", bad, np.append(-1, held.facet_support))
    else:  # a broken writer: meshio checks lengths when a Mesh is made, not when it is written
        raw = meshio.read(tmp_path / "lab.vtu")
        raw.cell_data["support"][1] = np.append(raw.cell_data["support"][1], np.int32([0, 1, 2]))
        meshio.write(bad, raw, file_format="vtu")
        assert b"<CellData>" in bad.read_bytes() and b'format="binary"' in bad.read_bytes()
    n = {"appended": cells + 2, "binary": cells + 3, "short": cells - 1}.get(how, cells + 1)
    if n > cells:  # what meshio alone reads: the first values, as many as the cells, and not a word
        got = meshio.read(bad).cell_data[name]
        assert [len(a) for a in got] == [tets, facets]
        if how in ("inserted", "paraview"):  # the facets' supports shifted by one, the last dropped: wrong
            np.testing.assert_array_equal(got[1], np.append(-1, held.facet_support[:-1]))
    redo = (r"or delete the 'support' array to read the mesh without the lab's supports" if name == "support"
            else r"or re-create it with liverforce\.mesh\.io\.write_mesh")
    dropped = (rf" \(meshio would keep the first {cells} without a word: the wrong ones if a value was inserted\)"
               if n > cells else "")
    with pytest.raises(MeshFileError) as exc:
        read_mesh(bad)
    assert re.fullmatch(rf"\S*bad\.vtu: cell data '{name}' holds {n} values, but the file has {cells} cells \({tets} "
                        rf"tetra, {facets} triangle\) and takes one value per cell, the tets' then the "
                        rf"facets'{dropped}\. Was it edited \(e\.g\. in ParaView\)\? Re-run the mesh stage "
                        rf"\(e\.g\. snakemake --forcerun mesh\) to write it again, {redo}", str(exc.value)), exc.value


def test_one_component_arrays_stated_as_columns_read_as_written(tmp_path, held):
    """A VTK writer that states ``NumberOfComponents="1"`` on the cell data (ours and ParaView leave it out) makes
    meshio read each array as a column, shape (n, 1): the mesh still reads back as written, supports included."""
    write_mesh(tmp_path / "lab.vtu", held)
    raw = meshio.read(tmp_path / "lab.vtu")
    raw.cell_data = {k: [np.asarray(a).reshape(-1, 1) for a in v] for k, v in raw.cell_data.items()}
    meshio.write(tmp_path / "cols.vtu", raw, file_format="vtu")
    assert b'NumberOfComponents="1"' in (tmp_path / "cols.vtu").read_bytes()
    assert meshio.read(tmp_path / "cols.vtu").cell_data["support"][1].shape == (len(held.facets), 1)
    back = read_mesh(tmp_path / "cols.vtu")
    for k in ("facets", "facet_region", "facet_visible", "facet_support"):
        np.testing.assert_array_equal(getattr(back, k), getattr(held, k))
        assert getattr(back, k).shape == getattr(held, k).shape


def test_a_vtu_of_two_pieces_is_refused_not_read_as_its_last(tmp_path, held):
    """A VTU whose mesh is split into two ``Piece`` elements (each a whole, valid mesh here): meshio keeps the last
    piece's cells only, on the points of both, without a word; read_mesh refuses it, saying what to do."""
    write_mesh(tmp_path / "lab.vtu", held)
    meshio.write(tmp_path / "one.vtu", meshio.read(tmp_path / "lab.vtu"), file_format="vtu", binary=False)
    text = (tmp_path / "one.vtu").read_text()
    start, end = text.index("<Piece"), text.index("</Piece>") + len("</Piece>")
    (tmp_path / "two.vtu").write_text(text[:end] + "\n" + text[start:end] + text[end:])
    got = meshio.read(tmp_path / "two.vtu")  # what meshio alone reads: one piece's cells on twice the points
    assert len(got.points) == 2 * len(held.points) and len(got.cells[0]) == len(held.tets)
    with pytest.raises(MeshFileError, match=r"two\.vtu: the file holds 2 pieces \(<Piece> elements\); a mesh is "
                       r"read from one .*Merge Blocks.*snakemake --forcerun mesh"):
        read_mesh(tmp_path / "two.vtu")


def test_a_meshio_without_the_reader_read_mesh_uses_is_no_corrupt_file(tmp_path, held, monkeypatch):
    """read_mesh decodes the VTU with meshio's private ``VtuReader`` (meshio is pinned): a meshio without it raises
    the ImportError, not a MeshFileError telling the user to re-create a file that is fine."""
    import meshio.vtu._vtu as vtu

    write_mesh(tmp_path / "lab.vtu", held)
    monkeypatch.delattr(vtu, "VtuReader")
    with pytest.raises(ImportError, match="VtuReader"):
        read_mesh(tmp_path / "lab.vtu")


def test_support_records_give_each_support_its_index_and_mesh_facets(held):
    records = support_records(held)
    assert [r["name"] for r in records] == ["cava", "left vein", "floor"]
    assert [r["index"] for r in records] == [0, 1, 2]
    assert [r["n_mesh_facets"] for r in records] == [int((held.facet_support == i).sum()) for i in range(3)]
    assert "index" not in held.meta["supports"][0]  # the mesh's own record is left as it was


@pytest.fixture(scope="module")
def lab_files(tmp_path_factory, liver_surface, liver_mesh):
    """The lab's liver as a surface (remeshed by the stage) and as a tet mesh (taken as given)."""
    d = tmp_path_factory.mktemp("lab_files")
    meshio.write(d / "liver.ply", meshio.Mesh(liver_surface.vertices, [("triangle", liver_surface.faces)]),
                 binary=True)
    meshio.write(d / "liver.vtu", meshio.Mesh(liver_mesh.points, [("tetra", liver_mesh.tets)]))
    return {"remesh": d / "liver.ply", "as_given": d / "liver.vtu"}


@pytest.mark.slow  # one of the default set's slowest (CI's --durations): run with -m slow
@pytest.mark.parametrize("kind", ["remesh", "as_given"])
def test_the_mesh_stage_writes_which_support_holds_each_facet_as_its_features_json_reports(tmp_path, lab_files,
                                                                                          lab_supports, kind):
    out, run = mesh_stage(tmp_path, lab_files[kind], {"mode": "replace", "list": lab_supports}, "warn")
    run()
    feats = json.loads((out / "imp-lab.features.json").read_text())
    assert feats["mesh_mode"] == kind
    raw = meshio.read(out / "imp-lab.vtu")
    tet_support, support = (np.asarray(a) for a in raw.cell_data["support"])
    region = np.asarray(raw.cell_data["region"][1])
    assert (tet_support == -1).all()
    reported = feats["supports"]
    assert [(r["index"], r["name"]) for r in reported] == list(enumerate(s["name"] for s in lab_supports))
    for r in reported:
        mine = support == r["index"]
        assert mine.sum() == r["n_mesh_facets"] > 0
        assert (region[mine] == r["region_code"]).all()
    assert set(np.unique(support)) == {-1, 0, 1, 2}
    np.testing.assert_array_equal(support >= 0, region != 0)  # replace: every tagged facet is a lab support's
    mesh = read_mesh(out / "imp-lab.vtu")
    np.testing.assert_array_equal(mesh.facet_support, support)
    cent = mesh.points[mesh.facets].mean(axis=1)
    spheres = [np.linalg.norm(cent - s["sphere"]["center_mm"], axis=1) <= s["sphere"]["radius_mm"]
               for s in lab_supports[:2]]
    if kind == "as_given":  # the stage selected on these very facets: exactly those, as counted in n_facets
        assert [r["n_facets"] for r in reported] == [r["n_mesh_facets"] for r in reported]
        floor = cent[:, 2] <= lab_supports[2]["box"]["max_mm"][2]
        expected = np.select([floor, spheres[1], spheres[0]], [2, 1, 0], -1)  # later supports override earlier
        np.testing.assert_array_equal(support, expected)
    else:  # remeshed: each held facet lies where its support selected input facets (a mesh facet's span apart)
        slack = 8.0
        for i, s in enumerate(lab_supports[:2]):
            d = np.linalg.norm(cent[support == i] - s["sphere"]["center_mm"], axis=1)
            assert (d <= s["sphere"]["radius_mm"] + slack).all()
        assert (cent[support == 2][:, 2] <= lab_supports[2]["box"]["max_mm"][2] + slack).all()


@pytest.mark.parametrize("how", ["below", "two codes"])
def test_a_support_array_read_mesh_would_refuse_is_never_written(tmp_path, held, how):
    import dataclasses

    s = held.facet_support.copy()
    if how == "below":
        s[0] = -2
    else:
        s[held.facet_support == 2] = 0  # the floor's facets (visceral) given to the cava (fixed)
    bad = dataclasses.replace(held, facet_support=s)
    with pytest.raises(ValueError, match=r"lab\.vtu: .*Not written: the mesh's facet_support and facet_region"):
        write_mesh(tmp_path / "lab.vtu", bad)
    assert not (tmp_path / "lab.vtu").exists()
