"""Synthetic side-view wheel-in-soil frames with EXACT ground truth (conventions §1).

A :class:`Scene` holds every parameter of one frame: camera set-up (wheel centre and rim radius in
the image), wheel (colours, rim ring, hub, lightening holes, lugs), terrain (the soil surface
``y = surface_y_px(scene, x)``, image coordinates, y down), soil and wall appearance, lighting and
sensor. :func:`true_geometry` computes the paper's quantities from the TRUE surface and rim circle
with the conventions' definitions; :func:`render` draws the frame. Edges are anti-aliased by
supersampling (an 8x8 rotated grid in every pixel within 0.75 px of an edge, one sample
elsewhere), so pixel values are area coverages and the rendered edges lie on the analytic ones
to a few hundredths of a pixel (``tests/test_synth.py`` measures it from the pixels).

Everything is vectorised numpy (OpenCV for resizing, blur, pebbles and JPEG); one 640x480 frame
takes about 0.1 s on one core (``experiments/synth_speed.py``).
"""

from __future__ import annotations

import colorsys
import csv
import math
import pathlib
from dataclasses import dataclass, replace

import cv2
import numpy as np
from jaxtyping import Float, Int, UInt8
from numpy.typing import NDArray

from ..rig import Rig, save_rig

PRESETS: tuple[str, ...] = ("clean", "full", "shading", "dust", "cast", "lowlight")
TERRAINS: tuple[str, ...] = ("flat", "bulldozed", "raised", "hollow", "rough")
TRUTH_COLUMNS: tuple[str, ...] = (
    "image",
    "sinkage_mm",
    "theta1_deg",
    "theta2_deg",
    "terrain",
    "contact",
    "sinkage_px",
    "center_x_px",
    "center_y_px",
    "radius_px",
    "k",
    "b_px",
)

# Layer ids of the label image (their order is irrelevant: _labels resolves occlusion).
_BG, _FACE, _RIM, _LUG, _HUB, _HOLE, _SOIL = range(7)
_N_LAYERS = 7
_WHEEL_LAYERS = (_FACE, _RIM, _LUG, _HUB, _HOLE)
_BOUNDARY_STEP_PX = 0.05  # conventions: boundary sampled uniformly in x, step <= 0.05 px
# > half a pixel diagonal (0.707): a pixel whose centre is farther than this from every edge is
# entirely inside one layer, so one sample at its centre is exact.
_EDGE_MARGIN_PX = 0.75

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Scene:
    """All parameters of one synthetic frame. Pixels, image coordinates (x right, y down).

    Colours are linear RGB triples in [0, 1]. The soil surface is
    ``soil_level_px + tilt*dx - bump + rut + rough`` with ``dx = x - centre_x_px`` (see
    :func:`surface_y_px`); terrain parameters are in image terms, so ``replace(scene,
    travel="left")`` keeps the picture and swaps entry and exit (use :func:`mirrored` to mirror
    the picture as well).
    """

    width: int = 640
    height: int = 480
    centre_x_px: float = 320.0
    centre_y_px: float = 200.0
    radius_px: float = 150.0  # RIM radius r; lugs stick out beyond it
    wheel_radius_mm: float = 140.0  # physical rim radius R
    travel: str = "right"
    # --- terrain
    terrain: str = "flat"
    soil_level_px: float = 330.0  # surface y at the wheel-centre column before the features
    tilt: float = 0.0  # dy/dx of the base level
    bump_height_px: float = 0.0  # Gaussian raise (mound, pile; < 0 digs a hollow)
    bump_dx_px: float = 0.0
    bump_sigma_px: float = 40.0
    rut_depth_px: float = 0.0  # smooth step lowering the surface on the ``rut_side`` of rut_dx
    rut_dx_px: float = 0.0
    rut_width_px: float = 20.0
    rut_side: float = -1.0  # -1: lowered on the left (behind a wheel travelling right)
    rough: tuple[tuple[float, float, float], ...] = ()  # (amplitude_px, signed wavelength_px, rad)
    # --- wheel
    wheel_rgb: tuple[float, float, float] = (0.85, 0.62, 0.10)
    rim_rgb: tuple[float, float, float] = (0.70, 0.50, 0.08)
    rim_width_px: float = 10.0
    lug_rgb: tuple[float, float, float] = (0.78, 0.58, 0.12)
    n_lugs: int = 0
    lug_height_px: float = 0.0
    lug_width_px: float = 0.0
    phase_rad: float = 0.0  # wheel rotation (lugs and holes), image angle atan2(dy, dx)
    hub_radius_px: float = 20.0
    hub_rgb: tuple[float, float, float] = (0.45, 0.43, 0.40)
    n_holes: int = 0
    hole_radius_px: float = 0.0
    hole_ring_px: float = 0.0  # distance of the hole centres from O
    hole_rgb: tuple[float, float, float] = (0.09, 0.09, 0.10)
    # --- soil and wall
    soil_rgb: tuple[float, float, float] = (0.62, 0.52, 0.40)
    soil_rgb2: tuple[float, float, float] = (0.55, 0.47, 0.38)  # hue variation partner
    soil_texture: float = 0.12  # relative intensity noise amplitude
    pebbles: int = 0
    wall_rgb: tuple[float, float, float] = (0.55, 0.56, 0.58)
    wall_gradient: float = 0.15
    wall_texture: float = 0.02  # relative low-frequency mottling of the wall
    face_texture: float = 0.02  # relative low-frequency variation on the wheel face
    # --- lighting
    light_dir: tuple[float, float] = (-0.6, -0.8)  # unit vector towards the lamp
    shading: float = 0.2  # relative intensity change across one rim radius
    lamp_white: float = 0.0  # additive white (desaturating) glow on the lamp side of the face
    specular: tuple[tuple[float, float, float, float], ...] = ()  # (dx, dy, sigma, amp) from O
    shadow_factor: float = 1.0  # cast shadow on soil multiplies by this (1: no shadow)
    shadow_offset_px: tuple[float, float] = (0.0, 0.0)
    shadow_soft_px: float = 4.0
    dust: float = 0.0  # max blend of the wheel face towards the soil colour
    dust_top_frac: float = 0.3  # dust starts at centre_y + dust_top_frac * r
    cast_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)  # per-channel gains (colour cast)
    gain: float = 1.0  # exposure
    black_level: float = 0.0  # sensor pedestal added to every channel, 8-bit units (desaturates)
    # --- sensor
    noise_std: float = 0.0  # 8-bit units
    blur_sigma_px: float = 0.0
    jpeg_quality: int = 0  # 0: lossless (PNG)
    supersample: int = 8  # supersample x supersample samples in pixels within 1 px of an edge

    def __post_init__(self) -> None:
        _sign(self.travel)
        if self.width < 8 or self.height < 8:
            raise ValueError(f"Scene needs width, height >= 8 px, got {self.width}x{self.height}")
        if not self.radius_px > 0 or not self.wheel_radius_mm > 0:
            raise ValueError(
                f"Scene needs radius_px > 0 and wheel_radius_mm > 0, got {self.radius_px} and "
                f"{self.wheel_radius_mm}"
            )
        if self.supersample < 1:
            raise ValueError(f"Scene.supersample must be >= 1, got {self.supersample}")
        if not 0 <= self.jpeg_quality <= 100:
            raise ValueError(f"Scene.jpeg_quality must be 0 (PNG) to 100, got {self.jpeg_quality}")
        if self.n_lugs and not 0 < self.lug_width_px < math.pi * self.radius_px / self.n_lugs:
            # Labelling tests each point against its nearest lug only; that needs narrow lugs.
            raise ValueError(
                "Scene.lug_width_px must be > 0 and under half the lug pitch "
                f"(2 pi r / n_lugs / 2 = {math.pi * self.radius_px / self.n_lugs:.2f} px), "
                f"got {self.lug_width_px}"
            )


