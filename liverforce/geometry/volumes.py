"""Label volumes (NIfTI, NRRD) to a triangle surface in physical mm.

The voxel-to-world map comes from the file (NIfTI ``affine``, RAS+; NRRD
``space directions``/``space origin``, converted to RAS from the stated
``space``: right-anterior-superior, left-anterior-superior or
left-posterior-superior). A header that states no anatomical frame (NIfTI
sform and qform codes 0; NRRD with no ``space`` or a ``scanner-xyz`` /
``3D-right-handed`` one) is read as RAS and says so in the messages; a
``3D-left-handed`` NRRD is refused (read as RAS, the liver would be
mirrored). The chosen label's mask is cropped, lightly smoothed (Gaussian,
σ = ``smooth_voxels``), contoured by marching cubes at 0.5 and mapped to the
world frame, so the surface is in the file's physical units (mm for nearly
all medical images).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import re
from pathlib import Path

import numpy as np

from liverforce.geometry.errors import refuse

#: Suffixes read as label volumes.
VOLUME_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr")


@dataclass
class LabelVolume:
    """A label image with its voxel-index → world (RAS) affine."""

    data: np.ndarray  # (i, j, k) integer labels
    affine: np.ndarray  # (4, 4)
    units: str | None  # spatial unit stated by the file ("mm", "m", "um") or None
    format: str
    messages: list[str] = field(default_factory=list)  # what the header did not state and what was assumed
    #: a 3D Slicer segmentation's named segments (``.seg.nrrd``: ``SegmentN_`` header fields); with ``layered``
    #: the data is ``(layer, i, j, k)`` (segments that overlap are kept in separate layers)
    segments: list[Segment] = field(default_factory=list)
    layered: bool = False


@dataclass
class Segment:
    """One named segment of a 3D Slicer segmentation: its voxels are ``label`` in layer ``layer``."""

    name: str
    id: str
    label: int
    layer: int


#: NRRD ``space`` (lower case) -> the diagonal that takes it to RAS
_NRRD_ANATOMICAL = {
    "right-anterior-superior": (1.0, 1.0, 1.0), "ras": (1.0, 1.0, 1.0),
    "left-anterior-superior": (-1.0, 1.0, 1.0), "las": (-1.0, 1.0, 1.0),
    "left-posterior-superior": (-1.0, -1.0, 1.0), "lps": (-1.0, -1.0, 1.0),
}
#: NRRD spaces with no anatomical meaning, right-handed: read as RAS, with a message
_NRRD_RIGHT_HANDED = ("scanner-xyz", "3d-right-handed")
_NO_FRAME_FIX = ("if the liver is mirrored or its supports and tool positions do not land on it, save the "
                 "segmentation with its orientation (3D Slicer does) or give frame=<4x4>")


def is_volume_file(path: Path) -> bool:
    """True for ``.nii``, ``.nii.gz``, ``.nrrd``, ``.nhdr``."""
    name = path.name.lower()
    return any(name.endswith(s) for s in VOLUME_SUFFIXES)


def read_label_volume(path: str | Path) -> LabelVolume:
    """Read a NIfTI (nibabel) or NRRD (pynrrd) label image."""
    path = Path(path)
    name = path.name.lower()
    if name.endswith((".nii", ".nii.gz")):
        import nibabel as nib

        try:
            img = nib.load(str(path))
            data = np.asanyarray(img.dataobj)
            affine = np.asarray(img.affine, dtype=np.float64)
            unit = img.header.get_xyzt_units()[0]
            coded = int(img.header["sform_code"]) > 0 or int(img.header["qform_code"]) > 0
        except Exception as exc:  # nibabel raises several types
            raise refuse(path, f"could not read the NIfTI image ({type(exc).__name__}: {exc})",
                         "Check the file opens in a NIfTI viewer (e.g. 3D Slicer, ITK-SNAP)") from None
        units = {"mm": "mm", "meter": "m", "micron": "um"}.get(unit)
        fmt = "nifti"
        messages = [] if coded else [
            "the NIfTI header states no frame (sform and qform codes 0): nibabel's default map was used "
            "(voxel sizes from pixdim, x reversed, the image centred on the origin) and read as RAS; "
            + _NO_FRAME_FIX]
    else:
        import nrrd

        try:
            data, header = nrrd.read(str(path))
        except Exception as exc:  # pynrrd raises several types
            raise refuse(path, f"could not read the NRRD image ({type(exc).__name__}: {exc})",
                         "Check the file opens in 3D Slicer") from None
        affine, messages = _nrrd_affine(header, data.ndim, path)
        su = header.get("space units")
        units = str(su[0]) if su is not None and len(su) else None
        fmt = "nrrd"
        kinds = [str(k).lower() for k in header.get("kinds", [])]
        if any(_SEGMENT_FIELD.match(str(k)) for k in header):
            return _slicer_segmentation(path, np.asarray(data), header, kinds, affine, units, messages)
        if np.ndim(data) == 4 and kinds[:1] == ["list"]:
            raise refuse(path, f"a 4-D NRRD with a list axis of {np.shape(data)[0]} and no segment names: "
                               "cannot tell which layer is the liver",
                         "Save it from 3D Slicer as a segmentation (.seg.nrrd) or export the liver as a 3-D "
                         "labelmap")
    data = np.asarray(data)
    if data.ndim == 4 and data.shape[3] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        raise refuse(path, f"expected a 3-D label image, got shape {data.shape}",
                     "Give a single 3-D segmentation (one label per voxel)")
    return LabelVolume(data, affine, units, fmt, messages)


_SEGMENT_FIELD = re.compile(r"^Segment([0-9]+)_")


def _slicer_segmentation(path: Path, data: np.ndarray, header: dict, kinds: list[str], affine: np.ndarray,
                         units: str | None, messages: list[str]) -> LabelVolume:
    """A 3D Slicer segmentation: its segments from the ``SegmentN_ID``, ``_Name``, ``_LabelValue`` and ``_Layer``
    header fields, read as Slicer reads them (a missing label value is 1, a missing layer the segment's index:
    Slicer before 4.11 wrote one segment per layer). The frame is the header's, as for any NRRD
    (:func:`_nrrd_affine`)."""
    fields: dict[int, dict] = {}
    for key, value in header.items():
        m = _SEGMENT_FIELD.match(str(key))
        if m:
            fields.setdefault(int(m.group(1)), {})[str(key)[m.end():]] = str(value).strip()
    if data.ndim not in (3, 4):
        raise refuse(path, f"expected a 3-D segmentation or a 4-D one of layers, got shape {data.shape}",
                     "Save the segmentation from 3D Slicer again")
    layered = data.ndim == 4
    if layered:  # the layers' axis: the 'list' kind, or without kinds the axis with no space direction
        dirs = header.get("space directions")
        spatial = [r is not None and bool(np.all(np.isfinite(np.asarray(r, dtype=float)))) for r in
                   (dirs if dirs is not None else [])]
        axis = kinds.index("list") if "list" in kinds else (spatial.index(False) if False in spatial else 0)
        if axis != 0:
            raise refuse(path, f"a 4-D segmentation whose layers are on axis {axis}, not the first",
                         "Save the segmentation from 3D Slicer again")
    segments = []
    for index in sorted(fields):
        f = fields[index]
        try:  # as Slicer reads a file that lacks them: label 1, the segment's index as its layer
            label = int(f.get("LabelValue", 1))
            layer = int(f.get("Layer", index))
        except ValueError:
            raise refuse(path, f"segment {index} ('{f.get('Name', '')}') has LabelValue '{f.get('LabelValue')}' "
                               f"and Layer '{f.get('Layer')}', not integers",
                         "Save the segmentation from 3D Slicer again") from None
        n_layers = data.shape[0] if layered else 1
        if not 0 <= layer < n_layers:
            raise refuse(path, f"segment {index} ('{f.get('Name', '')}') is in layer {layer}, but the file has "
                               f"{n_layers}", "Save the segmentation from 3D Slicer again")
        segments.append(Segment(f.get("Name", f.get("ID", f"Segment{index}")), f.get("ID", f"Segment{index}"),
                                label, layer))
    seen: dict = {}
    for sg in segments:
        if (sg.layer, sg.label) in seen:
            raise refuse(path, f"segments '{seen[sg.layer, sg.label]}' and '{sg.name}' are both label {sg.label} in "
                               f"layer {sg.layer}", "Save the segmentation from 3D Slicer again")
        seen[sg.layer, sg.label] = sg.name
    return LabelVolume(data, affine, units, "slicer segmentation (nrrd)", messages, segments, layered)


def _nrrd_affine(header: dict, ndim: int, path: Path) -> tuple[np.ndarray, list[str]]:
    """Voxel → RAS world affine from NRRD ``space directions``/``origin``/``spacings`` and ``space``, and the
    messages on what the header did not state."""
    aff = np.eye(4)
    dirs = header.get("space directions")
    if dirs is not None:
        rows = [np.asarray(d, dtype=np.float64) for d in dirs]
        rows = [r for r in rows if r.ndim == 1 and r.size == 3 and np.all(np.isfinite(r))]
        if len(rows) != 3:
            raise refuse(path, "NRRD 'space directions' do not give three spatial axes",
                         "Save the segmentation as a 3-D NRRD with space directions")
        aff[:3, :3] = np.stack(rows, axis=1)
        aff[:3, 3] = np.asarray(header.get("space origin", np.zeros(3)), dtype=np.float64)[:3]
    elif "spacings" in header:
        aff[:3, :3] = np.diag(np.asarray(header["spacings"], dtype=np.float64)[:3])
    given = header.get("space")
    space = str(given or "").strip().lower()
    if space.endswith("-time") or space in ("rast", "last", "lpst"):
        raise refuse(path, f"NRRD space '{given}' is a time series, not a 3-D segmentation",
                     "Save one 3-D segmentation of the liver")
    if space in _NRRD_ANATOMICAL:
        return np.diag([*_NRRD_ANATOMICAL[space], 1.0]) @ aff, []
    if space == "3d-left-handed":
        raise refuse(path, "NRRD space '3D-left-handed' has no anatomical frame, and read as RAS the liver "
                           "would be mirrored",
                     "Save the segmentation in an anatomical space (3D Slicer writes left-posterior-superior)")
    if not space:
        what = "states no 'space'"
    elif space in _NRRD_RIGHT_HANDED:
        what = f"states space '{given}', which has no anatomical frame"
    else:
        raise refuse(path, f"NRRD space '{given}' is not one this importer knows",
                     "Use right-anterior-superior, left-anterior-superior or left-posterior-superior")
    return aff, [f"the NRRD header {what}: its coordinates were read as RAS; {_NO_FRAME_FIX}"]


def labels_present(data: np.ndarray) -> list[int]:
    """Sorted non-zero labels in ``data``."""
    return [int(v) for v in np.unique(data) if v != 0]


def label_surface(
    volume: LabelVolume, label: int | str | None, path=None, smooth_voxels: float = 0.7,
    max_triangles: int = 80_000,
) -> tuple[np.ndarray, np.ndarray, list[str], int, str | None]:
    """Surface of ``label`` in world units (before unit scaling).

    ``label``: the liver's label value, or for a 3D Slicer segmentation also a segment's name or ID (None: the
    only label, the only segment, or the one segment named "liver").

    Returns
    -------
    vertices, faces, messages, label, segment
        Outward-oriented surface (not yet repaired), what was done, the
        label value used and the segment's ID (None: the file names no segments).
    """
    from scipy.ndimage import gaussian_filter
    from skimage.measure import marching_cubes

    msgs: list[str] = []
    data, label, sg, why = _resolve(volume, label, path)
    segment = None if sg is None else sg.id
    if sg is not None:
        msgs.append(f"segment '{sg.name}' (ID {sg.id}, label {sg.label}) used ({why})")
    present = labels_present(data)
    if label is None:
        if len(present) != 1:
            raise refuse(
                path,
                f"the volume holds {len(present)} labels {present[:20]}; cannot tell which is the liver"
                if present else "the volume holds no non-zero label (empty segmentation)",
                "Pass label=<the liver's label value>" if present else "Check the segmentation",
            )
        label = present[0]
        msgs.append(f"label {label} used (the only non-zero label)")
    mask = data == label
    if not mask.any():
        raise refuse(
            path,
            f"label {label} is not present in the volume (labels present: {present[:20] or 'none'})",
            "Choose one of the labels present with label=...",
        )
    idx = np.argwhere(mask)
    lo, hi = idx.min(axis=0), idx.max(axis=0) + 1
    pad = 3
    crop = np.zeros(tuple(hi - lo + 2 * pad), dtype=np.float32)
    crop[pad:-pad, pad:-pad, pad:-pad] = mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    if smooth_voxels > 0:
        crop = gaussian_filter(crop, smooth_voxels)
    # keep the marching-cubes output below ~max_triangles: ~2 triangles per boundary voxel face
    from scipy.ndimage import binary_erosion

    n_boundary = int((mask & ~binary_erosion(mask)).sum())
    step = max(1, int(np.ceil(np.sqrt(2.0 * n_boundary / max_triangles))))
    if step > 1:
        msgs.append(f"marching cubes with a step of {step} voxels (large mask, kept below ~{max_triangles} triangles)")
    verts, faces, _, _ = marching_cubes(crop, level=0.5, step_size=step, allow_degenerate=False)
    ijk = verts + (lo - pad)
    world = ijk @ volume.affine[:3, :3].T + volume.affine[:3, 3]
    faces = faces.astype(np.int64)
    vol = _signed_volume(world, faces)
    if vol < 0:
        faces = faces[:, ::-1].copy()
    return world, faces, msgs, int(label), segment


def _resolve(volume: LabelVolume, label, path) -> tuple[np.ndarray, int | None, Segment | None, str | None]:
    """The voxels a label value, segment name or ID (or None) refers to: ``(data, label value, segment, why)``
    (a segmentation's one layer; label None stays None in a file with no segments)."""
    label = _as_value(volume, label, path)
    if volume.segments:
        data, sg, why = _segment_voxels(volume, label, path)
        return data, sg.label, sg, why
    if isinstance(label, str):
        present = labels_present(volume.data)
        raise refuse(path, f"label '{label}' names a segment, but the file names none (labels present: "
                           f"{present[:20] or 'none'})",
                     f"Give its label value, e.g. label={present[0] if present else 1}")
    return volume.data, label, None, None


def _as_value(volume: LabelVolume, label, path):
    """A label given as digits in text (a command line, a config) is a label value, unless a segment is named
    or has that ID with another value: that is refused as ambiguous."""
    if not (isinstance(label, str) and label.strip().lstrip("-").isdigit()):
        return label
    value = int(label)
    same = [sg for sg in volume.segments if label.strip() in (sg.id, sg.name.strip())]
    if any(sg.label != value for sg in same):
        raise refuse(path, f"'{label}' is a label value and also the name or ID of segment '{same[0].name}' "
                           f"(label {same[0].label})",
                     "Give that segment by its ID, or the label value as a number, unquoted")
    return value


def _segment_voxels(volume: LabelVolume, label: int | str | None, path) -> tuple[np.ndarray, Segment, str]:
    """The voxels (one layer) holding the chosen segment of a 3D Slicer segmentation, the segment, and why it
    was chosen."""
    segs = volume.segments
    listing = "; ".join(f"'{sg.name}' (label {sg.label}" + (f", layer {sg.layer})" if volume.layered else ")")
                        for sg in segs[:30]) + (f"; and {len(segs) - 30} more" if len(segs) > 30 else "")
    fix = "Pass label=<a segment's name or label value>"
    if label is None:
        named = [sg for sg in segs if sg.name.strip().lower() == "liver"]
        if len(segs) == 1:
            chosen, why = segs, "the only segment"
        elif len(named) == 1:
            chosen, why = named, "the one named liver; give label= to choose another"
        else:
            raise refuse(path, f"the segmentation holds {len(segs)} segments and "
                               f"{'several' if named else 'none'} named liver: {listing}", fix)
    elif isinstance(label, str):
        want = label.strip().lower()
        chosen = [sg for sg in segs if sg.id == label] or [sg for sg in segs if sg.name.strip().lower() == want]
        why = f"label='{label}'"
        if len(chosen) != 1:
            raise refuse(path, f"{'several segments are' if chosen else 'no segment is'} named or has ID "
                               f"'{label}' (segments: {listing})",
                         "Give the segment's ID" if chosen else fix)
    else:
        chosen = [sg for sg in segs if sg.label == label]
        why = f"label={label}"
        if len(chosen) > 1 and volume.layered:
            raise refuse(path, f"label {label} is used by {len(chosen)} segments in different layers "
                               f"(segments: {listing})", "Give the segment's name or ID")
        if not chosen:
            raise refuse(path, f"no segment has label {label} (segments: {listing})", fix)
    sg = chosen[0]
    return (volume.data[sg.layer] if volume.layered else volume.data), sg, why


def segment_boundary_voxels(volume: LabelVolume, label: int | str, path=None
                            ) -> tuple[np.ndarray, str, int, str | None]:
    """Voxel indices ``(k, 3)`` of the boundary voxels of a label value or a segment (name or ID) (the voxel to
    world map is ``volume.affine``, world frame and units: the surface's before unit scaling); what it is
    (for messages); its label value and segment ID (None: the file names no segments).

    A support given as another segment of the liver's segmentation (e.g. the inferior vena cava) is where
    the liver's surface touches these points (:class:`liverforce.mesh.groups.VolumeGroups`).
    """
    from scipy.ndimage import binary_erosion

    if str(label).strip() == "0":
        raise refuse(path, "label 0 is the background: its boundary is the whole liver's",
                     "Give the label value or segment the liver rests on")
    data, value, sg, _ = _resolve(volume, label, path)
    segment = None if sg is None else sg.id
    what = f"label {value}" if sg is None else f"segment '{sg.name}' (ID {sg.id}, label {sg.label})"
    mask = data == value
    if not mask.any():
        raise refuse(path, f"{what} has no voxel (labels present: {labels_present(data)[:20] or 'none'})",
                     "Give a label value or segment present in the file")
    return np.argwhere(mask & ~binary_erosion(mask)), what, int(value), segment


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    v = v - v.mean(axis=0)
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)
