"""A camera's PCD files (PCL's Point Cloud Data, as ROS, PCL and Open3D write them) in ``liverforce predict``: each
encoding read back to the points, the x y z fields of any layout, an organised cloud's NaN pixels dropped and said,
the refusals, a sequence folder of frames, and the force of a PCD equal to that of the same cloud as .npy."""
from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from pypcd4 import Encoding, PointCloud

from liverforce.serve import Predictor, Preop
from liverforce.serve.errors import PredictionInputError
from liverforce.serve.files import read_cloud, read_points
from liverforce.serve.sequence import read_sequence

from tests.serve.test_predict_cli import context_doc, run

ENCODINGS = ("ascii", "binary", "binary_compressed")


def cloud(n=300, seed=0) -> np.ndarray:
    """``n`` points in mm, 3 decimals (exact through an ascii PCD's ``%.10f``; repeated enough to compress)."""
    return np.round(np.random.default_rng(seed).normal(scale=40.0, size=(n, 3)), 3)


def write_pcd(path, columns: dict, encoding: str, width=None, height=1):
    """A PCD file of ``columns`` (field name -> 1D array, their dtypes kept) with pypcd4, in ``encoding``.

    pypcd4 writes ``binary`` instead of ``binary_compressed`` when LZF does not make the data smaller (a camera's
    noisy coordinates): PCL writes them compressed all the same, the compressed and uncompressed sizes (two
    uint32) and the LZF stream of the fields one after the other, as done here then."""
    pc = PointCloud.from_points(list(columns.values()), tuple(columns), tuple(a.dtype for a in columns.values()))
    if height != 1:
        pc.metadata = pc.metadata.derive(width=width, height=height)
    pc.save(path, encoding=Encoding(encoding))
    if encoding == "binary_compressed" and b"\nDATA binary\n" in path.read_bytes()[:1000]:
        import lzf

        raw = b"".join(np.ascontiguousarray(pc.pc_data[f]).tobytes() for f in pc.pc_data.dtype.names)
        packed = lzf.compress(raw, 2 * len(raw) + 16)
        path.write_bytes(pc.metadata.compose_header(Encoding.BINARY_COMPRESSED).encode()
                         + struct.pack("<II", len(packed), len(raw)) + packed)
    assert f"\nDATA {encoding}\n".encode() in path.read_bytes()[:1000]
    return path


def xyz(P: np.ndarray, dtype=np.float64) -> dict:
    return {"x": P[:, 0].astype(dtype), "y": P[:, 1].astype(dtype), "z": P[:, 2].astype(dtype)}


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("encoding", ENCODINGS)
def test_each_encoding_reads_back_the_points(tmp_path, encoding, dtype):
    P = cloud()
    path = write_pcd(tmp_path / "cam.pcd", xyz(P, dtype), encoding)
    got = read_points(path)
    assert got.dtype == np.float64 and got.shape == P.shape
    np.testing.assert_array_equal(got, P.astype(dtype).astype(np.float64))
    got, note = read_cloud(path)  # a camera cloud without NaN: the same points, nothing said
    np.testing.assert_array_equal(got, P.astype(dtype).astype(np.float64))
    assert note is None
    # the suffix in any case, as the other formats
    path.rename(tmp_path / "CAM.PCD")
    np.testing.assert_array_equal(read_points(tmp_path / "CAM.PCD"), P.astype(dtype).astype(np.float64))


def test_an_ascii_file_written_by_hand_ignores_its_viewpoint_and_other_fields(tmp_path):
    """The format as PCL documents it, independent of pypcd4's writer: a comment, packed rgb, a sensor pose."""
    text = ("# .PCD v0.7 - Point Cloud Data file format\n"
            "VERSION 0.7\n"
            "FIELDS x y z rgb\n"
            "SIZE 4 4 4 4\n"
            "TYPE F F F F\n"
            "COUNT 1 1 1 1\n"
            "WIDTH 3\n"
            "HEIGHT 1\n"
            "VIEWPOINT 100 -50 20 0 1 0 0\n"  # the sensor 100 mm away, turned 180 degrees about x: not applied
            "POINTS 3\n"
            "DATA ascii\n"
            "12.5 -3.25 40 4.2108e+06\n"
            "0 0 0 4.2108e+06\n"
            "-7.75 8 -1.5 4.808e+06\n")
    (tmp_path / "hand.pcd").write_text(text)
    want = np.array([[12.5, -3.25, 40.0], [0.0, 0.0, 0.0], [-7.75, 8.0, -1.5]])
    np.testing.assert_array_equal(read_points(tmp_path / "hand.pcd"), want)
    np.testing.assert_array_equal(read_points(tmp_path / "hand.pcd", units="cm"), want * 10.0)
    # one point: a cloud of one row, not a scalar
    (tmp_path / "one.pcd").write_text(text.replace("WIDTH 3", "WIDTH 1").replace("POINTS 3", "POINTS 1")
                                      .rsplit("\n", 3)[0] + "\n")
    np.testing.assert_array_equal(read_points(tmp_path / "one.pcd"), want[:1])