@dataclass
class Truth:
    """Exact ground truth of one frame (conventions §1). Angles in degrees, k/b/A/B wheel frame."""

    sinkage_mm: float
    theta1_deg: float
    theta2_deg: float
    sinkage_px: float
    center_x_px: float
    center_y_px: float
    radius_px: float
    k: float
    b_px: float
    a_px: tuple[float, float]
    b_end_px: tuple[float, float]
    contact: bool
    terrain: str


# ----------------------------------------------------------------------------- terrain and truth


def _sign(travel: str) -> float:
    if travel == "right":
        return 1.0
    if travel == "left":
        return -1.0
    raise ValueError(f"travel must be 'right' or 'left', got {travel!r}")


def surface_y_px(scene: Scene, x_px: Float[np.ndarray, "*n"]) -> Float[np.ndarray, "*n"]:
    """The exact soil surface: image y (px, down) at image x (px), any shape, float64."""
    dx = np.asarray(x_px, dtype=np.float64) - scene.centre_x_px
    y = scene.soil_level_px + scene.tilt * dx
    if scene.bump_height_px:
        y = y - scene.bump_height_px * np.exp(
            -0.5 * ((dx - scene.bump_dx_px) / scene.bump_sigma_px) ** 2
        )
    if scene.rut_depth_px:
        s = scene.rut_side * (dx - scene.rut_dx_px) / scene.rut_width_px
        y = y + scene.rut_depth_px * 0.5 * (1.0 + np.tanh(s))
    for amp, wavelength, phase in scene.rough:
        y = y + amp * np.sin(2.0 * np.pi * dx / wavelength + phase)
    return y


def _inside_excess(scene: Scene, x: F64) -> F64:
    """|P - O|^2 - r^2 for the surface point above x: negative where it lies inside the rim."""
    dy = surface_y_px(scene, x) - scene.centre_y_px
    dx = x - scene.centre_x_px
    return dx * dx + dy * dy - scene.radius_px**2


def _bisect(scene: Scene, lo: float, hi: float) -> float:
    """Root of _inside_excess between lo and hi (signs differ), to far below 1e-6 px."""
    f_lo = _inside_excess(scene, np.array(lo))
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        f_mid = _inside_excess(scene, np.array(mid))
        if (f_mid < 0) == (f_lo < 0):
            lo, f_lo = mid, f_mid
        else:
            hi = mid
        if hi - lo < 1e-10:
            break
    return 0.5 * (lo + hi)


def _coarse_inside(scene: Scene, step_px: float = 0.1) -> tuple[F64, NDArray[np.bool_]]:
    r = scene.radius_px
    n = math.ceil(2 * r / step_px) + 1
    xs = np.linspace(scene.centre_x_px - r, scene.centre_x_px + r, n)
    return xs, _inside_excess(scene, xs) < 0


def n_rim_crossings(scene: Scene) -> int:
    """How often the surface crosses the rim circle (2 for a normal contact, 0 for none)."""
    _, inside = _coarse_inside(scene)
    return int(np.count_nonzero(inside[1:] != inside[:-1]))


def boundary_points(scene: Scene) -> tuple[F64, F64]:
    """The true boundary: surface points inside the rim, uniform in x (step <= 0.05 px), image px.

    Its first and last points are the exact rim intersections. Empty arrays without contact.
    """
    xs, inside = _coarse_inside(scene)
    if not inside.any():
        return np.zeros(0), np.zeros(0)
    idx = np.flatnonzero(inside)
    x_lo = _bisect(scene, xs[idx[0] - 1], xs[idx[0]])
    x_hi = _bisect(scene, xs[idx[-1]], xs[idx[-1] + 1])
    n = max(3, math.ceil((x_hi - x_lo) / _BOUNDARY_STEP_PX) + 1)
    x = np.linspace(x_lo, x_hi, n)
    # Several pieces only happen for pathological custom surfaces; keep the inside ones then.
    keep = _inside_excess(scene, x) <= 1e-6 * scene.radius_px
    keep[[0, -1]] = True
    return x[keep], surface_y_px(scene, x[keep])


def true_geometry(scene: Scene) -> Truth:
    """Eqs. 1-3 on the TRUE surface (conventions §1): OLS of the dense boundary, exact A and B."""
    cx, cy, r = scene.centre_x_px, scene.centre_y_px, scene.radius_px
    x, y = boundary_points(scene)
    if x.size == 0:
        return Truth(
            0.0, 0.0, 0.0, 0.0, cx, cy, r, 0.0, 0.0, (0.0, 0.0), (0.0, 0.0), False, scene.terrain
        )
    s = _sign(scene.travel)
    u, v = s * (x - cx), y - cy
    # Centred OLS: algebraically Eq. 1's k and b (same form as _geometry.equivalent_line).
    um, vm = u.mean(), v.mean()
    du = u - um
    k = float(np.sum(du * (v - vm)) / np.sum(du * du))
    b = float(vm - k * um)
    z0 = r - abs(b) / math.sqrt(k * k + 1.0)
    ia, ib = (-1, 0) if s > 0 else (0, -1)  # entry end A has the largest u
    a = (float(u[ia]), float(v[ia]))
    be = (float(u[ib]), float(v[ib]))
    t1 = math.pi / 2 - math.atan(a[1] / a[0]) if a[0] != 0 else 0.0
    t2 = math.pi / 2 + math.atan(be[1] / be[0]) if be[0] != 0 else 0.0
    return Truth(
        sinkage_mm=z0 * scene.wheel_radius_mm / r,
        theta1_deg=math.degrees(t1),
        theta2_deg=math.degrees(t2),
        sinkage_px=z0,
        center_x_px=cx,
        center_y_px=cy,
        radius_px=r,
        k=k,
        b_px=b,
        a_px=a,
        b_end_px=be,
        contact=True,
        terrain=scene.terrain,
    )


