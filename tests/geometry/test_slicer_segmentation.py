"""3D Slicer segmentations (``.seg.nrrd``): the liver chosen by segment name, ID or label value, in every layer.

The files are written as 3D Slicer writes them: by slicerio (Slicer's own reader and writer, voxel-to-LPS map
with the i and j axes reversed, segments that overlap in separate layers of a 4-D array), and by pynrrd with the
``SegmentN_`` header fields of a TotalSegmentator export. The expected positions are worked out here from the
voxel map, in RAS, not read back through the importer's code.
"""

from __future__ import annotations

import numpy as np
import pytest

from liverforce.geometry import GeometryError, load_surface

SHAPE = (80, 60, 40)
IJK_TO_LPS = np.array([[-2.0, 0.0, 0.0, 90.0], [0.0, -2.0, 0.0, 70.0], [0.0, 0.0, 2.5, -300.0], [0, 0, 0, 1.0]])


def ball(centre, radii):
    q = (np.indices(SHAPE).transpose(1, 2, 3, 0) - np.array(centre)) / np.array(radii)
    return (q**2).sum(axis=-1) <= 1.0


LIVER = ((40, 30, 20), (32, 24, 14))  # 128 x 96 x 70 mm
SPLEEN = ((8, 10, 8), (5, 5, 5))
TUMOUR = ((46, 30, 20), (5, 5, 5))  # inside the liver: overlapping, so Slicer puts it in a layer of its own


def ras_centre(centre):
    lps = IJK_TO_LPS @ np.array([*centre, 1.0])
    return lps[:3] * np.array([-1.0, -1.0, 1.0])


def ras_volume(radii):
    return 4.0 / 3.0 * np.pi * np.prod(radii) * abs(np.linalg.det(IJK_TO_LPS[:3, :3]))


def write_slicer(path, segments):
    """A segmentation as 3D Slicer saves it: ``segments`` = [(name, mask)], ids Segment_1, Segment_2, ..."""
    import slicerio

    seg = slicerio.create_segmentation(SHAPE, IJK_TO_LPS)
    for k, (name, mask) in enumerate(segments, start=1):
        slicerio.add_segment(seg, mask, {"id": f"Segment_{k}", "name": name})
    slicerio.write_segmentation(str(path), seg)
    return seg


@pytest.fixture
def two_organs(tmp_path):
    path = tmp_path / "Segmentation.seg.nrrd"
    write_slicer(path, [("spleen", ball(*SPLEEN)), ("Liver", ball(*LIVER))])
    return path


def test_the_segment_named_liver_is_taken_without_a_label(two_organs):
    s, msgs = load_surface(two_organs)
    assert np.allclose(s.vertices.mean(axis=0), ras_centre(LIVER[0]), atol=1.5)
    assert s.volume_mm3 == pytest.approx(ras_volume(LIVER[1]), rel=0.05)
    assert s.meta["label"] == 2 and s.meta["format"] == "slicer segmentation (nrrd)"
    assert any("segment 'Liver' (ID Segment_2, label 2) used (the one named liver" in m for m in msgs)


@pytest.mark.parametrize("label", ["liver", "Segment_2", 2, "2"])
def test_a_segment_by_name_id_or_label_value_is_the_same_liver(two_organs, label):
    s, _ = load_surface(two_organs, label=label)
    assert np.allclose(s.vertices.mean(axis=0), ras_centre(LIVER[0]), atol=1.5)
    assert s.volume_mm3 == pytest.approx(ras_volume(LIVER[1]), rel=0.05)


def test_another_segment_is_taken_when_named(two_organs):
    s, msgs = load_surface(two_organs, label="spleen", size_range_mm=(5, 500))
    assert np.allclose(s.vertices.mean(axis=0), ras_centre(SPLEEN[0]), atol=1.5)
    assert any("segment 'spleen'" in m for m in msgs)


@pytest.mark.parametrize("label, message", [
    ("kidney", r"no segment is named or has ID 'kidney' \(segments: 'spleen' \(label 1\); 'Liver' \(label 2\)\)"),
    (7, r"no segment has label 7 \(segments: 'spleen'"),
])
def test_a_segment_that_is_not_there_is_refused_with_the_list(two_organs, label, message):
    with pytest.raises(GeometryError, match=rf"Segmentation\.seg\.nrrd.*{message}.*label=<a segment's name"):
        load_surface(two_organs, label=label)


def test_without_a_liver_segment_the_choice_is_asked_for(tmp_path):
    path = tmp_path / "organs.seg.nrrd"
    write_slicer(path, [("spleen", ball(*SPLEEN)), ("Segment_2", ball(*LIVER))])
    with pytest.raises(GeometryError, match=r"2 segments and none named liver: 'spleen' \(label 1\); 'Segment_2'"):
        load_surface(path)


