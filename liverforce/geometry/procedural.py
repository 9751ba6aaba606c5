"""Built-in geometries: seeded procedural livers and a cube phantom.

Frame convention (RAS, the NIfTI world convention; right-handed), in mm:

* ``+x`` = patient **right** (the right lobe lies at ``+x``, the left lobe at
  ``-x``),
* ``+y`` = **anterior**,
* ``+z`` = **superior** (cranial).

The procedural liver is the zero level set of an implicit function built
from simple parts (see :func:`liver_implicit`), extracted by marching cubes
(scikit-image) and smoothed (Taubin, volume-preserving).  The shape is
centred so that its bounding-box centre is the origin.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from liverforce.geometry.surface import Surface
from liverforce.seeds import liver_rng

GENERATOR_VERSION = "procedural-liver-1"


@dataclass(frozen=True)
class LiverShapeParams:
    """Controls of the procedural liver (mean values; the seed adds spread).

    Parameters
    ----------
    size_scale : float
        Overall linear scale (1.0: about 255 × 150 × 110 mm and 1.3–1.8 L;
        measured over seeds 0–19: 234–276 × 130–165 × 99–119 mm,
        1.34–1.75 L).
    lobe_ratio : float
        Relative size of the left lobe (default 0.30): its planform area
        (and so its volume) scales with ``lobe_ratio / 0.30`` (both in-plane
        axes × ``sqrt(lobe_ratio / 0.30)``), the right lobe is unchanged.
        Seed 0: 0.15 → 0.6 takes the liver from 0.90× to 1.18× the default
        volume and its width from 0.91× to 1.14×.
    thickness : float
        Scale of the superior–inferior (z) extent of both lobes (1.0 default).
    undulation_mm : float
        Amplitude (RMS, mm) of the low-frequency surface undulation.
    undulation_wavelength_mm : float
        Mean wavelength (mm) of the undulation modes.
    anterior_border_deg : float
        Inclination (degrees) of the inferior (visceral) face rising toward
        the anterior border; larger = sharper anterior border.
    variation : float
        Relative spread of the seeded random draws of every shape factor
        (0 gives the same mean shape for every seed, apart from undulation).
    voxel_mm : float
        Marching-cubes grid spacing (mm); smaller = finer surface, slower.
    smoothing_iterations : int
        Taubin smoothing iterations applied after marching cubes.
    volume_range_l : (float, float) or None
        Population spread of the liver volume: each seed draws a target volume
        uniformly in this range (litres) and the extracted liver is scaled
        about its centre to it (shape factors unchanged). ``None`` keeps the
        volume the shape factors give (about 1.3-1.8 L at ``size_scale`` 1).
        Adult livers are about 1.0-2.2 L.
    """

    size_scale: float = 1.0
    lobe_ratio: float = 0.30
    thickness: float = 1.0
    undulation_mm: float = 3.0
    undulation_wavelength_mm: float = 90.0
    anterior_border_deg: float = 35.0
    variation: float = 0.12
    voxel_mm: float = 2.5
    smoothing_iterations: int = 15
    volume_range_l: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.volume_range_l is not None:
            object.__setattr__(self, "volume_range_l", tuple(float(v) for v in self.volume_range_l))
        checks = {
            "size_scale": self.size_scale > 0,
            "lobe_ratio": 0.02 <= self.lobe_ratio <= 1.5,
            "thickness": 0.3 <= self.thickness <= 2.0,
            "undulation_mm": self.undulation_mm >= 0,
            "undulation_wavelength_mm": self.undulation_wavelength_mm > 0,
            "anterior_border_deg": 0 <= self.anterior_border_deg <= 70,
            "variation": 0 <= self.variation <= 0.4,
            "voxel_mm": 0.2 <= self.voxel_mm <= 10 * self.size_scale,
            "smoothing_iterations": self.smoothing_iterations >= 0,
            "volume_range_l": self.volume_range_l is None or (
                len(self.volume_range_l) == 2 and 0.05 <= self.volume_range_l[0] <= self.volume_range_l[1] <= 10.0),
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(
                f"LiverShapeParams: invalid value for {', '.join(bad)} "
                f"({', '.join(f'{k}={getattr(self, k)!r}' for k in bad)}); "
                "see the class docstring for the allowed ranges"
            )


@dataclass(frozen=True)
class _Shape:
    """Concrete (seed-drawn) shape factors, all in mm / radians."""

    right_centre: np.ndarray
    right_axes: np.ndarray  # (ax, ay, az_superior, az_inferior)
    left_centre: np.ndarray
    left_axes: np.ndarray  # (ax, ay, az)
    left_taper: float
    border_angle: float
    border_y: float
    border_z: float
    notch_centre: np.ndarray
    notch_radius: float
    posterior_y: float
    shear: float
    rim_mm: float
    blend_mm: float
    wave_k: np.ndarray  # (m, 3) wave vectors, rad/mm
    wave_phase: np.ndarray  # (m,)
    wave_amp: float


def _draw_shape(seed: int, p: LiverShapeParams) -> _Shape:
    """Draw the concrete shape factors for ``seed`` (NumPy PCG64 stream)."""
    rng = liver_rng(seed, "shape")
    v = p.variation

    def jit(n: int = 1) -> np.ndarray:
        return 1.0 + v * rng.uniform(-1.0, 1.0, n)

    s = p.size_scale
    t = p.thickness
    lobe = np.sqrt(p.lobe_ratio / 0.30) * jit()[0]
    right_axes = s * np.array([80.0, 80.0, 58.0 * t, 38.0 * t]) * jit(4)
    right_centre = s * np.array([45.0, -2.0, 0.0]) + s * 12.0 * v * rng.uniform(-1, 1, 3)
    left_axes = s * np.array([88.0 * lobe, 62.0 * lobe, 24.0 * t]) * jit(3)
    left_centre = s * np.array([-45.0, 18.0, 18.0 * t]) + s * 12.0 * v * rng.uniform(-1, 1, 3)
    left_taper = float(np.clip(0.6 * jit()[0], 0.2, 0.85))
    angle = np.deg2rad(p.anterior_border_deg * jit()[0])
    border_y = s * 40.0 * jit()[0]
    border_z = -s * 35.0 * t * jit()[0]
    notch_centre = s * np.array([-8.0, 78.0, -12.0]) + s * 8.0 * v * rng.uniform(-1, 1, 3)
    notch_radius = s * 14.0 * jit()[0]
    posterior_y = -s * 70.0 * jit()[0]
    # undulation: a few plane waves with random directions and wavelengths
    m = 8
    dirs = rng.normal(size=(m, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    lam = p.undulation_wavelength_mm * s * rng.uniform(0.7, 1.4, m)
    wave_k = dirs * (2.0 * np.pi / lam)[:, None]
    wave_phase = rng.uniform(0.0, 2.0 * np.pi, m)
    return _Shape(
        right_centre=right_centre,
        right_axes=right_axes,
        left_centre=left_centre,
        left_axes=left_axes,
        left_taper=left_taper,
        border_angle=float(angle),
        border_y=float(border_y),
        border_z=float(border_z),
        notch_centre=notch_centre,
        notch_radius=float(notch_radius),
        posterior_y=float(posterior_y),
        shear=float(0.35 * jit()[0]),
        rim_mm=5.0 * s,
        blend_mm=18.0 * s,
        wave_k=wave_k,
        wave_phase=wave_phase,
        wave_amp=float(p.undulation_mm * np.sqrt(2.0 / m)),
    )


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (smooth union) with blend width ``k`` (mm)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _smax(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Smooth maximum (smooth intersection) with blend width ``k`` (mm)."""
    return -_smin(-a, -b, k)


