"""Boundary regions: non-empty, disjoint, anatomically placed, frame-invariant."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from liverforce.mesh.features import volume_moments
from liverforce.mesh.regions import RegionParams, tag_regions
from liverforce.mesh.types import REGION_CODES


def facet_centroids(mesh, mask):
    tri = mesh.points[mesh.facets[mask]]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return (area[:, None] * tri.mean(axis=1)).sum(axis=0) / area.sum(), area.sum()


def test_regions_and_visible_are_non_empty(liver_mesh):
    for name, code in REGION_CODES.items():
        assert (liver_mesh.facet_region == code).sum() >= 5, name
    assert liver_mesh.facet_visible.sum() >= 20
    assert liver_mesh.facet_region.dtype == np.int8 and liver_mesh.facet_visible.dtype == bool


def test_visible_is_free_and_keeps_its_margin(liver_mesh):
    vis, reg = liver_mesh.facet_visible, liver_mesh.facet_region
    assert not (vis & (reg != 0)).any()
    tagged_nodes = np.unique(liver_mesh.facets[reg != 0])
    d, _ = cKDTree(liver_mesh.points[tagged_nodes]).query(liver_mesh.points[np.unique(liver_mesh.facets[vis])])
    assert d.min() >= RegionParams().visible_margin_mm - 1e-9


def test_regions_sit_where_the_anatomy_puts_them(liver_mesh):
    _, c, _ = volume_moments(liver_mesh.points, liver_mesh.tets)  # RAS: x right, y anterior, z superior
    ivc, ivc_area = facet_centroids(liver_mesh, liver_mesh.facet_region == REGION_CODES["ivc"])
    lig, _ = facet_centroids(liver_mesh, liver_mesh.facet_region == REGION_CODES["ligament"])
    visc, _ = facet_centroids(liver_mesh, liver_mesh.facet_region == REGION_CODES["visceral"])
    rib, _ = facet_centroids(liver_mesh, liver_mesh.facet_region == REGION_CODES["rib"])
    vis, _ = facet_centroids(liver_mesh, liver_mesh.facet_visible)
    assert ivc[1] < c[1] - 40.0, "IVC patch on the posterior face"
    assert lig[2] > c[2] + 15.0 and lig[1] < c[1] - 15.0, "ligaments posterior-superior"
    assert visc[2] < c[2] - 15.0, "visceral face below"
    assert rib[1] > c[1] + 15.0 and rib[0] > c[0] + 20.0, "rib contact anterior, right"
    assert vis[1] > c[1] + 15.0 and vis[2] > c[2], "visible surface anterior-superior"
    r = RegionParams().ivc_radius_mm
    assert 0.5 * np.pi * r**2 < ivc_area < 1.6 * np.pi * r**2


def test_parameters_have_their_effect(liver_mesh):
    pts, fac = liver_mesh.points, liver_mesh.facets
    base_reg, base_vis = tag_regions(pts, fac, RegionParams())
    big_reg, _ = tag_regions(pts, fac, RegionParams(ivc_radius_mm=35.0))
    assert (big_reg == 1).sum() > 2 * (base_reg == 1).sum()
    wide_reg, _ = tag_regions(pts, fac, RegionParams(visceral_angle_deg=70.0))
    assert (wide_reg == 3).sum() > (base_reg == 3).sum()
    _, narrow_vis = tag_regions(pts, fac, RegionParams(visible_cone_deg=30.0))
    assert narrow_vis.sum() < base_vis.sum() and not (narrow_vis & ~base_vis).any()
    no_rib, _ = tag_regions(pts, fac, RegionParams(rib_min_right=1.0))
    assert (no_rib == 4).sum() < 0.2 * (base_reg == 4).sum()


def test_tags_follow_the_stated_frame(liver_mesh):
    """Rotating the liver and stating the rotated anatomical axes gives the same tags."""
    rot = Rotation.from_euler("zyx", [70.0, -30.0, 110.0], degrees=True).as_matrix()
    params = RegionParams()
    rotated = RegionParams(anterior=tuple(rot @ [0.0, 1.0, 0.0]), superior=tuple(rot @ [0.0, 0.0, 1.0]))
    reg, vis = tag_regions(liver_mesh.points, liver_mesh.facets, params)
    reg_r, vis_r = tag_regions(liver_mesh.points @ rot.T + [5.0, -3.0, 2.0], liver_mesh.facets, rotated)
    assert (reg == reg_r).mean() > 0.995 and (vis == vis_r).mean() > 0.995
    # and the default (RAS) frame on the rotated mesh does not
    reg_wrong, _ = tag_regions(liver_mesh.points @ rot.T, liver_mesh.facets, params)
    assert (reg == reg_wrong).mean() < 0.8


@pytest.mark.parametrize("kw", [dict(anterior=(0, 0, 1), superior=(0, 0, 2)), dict(ivc_radius_mm=0.0),
                                dict(ligament_band_fraction=1.5)])
def test_bad_region_params_are_refused(kw):
    with pytest.raises(ValueError, match="RegionParams"):
        RegionParams(**kw)