def test_overlapping_segments_are_read_from_their_own_layer(tmp_path):
    path = tmp_path / "overlap.seg.nrrd"
    seg = write_slicer(path, [("liver", ball(*LIVER)), ("tumour", ball(*TUMOUR))])
    assert seg["voxels"].ndim == 4  # as Slicer stores overlapping segments: one layer each
    s, _ = load_surface(path)  # the whole liver, not the liver with the tumour cut out
    assert s.volume_mm3 == pytest.approx(ras_volume(LIVER[1]), rel=0.05)
    assert np.allclose(s.vertices.mean(axis=0), ras_centre(LIVER[0]), atol=1.5)
    with pytest.raises(GeometryError, match=r"label 1 is used by 2 segments in different layers.*name or ID"):
        load_surface(path, label=1)
    t, _ = load_surface(path, label="tumour", size_range_mm=(5, 500))
    assert t.volume_mm3 == pytest.approx(ras_volume(TUMOUR[1]), rel=0.15)


def test_a_totalsegmentator_style_header_written_by_pynrrd(tmp_path):
    """The custom ``SegmentN_`` fields (``key:=value``) of a multi-organ export, liver at label 5, LPS."""
    import nrrd

    data = np.zeros(SHAPE, np.uint8)
    data[ball(*SPLEEN)] = 1
    data[ball(*LIVER)] = 5
    header = {"space": "left-posterior-superior", "kinds": ["domain"] * 3,
              "space directions": IJK_TO_LPS[:3, :3].T, "space origin": IJK_TO_LPS[:3, 3]}
    for k, (name, value) in enumerate([("spleen", 1), ("liver", 5)]):
        header.update({f"Segment{k}_ID": name, f"Segment{k}_Name": name, f"Segment{k}_LabelValue": str(value),
                       f"Segment{k}_Layer": "0", f"Segment{k}_Extent": "0 79 0 59 0 39"})
    path = tmp_path / "total.seg.nrrd"
    nrrd.write(str(path), data, header)
    assert "Segment1_Name:=liver" in path.read_bytes()[:4000].decode("latin-1")
    s, msgs = load_surface(path)
    assert s.meta["label"] == 5
    assert np.allclose(s.vertices.mean(axis=0), ras_centre(LIVER[0]), atol=1.5)


def test_a_name_for_a_file_without_segments_is_refused(tmp_path):
    import nibabel as nib

    data = np.zeros(SHAPE, np.uint8)
    data[ball(*LIVER)] = 3
    path = tmp_path / "seg.nii.gz"
    nib.save(nib.Nifti1Image(data, np.diag([2.0, 2.0, 2.5, 1.0])), path)
    with pytest.raises(GeometryError, match=r"label 'liver' names a segment, but the file names none \(labels "
                                             r"present: \[3\]\).*label=3"):
        load_surface(path, label="liver")
    s, _ = load_surface(path, label="3")  # a number given as text, as a command line gives it
    assert s.meta["label"] == 3


def test_a_four_d_nrrd_without_segment_names_is_refused(tmp_path):
    import nrrd

    data = np.zeros((2, *SHAPE), np.uint8)
    data[0][ball(*LIVER)] = 1
    header = {"space": "left-posterior-superior", "kinds": ["list", "domain", "domain", "domain"],
              "space directions": np.vstack([np.full(3, np.nan), IJK_TO_LPS[:3, :3].T]),  # 'none' for the list
              "space origin": IJK_TO_LPS[:3, 3]}
    path = tmp_path / "layers.nrrd"
    nrrd.write(str(path), data, header)
    with pytest.raises(GeometryError, match=r"4-D NRRD with a list axis of 2 and no segment names.*\.seg\.nrrd"):
        load_surface(path)


@pytest.mark.parametrize("label, ok", [("liver", True), (5, True), ("[1]", False), ("1.5", False)])
def test_the_config_takes_a_segment_name_or_a_label_value(label, ok):
    from liverforce.config import ConfigError, compose

    override = f"geometry.imported=[{{name:a,path:/x/seg.seg.nrrd,label:{label}}}]"
    if ok:
        assert compose([override])["geometry"]["imported"][0]["label"] == label
    else:
        with pytest.raises(ConfigError, match=r"'geometry.imported\[0\].label'.*segment's name or ID"):
            compose([override])


def test_a_legacy_segmentation_has_one_segment_per_layer_without_layer_fields(tmp_path):
    """Slicer before 4.11 wrote one segment per layer of a 4-D file and no Layer or LabelValue fields: a
    segment's layer is its index, as Slicer's own reader takes it (here the liver is in layer 1)."""
    import nrrd

    data = np.stack([ball(*SPLEEN), ball(*LIVER)]).astype(np.uint8)
    header = {"space": "left-posterior-superior", "kinds": ["list", "domain", "domain", "domain"],
              "space directions": np.vstack([np.full(3, np.nan), IJK_TO_LPS[:3, :3].T]),
              "space origin": IJK_TO_LPS[:3, 3]}
    for k, name in enumerate(["spleen", "liver"]):
        header.update({f"Segment{k}_ID": f"Segment_{k + 1}", f"Segment{k}_Name": name})
    path = tmp_path / "legacy.seg.nrrd"
    nrrd.write(str(path), data, header)
    s, msgs = load_surface(path)
    assert s.volume_mm3 == pytest.approx(ras_volume(LIVER[1]), rel=0.05)
    assert any("segment 'liver' (ID Segment_2, label 1) used" in m for m in msgs)