#: an ascii PCD as PCL writes it (single spaces, LF): x and z float32 (0.1 is not a float32), y float64, NaN (PCL's
#: nan, spelled NaN too) and inf, a padding field '_' of 4 bytes, normals (COUNT 3), rgb and an int16 ring
PCL_HEAD = ("# .PCD v0.7 - Point Cloud Data file format\n"
            "VERSION 0.7\n"
            "FIELDS x y z _ normal rgb ring\n"
            "SIZE 4 8 4 1 4 4 2\n"
            "TYPE F F F U F F I\n"
            "COUNT 1 1 1 4 3 1 1\n"
            "WIDTH 2\n"
            "HEIGHT 2\n"
            "VIEWPOINT 0 0 0 1 0 0 0\n"
            "POINTS 4\n"
            "DATA ascii\n")
PCL_DATA = ("0.1 -2.25 40 0 0 0 0 0 0 1 4.2108e+06 -3\n"
            "nan NaN nan 0 0 0 0 0.5 0.5 0.7071 4.2108e+06 12\n"
            "12.5 0.1 -1e-3 0 0 0 0 1 0 0 4.808e+06 7\n"
            "inf 8 -7.75 0 0 0 0 0 1 0 0 0\n")
PCL_XYZ = np.array([[np.float32(0.1), -2.25, 40.0], [np.nan] * 3, [12.5, 0.1, np.float32(-1e-3)],
                    [np.inf, 8.0, -7.75]])


def blanks(text: str, sep: str = " ", before: str = "", after: str = "", eol: str = "\n") -> str:
    """``text``'s lines with ``sep`` between values, ``before`` and ``after`` each line, ending in ``eol``."""
    return "".join(before + sep.join(line.split(" ")) + after + eol for line in text.splitlines())


def test_an_ascii_file_with_other_blanks_reads_as_pcls(tmp_path):
    """Tabs, runs of spaces, blanks at either end of a line and Windows' CRLF, in the data and in the header (a lab's
    own script, MATLAB, a file edited on Windows): PCL's own reader splits each line on any run of spaces, tabs and
    CR; each reads as the single-space file, the same dtypes (float32 x and z, float64 y), NaN and inf kept for
    read_cloud to drop (pypcd4 split a data line on each space: tabs, two spaces, a blank at either end refused)."""
    (tmp_path / "pcl.pcd").write_bytes((PCL_HEAD + PCL_DATA).encode())
    np.testing.assert_array_equal(read_points(tmp_path / "pcl.pcd"), PCL_XYZ)
    pcl_cloud, pcl_note = read_cloud(tmp_path / "pcl.pcd")
    assert "2 of 4 points dropped" in pcl_note
    variants = {
        "tabs": PCL_HEAD + blanks(PCL_DATA, "\t"),
        "two spaces": PCL_HEAD + blanks(PCL_DATA, "  "),
        "a trailing space": PCL_HEAD + blanks(PCL_DATA, after=" "),
        "blanks at either end, space-tab runs": PCL_HEAD + blanks(PCL_DATA, " \t ", before="\t  ", after="\t"),
        "CRLF data": PCL_HEAD + blanks(PCL_DATA, eol="\r\n"),
        "CRLF throughout, tabs": blanks(PCL_HEAD, eol="\r\n") + blanks(PCL_DATA, "\t", eol="\r\n"),
        "a header of tabs and runs of spaces": blanks(PCL_HEAD, "\t ", after="  ") + blanks(PCL_DATA, "\t"),
        "Notepad: a byte-order mark, CRLF, two spaces": "\ufeff" + blanks(PCL_HEAD + PCL_DATA, "  ", eol="\r\n"),
        "blank lines between points": PCL_HEAD + blanks(PCL_DATA, "\t", eol="\n\t\n"),
    }
    for name, text in variants.items():
        path = tmp_path / f"{name}.pcd"
        path.write_bytes(text.encode())
        np.testing.assert_array_equal(read_points(path), PCL_XYZ, err_msg=name)
        got, note = read_cloud(path)
        np.testing.assert_array_equal(got, pcl_cloud, err_msg=name)
        assert note == pcl_note.replace(str(tmp_path / "pcl.pcd"), str(path)), name


