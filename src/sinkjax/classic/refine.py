"""Classic pipeline refinements beyond the paper (``estimate_classic(..., refine=True)``).

Each one removes a bias that the paper's pixel-level method has, without changing what is
measured:

- lightening holes that the soil cuts open are filled like the intact ones
  (:func:`fill_cut_holes`), so their outline is not taken for wheel-soil boundary;
- the outline is located to sub-pixel precision on the colour profile across it
  (:func:`subpixel_edges`; the binary image's thresholds alone would move a blurred edge by a
  pixel or more, differently on rim and soil), and the rim is refitted on those points
  (:func:`refit_rim`);
- boundary points are weighted by the x-extent they cover (:func:`x_extent_weights`), so the
  equivalent line is the same integral over x as the ground truth's;
- A and B, which "closer than r" leaves a hair inside the rim, are carried along the boundary's
  end direction onto the rim (:func:`end_on_rim`).

(The fifth, failing loudly when the outline dips inside the rim above O, is a check in
:func:`sinkjax.classic.estimator.estimate_classic`.)
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .outline import MIN_RIM_POINTS, fit_circle, mad_px, off_border, rim_points, wheel_outline
from .segmentation import fill_holes


def fill_cut_holes(
    rgb: np.ndarray, region: np.ndarray, cx: float, cy: float, r: float
) -> np.ndarray:
    """Fill the holes (see :func:`fill_holes`), and also the lightening holes the soil cuts open.

    A lightening hole that reaches below the soil surface is no longer enclosed by the wheel: it
    opens into the soil, and its outline would be taken for wheel-soil boundary. The intact holes
    of the same frame say where the others are and what they look like: lightening holes are
    alike (same radius, same distance from O, same colour) and evenly spaced in angle. Where that
    pattern puts a hole that is not intact, non-wheel pixels inside it with the holes' colour are
    hole, not soil. With a single intact hole, hole-coloured patches on its ring no bigger than
    it are taken instead. A hub cut by the soil is not recognised (nothing to learn it from).

    ``rgb``: (H, W, 3) uint8; ``region``: (H, W) bool wheel component (holes not filled);
    (cx, cy, r): rim circle, image px. Returns the filled wheel region, (H, W) bool.
    """
    filled = fill_holes(region)
    holes = (filled & ~region).astype(np.uint8)
    n, labels, stats, cents = cv2.connectedComponentsWithStats(holes, connectivity=8)
    core = cv2.erode(holes, np.ones((3, 3), np.uint8)).astype(bool)  # no mixed edge pixels
    found = []  # (ring radius, angle, hole radius, mean rgb, label)
    for k in range(1, n):
        area = int(stats[k, cv2.CC_STAT_AREA])
        sel = core & (labels == k)
        if area < 15 or np.count_nonzero(sel) < 5:
            continue
        dx, dy = cents[k, 0] - cx, cents[k, 1] - cy
        ring, rad = math.hypot(dx, dy), math.sqrt(area / math.pi)
        if ring > 2 * rad:  # the hub sits on O; it is not one of a ring of holes
            found.append(
                (ring, math.atan2(dy, dx), rad, rgb[sel].mean(axis=0, dtype=np.float64), k)
            )
    pattern = _hole_pattern(found)
    if pattern is not None:
        ring, rad, n_holes, phase, members = pattern
        centres = [
            (ring * math.cos(a), ring * math.sin(a))
            for a in phase + 2.0 * math.pi * np.arange(n_holes) / n_holes
        ]
    elif len(found) == 1:
        # One intact hole: where its partners are is unknown, only that they are on its ring.
        ring, _, rad, _, label = found[0]
        members, centres = [label], []
    else:
        return filled
    sel = np.isin(labels, members) & core
    pix = rgb[sel].astype(np.float64)
    mean = pix.mean(axis=0)
    # Noise and JPEG spread a hole's colour by a few DN (8-bit units); more would take soil too.
    tol = min(3.0 * float(np.sqrt(pix.var(axis=0).sum())) + 8.0, 40.0)
    hh, ww = region.shape
    add = np.zeros(region.shape, np.uint8)
    reach = rad + 1.5
    if not centres:
        # Hole-coloured pixels on the ring, in patches no bigger than a hole: soil that happens
        # to look like the hole (in a shadow) makes bigger patches and is left alone.
        yy, xx = np.mgrid[0:hh, 0:ww]
        on_ring = np.abs(np.hypot(xx - cx, yy - cy) - ring) <= reach
        match = on_ring & ~filled & (np.linalg.norm(rgb - mean, axis=2) <= tol)
        m, _, st2, c2 = cv2.connectedComponentsWithStats(match.astype(np.uint8), connectivity=8)
        for k in range(1, m):
            w_k, h_k = st2[k, cv2.CC_STAT_WIDTH], st2[k, cv2.CC_STAT_HEIGHT]
            if st2[k, cv2.CC_STAT_AREA] >= 5 and max(w_k, h_k) <= 2 * reach + 1:
                centres.append((c2[k, 0] - cx, c2[k, 1] - cy))
    for ox, oy in centres:
        hx, hy = cx + ox, cy + oy
        x0, x1 = max(0, int(hx - reach)), min(ww, int(hx + reach) + 2)
        y0, y1 = max(0, int(hy - reach)), min(hh, int(hy + reach) + 2)
        if x0 >= x1 or y0 >= y1:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        disc = np.hypot(xx - hx, yy - hy) <= reach
        cand = disc & ~filled[y0:y1, x0:x1]
        if np.count_nonzero(cand) < 5:  # intact (filled already) or off the wheel
            continue
        match = np.linalg.norm(rgb[y0:y1, x0:x1] - mean, axis=2) <= tol
        patch = (cand & match).astype(np.uint8)
        # Close the crack of mixed pixels (neither wheel- nor hole-coloured) on the hole's rim;
        # within the disc only, and closing leaves a straight soil line under the hole as it is.
        merged = patch | filled[y0:y1, x0:x1].astype(np.uint8)
        closed = cv2.morphologyEx(merged, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
        add[y0:y1, x0:x1] |= (closed.astype(bool) & disc & ~filled[y0:y1, x0:x1]).astype(np.uint8)
    if not add.any():
        return filled
    return fill_holes(filled | add.astype(bool))


def _hole_pattern(
    found: list[tuple[float, float, float, np.ndarray, int]],
) -> tuple[float, float, int, float, list[int]] | None:
    """The lightening-hole pattern among enclosed holes: (ring, radius, count, phase, labels).

    ``found``: (ring radius px, angle rad, radius px, mean RGB, label) per enclosed hole. The
    pattern is the largest group (at least two) alike in ring, radius and colour; its count is the
    smallest n for which every member sits on a multiple of 2 pi / n from the first. None if no
    such group exists.
    """
    best: list[tuple[float, float, float, np.ndarray, int]] = []
    for ref in found:
        group = [
            f
            for f in found
            if abs(f[0] - ref[0]) <= 3.0
            and abs(f[2] - ref[2]) <= 0.25 * ref[2] + 1.0
            and float(np.linalg.norm(f[3] - ref[3])) <= 30.0
        ]
        if len(group) > len(best):
            best = group
    if len(best) < 2:
        return None
    ring = float(np.mean([f[0] for f in best]))
    rad = float(np.mean([f[2] for f in best]))
    angles = np.array([f[1] for f in best])
    tol = max(rad * 0.3, 1.5) / ring  # radians: a fraction of a hole radius along the ring
    for n_holes in range(len(best), 25):
        pitch = 2.0 * math.pi / n_holes
        off = np.mod(angles - angles[0] + 0.5 * pitch, pitch) - 0.5 * pitch
        if np.max(np.abs(off)) <= tol:
            phase = float(angles[0] + np.mean(off))
            return ring, rad, n_holes, phase, [f[4] for f in best]
    return None


def refit_rim(
    pts: np.ndarray, normals: np.ndarray, cx: float, cy: float, r: float
) -> tuple[float, float, float, float]:
    """Least-squares rim circle through the (sub-pixel) edge points on it (:func:`rim_points`).

    Returns (cx, cy, r, sigma) in px; sigma is the robust (MAD) scatter of the rim points about
    the circle, which sets how far inside the rim a point must be to count as soil boundary.
    """
    sigma = 0.5
    for _ in range(3):
        sel, e = rim_points(pts, normals, cx, cy, r)
        if np.count_nonzero(sel) < MIN_RIM_POINTS:
            break
        sigma = mad_px(e[sel])
        cx, cy, r = fit_circle(pts[sel], cx, cy, r)
    return cx, cy, r, sigma


def refined_outline(
    rgb: np.ndarray, region: np.ndarray, cx: float, cy: float, r: float
) -> tuple[np.ndarray, np.ndarray, float, float, float, float]:
    """The refined outline and rim: cut-open holes filled, sub-pixel edges, rim refitted on them.

    ``rgb``: (H, W, 3) uint8; ``region``: (H, W) bool wheel component (holes not filled);
    (cx, cy, r): the rim from the pixel outline, image px. Returns (edge points (n, 2) image px
    in contour order, (n,) bool off the image border, cx, cy, r, rim scatter sigma), all px.
    """
    filled = fill_cut_holes(rgb, region, cx, cy, r)
    contour, normals = wheel_outline(filled)
    inner = off_border(contour, rgb.shape)
    # Contour pixels are centres of the region's border pixels, ~half a pixel inside the edge;
    # locate the edge itself on the colour profile across it, and refit the rim there.
    edge = subpixel_edges(rgb, contour, normals)
    cx, cy, r_edge, sigma = refit_rim(edge[inner], normals[inner], cx, cy, r + 0.5)
    return edge, inner, cx, cy, r_edge, sigma


def subpixel_edges(
    rgb: np.ndarray, pts: np.ndarray, normals: np.ndarray, half_px: float = 4.0
) -> np.ndarray:
    """Sub-pixel edge points: where the colour across the outline is half wheel, half outside.

    ``rgb``: (H, W, 3) uint8; ``pts``: (n, 2) outline pixel centres (x, y); ``normals``: (n, 2)
    inward unit normals. Samples the colour along each normal over +-``half_px``, projects it on
    the axis from the outside colour (far end) to the wheel colour (near end) and returns (n, 2)
    image px where that crosses one half: the edge as drawn, independent of where the H and S
    thresholds happen to cut a blurred or anti-aliased edge. Points without a clear single edge
    (low contrast, corners) fall back to half a pixel outside the border pixel's centre.
    """
    t = np.arange(-half_px, half_px + 1e-9, 0.5)
    q = pts[:, None, :] + t[None, :, None] * normals[:, None, :]
    prof = cv2.remap(
        rgb,
        q[..., 0].astype(np.float32),
        q[..., 1].astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    ).astype(np.float64)  # (n, m, 3)
    c_out = prof[:, :4].mean(axis=1)
    c_in = prof[:, -4:].mean(axis=1)
    d = c_in - c_out
    dd = np.sum(d * d, axis=1)
    f = np.einsum("nmc,nc->nm", prof - c_out[:, None, :], d) / np.maximum(dd, 1e-9)[:, None]
    up = (f[:, :-1] < 0.5) & (f[:, 1:] >= 0.5)
    # Of several crossings (texture, a nearby lug), take the one whose sample interval's middle
    # (t + 0.25) is nearest to where the border pixel puts the edge (t = -0.5).
    dist = np.where(up, np.abs(t[:-1] + 0.25 + 0.5), np.inf)
    j = np.argmin(dist, axis=1)
    rows = np.arange(len(pts))
    f0, f1 = f[rows, j], f[rows, j + 1]
    tc = t[j] + 0.5 * (0.5 - f0) / np.maximum(f1 - f0, 1e-9)
    good = np.isfinite(dist[rows, j]) & (dd >= 20.0**2) & (np.abs(tc + 0.5) <= 2.0)
    tc = np.where(good, tc, -0.5)
    return pts + tc[:, None] * normals


def x_extent_weights(pts: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Eq. 1 weights of the boundary points ``pts[idx]``: the x-extent (px) each one covers.

    ``pts``: (n, 2) closed outline, image px; ``idx``: (m,) boundary indices into it. Each point
    covers half the x-step to each contour neighbour, so Eq. 1's sums become the integral over x
    that the ground truth uses; a staircase's vertical steps would otherwise count many times.
    Returns (m,) weights, all > 0.
    """
    dxl = np.abs(pts[:, 0] - np.roll(pts[:, 0], 1))
    dxr = np.abs(np.roll(pts[:, 0], -1) - pts[:, 0])
    return 0.5 * (dxl + dxr)[idx] + 1e-6