@pytest.mark.parametrize("space, kinds, to_ras", [
    ("left-anterior-superior", ["domain"] * 3, (-1, 1, 1)), ("LPS", ["domain"] * 3, (-1, -1, 1)),
    ("RAS", ["space"] * 3, (1, 1, 1)),
])
def test_a_segmentation_in_any_anatomical_space_is_read_in_it(tmp_path, space, kinds, to_ras):
    """The segment list is read from the header beside the frame, so every space the importer converts
    works for a .seg.nrrd too (slicerio's own reader takes only the two full LPS and RAS names)."""
    import nrrd

    data = np.zeros(SHAPE, np.uint8)
    data[ball(*LIVER)] = 4
    header = {"space": space, "kinds": kinds, "space directions": IJK_TO_LPS[:3, :3].T,
              "space origin": IJK_TO_LPS[:3, 3], "Segment0_ID": "Segment_1", "Segment0_Name": "Liver",
              "Segment0_LabelValue": "4", "Segment0_Layer": "0"}
    path = tmp_path / "seg.seg.nrrd"
    nrrd.write(str(path), data, header)
    s, _ = load_surface(path)
    lps_centre = IJK_TO_LPS @ np.array([*LIVER[0], 1.0])
    assert np.allclose(s.vertices.mean(axis=0), lps_centre[:3] * np.array(to_ras), atol=1.5)


def test_a_four_d_segmentation_without_kinds_is_read_by_layer(tmp_path):
    import nrrd

    data = np.stack([ball(*LIVER), ball(*TUMOUR)]).astype(np.uint8)
    header = {"space": "left-posterior-superior",
              "space directions": np.vstack([np.full(3, np.nan), IJK_TO_LPS[:3, :3].T]),
              "space origin": IJK_TO_LPS[:3, 3]}
    for k, name in enumerate(["liver", "tumour"]):
        header.update({f"Segment{k}_ID": name, f"Segment{k}_Name": name, f"Segment{k}_LabelValue": "1",
                       f"Segment{k}_Layer": str(k)})
    path = tmp_path / "nokinds.seg.nrrd"
    nrrd.write(str(path), data, header)
    s, _ = load_surface(path)
    assert s.volume_mm3 == pytest.approx(ras_volume(LIVER[1]), rel=0.05)


def test_digits_that_are_also_a_segments_name_are_refused_as_ambiguous(tmp_path):
    path = tmp_path / "digits.seg.nrrd"
    write_slicer(path, [("2", ball(*SPLEEN)), ("Liver", ball(*LIVER))])  # segment named "2" has label 1
    with pytest.raises(GeometryError, match=r"'2' is a label value and also the name or ID of segment '2' "
                                           r"\(label 1\)"):
        load_surface(path, label="2")
    s, _ = load_surface(path, label=2)  # an integer is a label value
    assert s.meta["label"] == 2


def test_a_three_d_segmentation_without_layer_fields_is_refused_not_misread(tmp_path):
    """Two segments with no Layer or LabelValue in a 3-D file would both be label 1 of one layer: as Slicer
    reads it, the second is in layer 1, which a 3-D file does not have."""
    import nrrd

    data = np.zeros(SHAPE, np.uint8)
    data[ball(*LIVER)] = 1
    header = {"space": "left-posterior-superior", "space directions": IJK_TO_LPS[:3, :3].T,
              "space origin": IJK_TO_LPS[:3, 3]}
    for k, name in enumerate(["liver", "kidney"]):
        header.update({f"Segment{k}_ID": name, f"Segment{k}_Name": name})
    path = tmp_path / "flat.seg.nrrd"
    nrrd.write(str(path), data, header)
    with pytest.raises(GeometryError, match=r"segment 1 \('kidney'\) is in layer 1, but the file has 1"):
        load_surface(path, label="kidney")


def test_a_four_d_segmentation_with_its_layers_last_is_refused(tmp_path):
    import nrrd

    data = np.stack([ball(*LIVER), ball(*TUMOUR)], axis=-1).astype(np.uint8)
    header = {"space": "left-posterior-superior",
              "space directions": np.vstack([IJK_TO_LPS[:3, :3].T, np.full(3, np.nan)]),
              "space origin": IJK_TO_LPS[:3, 3], "Segment0_ID": "liver", "Segment0_Layer": "0"}
    path = tmp_path / "last.seg.nrrd"
    nrrd.write(str(path), data, header)
    with pytest.raises(GeometryError, match=r"layers are on axis 3, not the first"):
        load_surface(path)