def test_an_ascii_line_with_another_number_of_values_is_refused_naming_it(tmp_path):
    """A short line, a file cut inside its last line, a value that is not a number, values separated by commas:
    refused naming the file's line (its header's 11 lines, then the points); a file cut after a line is refused
    for its points, as before. The lines are tab-separated with CRLF, read as PCL's otherwise."""
    lines = blanks(PCL_DATA, "\t", eol="\r\n").splitlines(keepends=True)

    def refused(name, data, match):
        (tmp_path / name).write_bytes((blanks(PCL_HEAD, eol="\r\n") + data).encode())
        with pytest.raises(PredictionInputError, match=match) as exc:
            read_points(tmp_path / name)
        assert str(exc.value).startswith(f"{tmp_path / name}: cannot read this PCD file's data: its line ")
        assert str(exc.value).endswith(": a truncated or damaged file; an ascii PCD holds a line per point, its "
                                       "values numbers separated by spaces or tabs")

    refused("short.pcd", "".join(lines[:1] + [lines[1].replace("\t12\r", "\r")] + lines[2:]),
            r"its line 13 holds 11 values, where a point of its FIELDS x y z _ normal rgb ring \(COUNT 1 1 1 4 3 1 "
            r"1\) has 12: a truncated")
    refused("cut.pcd", "".join(lines)[:-20], r"its line 15 holds 3 values, where")  # inf 8 -7.75
    refused("word.pcd", "".join(lines[:2] + [lines[2].replace("\t0.1\t", "\t0,1\t")] + lines[3:]),
            r"its line 14: its value 2, '0,1', is not a float64 number: a truncated")
    refused("commas.pcd", PCL_DATA.replace(" ", ","), r"its line 12 holds 1 value, where a point")
    (tmp_path / "cut_line.pcd").write_bytes((PCL_HEAD + "".join(lines[:3])).encode())
    with pytest.raises(PredictionInputError, match=r"its header says POINTS 4, its ascii data holds 3: a truncated "):
        read_points(tmp_path / "cut_line.pcd")


def test_a_header_in_lower_case_or_with_cr_line_ends_is_refused_saying_so(tmp_path):
    """PCL reads a header's keywords in capitals only, and lines that end in LF (a CRLF's CR is split off). pypcd4
    ends the header at 'DATA' or its tenth line: a header of ten lines in lower case read, a shorter one took its
    first data lines for the header's and read the points from the wrong line ('a truncated file', or points
    shifted when there were lines over). A file whose lines end in CR alone was one line: 'FIELDS: Field required'.
    Each is refused naming what is wrong and what to do, in any encoding."""
    def refused(name, data: bytes, match):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(PredictionInputError, match=match) as exc:
            read_points(tmp_path / name)
        assert str(exc.value).startswith(f"{tmp_path / name}: ")
        return str(exc.value)

    text = PCL_HEAD + PCL_DATA  # its header's ten lines and a comment
    refused("data.pcd", text.replace("DATA ascii", "data ascii").encode(),
            r"its header's line 11, 'data ascii': the keyword 'data' is not in capitals, which PCL reads only \(and "
            r"pypcd4 ends the header at 'DATA' only, else reads the points from the wrong line\); write 'DATA'$")
    short = text.replace("VIEWPOINT 0 0 0 1 0 0 0\n", "")  # nine lines: read from the wrong line
    refused("Fields.pcd", short.replace("FIELDS", "Fields").encode(), r"its header's line 3, 'Fields x y z _ normal "
                                                                      r"rgb ring': the keyword 'Fields' is not in")
    refused("points.pcd", short.replace("POINTS 4", "points 3").encode(), r"line 9, 'points 3'.* write 'POINTS'$")
    P = cloud(n=50, seed=8)
    binary = write_pcd(tmp_path / "b.pcd", xyz(P), "binary").read_bytes()
    head, data = binary.split(b"DATA binary\n", 1)
    refused("b_lower.pcd", head.replace(b"WIDTH", b"width") + b"DATA binary\n" + data, r"'width 50'.* write 'WIDTH'")
    said = "lines end in CR alone \\(a classic Mac OS text file\\), which neither PCL nor pypcd4 reads as lines: " \
           "convert its line ends to LF \\(or CRLF\\), e.g. tr '\\\\r' '\\\\n' < old.pcd > new.pcd for an ascii file$"
    refused("mac.pcd", text.replace("\n", "\r").encode(), f": its {said}")
    refused("mac_bom.pcd", ("\ufeff" + text.replace("\n", "\r")).encode(), f": its {said}")
    refused("mac_data.pcd", (PCL_HEAD + PCL_DATA.replace("\n", "\r")).encode(), f": its data's {said}")
    refused("mac_b.pcd", head.replace(b"\n", b"\r") + b"DATA binary\r" + data, f": its {said}")
    # capitals, LF or CRLF: read (a keyword's value in lower case is its own: 'ascii', field names)
    for name, data_ in (("lf", text), ("crlf", text.replace("\n", "\r\n"))):
        (tmp_path / f"{name}.pcd").write_bytes(data_.encode())
        np.testing.assert_array_equal(read_points(tmp_path / f"{name}.pcd"), PCL_XYZ)