def mirrored(scene: Scene) -> Scene:
    """The left-right mirror image of ``scene``, travelling the other way (same truth)."""
    lx, ly = scene.light_dir
    sx, sy = scene.shadow_offset_px
    return replace(
        scene,
        centre_x_px=scene.width - 1 - scene.centre_x_px,
        travel="left" if scene.travel == "right" else "right",
        tilt=-scene.tilt,
        bump_dx_px=-scene.bump_dx_px,
        rut_dx_px=-scene.rut_dx_px,
        rut_side=-scene.rut_side,
        rough=tuple((a, -w, p) for a, w, p in scene.rough),
        phase_rad=math.pi - scene.phase_rad,
        light_dir=(-lx, ly),
        specular=tuple((-dx, dy, sg, am) for dx, dy, sg, am in scene.specular),
        shadow_offset_px=(-sx, sy),
    )


# ----------------------------------------------------------------------------- labels and edges


def _hole_centres(scene: Scene) -> list[tuple[float, float]]:
    out = []
    for i in range(scene.n_holes):
        # Holes sit between the lugs' angles: offset by half a hole pitch from the phase.
        ang = scene.phase_rad + (i + 0.5) * 2 * math.pi / scene.n_holes
        out.append(
            (
                scene.centre_x_px + scene.hole_ring_px * math.cos(ang),
                scene.centre_y_px + scene.hole_ring_px * math.sin(ang),
            )
        )
    return out


