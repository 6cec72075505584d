"""The classic method's own plausibility tests: a frame is ``ok`` only when its outputs can
describe a wheel in soil (issue 12, item 5). The numbers stay the paper's; a frame that fails a
test keeps them, under status ``implausible`` with the reason.

- **the recording's rim**: the camera is fixed to the wheel, so the rim radius is the same in
  every frame (docs/conventions.md §2); a radius further than :data:`MAX_RADIUS_DEVIATION` from
  the recording's is another circle taken for the rim;
- **a soil curve**: the boundary cannot reach above the wheel centre (the confidence rectangle,
  above the hub, would be buried), and it must meet the rim at both ends;
- **the region agrees with the model**: on a ring just inside the rim, the binary wheel region
  (holes filled) must be wheel above the equivalent line and not below it. Lugs, holes and
  highlights never reach that ring on a wheel the binary image understood, so a disagreement over
  more than a tenth of it (:data:`~sinkjax.soft.checks.MAX_RING_DISAGREEMENT`, as the soft
  method's) means the image lost part of the wheel or took soil or shadow for it;
- **the soil goes on beyond the rim**: the soil surface does not end at the wheel. Just outside
  the rim, past the lugs, below the equivalent line's extension, the image must look more like
  the soil just inside the rim than like what lies above the extension. When, at both ends, it
  looks like what is above, the "boundary" is an edge on the wheel itself (soil-coloured dust
  on its lower part, a shadow line): the soft method's test at the same places
  (:func:`sinkjax.soft.probes.soil_lost`), without its second sample of the soil well below the
  extension (the classic method sees no wheel without colour, whose cast shadow it is for).
"""

from __future__ import annotations

import math

import numpy as np

from ..soft.checks import MAX_RING_DISAGREEMENT, N_RING_SAMPLES, RING_INSET, RING_INSET_PX
from ..soft.probes import (
    PROBE_ABOVE_PX,
    PROBE_BELOW_PX,
    PROBE_DROP,
    PROBE_INSIDE,
    PROBE_MIN_RGB,
    PROBE_NEARER,
    PROBE_OUTSIDE,
)

# A rim radius further than this fraction from the recording's is another circle (the camera is
# fixed to the wheel: the rim is the same in every frame, docs/conventions.md §2).
MAX_RADIUS_DEVIATION = 0.05
# A boundary end further inside the rim than this fraction of r (beyond the margin) never met it.
MAX_END_GAP_FRACTION = 0.1


def implausibility(
    boundary_uv: np.ndarray,
    a_uv: np.ndarray,
    b_uv: np.ndarray,
    r: float,
    margin: float,
    recording_radius_px: float | None = None,
) -> str:
    """Why the classic method's own outputs cannot describe a wheel in soil ("" if they can).

    ``boundary_uv`` (n, 2) are the wheel-soil boundary points in the wheel frame (px), A and B
    its ends, ``r`` the rim radius and ``margin`` the band inside the rim that is not boundary.
    The soil cannot reach above the wheel centre (the confidence rectangle is above the hub),
    the boundary must meet the rim at both ends, and with ``recording_radius_px`` the rim must
    be the recording's.
    """
    if recording_radius_px is not None and abs(r - recording_radius_px) > max(
        3.0, MAX_RADIUS_DEVIATION * recording_radius_px
    ):
        return (
            f"rim radius {r:.1f} px is far from the recording's {recording_radius_px:.1f} px: "
            "another circle was taken for the rim"
        )
    if np.mean(boundary_uv[:, 1] < 0.0) > 0.05:
        return "the wheel-soil boundary reaches above the wheel centre (segmentation?)"
    gap = max(r - math.hypot(*a_uv), r - math.hypot(*b_uv))
    if gap > margin + max(3.0, MAX_END_GAP_FRACTION * r):
        return (
            f"the wheel-soil boundary stops {gap:.0f} px short of the rim: it is not the soil "
            "surface (segmentation?)"
        )
    return ""


def _patch_rgb(image: np.ndarray, x: float, y: float) -> np.ndarray:
    # Mean colour (RGB in [0, 1]) of a 5 x 5 px neighbourhood sampled every 2 px, bilinear with
    # the edge replicated (as the soft method's map_coordinates): texture averages out. Only
    # the 9 samples' 4 neighbours are read, not the whole frame converted.
    height, width = image.shape[:2]
    offsets = np.asarray([-2.0, 0.0, 2.0])
    xs = np.clip(np.repeat(x + offsets, 3), 0.0, width - 1.0)
    ys = np.clip(np.tile(y + offsets, 3), 0.0, height - 1.0)
    x0 = np.minimum(np.floor(xs).astype(int), width - 2)
    y0 = np.minimum(np.floor(ys).astype(int), height - 2)
    fx, fy = (xs - x0)[:, None], (ys - y0)[:, None]
    px = lambda dy, dx: image[y0 + dy, x0 + dx].astype(np.float64)
    top = px(0, 0) * (1 - fx) + px(0, 1) * fx
    bottom = px(1, 0) * (1 - fx) + px(1, 1) * fx
    return (top * (1 - fy) + bottom * fy).mean(axis=0) / 255.0