def test_an_ascii_data_of_another_count_than_points_is_refused_in_its_own_words(tmp_path):
    """More lines of values than POINTS is not 'a truncated file' (as it was said); lines under POINTS 0 were read
    as no points, the lines dropped; no data under POINTS 4 is refused without numpy's warning 'input contained no
    data' of an object in memory on stderr; a comment after a point's values is named (numpy's 'use usecols' was)."""
    import warnings

    def refused(name, data: str, match):
        (tmp_path / name).write_bytes((PCL_HEAD + data).encode())
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with pytest.raises(PredictionInputError, match=match) as exc:
                read_cloud(tmp_path / name)
        assert not caught, [str(w.message) for w in caught]
        assert str(exc.value).startswith(f"{tmp_path / name}: ")
        return str(exc.value)

    more = ("its header says POINTS 4, its ascii data holds 5: more lines of values than its points (lines added "
            "after them, or a damaged header): correct POINTS (and WIDTH x HEIGHT) or remove the lines that are not "
            "points")
    said = refused("more.pcd", PCL_DATA + "1 2 3 0 0 0 0 0 0 1 0 0\n", "more lines")
    assert said == f"{tmp_path / 'more.pcd'}: {more}"
    zero = PCL_HEAD.replace("WIDTH 2", "WIDTH 0").replace("HEIGHT 2", "HEIGHT 1").replace("POINTS 4", "POINTS 0")
    (tmp_path / "zero.pcd").write_bytes((zero + PCL_DATA).encode())
    with pytest.raises(PredictionInputError, match="its header says POINTS 0, its ascii data holds 4: more lines"):
        read_cloud(tmp_path / "zero.pcd")
    (tmp_path / "none.pcd").write_bytes((zero + "\n# no points\n").encode())  # no points, said so: read as none
    assert read_cloud(tmp_path / "none.pcd")[0].shape == (0, 3)
    refused("empty.pcd", "", r"its header says POINTS 4, its ascii data holds 0: a truncated file \(or a damaged "
                             r"header\)$")
    refused("blank.pcd", "\n\t\n", "its ascii data holds 0: a truncated file")
    lines = PCL_DATA.splitlines(keepends=True)
    refused("note.pcd", "".join(lines[:2] + [lines[2].replace("\n", " # the tool's shadow\n")] + lines[3:]),
            r"its line 14 holds a comment after its values \('# the tool's shadow'\): a data line holds only numbers")


def test_fields_in_another_order_with_extra_fields(tmp_path):
    P = cloud(seed=1)
    n = len(P)
    columns = {"intensity": np.linspace(0, 1, n, dtype=np.float32), "z": P[:, 2], "normal_x": np.ones(n, np.float32),
               "ring": np.arange(n, dtype=np.uint16) % 16, "y": P[:, 1].astype(np.float32), "x": P[:, 0],
               "rgb": np.full(n, 4.2108e6, np.float32)}
    for encoding in ENCODINGS:
        got = read_points(write_pcd(tmp_path / f"{encoding}.pcd", columns, encoding))
        np.testing.assert_array_equal(got, np.column_stack([P[:, 0], P[:, 1].astype(np.float32), P[:, 2]]))