def _lug_angle(scene: Scene, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Image angle (rad) of the lug nearest in angle to each point (O-relative px).

    Lugs are narrower than half their pitch, so a point can only be in (or within 1 px of) the
    lug nearest to it in angle; one lug per point keeps this O(points), not O(points * lugs).
    """
    pitch = 2 * math.pi / scene.n_lugs
    ang = np.arctan2(dy, dx)
    return scene.phase_rad + np.rint((ang - scene.phase_rad) / pitch) * pitch


def _lug_local(
    scene: Scene, dx: np.ndarray, dy: np.ndarray, phi: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Radial and tangential coordinates of points relative to the lug at angle ``phi`` (default:
    each point's nearest lug)."""
    if phi is None:
        phi = _lug_angle(scene, dx, dy)
    c, s = np.cos(phi), np.sin(phi)
    return dx * c + dy * s, -dx * s + dy * c


def _labels(
    scene: Scene,
    x: np.ndarray,
    y: np.ndarray,
    surf_y: np.ndarray,
    lug_phi: np.ndarray | None = None,
) -> np.ndarray:
    """Layer id (int8) at sample points.

    ``x``, ``y`` (image px), ``surf_y`` (the surface y above each x) and the optional ``lug_phi``
    (the lug each point is tested against, default its nearest) broadcast together, e.g. (1, W),
    (H, 1), (1, W) for the pixel-centre grid or (n, 1) + (1, s) for s samples in n pixels.
    """
    cx, cy, r = scene.centre_x_px, scene.centre_y_px, scene.radius_px
    dx, dy = x - cx, y - cy
    d2 = dx * dx + dy * dy
    dx, dy = np.broadcast_to(dx, d2.shape), np.broadcast_to(dy, d2.shape)
    lab = np.full(d2.shape, _BG, dtype=np.int8)
    inside = d2 < r * r
    lab[inside] = _FACE
    lab[inside & (d2 >= (r - scene.rim_width_px) ** 2)] = _RIM
    lab[d2 < scene.hub_radius_px**2] = _HUB
    if scene.n_holes:
        rh, ring = scene.hole_radius_px, scene.hole_ring_px
        near = np.nonzero((d2 > (ring - rh) ** 2) & (d2 < (ring + rh) ** 2))
        nx, ny = dx[near] + cx, dy[near] + cy
        for hx, hy in _hole_centres(scene):
            hit = (nx - hx) ** 2 + (ny - hy) ** 2 < rh * rh
            lab[tuple(i[hit] for i in near)] = _HOLE
    if scene.n_lugs:
        h, w2 = scene.lug_height_px, 0.5 * scene.lug_width_px
        band = np.nonzero(~inside & (d2 < (r + h) ** 2 + w2 * w2))
        phi = None if lug_phi is None else np.broadcast_to(lug_phi, d2.shape)[band]
        t, n = _lug_local(scene, dx[band], dy[band], phi)
        hit = (np.abs(n) <= w2) & (t <= r + h)
        lab[tuple(i[hit] for i in band)] = _LUG
    lab[np.broadcast_to(y > surf_y, d2.shape)] = _SOIL  # the soil is in front of the wheel
    return lab


def _edge_pixels(scene: Scene, surf: F64) -> tuple[Int[np.ndarray, " n"], Int[np.ndarray, " n"]]:
    """(rows, cols) of pixels whose centre is within _EDGE_MARGIN_PX of any analytic edge."""
    hgt, wid, m = scene.height, scene.width, _EDGE_MARGIN_PX
    cx, cy, r = scene.centre_x_px, scene.centre_y_px, scene.radius_px
    dxr = np.arange(wid, dtype=np.float32) - np.float32(cx)
    dyc = np.arange(hgt, dtype=np.float32)[:, None] - np.float32(cy)
    d = np.sqrt(dxr * dxr + dyc * dyc)
    near = np.abs(d - r) < m
    near |= np.abs(d - (r - scene.rim_width_px)) < m
    near |= np.abs(d - scene.hub_radius_px) < m
    rh = scene.hole_radius_px
    for hx, hy in _hole_centres(scene):
        y0, y1 = max(0, int(hy - rh - 2)), min(hgt, int(hy + rh + 3))
        x0, x1 = max(0, int(hx - rh - 2)), min(wid, int(hx + rh + 3))
        if y0 >= y1 or x0 >= x1:
            continue
        dh = np.hypot(np.arange(x0, x1) - hx, np.arange(y0, y1)[:, None] - hy)
        near[y0:y1, x0:x1] |= np.abs(dh - rh) < m
    if scene.n_lugs:
        h, w2 = scene.lug_height_px, 0.5 * scene.lug_width_px
        ii, jj = np.nonzero((d > r - m) & (d < math.hypot(r + h, w2) + m))
        t, n = _lug_local(scene, jj - cx, ii - cy)
        # Signed distance to the lug box t in [r - 3, r + h], |n| <= w/2 (inner end is hidden).
        q1 = np.abs(t - (r + 0.5 * (h - 3))) - 0.5 * (h + 3)
        q2 = np.abs(n) - w2
        sdf = np.hypot(np.maximum(q1, 0), np.maximum(q2, 0)) + np.minimum(np.maximum(q1, q2), 0)
        hit = np.abs(sdf) < m
        near[ii[hit], jj[hit]] = True
    # Surface: per column, the range of y the curve spans over the pixel's width, widened by m.
    xs = np.arange(wid, dtype=np.float64)
    off = np.array([-0.5, -0.25, 0.25, 0.5])
    ys = np.concatenate([surf[None, :], surface_y_px(scene, xs[None, :] + off[:, None])])
    lo, hi = ys.min(axis=0) - m, ys.max(axis=0) + m
    rows = np.arange(hgt, dtype=np.float64)[:, None]
    near |= (rows > lo[None, :]) & (rows < hi[None, :])
    ii, jj = np.nonzero(near)
    return ii, jj


def _sample_offsets(n: int) -> tuple[F64, F64]:
    """n*n sample offsets in (-0.5, 0.5): an n x n grid rotated by atan(1/n).

    Every sub-cell, sub-row and sub-column holds one sample, so axis-aligned edges are resolved
    to 1/n^2 px (a plain grid: 1/n px), and the projections on both diagonals are distinct too
    (a sheared grid would stack them, resolving 45-degree edges to only 2n - 1 levels).
    """
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    ox = (i * n + j + 0.5) / (n * n) - 0.5
    oy = (j * n + (n - 1 - i) + 0.5) / (n * n) - 0.5
    return ox.ravel().astype(np.float64), oy.ravel().astype(np.float64)


def coverage(scene: Scene) -> Float[np.ndarray, "H W 7"]:
    """Per-pixel area fraction of each layer (bg, face, rim, lug, hub, hole, soil). For tests."""
    lab, rows, cols, frac = _coverage_parts(scene)
    out = np.eye(_N_LAYERS, dtype=np.float32)[lab]
    out[rows, cols] = frac
    return out


def _coverage_parts(
    scene: Scene,
) -> tuple[
    Int[np.ndarray, "H W"], Int[np.ndarray, " n"], Int[np.ndarray, " n"], Float[np.ndarray, "n 7"]
]:
    """Label at pixel centres (H, W) and layer fractions (n, 7) of the n edge pixels."""
    hgt, wid = scene.height, scene.width
    surf = surface_y_px(scene, np.arange(wid, dtype=np.float64))
    # Pixel centres in float32: only pixels >= 1 px from every edge keep this label.
    xg = np.arange(wid, dtype=np.float32)[None, :]
    yg = np.arange(hgt, dtype=np.float32)[:, None]
    lab = _labels(scene, xg, yg, surf.astype(np.float32)[None, :])
    rows, cols = _edge_pixels(scene, surf)
    ox, oy = _sample_offsets(scene.supersample)
    # The surface depends on x only: tabulate it per (column, x offset), W * n^2 evaluations
    # instead of one per sample.
    table = surface_y_px(scene, np.arange(wid, dtype=np.float64)[:, None] + ox[None, :])
    xs = cols[:, None] + ox[None, :]
    ys = rows[:, None] + oy[None, :]
    # A pixel within 1 px of a lug tests all its samples against that lug (gaps are >> 2 px).
    lug_phi = None
    if scene.n_lugs:
        lug_phi = _lug_angle(scene, cols - scene.centre_x_px, rows - scene.centre_y_px)[:, None]
    sub = _labels(scene, xs, ys, table[cols], lug_phi)
    counts = np.bincount(
        (np.arange(rows.size)[:, None] * _N_LAYERS + sub).ravel(), minlength=rows.size * _N_LAYERS
    )
    frac = counts.reshape(rows.size, _N_LAYERS).astype(np.float32) / np.float32(ox.size)
    return lab, rows, cols, frac


# ----------------------------------------------------------------------------- appearance


def _smooth_noise(
    rng: np.random.Generator, hgt: int, wid: int, cell_px: float
) -> NDArray[np.float32]:
    """Zero-mean, roughly unit-std noise smooth over ``cell_px``, (hgt, wid) float32."""
    gh, gw = max(2, round(hgt / cell_px) + 1), max(2, round(wid / cell_px) + 1)
    small = rng.standard_normal((gh, gw)).astype(np.float32)
    return np.asarray(cv2.resize(small, (wid, hgt), interpolation=cv2.INTER_CUBIC), np.float32)


def _layer_tables(
    scene: Scene,
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """Per-layer albedo (7, 3), specular weight (7,) and wheel membership (7,)."""
    alb = np.zeros((_N_LAYERS, 3), dtype=np.float32)
    alb[_FACE], alb[_RIM], alb[_LUG] = scene.wheel_rgb, scene.rim_rgb, scene.lug_rgb
    alb[_HUB], alb[_HOLE] = scene.hub_rgb, scene.hole_rgb
    spec = np.array([0, 1, 1, 0.8, 0.7, 0.05, 0], dtype=np.float32)
    wheel = np.zeros(_N_LAYERS, dtype=np.float32)
    wheel[list(_WHEEL_LAYERS)] = 1
    return alb, spec, wheel


def _soil_image(
    scene: Scene, rng: np.random.Generator, dyc: NDArray[np.float32], dxr: NDArray[np.float32]
) -> NDArray[np.float32]:
    """Textured soil colour on rows ``dyc`` (n, 1) x columns ``dxr`` (1, W), O-relative px: two-tone
    hue field, multi-scale intensity noise, lamp gradient, pebbles and the wheel's cast shadow."""
    hgt, wid = dyc.shape[0], dxr.shape[1]
    t = np.clip(0.5 + 0.35 * _smooth_noise(rng, hgt, wid, 90), 0, 1)[..., None]
    c1, c2 = np.asarray(scene.soil_rgb, np.float32), np.asarray(scene.soil_rgb2, np.float32)
    soil = c1 + t * (c2 - c1)
    tex = 0.5 * _smooth_noise(rng, hgt, wid, 40) + 0.35 * _smooth_noise(rng, hgt, wid, 10)
    tex += 0.3 * _smooth_noise(rng, hgt, wid, 2.5)
    lx, ly = scene.light_dir
    lit = 1 + 0.5 * scene.shading * (dxr * lx + dyc * ly) / scene.radius_px
    soil *= (lit * (1 + scene.soil_texture * tex))[..., None]
    if scene.pebbles:
        # Pebbles: a darker ellipse offset away from the lamp (the pebble's shadow), then the stone.
        n = round(scene.pebbles * hgt / scene.height)
        px, py = rng.uniform(0, wid, n), rng.uniform(0, hgt, n)
        ax = rng.uniform(0.8, 4.0, n)
        ay = ax * rng.uniform(0.5, 0.9, n)
        tone = rng.uniform(0.7, 1.4, n)
        ang = rng.uniform(0, 180, n)
        for i in range(n):
            c = (round(px[i]), round(py[i]))
            axes = (max(1, round(ax[i])), max(1, round(ay[i])))
            base = soil[min(hgt - 1, c[1]), min(wid - 1, c[0])]
            shadow_c = (round(px[i] - lx * 1.2), round(py[i] - ly * 1.2))
            cv2.ellipse(soil, shadow_c, axes, ang[i], 0, 360, (base * 0.7).tolist(), -1)
            cv2.ellipse(soil, c, axes, ang[i], 0, 360, (base * tone[i]).tolist(), -1)
    if scene.shadow_factor < 1:
        sx, sy = scene.shadow_offset_px
        ds = np.sqrt((dxr - sx) ** 2 + (dyc - sy) ** 2)
        reach = scene.radius_px + 0.6 * scene.lug_height_px
        mask = np.clip((reach - ds) / max(scene.shadow_soft_px, 1e-3) + 0.5, 0, 1)
        # Skylight fills the shadow: it darkens red most and blue least (a slight blue shift).
        dark = (1 - scene.shadow_factor) * mask[..., None]
        soil *= 1 - dark * np.array([1.0, 0.96, 0.8], np.float32)
    return soil


def _wheel_image(
    scene: Scene,
    rng: np.random.Generator,
    lab: NDArray[np.int8],
    edges: tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float32]],
    dyc: NDArray[np.float32],
    dxr: NDArray[np.float32],
) -> NDArray[np.float32]:
    """Coverage-weighted wheel colour (all wheel layers) on a window: albedo x shading + white
    (lamp glow, highlights), blended towards dust. ``lab`` and ``edges`` are window-relative."""
    hgt, wid = lab.shape
    r = scene.radius_px
    rows, cols, frac = edges
    alb_t, spec_t, wheel_t = _layer_tables(scene)
    alb, spec_w = alb_t[lab], spec_t[lab]
    alb[rows, cols] = frac @ alb_t
    spec_w[rows, cols] = frac @ spec_t
    lx, ly = scene.light_dir
    shade = np.maximum(1 + scene.shading * (dxr * lx + dyc * ly) / r, 0.12)
    shade = shade * (1 + scene.face_texture * _smooth_noise(rng, hgt, wid, 60))
    white = np.zeros((hgt, wid), dtype=np.float32)
    if scene.lamp_white:
        px, py, sg = 0.75 * r * lx, 0.75 * r * ly, 0.5 * r
        white += scene.lamp_white * np.exp(-((dxr - px) ** 2 + (dyc - py) ** 2) / (2 * sg * sg))
    for sdx, sdy, sg, amp in scene.specular:
        white += amp * np.exp(-((dxr - sdx) ** 2 + (dyc - sdy) ** 2) / (2 * sg * sg))
    wheel = alb * shade[..., None] + (spec_w * white)[..., None]
    if scene.dust:
        wheel_w = wheel_t[lab]
        wheel_w[rows, cols] = frac @ wheel_t
        ramp = np.clip((dyc - scene.dust_top_frac * r) / ((1 - scene.dust_top_frac) * r), 0, 1)
        patch = np.clip(1 + 0.35 * _smooth_noise(rng, hgt, wid, 25), 0, 1.5)
        dust = np.clip(scene.dust * ramp * patch, 0, 1)
        dust_rgb = np.asarray(scene.soil_rgb, np.float32) * 1.05
        # Linear in the layer fractions, so anti-aliased edges keep their 50 % crossing.
        wheel = wheel * (1 - dust)[..., None] + (wheel_w * dust * shade)[..., None] * dust_rgb
    return wheel