def end_on_rim(run_pts: np.ndarray, end_first: bool, r: float, reach_px: float) -> np.ndarray:
    """Carry a boundary run's end point along its local direction onto the rim |q| = r.

    ``run_pts``: (m, 2) wheel-frame points of one contour run, in contour order; ``end_first``
    says which end. The "closer than r - margin" rule stops the boundary short of the rim, which
    would bias theta by degrees at shallow sinkage; the soil surface's own direction over its last
    few pixels puts the end where it meets the rim. Falls back to the radial projection of the end
    point when the extrapolation would be longer than ``reach_px``.
    """
    seg = run_pts[:8] if end_first else run_pts[-8:]
    end = seg[0] if end_first else seg[-1]
    rho = float(np.hypot(*end))
    radial = end * (r / max(rho, 1e-9))
    if len(seg) < 3:
        return radial
    centred = seg - seg.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    d = vt[0]
    if np.dot(d, end - seg.mean(axis=0)) < 0:
        d = -d
    pd = float(np.dot(end, d))
    disc = pd * pd - (rho * rho - r * r)
    if disc < 0:
        return radial
    t = -pd + math.sqrt(disc)
    if not 0 <= t <= reach_px:
        return radial
    return end + t * d


def ends_on_rim(
    uv: np.ndarray, runs: list[np.ndarray], r: float, reach_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """A and B (wheel frame, px): the entry- and exit-most run ends, carried onto the rim.

    ``uv``: (n, 2) outline in the wheel frame (entry side at +u); ``runs``: index arrays of the
    boundary's runs in contour order. See :func:`end_on_rim`.
    """
    ends = []
    for want_max in (True, False):
        best_run, best_first, best_u = runs[0], True, -np.inf
        for run in runs:
            for first in (True, False):
                u = uv[run[0] if first else run[-1], 0] * (1 if want_max else -1)
                if u > best_u:
                    best_run, best_first, best_u = run, first, u
        ends.append(end_on_rim(uv[best_run], best_first, r, reach_px))
    return ends[0], ends[1]
