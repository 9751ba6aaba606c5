"""One PLY reader (:mod:`liverforce.geometry.ply`) for the mesh stage's point files and ``liverforce predict``'s
clouds and surfaces: the PLY variants labs and tools write are read alike by both callers, and a broken file is
refused by both with the file named (the mesh stage's wording ``expected ...`` kept), never a traceback, never a
silently short point list."""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.geometry.ply import PlyError, read_ply
from liverforce.mesh.supports import SupportError, read_point_file
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.files import read_points, read_surface

P = np.array([[0.0, 0.0, 0.0], [10.5, 0.0, 0.0], [0.0, 10.25, 0.0], [0.0, 0.0, -10.0]])
F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
TYPES = {"f4": "float", "f8": "double", "u1": "uchar", "i4": "int", "u4": "uint"}


def _header(fmt, vprops, nv, fprops=(), nf=0, before=(), eol="\n"):
    lines = ["ply", f"format {fmt} 1.0", "comment exported by a lab", "obj_info scanner frame", *before,
             f"element vertex {nv}", *(f"property {TYPES[t]} {n}" for t, n in vprops)]
    if fprops:
        lines += [f"element face {nf}", *fprops]
    return (eol.join([*lines, "end_header"]) + eol).encode()


def _binary(endian, vprops=(("f4", "x"), ("f4", "y"), ("f4", "z")), faces=None, itype="i4", name="vertex_indices",
            face_flags=False):
    fmt = "binary_little_endian" if endian == "<" else "binary_big_endian"
    fprops = () if faces is None else (f"property list uchar {TYPES[itype]} {name}",
                                       *(["property uchar flags"] if face_flags else []))
    out = _header(fmt, vprops, len(P), fprops, 0 if faces is None else len(faces))
    v = np.zeros(len(P), [(n, endian + t) for t, n in vprops])
    for t, n in vprops:
        v[n] = P[:, "xyz".index(n)] if n in "xyz" else 7
    out += v.tobytes()
    for tri in faces if faces is not None else []:
        out += np.uint8(3).tobytes() + np.asarray(tri, endian + itype).tobytes() + (b"\x05" if face_flags else b"")
    return out


def _ascii(vprops=(("f4", "x"), ("f4", "y"), ("f4", "z")), faces=None, fprops=None, face_extra="", eol="\n",
           before=(), before_rows=""):
    fprops = fprops or ("property list uchar int vertex_indices",)
    out = _header("ascii", vprops, len(P), fprops if faces is not None else (), len(faces or []), before, eol)
    out += before_rows.encode()
    for p in P:
        out += (" ".join(repr(float(p["xyz".index(n)])) if n in "xyz" else "7" for _, n in vprops) + eol).encode()
    for tri in faces or []:
        out += (f"{len(tri)} " + " ".join(map(str, tri)) + face_extra + eol).encode()
    return out


GOOD = {  # file name: (bytes, triangles read)
    "ascii_points.ply": (_ascii(), None),
    "ascii_crlf_faces.ply": (_ascii(faces=F.tolist(), eol="\r\n"), F),
    "ascii_normals_colours.ply": (_ascii(vprops=(("f4", "nx"), ("f8", "z"), ("f4", "x"), ("f4", "y"), ("u1", "red"))),
                                  None),
    "ascii_face_flags.ply": (_ascii(faces=F.tolist(), fprops=("property list uchar int vertex_indices",
                                                              "property uchar flags"), face_extra=" 1"), F),
    "ascii_camera_first.ply": (_ascii(before=("element camera 1", "property float view_px", "property float view_py"),
                                      before_rows="5 6\n"), None),
    "binary_le_points.ply": (_binary("<"), None),
    "binary_be_points.ply": (_binary(">"), None),
    "binary_le_double_colour_faces.ply": (_binary("<", (("f8", "x"), ("f8", "y"), ("f8", "z"), ("u1", "red")), F), F),
    "binary_be_uint_faces.ply": (_binary(">", faces=F, itype="u4"), F),
    "binary_le_face_flags.ply": (_binary("<", faces=F, face_flags=True), F),
    "binary_le_vertex_index.ply": (_binary("<", faces=F, name="vertex_index"), F),
}


@pytest.mark.parametrize("name", sorted(GOOD))
def test_ply_variants_are_read_alike_by_the_mesh_stage_and_predict(tmp_path, name):
    data, tri = GOOD[name]
    path = tmp_path / name
    path.write_bytes(data)
    got = read_ply(path)
    np.testing.assert_allclose(got.points, P, rtol=0, atol=1e-6)
    np.testing.assert_allclose(read_point_file(path, "mm"), P, atol=1e-6)  # a support / exertion-point file
    np.testing.assert_allclose(read_points(path), P, atol=1e-6)  # liverforce predict's cloud
    if tri is None:
        assert got.faces is None
        with pytest.raises(PredictionInputError, match=f"{name}: a surface needs faces"):
            read_surface(path)
    else:
        np.testing.assert_array_equal(got.faces, tri)
        pts, faces = read_surface(path, units="m")
        np.testing.assert_allclose(pts, P * 1000.0, atol=1e-3)
        np.testing.assert_array_equal(faces, tri)