def soil_ends_beyond_rim(
    image: np.ndarray,
    centre_px: tuple[float, float],
    r: float,
    k: float,
    a_uv: np.ndarray,
    b_uv: np.ndarray,
    sign: float,
) -> bool:
    """True when the soil surface goes on beyond the rim at neither end (module docstring):
    the boundary is an edge on the wheel, not the soil surface.

    ``image`` (H, W, 3) uint8 RGB; ``centre_px`` the rim centre, ``r`` its radius (px); ``k`` the
    equivalent line's slope in the wheel frame (v = k u + b, y down, u along travel); A and B
    (``a_uv``, ``b_uv``) the boundary's ends on the rim; ``sign`` the travel sign (+1 right).
    A probe outside the image counts as soil (no evidence against the frame).
    """
    height, width = image.shape[:2]
    cx, cy = centre_px
    norm = math.hypot(1.0, k)
    n = np.asarray([-k, 1.0]) / norm  # down, across the line
    for side, end in ((1.0, a_uv), (-1.0, b_uv)):
        t = side * np.asarray([1.0, k]) / norm  # along the line, away from the wheel
        e = np.asarray(end, dtype=np.float64)
        out = e + PROBE_OUTSIDE * r * t
        probes = (
            e - PROBE_INSIDE * r * t + PROBE_BELOW_PX * n,  # soil, inside the rim
            out + PROBE_BELOW_PX * n,  # beyond the rim, just below the extension
            out + (PROBE_BELOW_PX + PROBE_DROP * r) * n,  # ... and a little lower
            out - PROBE_ABOVE_PX * n,  # above the extension
        )
        xy = [(cx + sign * q[0], cy + q[1]) for q in probes]
        if not all(2 <= x <= width - 3 and 2 <= y <= height - 3 for x, y in xy):
            return False
        c_in, c_out, c_low, c_up = (_patch_rgb(image, x, y) for x, y in xy)
        for c in (c_out, c_low):
            if np.sum((c - c_in) ** 2) <= PROBE_NEARER * np.sum((c - c_up) ** 2) + PROBE_MIN_RGB**2:
                return False  # this end's surface goes on as soil
    return True


def ring_disagreement(
    region: np.ndarray,
    centre_px: tuple[float, float],
    r: float,
    k: float,
    b: float,
    sign: float,
) -> float:
    """Share, in [0, 1], of a ring just inside the rim where the wheel region (filled: holes
    are wheel) disagrees with the fitted model: not wheel above the equivalent line v = k u + b,
    wheel below it (nearest pixel; samples outside the image are left out)."""
    height, width = region.shape
    cx, cy = centre_px
    rho = r - max(RING_INSET_PX, RING_INSET * r)
    phi = np.linspace(0.0, 2.0 * np.pi, N_RING_SAMPLES, endpoint=False)
    u, v = rho * np.cos(phi), rho * np.sin(phi)
    x, y = cx + sign * u, cy + v
    seen = (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
    if not seen.any():
        return 0.0
    xi = np.clip(np.rint(x), 0, width - 1).astype(int)
    yi = np.clip(np.rint(y), 0, height - 1).astype(int)
    wheel = region[yi, xi] > 0
    return float(np.mean((wheel != (v < k * u + b))[seen]))


def image_implausibility(
    image: np.ndarray,
    region: np.ndarray,
    centre_px: tuple[float, float],
    r: float,
    line: tuple[float, float],
    a_uv: np.ndarray,
    b_uv: np.ndarray,
    sign: float,
) -> str:
    """Why the image does not show what the classic method's outputs describe ("" if it
    does): the filled wheel region against the rim circle and the equivalent line ``line`` =
    (k, b) on a ring just inside the rim (:func:`ring_disagreement`), and the soil surface
    beyond the rim at A and B (:func:`soil_ends_beyond_rim`). ``image`` uint8 RGB, ``region``
    the binary wheel region with its holes filled; the rest as :func:`soil_ends_beyond_rim`."""
    k, b = line
    ring = ring_disagreement(region, centre_px, r, k, b, sign)
    if ring > MAX_RING_DISAGREEMENT:
        return (
            "the wheel region disagrees with the rim circle and the soil line over "
            f"{100 * ring:.0f} % of the rim (more than a tenth): the binary image is not a "
            "wheel in soil (segmentation?)"
        )
    if soil_ends_beyond_rim(image, centre_px, r, k, a_uv, b_uv, sign):
        return (
            "the soil surface does not continue beyond the rim at the boundary's ends: the "
            "boundary is an edge on the wheel (dust or a shadow line?), not the soil surface"
        )
    return ""
