"""Which layer (wall, wheel face, rim, lug, hub, hole, soil) covers how much of each pixel.

Edges are anti-aliased by supersampling (an 8x8 rotated grid in every pixel within 0.75 px of an
edge, one sample elsewhere), so pixel values are area coverages and the rendered edges lie on the
analytic ones to a few hundredths of a pixel (``tests/test_synth.py`` measures it from the pixels).
"""

from __future__ import annotations

import math

import numpy as np
from jaxtyping import Float, Int

from .scene import F64, Scene, surface_y_px

# Layer ids of the label image (their order is irrelevant: _labels resolves occlusion).
BG, FACE, RIM, LUG, HUB, HOLE, SOIL = range(7)
N_LAYERS = 7
WHEEL_LAYERS = (FACE, RIM, LUG, HUB, HOLE)
# > half a pixel diagonal (0.707): a pixel whose centre is farther than this from every edge is
# entirely inside one layer, so one sample at its centre is exact.
_EDGE_MARGIN_PX = 0.75


def hole_centres(scene: Scene) -> list[tuple[float, float]]:
    """Image (x, y) px of the lightening-hole centres."""
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
    lab = np.full(d2.shape, BG, dtype=np.int8)
    inside = d2 < r * r
    lab[inside] = FACE
    lab[inside & (d2 >= (r - scene.rim_width_px) ** 2)] = RIM
    lab[d2 < scene.hub_radius_px**2] = HUB
    if scene.n_holes:
        rh, ring = scene.hole_radius_px, scene.hole_ring_px
        near = np.nonzero((d2 > (ring - rh) ** 2) & (d2 < (ring + rh) ** 2))
        nx, ny = dx[near] + cx, dy[near] + cy
        for hx, hy in hole_centres(scene):
            hit = (nx - hx) ** 2 + (ny - hy) ** 2 < rh * rh
            lab[tuple(i[hit] for i in near)] = HOLE
    if scene.n_lugs:
        h, w2 = scene.lug_height_px, 0.5 * scene.lug_width_px
        band = np.nonzero(~inside & (d2 < (r + h) ** 2 + w2 * w2))
        phi = None if lug_phi is None else np.broadcast_to(lug_phi, d2.shape)[band]
        t, n = _lug_local(scene, dx[band], dy[band], phi)
        hit = (np.abs(n) <= w2) & (t <= r + h)
        lab[tuple(i[hit] for i in band)] = LUG
    lab[np.broadcast_to(y > surf_y, d2.shape)] = SOIL  # the soil is in front of the wheel
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
    for hx, hy in hole_centres(scene):
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
    lab, rows, cols, frac = coverage_parts(scene)
    out = np.eye(N_LAYERS, dtype=np.float32)[lab]
    out[rows, cols] = frac
    return out


def coverage_parts(
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
        (np.arange(rows.size)[:, None] * N_LAYERS + sub).ravel(), minlength=rows.size * N_LAYERS
    )
    frac = counts.reshape(rows.size, N_LAYERS).astype(np.float32) / np.float32(ox.size)
    return lab, rows, cols, frac