def test_pcls_binary_padding_fields_are_skipped_and_named_as_written(tmp_path):
    """PCL's binary writer (savePCDFileBinary) keeps a point type's padding as fields named '_' of U bytes: a
    PointXYZ is ``x y z _`` (COUNT 1 1 1 4), a PointXYZRGB ``x y z _ rgb _``. The points read as written, and a
    header that lacks a coordinate is quoted as written, not with the names pypcd4 gives '_' inside."""
    P = np.array([[1.5, -2.25, 30.0], [4.0, 5.0, -6.5], [np.nan] * 3, [7.0, 8.0, 9.0]], np.float32)

    def pcl_binary(name, fields, sizes, types, counts, dtype):
        rec = np.zeros(len(P), dtype=dtype)
        for k, axis in enumerate("xyz"):
            if axis in rec.dtype.names:
                rec[axis] = P[:, k]
        head = (f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\nSIZE {sizes}\n"
                f"TYPE {types}\nCOUNT {counts}\nWIDTH 2\nHEIGHT 2\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4\nDATA binary\n")
        (tmp_path / name).write_bytes(head.encode() + rec.tobytes())
        return tmp_path / name

    xyz_ = pcl_binary("xyz.pcd", "x y z _", "4 4 4 1", "F F F U", "1 1 1 4",
                      [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("pad", "u1", 4)])
    rgb = pcl_binary("rgb.pcd", "x y z _ rgb _", "4 4 4 1 4 1", "F F F U F U", "1 1 1 4 1 12",
                     [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("p", "u1", 4), ("rgb", "<f4"), ("q", "u1", 12)])
    for path in (xyz_, rgb):
        got, note = read_cloud(path)
        np.testing.assert_array_equal(got, P[[0, 1, 3]].astype(np.float64))
        assert "1 of 4 points dropped" in note
    no_z = pcl_binary("noz.pcd", "x y _ rgb _", "4 4 1 4 1", "F F U F U", "1 1 4 1 12",
                      [("x", "<f4"), ("y", "<f4"), ("p", "u1", 4), ("rgb", "<f4"), ("q", "u1", 12)])
    with pytest.raises(PredictionInputError, match=r"no 'z' field \(FIELDS x y _ rgb _\); a point cloud's PCD has"):
        read_points(no_z)


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_an_organised_cloud_drops_its_nan_pixels_and_says_how_many(tmp_path, encoding):
    P = cloud(n=48, seed=2)
    holes = np.zeros(48, bool)
    holes[[0, 5, 6, 7, 20, 33, 40, 41, 46, 47]] = True
    Q = P.copy()
    Q[holes] = np.nan  # PCL's mark of a pixel without depth: x, y and z NaN
    path = write_pcd(tmp_path / "depth.pcd", xyz(Q), encoding, width=8, height=6)
    got, note = read_cloud(path)
    np.testing.assert_array_equal(got, P[~holes])  # the finite points, in their order
    assert note.startswith(f"{path}: 10 of 48 points dropped, their coordinates NaN") and "8 x 6" in note
    assert note.endswith("38 read")
    # read as ordered points (nodes), none is dropped: the NaN reach the checks, which refuse them
    assert np.isnan(read_points(path)).any(axis=1).sum() == 10
    # metres: the finite points scaled, the same note
    got_m, note_m = read_cloud(write_pcd(tmp_path / "depth_m.pcd", xyz(Q / 1000.0), encoding, 8, 6), units="m")
    np.testing.assert_allclose(got_m, P[~holes], rtol=1e-12, atol=1e-9)
    assert "10 of 48 points dropped" in note_m


