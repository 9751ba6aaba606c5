"""Surface-label cleaning: the vectorised clean_labels against the straightforward loop it replaced."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from liverforce.mesh.patches import disc_patches
from liverforce.mesh.regions import RegionParams, tag_regions
from liverforce.mesh.surface_labels import _edge_pairs, clean_labels, label_boundary_edges


def clean_labels_reference(faces: np.ndarray, labels: np.ndarray, passes: int = 20) -> np.ndarray:
    """The original implementation (pure-Python neighbour table rebuilt every pass), kept as the oracle."""
    faces = np.asarray(faces, dtype=np.int64)
    lab = np.asarray(labels, dtype=np.int64).copy()
    _, ta, tb = _edge_pairs(faces)
    k = len(faces)
    nl = int(lab.max()) + 1 if lab.size else 1
    for _ in range(passes):
        changed = False
        nbr = np.full((k, 3), -1, dtype=np.int64)
        fill = np.zeros(k, dtype=np.int64)
        for x, y in ((ta, tb), (tb, ta)):
            for t, o in zip(x, y):
                nbr[t, fill[t]] = o
                fill[t] += 1
        nl_ = lab[nbr]
        agree = np.where(nl_[:, 0] == nl_[:, 1], nl_[:, 0], np.where(nl_[:, 1] == nl_[:, 2], nl_[:, 1],
                                                                     np.where(nl_[:, 0] == nl_[:, 2], nl_[:, 0], -1)))
        flip = (agree >= 0) & (agree != lab)
        if flip.any():
            lab[flip] = agree[flip]
            changed = True
        v_of = faces.ravel()
        code_t = v_of * nl + np.repeat(lab, 3)
        n_t = np.bincount(code_t, minlength=len(v_of) and (faces.max() + 1) * nl)
        same = lab[ta] == lab[tb]
        keys, _, _ = _edge_pairs(faces)
        ev = keys[same].ravel()
        code_e = ev * nl + np.repeat(lab[ta][same], 2)
        n_e = np.bincount(code_e, minlength=n_t.size)
        pinch = np.flatnonzero(n_t - n_e >= 2)
        if pinch.size:
            for code in pinch:
                v, L = divmod(int(code), nl)
                fan = np.flatnonzero((faces == v).any(axis=1))
                mine = fan[lab[fan] == L]
                others = lab[fan][lab[fan] != L]
                if others.size:
                    lab[mine] = np.bincount(others).argmax()
            changed = True
        if not changed:
            break
    return lab


def pinches(faces, lab):
    """(vertex, label) pairs where the label occupies two or more sectors of the vertex's fan."""
    keys, ta, tb = _edge_pairs(faces)
    nl = int(lab.max()) + 1
    n_t = np.bincount(faces.ravel() * nl + np.repeat(lab, 3), minlength=(faces.max() + 1) * nl)
    same = lab[ta] == lab[tb]
    n_e = np.bincount(keys[same].ravel() * nl + np.repeat(lab[ta][same], 2), minlength=n_t.size)
    return np.flatnonzero(n_t - n_e >= 2)


# hexagonal bipyramid: equator vertices 0-5, apex 6 (upper fan: faces 0-5 in order), apex 7 (lower: 6-11)
BIPYRAMID = np.array([[i, (i + 1) % 6, 6] for i in range(6)] + [[(i + 1) % 6, i, 7] for i in range(6)])


def test_crafted_ties_match_the_reference_and_the_rules():
    # upper fan 0 1 1 0 2 2: label 0 occupies two single-face sectors around apex 6 (a pinch); the
    # fan's other labels tie, 1 and 2 twice each. The lower fan (all 3) makes no edge-neighbour
    # majority anywhere on the upper fan, so the pinch alone acts, and the tie goes to the smaller label.
    labels = np.array([0, 1, 1, 0, 2, 2] + [3] * 6)
    assert len(pinches(BIPYRAMID, labels)) == 1
    for passes in (1, 2, 20):
        out = clean_labels(BIPYRAMID, labels, passes)
        assert np.array_equal(out, clean_labels_reference(BIPYRAMID, labels, passes))
    assert clean_labels(BIPYRAMID, labels).tolist() == [1, 1, 1, 1, 2, 2] + [3] * 6
    # same with the tie the other way round in label order: still the smaller label (1) wins
    swapped = np.array([0, 2, 2, 0, 1, 1] + [3] * 6)
    assert clean_labels(BIPYRAMID, swapped).tolist() == [1, 2, 2, 1, 1, 1] + [3] * 6
    assert np.array_equal(clean_labels(BIPYRAMID, swapped), clean_labels_reference(BIPYRAMID, swapped))
    # two pinches at one apex (labels 0 and 1 alternate): resolved one after the other, in label order
    alternate = np.array([0, 1, 0, 1, 0, 1] + [3] * 6)
    assert np.array_equal(clean_labels(BIPYRAMID, alternate), clean_labels_reference(BIPYRAMID, alternate))
    # a spike: a face whose three neighbours agree takes their label
    spike = np.array([7] + [1] * 11)
    assert clean_labels(BIPYRAMID, spike).tolist() == [1] * 12


@pytest.mark.parametrize("seed", range(6))
def test_random_labels_on_a_sphere_match_the_reference(seed):
    # many spikes, pinches and ties: few labels scattered in small blobs over a sphere
    s = trimesh.creation.icosphere(subdivisions=3, radius=50.0)
    faces = np.asarray(s.faces, dtype=np.int64)
    rng = np.random.default_rng(seed)
    cent = s.triangles_center
    seeds = rng.choice(len(faces), 12, replace=False)
    labels = rng.integers(0, 4, 12)[np.argmin(np.linalg.norm(cent[:, None] - cent[seeds][None], axis=2), axis=1)]
    flip = rng.random(len(faces)) < 0.15
    labels[flip] = rng.integers(0, 4, flip.sum())
    for passes in (1, 3, 20):
        assert np.array_equal(clean_labels(faces, labels, passes), clean_labels_reference(faces, labels, passes))


def test_labelled_liver_surface_matches_the_reference(liver_surface):
    """The route's own inputs: the region labels of a procedural liver, then its disc patches."""
    verts, faces = liver_surface.vertices, np.asarray(liver_surface.faces, dtype=np.int64)
    regions, _ = tag_regions(verts, faces, RegionParams())
    labels = np.asarray(regions, dtype=np.int64)
    cleaned = clean_labels(faces, labels)
    assert np.array_equal(cleaned, clean_labels_reference(faces, labels))
    patches = disc_patches(verts, faces, cleaned)
    cleaned_patches = clean_labels(faces, patches)
    assert np.array_equal(cleaned_patches, clean_labels_reference(faces, patches))
    assert len(pinches(faces, cleaned_patches)) == 0
    assert len(label_boundary_edges(faces, cleaned_patches)) > 0


def test_a_non_manifold_surface_is_refused():
    faces = np.concatenate([BIPYRAMID, [[0, 1, 3]]])  # edge (0, 1) now borders three triangles
    with pytest.raises(ValueError, match="not manifold"):
        clean_labels(faces, np.zeros(len(faces), dtype=np.int64))
