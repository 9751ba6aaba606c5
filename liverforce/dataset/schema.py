"""The shard schema: one row per simulated case (the only place it is defined).

Units: mm, N, MPa. Point clouds are ``list<fixed_size_list<float32, 3>>``
(one variable-length list of xyz points per row), so they convert to NumPy
without copies. The schema version and the column units are written into the
Parquet file metadata (``liverforce.schema_version``, ``liverforce.units``).

Frames: every coordinate is in the geometry's own (source) frame, in mm.
``frame_normal`` / ``frame_t1`` / ``frame_t2`` give the local frame at the
exertion point (outward surface normal and two tangents) that learning uses to
make features and forces comparable across geometries.

Columns
-------
case_id : str            unique id ``<scenario>-<index:06d>``
scenario : str           I, II, III, IV or V (validation)
geometry_id : str        e.g. ``proc-0000``
shard_index : int32
seed : int64             per-case seed
material_model : str     e.g. ``yeoh``
material_param_names : list<str>
material_params_mpa : list<float64>   constants in MPa, same order as names
bulk_modulus_mpa : float64
exertion_id : int32      index of the exertion point in the geometry's candidate list
exertion_point_mm : fixed_size_list<float64,3>
force_n : fixed_size_list<float64,3>  the label: tool force vector, N
force_magnitude_n : float64
frame_normal, frame_t1, frame_t2 : fixed_size_list<float64,3>
liver_centroid_mm : fixed_size_list<float64,3>
inertia_mm5 : fixed_size_list<float64,9>   volume second-moment (inertia) tensor, unit density
tool_thickness_mm : float64   tissue thickness under the tool: from the exertion point along the
    inward normal to the opposite surface (pre-operative, from the undeformed surface)
probe_compliance_mm_per_n : fixed_size_list<float64,9>   the pre-operative linear stiffness probe
    (:mod:`liverforce.fem.probe`): compliance C (3 x 3, row-major, mm/N) of the liver on its
    supports at the exertion point, in the local frame (rows/columns t1, t2, n), for the
    experiment's reference material (``material`` config at its nominal constants; recorded in
    the file metadata ``liverforce.probe``). One factorisation per liver, no intraoperative cost.
roi_fraction : float64   target ROI area fraction
roi_area_fraction : float64   achieved ROI area fraction
roi_node_ids : list<int32>    mesh point ids of the ROI surface nodes
roi_triangles : list<fixed_size_list<int32,3>>   the ROI patch's own triangles (the surface facets whose three
    nodes are ROI nodes), as indices into the row's ROI node order; models read node displacements and camera
    heights on the patch's top sheet through them (:func:`liverforce.dataset.roi.roi_triangles`)
roi_undeformed_mm : list<fixed_size_list<float32,3>>
roi_deformed_mm : list<fixed_size_list<float32,3>>
roi_centroid_undeformed_mm, roi_centroid_deformed_mm : fixed_size_list<float64,3>
surface_displacement_mm : list<fixed_size_list<float32,3>>  every surface node (order: the
    mesh's sorted surface node ids), so ROI studies need no new simulation; empty if not stored
max_displacement_mm : float64
max_principal_stretch, min_principal_stretch : float64   largest and smallest principal stretch
    (sqrt of the eigenvalues of C = F^T F, dimensionless) over every quadrature point of the FE
    elements at the returned state (the converged one, or a failed case's last accepted state;
    NaN when the solve crashed). Compare with the Drucker-checked range
    ``material.stability_stretch``: outside it, the material's stability was never checked.
converged : bool
reason : str             empty when converged
load_fraction : float64  fraction of the load reached
load_steps, newton_iterations : int32
final_residual : float64
linear_solver : str
wall_time_s : float64    (not part of the deterministic payload)
"""

from __future__ import annotations

import pyarrow as pa

SCHEMA_VERSION = "1.4"  # 1.2: probe_compliance_mm_per_n; 1.3: max/min_principal_stretch; 1.4: roi_triangles

