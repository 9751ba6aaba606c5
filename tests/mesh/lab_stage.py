"""The mesh stage of a lab's imported liver with its own supports, as the pipeline runs it (smoke config, a coarse
mesh), for the tests of the regions checks under ``replace`` and ``add`` supports."""

from __future__ import annotations


def mesh_stage(tmp_path, path, supports, mode, frame="RAS"):
    """``(out_dir, run)``: the geometry stage run on ``path`` (mm, ``frame``) with ``supports``; ``run()`` runs the
    mesh stage with ``mesh.regions_check = mode`` into ``out_dir``."""
    from liverforce.config import compose
    from liverforce.pipeline.geometry import make_geometry
    from liverforce.pipeline.mesh import make_mesh

    spec = {"kind": "imported", "name": "lab", "path": str(path), "units": "mm", "label": None, "frame": frame,
            "supports": supports}
    surface = tmp_path / "geometry" / "imp-lab.ply"
    make_geometry(spec, surface, surface.with_suffix(".json"))
    cfg = compose(["experiment=smoke"])["mesh"]
    cfg = {**cfg, "target_nodes": 200, "refine_radius_mm": 0.0, "refine_ivc_edge_mm": 0.0, "regions_check": mode}
    out = tmp_path / "mesh"
    return out, lambda: make_mesh(surface, cfg, 0, out / "imp-lab.vtu", out / "imp-lab.features.json",
                                  out / "imp-lab.regions.png")