def test_points_at_inf_are_dropped_too_as_pcl_drops_what_is_not_finite(tmp_path):
    """A stereo camera's driver marks a pixel whose depth is out of its range with inf (the ZED's: +inf too far,
    -inf too close; NaN occluded): such a point is no measurement either, and one inf in a cloud kept for the
    checks refused the whole cloud ("drop invalid points before predicting") though the reader says it drops them."""
    P = cloud(n=48, seed=5)
    Q = P.copy()
    Q[[1, 2]] = np.nan
    Q[[10, 11, 12], 2] = np.inf
    Q[30, 0] = -np.inf  # one coordinate alone
    for encoding in ENCODINGS:
        path = write_pcd(tmp_path / f"zed_{encoding}.pcd", xyz(Q / 1000.0), encoding, width=8, height=6)
        got, note = read_cloud(path, units="m")
        keep = np.isfinite(Q).all(axis=1)
        np.testing.assert_allclose(got, P[keep], rtol=1e-12, atol=1e-9)
        assert note == (f"{path}: 6 of 48 points dropped, their coordinates NaN or inf (PCL's mark of a pixel "
                        "without depth in an organised cloud, here 8 x 6; inf: a depth camera's mark of a depth out "
                        "of its range); 42 read")
    # inf alone, and a frame that saw nothing but the too-far
    path = write_pcd(tmp_path / "far.pcd", xyz(np.where(np.arange(48)[:, None] < 8, np.inf, P)), "binary", 8, 6)
    assert read_cloud(path)[1] == (f"{path}: 8 of 48 points dropped, their coordinates inf (a depth camera's mark "
                                   "of a depth out of its range); 40 read")
    path = write_pcd(tmp_path / "void.pcd", xyz(np.full((12, 3), np.inf)), "binary", width=4, height=3)
    with pytest.raises(PredictionInputError, match=r"every one of its 12 points is inf \(a depth camera's mark of a "
                                                   r"depth out of its range\): the camera saw no surface"):
        read_cloud(path)
    got, note = read_cloud(path, empty=True)  # a sequence's frame: no points, refused as its own row
    assert got.shape == (0, 3) and note.startswith(f"{path}: every one of its 12 points is inf")


def test_metres_are_read_with_units_m(tmp_path):
    P = cloud(seed=3)
    path = write_pcd(tmp_path / "m.pcd", xyz(P / 1000.0), "binary")
    np.testing.assert_allclose(read_points(path, units="m"), P, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(read_cloud(path, units="m")[0], P, rtol=1e-12, atol=1e-9)


def test_refusals_name_the_file_and_what_is_wrong(tmp_path):
    P = cloud(n=200, seed=4)

    def refused(path, match, reader=read_points):
        with pytest.raises(PredictionInputError, match=match) as exc:
            reader(path)
        assert str(exc.value).startswith(f"{path}: ")
        return str(exc.value)

    nan = write_pcd(tmp_path / "blind.pcd", xyz(np.full((12, 3), np.nan)), "binary", width=4, height=3)
    refused(nan, r"every one of its 12 points is NaN \(PCL's mark of a pixel without depth in an organised "
                 r"cloud, here 4 x 3\): the camera saw no surface", read_cloud)
    refused(write_pcd(tmp_path / "xy.pcd", {"x": P[:, 0], "y": P[:, 1], "intensity": P[:, 2]}, "binary"),
            r"no 'z' field \(FIELDS x y intensity\)")
    binary = write_pcd(tmp_path / "b.pcd", xyz(P), "binary").read_bytes()
    (tmp_path / "cut.pcd").write_bytes(binary[:-24])  # one point short: pypcd4 alone reads 199 points
    refused(tmp_path / "cut.pcd", r"its header says POINTS 200, its binary data holds 199: a truncated file")
    (tmp_path / "cut_odd.pcd").write_bytes(binary[:-5])
    assert "ascii" not in refused(tmp_path / "cut_odd.pcd", r"cannot read this PCD file's data \(ValueError: .*\): "
                                                            r"a truncated or damaged file$")
    ascii_ = write_pcd(tmp_path / "a.pcd", xyz(P), "ascii").read_bytes()
    (tmp_path / "cut_a.pcd").write_bytes(ascii_.rsplit(b"\n", 2)[0] + b"\n")
    refused(tmp_path / "cut_a.pcd", r"its header says POINTS 200, its ascii data holds 199")
    packed = write_pcd(tmp_path / "c.pcd", xyz(P), "binary_compressed").read_bytes()
    (tmp_path / "cut_c.pcd").write_bytes(packed[:-40])
    refused(tmp_path / "cut_c.pcd", r"cannot read this PCD file's data .*: a truncated or damaged file$")
    (tmp_path / "ply.pcd").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                                      "property float z\nend_header\n1 2 3\n")
    said = refused(tmp_path / "ply.pcd", r"not a PCD file pypcd4 can read, its header wrong")
    assert "FIELDS: Field required" in said and "COUNT: Field required" in said
    (tmp_path / "noise.pcd").write_bytes(bytes(range(256)) * 4)
    refused(tmp_path / "noise.pcd", r"not a PCD file \(its header is not text")
    (tmp_path / "wh.pcd").write_bytes(binary.replace(b"WIDTH 200\n", b"WIDTH 20\n"))
    refused(tmp_path / "wh.pcd", r"WIDTH 20 x HEIGHT 1 is not its POINTS 200")
    (tmp_path / "q.pcd").write_bytes(binary.replace(b"FIELDS x y z", b"FIELDS x y q"))
    refused(tmp_path / "q.pcd", r"no 'z' field \(FIELDS x y q\)")
    (tmp_path / "x3.pcd").write_text("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 3 1 1\nWIDTH 1\n"
                                     "HEIGHT 1\nPOINTS 1\nDATA ascii\n1 2 3 4 5\n")
    refused(tmp_path / "x3.pcd", r"its 'x' field has COUNT 3")
    refused(tmp_path / "missing.pcd", "no such point-cloud file", read_cloud)