#: columns excluded from the deterministic payload hash (vary run to run)
NONDETERMINISTIC_COLUMNS = ("wall_time_s",)

_V3 = pa.list_(pa.float64(), 3)
_P3 = pa.list_(pa.float32(), 3)

SHARD_SCHEMA = pa.schema(
    [
        ("case_id", pa.string()),
        ("scenario", pa.string()),
        ("geometry_id", pa.string()),
        ("shard_index", pa.int32()),
        ("seed", pa.int64()),
        ("material_model", pa.string()),
        ("material_param_names", pa.list_(pa.string())),
        ("material_params_mpa", pa.list_(pa.float64())),
        ("bulk_modulus_mpa", pa.float64()),
        ("exertion_id", pa.int32()),
        ("exertion_point_mm", _V3),
        ("force_n", _V3),
        ("force_magnitude_n", pa.float64()),
        ("frame_normal", _V3),
        ("frame_t1", _V3),
        ("frame_t2", _V3),
        ("liver_centroid_mm", _V3),
        ("inertia_mm5", pa.list_(pa.float64(), 9)),
        ("tool_thickness_mm", pa.float64()),
        ("probe_compliance_mm_per_n", pa.list_(pa.float64(), 9)),
        ("roi_fraction", pa.float64()),
        ("roi_area_fraction", pa.float64()),
        ("roi_node_ids", pa.list_(pa.int32())),
        ("roi_triangles", pa.list_(pa.list_(pa.int32(), 3))),
        ("roi_undeformed_mm", pa.list_(_P3)),
        ("roi_deformed_mm", pa.list_(_P3)),
        ("roi_centroid_undeformed_mm", _V3),
        ("roi_centroid_deformed_mm", _V3),
        ("surface_displacement_mm", pa.list_(_P3)),
        ("max_displacement_mm", pa.float64()),
        ("max_principal_stretch", pa.float64()),
        ("min_principal_stretch", pa.float64()),
        ("converged", pa.bool_()),
        ("reason", pa.string()),
        ("load_fraction", pa.float64()),
        ("load_steps", pa.int32()),
        ("newton_iterations", pa.int32()),
        ("final_residual", pa.float64()),
        ("linear_solver", pa.string()),
        ("wall_time_s", pa.float64()),
    ]
)

#: the case table (sweep stage output): the inputs of every case
CASE_SCHEMA = pa.schema(
    [
        ("case_id", pa.string()),
        ("scenario", pa.string()),
        ("geometry_id", pa.string()),
        ("shard_index", pa.int32()),
        ("seed", pa.int64()),
        ("material_model", pa.string()),
        ("material_param_names", pa.list_(pa.string())),
        ("material_params_mpa", pa.list_(pa.float64())),
        ("bulk_modulus_mpa", pa.float64()),
        ("exertion_id", pa.int32()),
        ("exertion_point_mm", _V3),
        ("exertion_normal", _V3),
        ("force_n", _V3),
        ("force_magnitude_n", pa.float64()),
    ]
)

UNITS = {
    "exertion_point_mm": "mm",
    "force_n": "N",
    "force_magnitude_n": "N",
    "material_params_mpa": "MPa",
    "bulk_modulus_mpa": "MPa",
    "liver_centroid_mm": "mm",
    "inertia_mm5": "mm^5 (unit density)",
    "tool_thickness_mm": "mm",
    "probe_compliance_mm_per_n": "mm/N (local frame t1, t2, n; reference material)",
    "roi_undeformed_mm": "mm",
    "roi_deformed_mm": "mm",
    "surface_displacement_mm": "mm",
    "max_displacement_mm": "mm",
    "max_principal_stretch": "1 (stretch ratio, dimensionless)",
    "min_principal_stretch": "1 (stretch ratio, dimensionless)",
    "wall_time_s": "s",
}