def _binary_polygons(polys):
    out = _header("binary_little_endian", (("f4", "x"), ("f4", "y"), ("f4", "z")), len(P),
                  ("property list uchar int vertex_indices",), len(polys)) + P.astype("<f4").tobytes()
    return out + b"".join(np.uint8(len(f)).tobytes() + np.asarray(f, "<i4").tobytes() for f in polys)


@pytest.mark.parametrize("kind", ["ascii", "binary_quads", "binary_mixed"])
def test_a_quad_face_is_refused_as_a_surface_but_its_vertices_are_a_cloud(tmp_path, kind):
    """Binary faces of one length are read in one block, quads too; mixed lengths are read again row by row."""
    path = tmp_path / "quad.ply"
    quads = {"ascii": 1, "binary_quads": 2, "binary_mixed": 1}[kind]
    path.write_bytes(_ascii(faces=[[0, 1, 2, 3]]) if kind == "ascii" else
                     _binary_polygons([[0, 1, 2, 3]] * quads + ([[0, 2, 1]] if kind == "binary_mixed" else [])))
    got = read_ply(path)
    assert got.polygons == quads
    np.testing.assert_array_equal(got.faces, [[0, 2, 1]] if kind == "binary_mixed" else np.zeros((0, 3)))
    np.testing.assert_allclose(read_points(path), P, atol=1e-6)
    np.testing.assert_allclose(read_point_file(path), P, atol=1e-6)
    with pytest.raises(PredictionInputError, match=rf"quad\.ply: only triangular faces are supported \({quads} of"):
        read_surface(path)


def test_large_binary_faces_are_read_in_one_block(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(5000, 3))
    tri = rng.integers(0, 5000, size=(20000, 3))
    body = _header("binary_little_endian", (("f8", "x"), ("f8", "y"), ("f8", "z")), len(pts),
                   ("property list uchar int vertex_indices",), len(tri))
    rec = np.zeros(len(tri), [("n", "u1"), ("v", "<i4", (3,))])
    rec["n"], rec["v"] = 3, tri
    (tmp_path / "big.ply").write_bytes(body + pts.astype("<f8").tobytes() + rec.tobytes())
    got = read_ply(tmp_path / "big.ply")
    np.testing.assert_array_equal(got.points, pts)
    np.testing.assert_array_equal(got.faces, tri)


HEAD = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
BAD = {  # file name: (bytes, what the message says)
    "empty.ply": (b"", r"the file is empty \(0 bytes: no header, no points"),
    "no_end.ply": (b"ply\nformat ascii 1.0\nelement vertex 1\n", "has no end_header"),
    "count_word.ply": (b"ply\nformat ascii 1.0\nelement vertex many\nproperty float x\nend_header\n",
                       r"header line 3 'element vertex many': expected 'element <name> <count>'"),
    "prop_first.ply": (b"ply\nformat ascii 1.0\nproperty float x\nelement vertex 1\nend_header\n1\n",
                       "a property before any element"),
    "float128.ply": (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float128 x\nend_header\n",
                     "unknown property type float128"),
    "format.ply": (b"ply\nformat binary_middle_endian 1.0\nend_header\n", "unsupported PLY format"),
    "no_xyz.ply": (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nproperty float b\nend_header\n1 2\n",
                   r"the PLY vertex element has no x, y, z property \(it has a, b\)"),
    "short_ascii.ply": (HEAD + b"1 2 3\n4 5 6\n", "ends early: its header promises 3 vertex rows, the data holds 2"),
    "word.ply": (HEAD + b"1 2 3\n4 abc 6\n7 8 9\n", "PLY vertex row 1: its y value is not a number"),
    "truncated.ply": (_binary("<")[:-10], "ends early: its header promises 4 vertex rows, the data holds 3"),
    "truncated_faces.ply": (_binary("<", faces=F)[:-3], "ends early: its header promises 4 face rows"),
    "face_index.ply": (_ascii(faces=[[0, 1, 9]]), "a PLY face refers to a vertex that does not exist"),
    "short_row.ply": (HEAD + b"1 2 3\n4 5\n7 8 9\n",
                      r"PLY vertex row 1 stops before its z value \(each row holds x, y, z"),
    "long_row.ply": (HEAD + b"1 2 3\n4 5 6 7\n7 8 9\n", r"PLY vertex row 1 holds more values than its header's"),
    "face_word.ply": (_ascii(faces=[[0, 1, 2]]).replace(b"3 0 1 2", b"3 0 x 2"),
                      "PLY face row 0: its vertex_indices list holds a value that is not a whole number"),
    "blank_header_line.ply": (HEAD.replace(b"1.0\n", b"1.0\n\n") + b"1 2 3\n4 5 6\n7 8 9\n",
                              "PLY header line 3 is blank"),
    "list_x.ply": (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar float x\nproperty float y\n"
                   b"property float z\nend_header\n2 1 2 3 4\n", "the PLY vertex property x is a list"),
    "float_faces.ply": (HEAD.replace(b"end_header", b"element face 1\nproperty list uchar float vertex_indices\n"
                                     b"end_header") + b"1 2 3\n4 5 6\n7 8 9\n3 0 1.7 2\n",
                        "the PLY face list vertex_indices holds float32 values; vertex indices are whole numbers"),
    "latin1_element.ply": (HEAD.replace(b"element vertex", b"element v\xe9rtex") + b"1 2 3\n4 5 6\n7 8 9\n",
                           r"the PLY header \(or, format ascii, its data\) holds a byte that is not ASCII text"),
    "latin1_data.ply": (HEAD.replace(b"1.0\n", b"1.0\ncomment M\xfcller\n") + b"1 2 3\n4 5 6\n7 8 \xb59\n",
                        r"the PLY header \(or, format ascii, its data\) holds a byte that is not ASCII text"),
}


