"""Classic pipeline, step 4: the wheel region's outline, its 3-D Hough rim and the rim's points.

Float64 NumPy and OpenCV, no gradients (the soft counterpart is :mod:`sinkjax.soft.hough`).
Everything here is the paper's method as written (outline of the wheel area -> Hough rim -> the
outline points closer to O than r), with the care that a pixel outline needs: the Hough votes go
along the outline's inward normal, and its peak is polished by a least-squares fit that keeps
only the inner envelope (:func:`rim_points`), so lugs never pull the rim outwards. The
refinements beyond the paper (sub-pixel edges, cut-open holes, ...) live in
:mod:`sinkjax.classic.refine`.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

# Contour points within this many pixels of the image border are the frame's edge, not the wheel's.
_BORDER_PX = 1
# Half-width (in contour steps) of the chord used for the outline's tangent.
_TANGENT_HALF = 3
# Most channels one OpenCV filter call takes (CV_CN_MAX is 128 in OpenCV 5, 512 before).
_CV_MAX_CHANNELS = 128
# Rim points: residual |p - O| - r within this band (px) and normal within ~37 degrees of radial.
# The outer side is tight so that lug tips only a few pixels high stay out; the inner side admits
# the outline's pixel staircase and noise.
RIM_BAND_PX = (-1.5, 1.0)
_MIN_RADIAL = 0.8
# Fewer rim points than this cannot pin a circle (or a scatter) down.
MIN_RIM_POINTS = 10


def wheel_outline(region: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """External contour of the wheel region and its inward unit normals.

    ``region``: (H, W) bool. Returns points (n, 2) float64 image px (x, y), pixel centres of the
    region's border pixels in contour order (closed), and normals (n, 2) pointing into the region.
    """
    contours, _ = cv2.findContours(
        region.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE
    )
    if not contours:
        return np.zeros((0, 2)), np.zeros((0, 2))
    c = max(contours, key=len)[:, 0, :].astype(np.float64)
    if len(c) < 2 * _TANGENT_HALF + 1:
        return c, np.zeros_like(c)
    t = np.roll(c, -_TANGENT_HALF, axis=0) - np.roll(c, _TANGENT_HALF, axis=0)
    t /= np.maximum(np.hypot(t[:, 0], t[:, 1]), 1e-9)[:, None]
    n = np.stack([-t[:, 1], t[:, 0]], axis=1)
    # Orientation-free sign: the normals of a closed outline point inwards on the whole, and the
    # region's pixels are where "inwards" is. Probe one pixel along each normal.
    probe = np.rint(c + 1.5 * n).astype(int)
    hh, ww = region.shape
    ok = (probe[:, 0] >= 0) & (probe[:, 0] < ww) & (probe[:, 1] >= 0) & (probe[:, 1] < hh)
    inside = region[probe[ok, 1], probe[ok, 0]]
    if 2 * np.count_nonzero(inside) < len(inside):
        n = -n
    return c, n


def off_border(pts: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """(n,) bool: outline points not on the image border (there the outline is the frame's)."""
    b = _BORDER_PX
    return (
        (pts[:, 0] >= b)
        & (pts[:, 0] <= shape[1] - 1 - b)
        & (pts[:, 1] >= b)
        & (pts[:, 1] <= shape[0] - 1 - b)
    )


def hough_bin_px(height: int, width: int) -> float:
    """Centre bin size (px) of :func:`hough_rim_np`'s accumulator: ~1/120 of the image, >= 2."""
    return max(2.0, min(height, width) / 120.0)


def hough_rim_np(
    pts: np.ndarray,
    normals: np.ndarray,
    image_shape: tuple[int, int],
    r_range_px: tuple[float, float],
) -> tuple[float, float, float, int] | None:
    """3-D Hough transform of the outline into (cx, cy, r) space; the rim's coarse circle.

    ``pts``, ``normals``: (n, 2) image px and inward unit normals. Each point votes, for every
    candidate radius, for the centre one radius along its normal; the accumulator is binned
    coarsely (centre bins :func:`hough_bin_px`, radius bins half that) and box-smoothed. Lugs make a
    second, concentric peak at a larger radius (their tips); among concentric strong peaks the
    innermost is the rim. Centres are searched inside the image, radii in ``r_range_px``.
    Returns (cx, cy, r, smoothed votes) in image px, or None when there are no votes.
    """
    height, width = image_shape
    bc = hough_bin_px(height, width)
    br = bc / 2.0
    r_lo, r_hi = r_range_px
    nr = max(1, math.ceil((r_hi - r_lo) / br))
    nx = math.ceil(width / bc)
    ny = math.ceil(height / bc)
    radii = r_lo + br * (np.arange(nr) + 0.5)
    cx = pts[:, 0:1] + radii[None, :] * normals[:, 0:1]
    cy = pts[:, 1:2] + radii[None, :] * normals[:, 1:2]
    ix = np.floor(cx / bc).astype(np.int64)
    iy = np.floor(cy / bc).astype(np.int64)
    ir = np.broadcast_to(np.arange(nr), ix.shape)
    ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    if not np.any(ok):
        return None
    # Radius innermost, so that OpenCV's box filter treats it as channels.
    flat = (iy[ok] * nx + ix[ok]) * nr + ir[ok]
    acc_yxr = np.bincount(flat, minlength=ny * nx * nr).reshape(ny, nx, nr).astype(np.float32)
    # Normals from a pixel staircase are good to a few degrees, which at r ~ 200 px spreads a
    # circle's votes over neighbouring bins: sum 3x3x3 neighbourhoods before taking the peak.
    # The filter works channel by channel, and OpenCV takes at most _CV_MAX_CHANNELS at a time.
    sm_yx = np.empty_like(acc_yxr)
    for j in range(0, nr, _CV_MAX_CHANNELS):
        part = np.ascontiguousarray(acc_yxr[:, :, j : j + _CV_MAX_CHANNELS])
        box = cv2.boxFilter(part, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        # OpenCV drops a last axis of 1.
        sm_yx[:, :, j : j + _CV_MAX_CHANNELS] = np.asarray(box, np.float32).reshape(ny, nx, -1)
    sm_yxr = sm_yx.copy()
    sm_yxr[:, :, 1:] += sm_yx[:, :, :-1]
    sm_yxr[:, :, :-1] += sm_yx[:, :, 1:]
    acc = np.moveaxis(acc_yxr, 2, 0)  # (nr, ny, nx) views
    sm = np.moveaxis(sm_yxr, 2, 0)
    ky, kx, kr = (int(v) for v in np.unravel_index(int(np.argmax(sm_yxr)), sm_yxr.shape))
    top = float(sm[kr, ky, kx])
    if top <= 0:
        return None
    # Concentric peaks (same centre bin +-1, smaller radius, at least half as strong) are the rim
    # under the lug tips; take the innermost local maximum of the radius profile.
    prof = sm[:, max(ky - 1, 0) : ky + 2, max(kx - 1, 0) : kx + 2].reshape(nr, -1).max(axis=1)
    lo = max(0, kr - math.ceil(0.15 * radii[kr] / br))
    for j in range(lo, kr):
        left = prof[j - 1] if j > 0 else -1
        if prof[j] >= 0.5 * top and prof[j] >= left and prof[j] >= prof[j + 1]:
            kr = j
            sub = sm[j, max(ky - 1, 0) : ky + 2, max(kx - 1, 0) : kx + 2]
            dy, dx = (int(v) for v in np.unravel_index(int(np.argmax(sub)), sub.shape))
            ky, kx = max(ky - 1, 0) + dy, max(kx - 1, 0) + dx
            break
    # Sub-bin estimate: vote-weighted mean over the raw 3x3x3 neighbourhood of the peak.
    r0, y0, x0 = max(kr - 1, 0), max(ky - 1, 0), max(kx - 1, 0)
    block = acc[r0 : kr + 2, y0 : ky + 2, x0 : kx + 2].astype(np.float64)
    wsum = block.sum()
    gr, gy, gx = np.meshgrid(
        r0 + np.arange(block.shape[0]),
        y0 + np.arange(block.shape[1]),
        x0 + np.arange(block.shape[2]),
        indexing="ij",
    )
    c_x = (float((gx * block).sum() / wsum) + 0.5) * bc
    c_y = (float((gy * block).sum() / wsum) + 0.5) * bc
    r = r_lo + (float((gr * block).sum() / wsum) + 0.5) * br
    return c_x, c_y, r, int(sm[kr, ky, kx])


def fit_circle(pts: np.ndarray, cx: float, cy: float, r: float) -> tuple[float, float, float]:
    """Geometric least-squares circle through ``pts`` (n, 2), Gauss-Newton from (cx, cy, r)."""
    p = np.array([cx, cy, r], dtype=np.float64)
    for _ in range(8):
        d = pts - p[:2]
        rho = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
        res = rho - p[2]
        jac = np.column_stack([-d[:, 0] / rho, -d[:, 1] / rho, -np.ones_like(rho)])
        step, *_ = np.linalg.lstsq(jac, -res, rcond=None)
        p += step
        if np.max(np.abs(step)) < 1e-6:
            break
    return float(p[0]), float(p[1]), float(p[2])


def refine_rim(
    pts: np.ndarray, normals: np.ndarray, cx: float, cy: float, r: float, band0_px: float
) -> tuple[float, float, float, int]:
    """Least-squares rim circle on the inner envelope of the outline near (cx, cy, r).

    Inliers: outline points whose normal is nearly radial and whose residual |p - O| - r lies in a
    band that shrinks from +-``band0_px`` (the Hough bin error) to [-1.5, +1.0] px. The tight
    outer side keeps lug tips out even when they are only a few pixels high. Returns
    (cx, cy, r, number of inliers) in image px.
    """
    bands = [(-band0_px, band0_px), (-3.0, 2.0), (-2.0, 1.5), RIM_BAND_PX, RIM_BAND_PX]
    n_in = 0
    for band in bands:
        sel, _ = rim_points(pts, normals, cx, cy, r, band)
        n_in = int(np.count_nonzero(sel))
        if n_in < MIN_RIM_POINTS:
            break
        cx, cy, r = fit_circle(pts[sel], cx, cy, r)
    return cx, cy, r, n_in


def rim_points(
    pts: np.ndarray,
    normals: np.ndarray,
    cx: float,
    cy: float,
    r: float,
    band_px: tuple[float, float] = RIM_BAND_PX,
) -> tuple[np.ndarray, np.ndarray]:
    """The outline points that lie on the rim circle (cx, cy, r), and every point's residual.

    ``pts``, ``normals``: (n, 2) image px and inward unit normals. A rim point's normal is nearly
    radial and its residual |p - O| - r lies in ``band_px``. Returns ((n,) bool, (n,) residual px).
    """
    lo, hi = band_px
    d = pts - (cx, cy)
    rho = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    radial = -np.sum(normals * d, axis=1) / rho  # inward normal . (O - p)/|O - p|
    e = rho - r
    return (e >= lo) & (e <= hi) & (radial > _MIN_RADIAL), e


def mad_px(residual_px: np.ndarray) -> float:
    """Robust scatter (px): the median absolute deviation, scaled to a Gaussian's sigma."""
    return 1.4826 * float(np.median(np.abs(residual_px - np.median(residual_px))))


def rim_scatter_px(pts: np.ndarray, normals: np.ndarray, cx: float, cy: float, r: float) -> float:
    """Robust (MAD) scatter, px, of the rim's outline points about the circle (cx, cy, r).

    Rim points: :func:`rim_points`, the inliers of :func:`refine_rim`'s last band. On a pixel
    outline it is the staircase's quantisation, plus noise; it sets how far inside the rim a
    point must be to count as soil boundary. 0.5 px when there are too few rim points to tell.
    """
    sel, e = rim_points(pts, normals, cx, cy, r)
    if np.count_nonzero(sel) < MIN_RIM_POINTS:
        return 0.5
    return mad_px(e[sel])


def runs_of(flags: np.ndarray) -> list[np.ndarray]:
    """Index arrays of maximal runs of True in a CLOSED sequence (the run across the seam joins)."""
    n = len(flags)
    if n == 0 or not flags.any():
        return []
    if flags.all():
        return [np.arange(n)]
    start = int(np.argmin(flags))  # a False: unroll the cycle there
    order = (np.arange(n) + start) % n
    f = flags[order]
    edges = np.diff(np.concatenate([[0], f.astype(np.int8), [0]]))
    starts = np.flatnonzero(edges == 1)
    ends = np.flatnonzero(edges == -1)
    return [order[s:e] for s, e in zip(starts, ends, strict=True)]