def _round_max(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection of two distance fields with an exact (circular) corner."""
    return np.hypot(np.maximum(a, 0.0), np.maximum(b, 0.0)) + np.minimum(np.maximum(a, b), 0.0)


def _ellipsoid_sdf(q: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Approximate signed distance (mm) to an axis-aligned ellipsoid at 0.

    ``q`` is ``(..., 3)`` relative position, ``axes`` broadcastable to it.
    Uses the first-order estimate ``(|q/a| - 1) |q/a| / |q/a²|``.
    """
    k0 = np.linalg.norm(q / axes, axis=-1)
    k1 = np.linalg.norm(q / axes**2, axis=-1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def _shape_bounds(shape: _Shape, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Box (mm) holding both lobes (sheared) plus ``margin``."""
    rc, (ax, ay, azs, azi) = shape.right_centre, shape.right_axes
    lc, (lx, ly, lz) = shape.left_centre, shape.left_axes
    shear_z = abs(shape.shear) * max(ay, ly)
    lo = np.minimum(rc - [ax, ay, azi + shear_z], lc - [lx, ly, lz + shear_z])
    hi = np.maximum(rc + [ax, ay, azs + shear_z], lc + [lx, ly, lz + shear_z])
    return lo - margin, hi + margin


def liver_implicit(points: np.ndarray, shape: _Shape) -> np.ndarray:
    """Implicit liver function ``f`` (≈ signed distance in mm, < 0 inside).

    Notes
    -----
    * right lobe: ellipsoid with a taller superior dome (``az_sup``) than its
      flatter inferior half (``az_inf``);
    * left lobe: flat slab over an elliptic planform, lens-shaped in
      thickness, thinning toward its left (``-x``) tip and its anterior
      margin, with a rounded rim of radius ``rim_mm`` (no knife edges the
      mesher cannot resolve), smoothly united with the right lobe;
    * anterior border: intersection with a half-space whose plane rises
      anteriorly at ``border_angle`` — the inferior (visceral) face meets the
      diaphragmatic dome at a sharp edge;
    * posterior face flattened by a half-space ``y > posterior_y``;
    * a small umbilical notch at the anterior border between the lobes;
    * undulation: sum of plane waves added to ``f``.
    """
    p = points
    # right lobe
    q = p - shape.right_centre
    q = np.stack([q[..., 0], q[..., 1], q[..., 2] + shape.shear * q[..., 1]], axis=-1)
    ax, ay, az_sup, az_inf = shape.right_axes
    az = np.where(q[..., 2] >= 0.0, az_sup, az_inf)
    axes_r = np.stack(np.broadcast_arrays(ax, ay, az), axis=-1)
    f_right = _ellipsoid_sdf(q, axes_r)
    # left lobe: elliptic planform (x-y) x lens-shaped thickness profile,
    # thinning toward the left tip and the anterior margin, with a rounded rim
    q = p - shape.left_centre
    lx, ly, lz = shape.left_axes
    qz = q[..., 2] + 0.5 * shape.shear * q[..., 1]
    rho = np.sqrt((q[..., 0] / lx) ** 2 + (q[..., 1] / ly) ** 2)
    u = np.clip(-q[..., 0] / lx, 0.0, 1.0)  # 0 at centre, 1 at the left tip
    w = np.clip(q[..., 1] / ly, 0.0, 1.0)  # 0 at centre, 1 at the anterior margin
    lens = 0.35 + 0.65 * np.sqrt(np.clip(1.0 - rho**2, 0.0, 1.0))
    r = shape.rim_mm
    half = np.maximum(lz * (1.0 - shape.left_taper * u) * (1.0 - 0.4 * w) * lens, r + 0.5)
    d_plan = (rho - 1.0) * np.minimum(lx, ly)  # approx. distance to the planform rim
    d_slab = np.abs(qz) - half
    f_left = _round_max(d_plan + r, d_slab + r) - r
    f = _smin(f_right, f_left, shape.blend_mm)
    # sharp anterior border: visceral plane rising anteriorly
    n = np.array([0.0, np.sin(shape.border_angle), -np.cos(shape.border_angle)])
    plane = (p[..., 1] - shape.border_y) * n[1] + (p[..., 2] - shape.border_z) * n[2]
    f = _smax(f, plane, 6.0 * shape.rim_mm / 5.0)
    # flattened posterior face
    f = _smax(f, shape.posterior_y - p[..., 1], 25.0)
    # umbilical notch (subtract a vertical cylinder)
    dq = p[..., :2] - shape.notch_centre[:2]
    notch = shape.notch_radius - np.linalg.norm(dq, axis=-1)
    f = _smax(f, notch, 6.0)
    # undulation
    if shape.wave_amp > 0:
        phase = p @ shape.wave_k.T + shape.wave_phase
        f = f + shape.wave_amp * np.sin(phase).sum(axis=-1)
    return f


def procedural_liver(seed: int, params: LiverShapeParams | None = None) -> Surface:
    """Seeded, liver-like closed surface in mm (RAS frame, see module doc).

    Parameters
    ----------
    seed : int
        Generator seed; the same seed and params give bitwise identical
        arrays, different seeds give visibly different shapes.
    params : LiverShapeParams, optional
        Mean shape controls and their seeded spread; defaults if ``None``.

    Returns
    -------
    Surface
        Closed, manifold, outward-oriented triangle surface (mm) with
        ``meta`` = ``{"source": "procedural", "generator", "seed", "params",
        "units": "mm", "scale_to_mm": 1.0}``.

    Examples
    --------
    >>> s = procedural_liver(0)
    >>> 1.0e6 < s.volume_mm3 < 2.0e6
    True
    """
    p = params or LiverShapeParams()
    shape = _draw_shape(seed, p)
    h = p.voxel_mm
    lo, hi = _shape_bounds(shape, margin=3.0 * h + 3.0 * p.undulation_mm)
    for _ in range(4):
        lo, hi = np.floor(lo / h) * h, np.ceil(hi / h) * h
        axes = [np.arange(a, b + 0.5 * h, h, dtype=np.float64) for a, b in zip(lo, hi)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
        f = liver_implicit(grid, shape)
        shell = np.concatenate([f[[0, 1, -2, -1]].ravel(), f[:, [0, 1, -2, -1]].ravel(), f[:, :, [0, 1, -2, -1]].ravel()])
        if shell.min() > 0:
            break
        # the shape reaches the grid boundary (unusual parameters): enlarge
        centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        lo, hi = centre - 1.25 * half, centre + 1.25 * half
    # keep the grid boundary outside so the surface is closed
    f[[0, -1], :, :] = f[:, [0, -1], :] = f[:, :, [0, -1]] = np.abs(f).max() + 1.0
    vertices, faces = _extract_surface(f, lo, h, p.smoothing_iterations)
    lo_b, hi_b = vertices.min(axis=0), vertices.max(axis=0)
    vertices = vertices - 0.5 * (lo_b + hi_b)
    target_l = None
    if p.volume_range_l is not None:
        lo_v, hi_v = p.volume_range_l
        target_l = float(liver_rng(seed, "volume").uniform(lo_v, hi_v))
        volume_l = Surface(vertices, faces, {}).volume_mm3 / 1e6
        vertices = vertices * (target_l / volume_l) ** (1.0 / 3.0)
    meta = {
        "source": "procedural",
        "generator": GENERATOR_VERSION,
        "seed": int(seed),
        "params": asdict(p),
        "units": "mm",
        "scale_to_mm": 1.0,
        "frame": "RAS: +x patient right, +y anterior, +z superior",
        "volume_target_l": target_l,
    }
    return Surface(vertices, faces, meta)


def _extract_surface(
    f: np.ndarray, origin: np.ndarray, h: float, smoothing_iterations: int
) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes on ``f`` (level 0), largest component, Taubin smoothing."""
    import trimesh
    from skimage.measure import marching_cubes

    verts, faces, _, _ = marching_cubes(
        f.astype(np.float64), level=0.0, spacing=(h, h, h), gradient_direction="descent",
        allow_degenerate=False,
    )
    mesh = trimesh.Trimesh(verts + origin, faces.astype(np.int64), process=True)
    parts = mesh.split(only_watertight=False)
    if len(parts) > 1:
        mesh = max(parts, key=lambda m: abs(m.volume))
    if smoothing_iterations:
        trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=smoothing_iterations)
    if mesh.volume < 0:
        mesh.invert()
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def cube_phantom(edge_mm: float = 50.0, divisions: int = 4, centre_mm=(0.0, 0.0, 0.0)) -> Surface:
    """Axis-aligned cube surface, outward oriented, each face split in a grid.

    Parameters
    ----------
    edge_mm : float
        Edge length in mm.
    divisions : int
        Squares per cube edge on each face (each square = 2 triangles); the
        cube stays exact (volume ``edge_mm**3``) for any value.
    centre_mm : sequence of 3 float
        Cube centre in mm.

    Returns
    -------
    Surface
        Closed cube surface with ``meta["source"] == "cube_phantom"``.
    """
    if edge_mm <= 0 or divisions < 1:
        raise ValueError(f"cube_phantom: need edge_mm > 0 and divisions >= 1, got {edge_mm}, {divisions}")
    n = int(divisions)
    # unit cube [0,1]^3 surface built from six structured faces
    verts: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    t = np.linspace(0.0, 1.0, n + 1)
    uu, vv = np.meshgrid(t, t, indexing="ij")
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    quad = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], axis=-1).reshape(-1, 4)
    tri = np.concatenate([quad[:, [0, 1, 2]], quad[:, [0, 2, 3]]])
    offset = 0
    for axis in range(3):
        for side in (0.0, 1.0):
            a, b = [(axis + 1) % 3, (axis + 2) % 3]
            pts = np.zeros(((n + 1) ** 2, 3))
            pts[:, axis] = side
            pts[:, a] = uu.ravel()
            pts[:, b] = vv.ravel()
            # (u along a, v along b): e_a × e_b = +e_axis; flip on the low side
            f = tri if side == 1.0 else tri[:, ::-1]
            verts.append(pts)
            faces.append(f + offset)
            offset += len(pts)
    import trimesh

    mesh = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)
    mesh.merge_vertices()
    vertices = (np.asarray(mesh.vertices) - 0.5) * float(edge_mm) + np.asarray(centre_mm, dtype=float)
    meta = {
        "source": "cube_phantom",
        "generator": GENERATOR_VERSION,
        "feature_angle_deg": 45.0,  # keep the edges sharp when meshing
        "params": {"edge_mm": float(edge_mm), "divisions": n, "centre_mm": [float(c) for c in centre_mm]},
        "units": "mm",
        "scale_to_mm": 1.0,
    }
    return Surface(vertices, np.asarray(mesh.faces, dtype=np.int64), meta)