@pytest.mark.parametrize("name", sorted(BAD))
def test_broken_ply_files_are_refused_by_both_callers_naming_the_file(tmp_path, name):
    data, why = BAD[name]
    path = tmp_path / name
    path.write_bytes(data)
    with pytest.raises(PlyError, match=why):
        read_ply(path)
    with pytest.raises(SupportError, match=f"{name}: .*{why}.*expected 3 numbers per row"):
        read_point_file(path, "m")
    for read in (read_points, read_surface):
        with pytest.raises(PredictionInputError, match=f"{name}: .*{why}"):
            read(path)


@pytest.mark.parametrize("comment", [b"comment Cr\xe9\xe9 par M\xfcller", b"comment Cr\xc3\xa9\xc3\xa9 (UTF-8)",
                                     b"obj_info scanner \xb5m"])
@pytest.mark.parametrize("eol", [b"\n", b"\r\n", b"\r"])
def test_a_comment_that_is_not_ascii_does_not_stop_the_file(tmp_path, comment, eol):
    """An exporter's name with an accent (Latin-1 or UTF-8) in a comment: the file is read, ASCII and binary."""
    for data in (HEAD.replace(b"1.0\n", b"1.0\n" + comment + b"\n") + b"0 0 0\n10.5 0 0\n0 10.25 0\n",
                 _binary("<").replace(b"comment exported by a lab", comment)):
        path = tmp_path / "accent.ply"
        path.write_bytes(data.replace(b"\n", eol) if data.startswith(HEAD[:4]) and b"ascii" in data[:30] else data)
        got = read_ply(path)
        np.testing.assert_array_equal(got.points, P[:len(got.points)])
        assert len(got.points) in (3, 4)
        np.testing.assert_array_equal(read_point_file(path, "mm"), got.points)


@pytest.mark.parametrize("variant", ["end_header_blank", "mixed_eol", "mixed_eol_binary", "accent_binary_faces"])
def test_headers_plyfile_would_refuse_for_their_form_are_read(tmp_path, variant):
    """Trailing blanks after ``end_header``, line ends that change after the ``ply`` line (an exporter's template),
    an accented comment in a binary file with faces: read as written, through a temporary plain copy."""
    if variant == "end_header_blank":
        data = HEAD.replace(b"end_header\n", b"end_header \t\n") + b"0 0 0\n10.5 0 0\n0 10.25 0\n"
    elif variant == "mixed_eol":
        data = b"ply\n" + HEAD[4:].replace(b"\n", b"\r\n") + b"0 0 0\r\n10.5 0 0\r\n0 10.25 0\r\n"
    elif variant == "mixed_eol_binary":
        raw = _binary("<", faces=F)
        end = raw.index(b"end_header\n") + len(b"end_header\n")
        data = b"ply\r\n" + raw[4:end] + raw[end:]
    else:
        data = _binary(">", faces=F).replace(b"comment exported by a lab", b"comment export\xe9 par M\xfcller")
    (tmp_path / "x.ply").write_bytes(data)
    got = read_ply(tmp_path / "x.ply")
    np.testing.assert_array_equal(got.points, P[:len(got.points)])
    if variant.endswith("faces"):
        np.testing.assert_array_equal(got.faces, F)
        got.points[0] = 99.0  # in memory, writable: not a map of the deleted copy
    assert list((tmp_path).iterdir()) == [tmp_path / "x.ply"]


def test_a_face_of_no_vertices_is_counted_as_a_polygon_without_a_warning(tmp_path):
    import warnings

    data = HEAD.replace(b"end_header", b"element face 2\nproperty list uchar int vertex_indices\nend_header") + \
        b"0 0 0\n10.5 0 0\n0 10.25 0\n3 0 1 2\n0\n"
    (tmp_path / "empty_face.ply").write_bytes(data)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = read_ply(tmp_path / "empty_face.ply")
    assert got.polygons == 1
    np.testing.assert_array_equal(got.faces, [[0, 1, 2]])
