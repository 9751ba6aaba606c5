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


def _truncate_support(src, dst):
    """``src`` written as ASCII VTU to ``dst`` with the last value of its ``support`` array dropped."""
    meshio.write(dst, meshio.read(src), file_format="vtu", binary=False)
    text = dst.read_text()
    head = re.search(r'<DataArray[^>]*Name="support"[^>]*>', text)
    end = text.index("</DataArray>", head.end())
    values = text[head.end():end].split()
    dst.write_text(text[:head.end()] + "\n" + "\n".join(values[:-1]) + "\n" + text[end:])


@pytest.mark.parametrize("how, message", [
    ("free", r"free facets \(region 0, e\.g\. facet \d+\) are held by a support \(cell data 'support' = 1\)"),
    ("below", r"cell data 'support' holds -2 on facet \d+; values are a support's index \(0, 1, \.\.\.\) or -1"),
    ("fraction", r"cell data 'support' holds non-integer values \(dtype float64\)"),
    ("two codes", r"support 0 holds facets of region codes \[1, 3\]; a support sets one code"),
    ("short", r"A cell-data array \(region, visible or support\) does not hold one value per cell: was it edited\?"),
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
    if how == "short":
        _truncate_support(tmp_path / "lab.vtu", bad)
    else:
        _tamper(tmp_path / "lab.vtu", bad, s + 0.5 * (s == 0) if how == "fraction" else s)
    with pytest.raises(MeshFileError, match=r"bad\.vtu: .*" + message + r".*snakemake --forcerun mesh"):
        read_mesh(bad)


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