def _compose(scene: Scene, rng: np.random.Generator) -> NDArray[np.float32]:
    """Noise-free linear RGB image (H, W, 3) in about [0, 1].

    Each layer's colour is only computed where it can appear: the wall above the lowest surface
    point, the soil below the highest, the wheel in its bounding box.
    """
    hgt, wid = scene.height, scene.width
    cx, cy, r = scene.centre_x_px, scene.centre_y_px, scene.radius_px
    lab, rows, cols, frac = _coverage_parts(scene)
    bg_w = (lab == _BG).astype(np.float32)
    soil_w = (lab == _SOIL).astype(np.float32)
    bg_w[rows, cols] = frac[:, _BG]
    soil_w[rows, cols] = frac[:, _SOIL]
    surf = surface_y_px(scene, np.arange(wid, dtype=np.float64))
    dxr = np.arange(wid, dtype=np.float32)[None, :] - np.float32(cx)
    dyc = np.arange(hgt, dtype=np.float32)[:, None] - np.float32(cy)
    img = np.zeros((hgt, wid, 3), dtype=np.float32)

    y_wall = int(np.clip(math.ceil(surf.max()) + 2, 1, hgt))
    lx = scene.light_dir[0]
    shade = 1 - scene.wall_gradient * ((dyc[:y_wall] + cy) / hgt + 0.3 * dxr * lx / wid)
    shade = shade + scene.wall_texture * _smooth_noise(rng, y_wall, wid, 30)
    img[:y_wall] = (bg_w[:y_wall] * shade)[..., None] * np.asarray(scene.wall_rgb, np.float32)

    y_soil = int(np.clip(math.floor(surf.min()) - 2, 0, hgt - 1))
    soil = _soil_image(scene, rng, dyc[y_soil:], dxr)
    img[y_soil:] += soil_w[y_soil:, :, None] * soil

    reach = r + scene.lug_height_px + 0.5 * scene.lug_width_px + 3
    y0, y1 = max(0, math.floor(cy - reach)), min(hgt, math.ceil(cy + reach) + 1)
    x0, x1 = max(0, math.floor(cx - reach)), min(wid, math.ceil(cx + reach) + 1)
    if y0 < y1 and x0 < x1:
        sel = (rows >= y0) & (rows < y1) & (cols >= x0) & (cols < x1)
        edges = (rows[sel] - y0, cols[sel] - x0, frac[sel])
        img[y0:y1, x0:x1] += _wheel_image(
            scene, rng, lab[y0:y1, x0:x1], edges, dyc[y0:y1], dxr[:, x0:x1]
        )
    return img * (scene.gain * np.asarray(scene.cast_rgb, np.float32))