def test_a_sequence_folder_of_pcd_frames_in_natural_order(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    want = {}
    for k in (10, 2, 1, 0):
        P = cloud(n=60, seed=10 + k)
        Q = P.copy()
        if k == 2:
            Q[:5] = np.nan
        write_pcd(frames / f"frame_{k}.pcd", xyz(Q), ENCODINGS[k % 3], width=10, height=6)
        want[f"frame_{k}.pcd"] = P[5:] if k == 2 else P
    (frames / "tips.csv").write_text("0,0,0\n")  # skipped, as the command line skips its --tool-tips
    notes: dict = {}
    names, clouds = read_sequence([frames], skip=(frames / "tips.csv",), notes=notes)
    assert names == ["frame_0.pcd", "frame_1.pcd", "frame_2.pcd", "frame_10.pcd"]
    for name, c in zip(names, clouds):
        np.testing.assert_array_equal(c, want[name])
    assert list(notes) == [2] and notes[2].startswith(f"{frames / 'frame_2.pcd'}: 5 of 60 points dropped")
    # files named one by one keep their order, and their notes their positions
    notes = {}
    names, _ = read_sequence([frames / "frame_2.pcd", frames / "frame_0.pcd"], notes=notes)
    assert names == ["frame_2.pcd", "frame_0.pcd"] and list(notes) == [0]
    # a damaged frame (cut short) is named, with what to do
    data = (frames / "frame_1.pcd").read_bytes()
    (frames / "frame_1.pcd").write_bytes(data[: len(data) - 100])
    with pytest.raises(PredictionInputError, match="frame_1.pcd") as exc:
        read_sequence([frames], skip=(frames / "tips.csv",))
    assert "repair or remove a damaged cloud" in str(exc.value)


def test_predict_from_a_pcd_gives_the_force_of_the_same_cloud_as_npy(trained, test_cases, tmp_path, capsys):
    model = trained("deformed")
    ctx = Preop.from_arrays(test_cases, 1)
    D = np.asarray(test_cases["roi_deformed_mm"][1], dtype=np.float64)
    np.save(tmp_path / "roi.npy", ctx.roi_undeformed_mm)
    (tmp_path / "ctx.json").write_text(json.dumps(context_doc(ctx, "roi.npy", with_state=False)))
    np.save(tmp_path / "cloud.npy", D)
    rc, out, err = run(["-m", model, tmp_path / "cloud.npy", "--context", tmp_path / "ctx.json"], capsys)
    assert rc == 0, err
    ref = json.loads(out)
    assert ref["force_n"] == pytest.approx(Predictor.load(model).predict_cloud(D, ctx), abs=1e-12)
    for encoding in ENCODINGS:
        pcd = write_pcd(tmp_path / f"cloud_{encoding}.pcd", xyz(D), encoding)
        rc, out, err = run(["-m", model, pcd, "--context", tmp_path / "ctx.json"], capsys)
        assert rc == 0, err
        doc = json.loads(out)
        np.testing.assert_allclose(doc["force_n"], ref["force_n"], rtol=0, atol=1e-12)
        assert doc["points_used"] == ref["points_used"] and doc["warnings"] == ref["warnings"]
    # an organised cloud with holes: the same force from its finite points, and the output says what was dropped
    n = len(D)
    holes = np.full((n + 7, 3), np.nan)
    holes[np.r_[0:3, 10:n + 7]] = D
    pcd = write_pcd(tmp_path / "holes.pcd", xyz(holes), "binary_compressed", width=n + 7, height=1)
    rc, out, err = run(["-m", model, pcd, "--context", tmp_path / "ctx.json", "--out", tmp_path / "f.json"], capsys)
    assert rc == 0, err
    doc = json.loads((tmp_path / "f.json").read_text())
    np.testing.assert_allclose(doc["force_n"], ref["force_n"], rtol=0, atol=1e-12)
    assert doc["warnings"] == [f"{pcd}: 7 of {n + 7} points dropped, their coordinates NaN (PCL's mark of a point "
                               f"without a measurement); {n} read"] + ref["warnings"]
    # points at inf (a stereo camera's depth out of range) are dropped as well: the same force
    holes[3:6] = np.inf
    pcd_inf = write_pcd(tmp_path / "inf.pcd", xyz(holes), "binary", width=n + 7, height=1)
    rc, out, err = run(["-m", model, pcd_inf, "--context", tmp_path / "ctx.json"], capsys)
    assert rc == 0, err
    np.testing.assert_allclose(json.loads(out)["force_n"], ref["force_n"], rtol=0, atol=1e-12)
    # a depth camera's frame that was mostly pixels without depth: refused for the points left, and the refusal
    # says that the file held more, and why they were dropped (its 1,000 points are not what the model saw)
    blind = np.full((1000, 3), np.nan)
    blind[:2] = D[:2]
    pcd_blind = write_pcd(tmp_path / "blind.pcd", xyz(blind), "binary", width=50, height=20)
    rc, _, err = run(["-m", model, pcd_blind, "--context", tmp_path / "ctx.json"], capsys)
    assert rc == 2 and f"(reading the clouds: {pcd_blind}: 998 of 1000 points dropped, their coordinates NaN" in err
    # ... but ordered nodes are not dropped: the same file as --mode nodes is refused for its NaN
    rc, _, err = run(["-m", model, pcd, "--mode", "nodes", "--context", tmp_path / "ctx.json"], capsys)
    assert rc == 2 and "NaN or inf" in err
    # the same cloud in metres with --units m (the context in metres too)
    in_m = Preop.from_dict({**ctx.to_dict(), "exertion_point_mm": ctx.exertion_point_mm / 1000})
    np.save(tmp_path / "roi_m.npy", ctx.roi_undeformed_mm / 1000)
    (tmp_path / "ctx_m.json").write_text(json.dumps(context_doc(in_m, "roi_m.npy", with_state=False)))
    pcd = write_pcd(tmp_path / "cloud_m.pcd", xyz(D / 1000), "binary")
    rc, out, err = run(["-m", model, pcd, "--context", tmp_path / "ctx_m.json", "--units", "m"], capsys)
    assert rc == 0, err
    np.testing.assert_allclose(json.loads(out)["force_n"], ref["force_n"], atol=1e-6)
    # a PCD that is not one: exit 2, the file named
    (tmp_path / "bad.pcd").write_text("not a point cloud\n")
    rc, _, err = run(["-m", model, tmp_path / "bad.pcd", "--context", tmp_path / "ctx.json"], capsys)
    assert rc == 2 and f"{tmp_path / 'bad.pcd'}: not a PCD file" in err


def test_an_empty_pcd_or_ply_file_is_refused_as_empty(tmp_path):
    """A frame of 0 bytes (a camera's driver or a copy that stopped): it was said to be a PCD header without FIELDS,
    SIZE, TYPE, COUNT, POINTS and WIDTH, or a PLY without its magic line; a CSV's says 'the file is empty'."""
    for name in ("frame.pcd", "frame.PLY"):
        (tmp_path / name).write_bytes(b"")
        for read in (read_points, read_cloud):
            with pytest.raises(PredictionInputError) as exc:
                read(tmp_path / name)
            assert str(exc.value) == (f"{tmp_path / name}: the file is empty (0 bytes: no header, no points; a "
                                      "writer or a copy that stopped, a camera's driver for a frame): write or export "
                                      "it again")
