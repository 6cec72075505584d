"""The paper's classic pipeline, step by step, in float64 NumPy and OpenCV (no gradients).

"The Processes of Sinkage Detection", as written:

1. confidence rectangle on the wheel face (the rig's ``confidence_rect``);
2. RGB -> HSI (:func:`rgb_to_hsi_np`, the textbook arccos formula, not OpenCV's HSV);
3. H_w, S_w over the rectangle (Eqs. 4-5, :func:`confidence_means`), H and S ranges from P_a/P_d,
   binary image (:func:`hard_mask`), then dilation, erosion and area filtering;
4. the wheel outline (external contour), a 3-D Hough transform of it into (cx, cy, r) space for
   the rim circle, and the wheel-soil boundary = outline points closer to O than r;
5. Eqs. 1-3 (:func:`sinkjax._geometry.geometry_from_boundary`).

What is added to make it measure well, each step still the paper's: the hue band is circular
(see ``_rig.HUE_SCALE_DEG``); the Hough votes go along the outline's inward normal and its peak is
polished by a least-squares fit that keeps only the inner envelope, so lugs never pull the rim
outwards; lightening holes that the soil cuts open are filled like the intact ones; the outline
is located to sub-pixel precision on the colour profile across it (the binary image's thresholds
alone would move a blurred edge by a pixel or more, differently on rim and soil); boundary points
are weighted by the x-extent they cover, so the equivalent line is the same integral over x as
the ground truth's; and A and B, which "closer than r" leaves a hair inside the rim, are carried
along the boundary's end direction onto the rim.
"""

from __future__ import annotations

import functools
import math

import cv2
import jax
import numpy as np

from ._geometry import SinkageGeometry, geometry_from_boundary, travel_sign
from ._results import (
    BAD_IMAGE,
    BAD_RECT,
    FIT_FAILED,
    NO_CONTACT,
    NO_WHEEL,
    OK,
    FrameResult,
    Overlay,
    failed,
)
from ._rig import HUE_SCALE_DEG, Rig, SegmentationParams

# Plausible rim radius as a fraction of min(H, W): a wheel that fills less or more of the frame is
# not the camera set-up this method is for.
R_MIN_FRAC = 0.15
R_MAX_FRAC = 0.6
# Least margin (px) inside the rim for an outline point to count as wheel-soil boundary; it grows
# with the scatter of the rim's edge points (noise, JPEG), see estimate_classic.
BOUNDARY_MARGIN_PX = 0.75
# Contour points within this many pixels of the image border are the frame's edge, not the wheel's.
_BORDER_PX = 1
# Half-width (in contour steps) of the chord used for the outline's tangent.
_TANGENT_HALF = 3
_MIN_WHEEL_PIXELS = 200


# --------------------------------------------------------------------------------------------
# Step 2: colour