def _render(
    scene: Scene, seed: int, *, encode: bool
) -> tuple[UInt8[np.ndarray, "H W 3"], Truth, bytes | None]:
    rng = np.random.default_rng(seed)
    img = _compose(scene, rng) * np.float32(255)
    if scene.black_level:
        img += np.float32(scene.black_level)
    if scene.blur_sigma_px > 0.05:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), scene.blur_sigma_px), np.float32)
    if scene.noise_std > 0:
        img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(scene.noise_std)
    # Round half up: +0.5 then truncate (one pass fewer than rint, same result after clipping).
    img += np.float32(0.5)
    out = np.clip(img, 0, 255, out=img).astype(np.uint8)
    data = None
    if scene.jpeg_quality:
        ok, buf = cv2.imencode(
            ".jpg", out[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(scene.jpeg_quality)]
        )
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        data = buf.tobytes()
        decoded = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        if decoded is None:
            raise RuntimeError("JPEG decoding failed")
        out = np.ascontiguousarray(decoded[..., ::-1], dtype=np.uint8)
    elif encode:
        ok, buf = cv2.imencode(".png", out[..., ::-1])
        if not ok:
            raise RuntimeError("PNG encoding failed")
        data = buf.tobytes()
    return out, true_geometry(scene), data


def render(scene: Scene, seed: int) -> tuple[UInt8[np.ndarray, "H W 3"], Truth]:
    """Render one frame: uint8 RGB (height, width, 3) and its exact :class:`Truth`.

    ``seed`` drives the soil texture, pebbles and sensor noise; the same (scene, seed) gives the
    same bytes. With ``scene.jpeg_quality`` > 0 the image is the decoded JPEG.
    """
    img, truth, _ = _render(scene, seed, encode=False)
    return img, truth


# ----------------------------------------------------------------------------- random scenes

# Hue ranges (degrees) of the wheel paints; red straddles 0/360 on purpose (hue wrap-around).
_WHEEL_HUES = {
    "gold": (44, 56),
    "orange": (20, 32),
    "red": (-8, 8),
    "blue": (205, 230),
    "green": (100, 140),
}
# Soils: (hue range, saturation range, value range); all less saturated than any wheel paint.
_SOILS = {
    "sand": ((33, 43), (0.25, 0.40), (0.55, 0.75)),
    "brown": ((22, 32), (0.32, 0.48), (0.35, 0.50)),
    "grey-orange": ((16, 26), (0.15, 0.25), (0.50, 0.65)),
    "reddish-grey": ((2, 14), (0.18, 0.30), (0.45, 0.60)),
}
_MIN_HUE_GAP_DEG = 12.0


def _hsv(h_deg: float, s: float, v: float) -> tuple[float, float, float]:
    r, g, b = colorsys.hsv_to_rgb(
        (h_deg % 360.0) / 360.0, min(max(s, 0.0), 1.0), min(max(v, 0.0), 1.0)
    )
    return (r, g, b)


def _hue_gap(a: float, b: float) -> float:
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)


def _camera_setup(rng: np.random.Generator, width: int, height: int, preset: str) -> Scene:
    """One camera set-up: wheel placement and paint, soil and wall colours, lamp, sensor."""
    if preset not in PRESETS:
        raise ValueError(f"preset must be one of {PRESETS}, got {preset!r}")
    if width < 64 or height < 64:
        raise ValueError(f"image must be at least 64x64 px, got {width}x{height}")
    u = rng.uniform
    m = min(width, height)
    clean = preset == "clean"
    n_lugs = 0 if clean else int(rng.integers(0, 31))
    soil_below = max(0.1 * height, 24.0)
    r = u(0.27, 0.4) * m
    lug_h = u(0.03, 0.1) * r if n_lugs else 0.0
    # Shrink until the wheel with lugs fits with a margin above and soil visible below.
    while 2 * r + lug_h + 4 + soil_below > height or 2 * (r + lug_h + 4) > width:
        r *= 0.95
        lug_h *= 0.95
    lug_w = 0.0
    if n_lugs:
        pitch = 2 * math.pi * r / n_lugs
        lug_w = min(u(0.15, 0.35) * pitch, 0.12 * r)
        lug_w = max(lug_w, min(2.0, 0.4 * pitch))
    cy = u(r + lug_h + 4, height - r - soil_below)
    x_lo, x_hi = r + lug_h + 4, width - r - lug_h - 4
    cx = float(np.clip(width / 2 + u(-0.12, 0.12) * width, x_lo, x_hi))

    paint = list(_WHEEL_HUES)[int(rng.integers(len(_WHEEL_HUES)))]
    hue = u(*_WHEEL_HUES[paint]) % 360.0
    sat, val = u(0.65, 0.95), u(0.6, 0.9)
    wheel = _hsv(hue, sat, val)
    rim = _hsv(hue, sat * u(0.95, 1.05), val * u(0.75, 0.85))
    lug = _hsv(hue + u(-3, 3), sat * u(0.85, 1.0), val * u(0.85, 0.95))
    hub = _hsv(hue, sat * u(0.1, 0.35), val * u(0.5, 0.75))
    hole = _hsv(u(0, 360), u(0.03, 0.15), u(0.06, 0.2))
    for _ in range(100):
        kind = list(_SOILS)[int(rng.integers(len(_SOILS)))]
        (h0, h1), (s0, s1), (v0, v1) = _SOILS[kind]
        soil_hue = u(h0, h1)
        if _hue_gap(soil_hue, hue) >= _MIN_HUE_GAP_DEG:
            break
    soil_s, soil_v = u(s0, s1), u(v0, v1)
    soil = _hsv(soil_hue, soil_s, soil_v)
    soil2 = _hsv(soil_hue + u(-6, 6), soil_s * u(0.8, 1.15), soil_v * u(0.85, 1.05))
    wall = _hsv(u(0, 360), u(0.02, 0.1), u(0.35, 0.8))

    rim_w = max(3.0, u(0.05, 0.09) * r)
    hub_r = u(0.1, 0.16) * r
    n_holes = int(rng.integers(0, 9))
    hole_r = hole_ring = 0.0
    if n_holes:
        # Holes in a ring leaving a clear band above the hub for the confidence rectangle.
        hole_r = u(0.07, 0.12) * r
        lo, hi = hub_r + 0.26 * r + hole_r, r - rim_w - 0.05 * r - hole_r
        hole_ring = u(lo, max(lo, hi))
        if n_holes > 1:
            hole_r = min(hole_r, hole_ring * math.sin(math.pi / n_holes) - 3)
        if hole_r < 2:
            n_holes, hole_r, hole_ring = 0, 0.0, 0.0

    ang = math.radians(u(200, 340))  # the lamp is above the wheel, left or right
    light = (math.cos(ang), math.sin(ang))
    shading = u(0.1, 0.25) if clean else u(0.1, 0.35)
    lamp_white = 0.0
    specular: tuple[tuple[float, float, float, float], ...] = ()
    shadow_factor, shadow_off, soft = 1.0, (0.0, 0.0), 4.0
    if not clean:
        spec = []
        for _ in range(int(rng.integers(0, 5))):
            rr, aa = r * 0.8 * math.sqrt(u(0, 1)), u(0, 2 * math.pi)
            spec.append(
                (rr * math.cos(aa), rr * math.sin(aa), u(2.0, max(2.5, 0.06 * r)), u(0.25, 0.7))
            )
        specular = tuple(spec)
        if u(0, 1) < 0.8:
            off = u(0.1, 0.3) * r
            shadow_factor, shadow_off, soft = (
                u(0.35, 0.7),
                (-light[0] * off, -light[1] * off),
                u(2, 8),
            )
    noise = u(0.5, 1.5) if clean else u(1.0, 4.0)
    blur = u(0.3, 0.6) if clean else u(0.0, 1.0)
    jpeg = 0 if clean else int(rng.integers(70, 96))
    dust, dust_top, cast, gain, black = 0.0, 0.3, (1.0, 1.0, 1.0), 1.0, 0.0
    if preset == "shading":
        shading, lamp_white = u(0.5, 0.8), u(0.35, 0.7)
    elif preset == "dust":
        dust, dust_top = u(0.6, 0.9), u(0.0, 0.35)
    elif preset == "cast":
        c = np.asarray(_hsv(u(0, 360), 1.0, 1.0))
        cast = tuple(float(g) for g in 1 + u(0.2, 0.4) * (2 * c - 1 - (2 * c - 1).mean()))  # type: ignore[assignment]
    elif preset == "lowlight":
        gain, noise, black = u(0.1, 0.25), u(4.0, 10.0), u(6.0, 16.0)
    return Scene(
        width=width,
        height=height,
        centre_x_px=cx,
        centre_y_px=cy,
        radius_px=r,
        wheel_rgb=wheel,
        rim_rgb=rim,
        rim_width_px=rim_w,
        lug_rgb=lug,
        n_lugs=n_lugs,
        lug_height_px=lug_h,
        lug_width_px=lug_w,
        hub_radius_px=hub_r,
        hub_rgb=hub,
        n_holes=n_holes,
        hole_radius_px=hole_r,
        hole_ring_px=hole_ring,
        hole_rgb=hole,
        soil_rgb=soil,
        soil_rgb2=soil2,
        soil_texture=u(0.08, 0.2),
        pebbles=int(u(50, 250) * width * height / (640 * 480)),
        wall_rgb=wall,
        wall_gradient=u(0.05, 0.3),
        face_texture=u(0.01, 0.04),
        light_dir=light,
        shading=shading,
        lamp_white=lamp_white,
        specular=specular,
        shadow_factor=shadow_factor,
        shadow_offset_px=shadow_off,
        shadow_soft_px=soft,
        dust=dust,
        dust_top_frac=dust_top,
        cast_rgb=cast,
        gain=gain,
        black_level=black,
        noise_std=noise,
        blur_sigma_px=blur,
        jpeg_quality=jpeg,
    )


def _sample_sinkage_mm(rng: np.random.Generator) -> float:
    """About 12 % of contact frames below 5 mm, the rest spread over 5-50 mm (R = 140 mm)."""
    return rng.uniform(0.5, 5.0) if rng.random() < 0.12 else rng.uniform(5.0, 50.0)


def _terrain_features(
    rng: np.random.Generator, kind: str, r: float, z0: float
) -> dict[str, object]:
    """Terrain parameters for a wheel travelling right (entry at +dx), heights in px."""
    u = rng.uniform
    half = math.sqrt(max(2 * r * z0 - z0 * z0, 1.0))  # half chord of the flat-ground contact
    if kind == "flat":
        return {}
    if kind == "bulldozed":
        return {
            "bump_height_px": u(0.03, 0.1) * r,
            "bump_dx_px": half + u(0.0, 0.3) * r,
            "bump_sigma_px": u(0.12, 0.25) * r,
            "rut_depth_px": u(0.3, 0.8) * z0,
            "rut_dx_px": -half * u(0.6, 1.1),
            "rut_width_px": u(0.05, 0.15) * r,
            "rut_side": -1.0,
        }
    if kind in ("raised", "hollow"):
        sign = 1.0 if kind == "raised" else -1.0
        return {
            "bump_height_px": sign * u(0.03, 0.12) * r,
            "bump_dx_px": u(-0.5, 0.5) * r,
            "bump_sigma_px": u(0.3, 0.8) * r,
        }
    if kind == "rough":
        n = int(rng.integers(3, 6))
        amps = u(0.3, 1.0, n) / np.arange(1, n + 1)
        amps *= u(0.015, 0.04) * r / amps.sum()
        return {
            "tilt": u(-0.05, 0.05),
            "rough": tuple(
                (float(a), float(u(0.25, 1.5) * r * rng.choice([-1, 1])), float(u(0, 2 * math.pi)))
                for a in amps
            ),
        }
    raise ValueError(f"terrain must be one of {TERRAINS}, got {kind!r}")


def _ok_contact(scene: Scene) -> bool:
    """A usable contact frame: two rim crossings, A and B on either side of the lowest point, soil
    below the hub (the confidence rectangle is above it) and above the image's bottom."""
    if n_rim_crossings(scene) != 2:
        return False
    t = true_geometry(scene)
    _, y = boundary_points(scene)
    surf = surface_y_px(scene, np.arange(scene.width, dtype=np.float64))
    # Eqs. 2-3 assume x_A > 0 > x_B: a contact patch entirely on one side of the lowest point
    # would give an exit angle near 180 deg that jumps to 0 as x_B crosses 0.
    straddles = t.a_px[0] > 0.02 * scene.radius_px and t.b_end_px[0] < -0.02 * scene.radius_px
    return bool(
        straddles
        and y.min() > scene.centre_y_px + 0.12 * scene.radius_px
        and surf.max() < scene.height - 3
    )