def rgb_to_hsi_np(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RGB -> the paper's HSI (textbook arccos hue), float64.

    ``rgb``: (H, W, 3) uint8, or float in [0, 1]. Returns H in degrees [0, 360), S and I in [0, 1],
    each (H, W). Grey pixels (R = G = B) get H = 0, black pixels S = 0; never NaN, never warns.
    Raises ValueError if the last axis is not 3.
    """
    a = np.asarray(rgb)
    if a.ndim < 1 or a.shape[-1] != 3:
        raise ValueError(f"rgb must have shape (..., 3), got {a.shape}")
    x = a.astype(np.float64) / 255.0 if a.dtype == np.uint8 else a.astype(np.float64)
    r, g, b = np.moveaxis(x, -1, 0).copy()  # contiguous planes: faster than strided channels
    rg, rb = r - g, r - b
    num = 0.5 * (rg + rb)
    # (R-G)^2 + (R-B)(G-B) = R^2+G^2+B^2-RG-RB-GB >= 0, zero only for grey.
    den = np.sqrt(np.maximum(rg * rg + rb * (g - b), 0.0))
    grey = den <= 1e-12
    theta = np.degrees(np.arccos(np.clip(num / np.where(grey, 1.0, den), -1.0, 1.0)))
    h = np.where(b <= g, theta, 360.0 - theta)
    h[grey | (h >= 360.0)] = 0.0
    total = r + g + b
    dark = total <= 1e-12
    s = 1.0 - 3.0 * np.minimum(np.minimum(r, g), b) / np.where(dark, 1.0, total)
    s[dark] = 0.0
    return h, np.clip(s, 0.0, 1.0), total / 3.0


# --------------------------------------------------------------------------------------------
# Step 3: confidence means and the binary image


def _check_rect(
    rect: tuple[int, int, int, int], shape: tuple[int, ...]
) -> tuple[int, int, int, int]:
    x, y, w, h = (int(v) for v in rect)
    height, width = shape[:2]
    if w < 1 or h < 1 or x < 0 or y < 0 or x + w > width or y + h > height:
        raise ValueError(
            f"confidence rect [x, y, w, h] = {[x, y, w, h]} is not inside the {width}x{height} "
            "image; choose a rectangle on the wheel face that lies fully inside the frame"
        )
    return x, y, w, h


def confidence_means(
    h_deg: np.ndarray, s: np.ndarray, rect: tuple[int, int, int, int]
) -> tuple[float, float]:
    """Eqs. 4-5: mean hue H_w (degrees, [0, 360)) and saturation S_w over ``rect`` = (x, y, w, h).

    ``h_deg``, ``s``: (H, W). The hue mean is circular (a red wheel straddles 0/360, where the
    arithmetic mean of Eq. 4 would land on cyan). Raises ValueError if ``rect`` is not fully inside
    the image.
    """
    x, y, w, h = _check_rect(rect, np.shape(h_deg))
    hh = np.radians(np.asarray(h_deg, dtype=np.float64)[y : y + h, x : x + w])
    h_w = math.degrees(math.atan2(float(np.mean(np.sin(hh))), float(np.mean(np.cos(hh)))))
    s_w = float(np.mean(np.asarray(s, dtype=np.float64)[y : y + h, x : x + w]))
    return h_w % 360.0, s_w


def hard_mask(
    h_deg: np.ndarray, s: np.ndarray, h_w_deg: float, s_w: float, seg: SegmentationParams
) -> np.ndarray:
    """The paper's binary image: pixels whose H and S lie in the P_d/P_a ranges. (H, W) bool.

    Hue: wrap(H - H_w) in [(p_d_hue - 1) * 180, (p_a_hue - 1) * 180] degrees (circular band, see
    ``_rig.HUE_SCALE_DEG``). Saturation: S in [p_d_sat * S_w, p_a_sat * S_w].
    """
    d = np.mod(np.asarray(h_deg, dtype=np.float64) - h_w_deg + 180.0, 360.0) - 180.0
    lo_h = (float(seg.p_d_hue) - 1.0) * HUE_SCALE_DEG
    hi_h = (float(seg.p_a_hue) - 1.0) * HUE_SCALE_DEG
    s = np.asarray(s, dtype=np.float64)
    return (
        (d >= lo_h)
        & (d <= hi_h)
        & (s >= float(seg.p_d_sat) * s_w)
        & (s <= float(seg.p_a_sat) * s_w)
    )


def wheel_region(mask: np.ndarray, rect: tuple[int, int, int, int]) -> np.ndarray | None:
    """Dilation, erosion and area filtering: the wheel's connected component (holes not filled).

    ``mask``: (H, W) bool. Returns a (H, W) bool mask, or None when no component reaches into the
    confidence rectangle. Closing bridges one-pixel cracks (noise, anti-aliasing); the component
    with the most pixels in the rectangle is the wheel. Its holes (lightening holes, hub, specular
    highlights) are no part of its outline; :func:`fill_holes` fills them.
    """
    k3 = np.ones((3, 3), np.uint8)
    closed = cv2.erode(cv2.dilate(mask.astype(np.uint8), k3), k3)
    # An opening after the closing drops one-pixel spurs and soil specks touching the wheel.
    opened = cv2.dilate(cv2.erode(closed, k3), k3)
    n, labels = cv2.connectedComponents(opened, connectivity=8)
    if n <= 1:
        return None
    x, y, w, h = rect
    counts = np.bincount(labels[y : y + h, x : x + w].ravel(), minlength=n)
    counts[0] = 0
    best = int(np.argmax(counts))
    if counts[best] == 0:
        return None
    return labels == best


def fill_holes(region: np.ndarray) -> np.ndarray:
    """``region`` (H, W) bool with its enclosed holes filled (inside its external contour)."""
    contours, _ = cv2.findContours(
        region.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE
    )
    out = np.zeros(region.shape, np.uint8)
    cv2.drawContours(out, contours, -1, 1, thickness=cv2.FILLED)
    return out.astype(bool) | region


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


# --------------------------------------------------------------------------------------------
# Step 4: outline, Hough, boundary


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


def _off_border(pts: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """(n,) bool: outline points not on the image border (there the outline is the frame's)."""
    b = _BORDER_PX
    return (
        (pts[:, 0] >= b)
        & (pts[:, 0] <= shape[1] - 1 - b)
        & (pts[:, 1] >= b)
        & (pts[:, 1] <= shape[0] - 1 - b)
    )


def hough_rim(
    pts: np.ndarray,
    normals: np.ndarray,
    image_shape: tuple[int, int],
    r_range_px: tuple[float, float],
) -> tuple[float, float, float, int] | None:
    """3-D Hough transform of the outline into (cx, cy, r) space; the rim's coarse circle.

    ``pts``, ``normals``: (n, 2) image px and inward unit normals. Each point votes, for every
    candidate radius, for the centre one radius along its normal; the accumulator is binned
    coarsely (centre bins ~1/120 of the image, radius bins half that) and box-smoothed. Lugs make a
    second, concentric peak at a larger radius (their tips); among concentric strong peaks the
    innermost is the rim. Centres are searched inside the image, radii in ``r_range_px``.
    Returns (cx, cy, r, smoothed votes) in image px, or None when there are no votes.
    """
    height, width = image_shape
    bc = max(2.0, min(height, width) / 120.0)
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
    sm_yx = cv2.boxFilter(acc_yxr, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    sm_yx = np.asarray(sm_yx, np.float32).reshape(ny, nx, nr)  # OpenCV drops a last axis of 1
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
    bands = [(-band0_px, band0_px), (-3.0, 2.0), (-2.0, 1.5), (-1.5, 1.0), (-1.5, 1.0)]
    n_in = 0
    for lo, hi in bands:
        d = pts - (cx, cy)
        rho = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
        radial = -np.sum(normals * d, axis=1) / rho  # inward normal . (O - p)/|O - p|
        e = rho - r
        sel = (e >= lo) & (e <= hi) & (radial > 0.8)
        n_in = int(np.count_nonzero(sel))
        if n_in < 10:
            break
        cx, cy, r = fit_circle(pts[sel], cx, cy, r)
    return cx, cy, r, n_in


def _refit_rim(
    pts: np.ndarray, normals: np.ndarray, cx: float, cy: float, r: float
) -> tuple[float, float, float, float]:
    """Least-squares rim circle through the (sub-pixel) edge points within [-1.5, +1] px of it.

    Returns (cx, cy, r, sigma) in px; sigma is the robust (MAD) scatter of the rim points about
    the circle, which sets how far inside the rim a point must be to count as soil boundary.
    """
    sigma = 0.5
    for _ in range(3):
        d = pts - (cx, cy)
        rho = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
        radial = -np.sum(normals * d, axis=1) / rho
        e = rho - r
        sel = (e >= -1.5) & (e <= 1.0) & (radial > 0.8)
        if np.count_nonzero(sel) < 10:
            break
        sigma = 1.4826 * float(np.median(np.abs(e[sel] - np.median(e[sel]))))
        cx, cy, r = fit_circle(pts[sel], cx, cy, r)
    return cx, cy, r, sigma


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


def _runs(flags: np.ndarray) -> list[np.ndarray]:
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


def _end_on_rim(run_pts: np.ndarray, end_first: bool, r: float, reach_px: float) -> np.ndarray:
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


# --------------------------------------------------------------------------------------------
# Step 5: Eqs. 1-3 (JAX), compiled once per power-of-two point-count bucket


@functools.partial(jax.jit, static_argnames=("travel",))
def _geometry_padded(x, y, w, cx, cy, r, a_uv, b_uv, travel):  # type: ignore[no-untyped-def]
    return geometry_from_boundary(
        x, y, cx, cy, r, travel=travel, weight=w, a_px=a_uv, b_end_px=b_uv
    )


def _geometry(
    pts: np.ndarray,
    weight: np.ndarray,
    centre: tuple[float, float],
    r: float,
    a_uv: np.ndarray,
    b_uv: np.ndarray,
    travel: str,
) -> SinkageGeometry:
    """Eqs. 1-3 on boundary points (n, 2) image px with weights (n,), A/B in the wheel frame.

    The points are zero-padded (weight 0) to a power of two >= 64, so the jitted function
    compiles once per size bucket instead of once per point count.
    """
    n = len(pts)
    size = max(64, 1 << (n - 1).bit_length())
    xp = np.zeros(size)
    yp = np.zeros(size)
    wp = np.zeros(size)
    xp[:n], yp[:n], wp[:n] = pts[:, 0], pts[:, 1], weight
    return _geometry_padded(xp, yp, wp, centre[0], centre[1], r, a_uv, b_uv, travel)


# --------------------------------------------------------------------------------------------
# The whole pipeline


def estimate_classic(image: np.ndarray, rig: Rig, name: str = "") -> FrameResult:
    """Sinkage and entry/exit angles of one frame by the paper's classic pipeline.

    ``image``: (H, W, 3) uint8 RGB; ``rig``: R (mm), confidence rectangle, travel and the P_d/P_a
    of ``rig.segmentation``. Returns a FrameResult: status ``ok`` or ``no_contact`` with sinkage
    (mm), theta1/theta2 (degrees), rim centre and radius (image px) and an overlay (rim, boundary
    points, equivalent-line ends, A, B in image px); or ``bad_image`` / ``bad_rect`` /
    ``no_wheel`` / ``fit_failed`` with a message saying what went wrong. ``fit_failed`` also
    covers a binary image that lost part of the wheel face (an outline dipping inside the rim
    above O), which would otherwise read as a wrong sinkage. Never raises for bad image content.
    The classic method has no uncertainty: the ``*_std_*`` fields stay None.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        return failed(
            name,
            BAD_IMAGE,
            f"expected an (H, W, 3) uint8 RGB image, got shape {img.shape} dtype {img.dtype}",
        )
    height, width = img.shape[:2]
    # Step 1: the confidence rectangle.
    try:
        rect = _check_rect(rig.confidence_rect, img.shape)
    except ValueError as e:
        return failed(name, BAD_RECT, str(e))
    # Step 2: HSI. Step 3: means, ranges, binary image, morphology.
    h_deg, s, _ = rgb_to_hsi_np(img)
    h_w, s_w = confidence_means(h_deg, s, rect)
    mask = hard_mask(h_deg, s, h_w, s_w, rig.segmentation)
    region = wheel_region(mask, rect)
    if region is None or np.count_nonzero(region) < _MIN_WHEEL_PIXELS:
        return failed(
            name,
            NO_WHEEL,
            f"no wheel-coloured region at the confidence rect {list(rect)} (H_w = {h_w:.1f} deg, "
            f"S_w = {s_w:.3f}); check that the rectangle lies on the wheel face",
        )
    # Step 4: outline -> Hough rim -> boundary.
    contour, normals = wheel_outline(region)
    inner = _off_border(contour, img.shape)
    if np.count_nonzero(inner) < 50:
        return failed(name, NO_WHEEL, "the wheel region's outline is too short to hold a rim")
    m = min(height, width)
    r_range = (R_MIN_FRAC * m, R_MAX_FRAC * m)
    coarse = hough_rim(contour[inner], normals[inner], (height, width), r_range)
    if coarse is None:
        return failed(name, FIT_FAILED, "the Hough transform found no rim circle in the outline")
    bc = max(2.0, m / 120.0)
    cx, cy, r, n_in = refine_rim(
        contour[inner], normals[inner], coarse[0], coarse[1], coarse[2], band0_px=2.0 * bc
    )
    if not (np.isfinite([cx, cy, r]).all() and r_range[0] * 0.9 <= r <= r_range[1] * 1.1):
        return failed(name, FIT_FAILED, f"rim fit diverged (r = {r:.1f} px)")
    if n_in < 0.1 * 2.0 * math.pi * r:
        return failed(
            name,
            FIT_FAILED,
            f"rim circle (r = {r:.1f} px) is supported by only {n_in} outline points; "
            "the wheel's outline is not a circle (segmentation?)",
        )
    rx, ry, rw, rh = rect
    if math.hypot(rx + 0.5 * (rw - 1) - cx, ry + 0.5 * (rh - 1) - cy) > r:
        return failed(
            name,
            NO_WHEEL,
            f"the only circle in the outline of the region at the confidence rect (centre "
            f"({cx:.0f}, {cy:.0f}) px, r = {r:.0f} px) does not contain the rectangle; "
            "check that the rectangle lies on the wheel face",
        )
    region = fill_cut_holes(img, region, cx, cy, r)
    contour, normals = wheel_outline(region)
    inner = _off_border(contour, img.shape)
    # Contour pixels are centres of the region's border pixels, ~half a pixel inside the edge;
    # locate the edge itself on the colour profile across it, and refit the rim there.
    edge = subpixel_edges(img, contour, normals)
    cx, cy, r_edge, sigma = _refit_rim(edge[inner], normals[inner], cx, cy, r + 0.5)
    # Between lugs the outline runs along the rim, scattered by +-sigma: "closer than r" needs a
    # margin of a few sigma to leave those points out of the wheel-soil boundary.
    margin = min(max(BOUNDARY_MARGIN_PX, 4.0 * sigma), 3.0)
    sign = travel_sign(rig.travel)
    uv = np.column_stack([sign * (edge[:, 0] - cx), edge[:, 1] - cy])
    rho = np.hypot(uv[:, 0], uv[:, 1])
    inside = inner & (rho < r_edge - margin)
    overlay = Overlay(centre_px=(cx, cy), radius_px=r_edge)
    # Runs that barely dip inside the margin and are short are rim noise (a notch at a lug root,
    # a highlight on the rim edge), not soil: soil that reaches inside the rim either cuts in
    # deeper or spans a long chord.
    runs = [
        run
        for run in _runs(inside)
        if r_edge - rho[run].min() >= margin + 1.0 or np.ptp(uv[run, 0]) >= 0.05 * r_edge
    ]
    if not runs:
        return FrameResult(
            image=name,
            status=NO_CONTACT,
            sinkage_mm=0.0,
            theta1_deg=0.0,
            theta2_deg=0.0,
            center_x_px=cx,
            center_y_px=cy,
            radius_px=r_edge,
            message="the soil does not reach inside the rim (no wheel-soil boundary)",
            overlay=overlay,
        )
    idx = np.concatenate(runs)
    if uv[idx, 1].min() < 0.0:
        # Soil above the wheel centre: Eq. 1 (which takes |b|) would read it as less sinkage,
        # and the confidence rectangle, above the hub, would be buried. The binary image has
        # lost part of the wheel face instead; say so rather than report a number.
        return failed(
            name,
            FIT_FAILED,
            "the wheel outline dips inside the rim above the wheel centre: the binary image lost "
            "part of the wheel face (shading, highlights or dust?); widen P_d/P_a or calibrate",
        )
    # Weight each point by the x-extent it covers (half the x-step to each contour neighbour), so
    # Eq. 1's sums become the integral over x that the ground truth uses; a staircase's vertical
    # steps would otherwise count many times.
    dxl = np.abs(edge[:, 0] - np.roll(edge[:, 0], 1))
    dxr = np.abs(np.roll(edge[:, 0], -1) - edge[:, 0])
    weight = 0.5 * (dxl + dxr)[idx] + 1e-6
    reach = max(6.0 * margin, 0.1 * r_edge)
    ends = []
    for want_max in (True, False):
        best_run, best_first, best_u = runs[0], True, -np.inf
        for run in runs:
            for first in (True, False):
                u = uv[run[0] if first else run[-1], 0] * (1 if want_max else -1)
                if u > best_u:
                    best_run, best_first, best_u = run, first, u
        ends.append(_end_on_rim(uv[best_run], best_first, r_edge, reach))
    a_uv, b_uv = ends
    geo = _geometry(edge[idx], weight, (cx, cy), r_edge, a_uv, b_uv, rig.travel)
    z0 = float(geo.sinkage_px)
    t1 = math.degrees(float(geo.theta1_rad))
    t2 = math.degrees(float(geo.theta2_rad))
    if not all(math.isfinite(v) for v in (z0, t1, t2)):
        return failed(name, FIT_FAILED, "Eqs. 1-3 gave a non-finite result")
    k, bb = float(geo.k), float(geo.b_px)

    line_uv = np.array([[b_uv[0], k * b_uv[0] + bb], [a_uv[0], k * a_uv[0] + bb]])
    to_img = lambda q: (float(sign * q[0] + cx), float(q[1] + cy))
    overlay.boundary_px = edge[idx].copy()
    overlay.line_px = (to_img(line_uv[0]), to_img(line_uv[1]))
    overlay.a_px = to_img(a_uv)
    overlay.b_px = to_img(b_uv)
    return FrameResult(
        image=name,
        status=OK,
        sinkage_mm=z0 * rig.wheel_radius_mm / r_edge,
        theta1_deg=t1,
        theta2_deg=t2,
        center_x_px=cx,
        center_y_px=cy,
        radius_px=r_edge,
        overlay=overlay,
    )