def _with_terrain(rng: np.random.Generator, base: Scene, kind: str, contact: bool) -> Scene:
    """``base`` with a sampled terrain of ``kind``, sinkage and wheel phase (travel right)."""
    r, cy = base.radius_px, base.centre_y_px
    scene = base
    for attempt in range(30):
        z0 = _sample_sinkage_mm(rng) * r / base.wheel_radius_mm
        feats = _terrain_features(rng, kind, r, z0) if attempt < 25 else {}
        scene = replace(
            base,
            terrain=kind,
            phase_rad=float(rng.uniform(0, 2 * math.pi)),
            soil_level_px=cy + r - z0,
            **feats,  # type: ignore[arg-type]
        )
        if not contact:
            # Lower the whole surface until it clears the rim by a few pixels.
            xs = np.linspace(base.centre_x_px - r, base.centre_x_px + r, 801)
            rim_bottom = cy + np.sqrt(np.maximum(r * r - (xs - base.centre_x_px) ** 2, 0))
            clearance = float(np.min(surface_y_px(scene, xs) - rim_bottom))
            scene = replace(
                scene, soil_level_px=scene.soil_level_px - clearance + rng.uniform(1.5, 15)
            )
            surf = surface_y_px(scene, np.arange(scene.width, dtype=np.float64))
            if n_rim_crossings(scene) == 0 and surf.max() < scene.height - 3:
                return scene
            continue
        # Newton-like steps on the level: lowering the surface by d lowers z0 by about d.
        for _ in range(6):
            t = true_geometry(scene)
            step = t.sinkage_px - z0 if t.contact else -max(1.0, z0)
            scene = replace(scene, soil_level_px=scene.soil_level_px + step)
            if abs(step) < 1e-3:
                break
        if _ok_contact(scene):
            return scene
    raise RuntimeError(
        "could not sample a valid terrain; the wheel leaves too little room for soil"
    )


def random_scene(
    rng: np.random.Generator,
    *,
    width: int = 640,
    height: int = 480,
    preset: str = "full",
    travel: str = "right",
) -> Scene:
    """One random frame: its own camera set-up, terrain kind, sinkage (~3 % no contact), phase."""
    base = _camera_setup(rng, width, height, preset)
    kind = TERRAINS[int(rng.integers(len(TERRAINS)))]
    scene = _with_terrain(rng, base, kind, contact=rng.random() >= 0.03)
    return mirrored(scene) if _sign(travel) < 0 else scene


def recording_scenes(
    rng: np.random.Generator,
    n_frames: int,
    *,
    preset: str = "full",
    width: int = 640,
    height: int = 480,
    travel: str = "right",
) -> list[Scene]:
    """Frames of ONE camera set-up (same wheel, centre, radius, colours, lamp, sensor).

    Terrain kinds cycle flat, bulldozed, raised, hollow, rough; sinkage, terrain details and the
    wheel phase vary per frame; about 3 % of frames have no contact.
    """
    s = _sign(travel)
    base = _camera_setup(rng, width, height, preset)
    scenes = []
    for i in range(n_frames):
        scene = _with_terrain(rng, base, TERRAINS[i % len(TERRAINS)], contact=rng.random() >= 0.03)
        scenes.append(mirrored(scene) if s < 0 else scene)
    return scenes


def rig_for(scene: Scene) -> Rig:
    """A rig for ``scene``'s camera set-up: R, travel and a confidence rectangle on the face.

    The rectangle lies above the hub, inside the band between the hub and the lightening-hole ring
    (or the rim ring without holes), so no wheel phase puts a hole, lug, hub or rim in it, and the
    soil (always below the hub) never covers it. It covers up to ~3 % of the rim disc.
    """
    cx, cy, r = scene.centre_x_px, scene.centre_y_px, scene.radius_px
    # Clearance from every other edge: blur, JPEG ringing and the pixels' own extent.
    gap = 1.5 + 0.015 * r
    inner = scene.hub_radius_px + gap
    if scene.n_holes:
        outer = scene.hole_ring_px - scene.hole_radius_px - gap
    else:
        outer = r - scene.rim_width_px - gap
    target = 0.03 * math.pi * r * r
    best = (0.0, 1.0, 1.0)
    for hgt in np.linspace(2, max(2.0, outer - inner), 64):
        top = inner + hgt
        if top >= outer:
            continue
        wid = 2 * math.sqrt(outer * outer - top * top)
        area = wid * hgt
        if area > best[0]:
            best = (area, float(wid), float(hgt))
    area, wid, hgt = best
    if area > target:  # keep the aspect, shrink to the target area
        f = math.sqrt(target / area)
        wid, hgt = wid * f, hgt * f
    # Integer pixel rectangle strictly within the continuous one (pixel j spans j-0.5..j+0.5).
    x0 = math.ceil(cx - wid / 2 + 0.5)
    x1 = math.floor(cx + wid / 2 - 0.5)
    y1 = math.floor(cy - inner - 0.5)
    y0 = math.ceil(cy - inner - hgt + 0.5)
    w, h = max(1, x1 - x0 + 1), max(1, y1 - y0 + 1)
    return Rig(
        wheel_radius_mm=float(scene.wheel_radius_mm),
        confidence_rect=(max(0, x0), max(0, y0), w, h),
        travel=scene.travel,
    )


def _fmt(v: float) -> str:
    return repr(round(float(v), 9))


def _frame_seed(seed: int, i: int) -> int:
    return int(np.random.SeedSequence([seed, i]).generate_state(1)[0])


def write_recording(
    out_dir: str | pathlib.Path,
    *,
    n_frames: int = 12,
    seed: int = 0,
    preset: str = "full",
    width: int = 640,
    height: int = 480,
    travel: str = "right",
    progress: bool = True,
) -> pathlib.Path:
    """Write a synthetic recording: frames, ``rig.toml`` and ``truth.csv``; returns the folder.

    Frames are ``frame_0000.png`` ... (``.jpg`` when the preset uses JPEG). ``truth.csv`` has the
    LABELS columns ``image,sinkage_mm,theta1_deg,theta2_deg`` then ``terrain,contact,sinkage_px,
    center_x_px,center_y_px,radius_px,k,b_px`` (no-contact frames: zeros, ``contact`` false).
    """
    from tqdm import tqdm

    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    scenes = recording_scenes(
        rng, n_frames, preset=preset, width=width, height=height, travel=travel
    )
    if scenes:
        save_rig(
            rig_for(scenes[0]),
            out / "rig.toml",
            comment=f"sinkjax synthetic recording: preset={preset} seed={seed} frames={n_frames}",
        )
    with (out / "truth.csv").open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(TRUTH_COLUMNS)
        for i, scene in enumerate(tqdm(scenes, desc="synth", unit="frame", disable=not progress)):
            _, t, data = _render(scene, _frame_seed(seed, i), encode=True)
            name = f"frame_{i:04d}.{'jpg' if scene.jpeg_quality else 'png'}"
            assert data is not None
            (out / name).write_bytes(data)
            writer.writerow(
                [
                    name,
                    _fmt(t.sinkage_mm),
                    _fmt(t.theta1_deg),
                    _fmt(t.theta2_deg),
                    t.terrain,
                    "true" if t.contact else "false",
                    _fmt(t.sinkage_px),
                    _fmt(t.center_x_px),
                    _fmt(t.center_y_px),
                    _fmt(t.radius_px),
                    _fmt(t.k),
                    _fmt(t.b_px),
                ]
            )
            fh.flush()
    return out
