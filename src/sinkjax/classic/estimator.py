"""The paper's classic pipeline, step by step, in float64 NumPy and OpenCV (no gradients).

"The Processes of Sinkage Detection" (docs/paper.md), as written, one module per stage
(``estimate_classic(image, rig)`` runs them in order):

1. confidence rectangle on the wheel face (the rig's ``confidence_rect``, docs/conventions.md §2);
2. RGB -> HSI (:func:`~sinkjax.classic.segmentation.rgb_to_hsi_np`, the textbook arccos formula,
   not OpenCV's HSV);
3. H_w, S_w over the rectangle (Eqs. 4-5), H and S ranges from P_a/P_d, binary image, then
   dilation, erosion, area filtering and filling of the enclosed holes
   (:mod:`sinkjax.classic.segmentation`);
4. the wheel outline (external contour, integer pixel centres), a 3-D Hough transform of it into
   (cx, cy, r) space for the rim circle (:mod:`sinkjax.classic.outline`), and the wheel-soil
   boundary = outline points closer to O than r (less a margin for the outline's pixel staircase
   along the rim);
5. Eqs. 1-3 (:func:`sinkjax.geometry.geometry_from_boundary`, docs/conventions.md §1): plain
   least squares of the boundary points, A and B the boundary's extreme points on the entry and
   exit sides.

The hue band is circular (see ``rig.HUE_SCALE_DEG``), the Hough rim is the inner envelope of the
outline (lugs stick out beyond it), and boundary runs that barely dip inside the margin over a
short stretch are rim noise, not soil (the paper extracts the boundary "according to its
morphological features"); otherwise this is the paper's method, the baseline that every other
estimator is measured against.

``refine=True`` adds what makes it measure well (:mod:`sinkjax.classic.refine`): lightening holes
cut open by the soil are filled from the intact ones' pattern, the outline is located to
sub-pixel precision on the colour profile and the rim refitted there, boundary points are weighted
by their x-extent in Eq. 1, A and B are carried along the boundary's end direction onto the rim,
and an outline dipping inside the rim above O fails loudly instead of reading as less sinkage.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import numpy as np

from ..geometry import (
    SinkageGeometry,
    geometry_from_boundary,
    rim_radius_range_px,
    travel_sign,
)
from ..result import FEATURE_CHOICES, FEATURES_HUE_SAT, FrameResult, Overlay, failed, no_contact
from ..rig import MIN_WHEEL_CHROMA, Rig, rim_hint_range_px
from ..status import Status
from .outline import (
    hough_bin_px,
    hough_rim_np,
    off_border,
    refine_rim,
    rim_scatter_px,
    runs_of,
    wheel_outline,
)
from .plausible import image_implausibility, implausibility
from .refine import ends_on_rim, refined_outline, x_extent_weights
from .segmentation import (
    check_rect,
    confidence_means_np,
    fill_holes,
    hard_mask,
    rgb_to_hsi_np,
    wheel_chroma_np,
    wheel_region,
)

# Least margin (px) inside the rim for an outline point to count as wheel-soil boundary; it grows
# with the scatter of the rim's outline points (staircase, noise, JPEG), see estimate_classic.
BOUNDARY_MARGIN_PX = 0.75
_MIN_WHEEL_PIXELS = 200
# Radii (fractions of min(H, W)) the Hough accumulator spans: a search window inside the plausible
# rim radii of rim_radius_range_px, which alone decides whether a rim is accepted. The radius bins
# are laid out from the window's lower end, so spanning the whole plausible range instead would
# move every bin and, through the peak's sub-bin estimate and the rim polish that starts from it,
# change the baseline's numbers (paper mode: 4 of the 160 benchmark frames, up to 0.07 mm, 0.3 deg).
HOUGH_WINDOW_FRAC = (0.15, 0.6)


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


def _searched(r_min: float, r_max: float, hinted: bool) -> str:
    """Which rim radii a failed search looked at, and how to change them (for its message)."""
    if hinted:
        return f"rim radii searched: {r_min:.0f}-{r_max:.0f} px, from the rig's rim_radius_px"
    return (
        f"rim radii searched: {r_min:.0f}-{r_max:.0f} px, fractions of the image size; set "
        "rim_radius_px in the rig if the rim's radius is outside"
    )


# --------------------------------------------------------------------------------------------
# The whole pipeline


def estimate_classic(
    image: np.ndarray,
    rig: Rig,
    name: str = "",
    *,
    refine: bool = False,
    recording_radius_px: float | None = None,
) -> FrameResult:
    """Sinkage and entry/exit angles of one frame by the paper's classic pipeline.

    ``image``: (H, W, 3) uint8 RGB; ``rig``: R (mm), confidence rectangle, travel and the P_d/P_a
    of ``rig.segmentation``. ``refine=False`` (the default) is the paper's method on the integer
    pixel outline; ``refine=True`` adds the refinements of :mod:`sinkjax.classic.refine` (module
    docstring). Returns a FrameResult: status ``ok`` or ``no_contact`` with sinkage (mm),
    theta1/theta2 (degrees), rim centre and radius (image px) and an overlay (rim, boundary
    points, equivalent-line ends, A, B in image px, of whichever mode ran); or ``bad_image`` /
    ``bad_rect`` / ``no_wheel`` / ``fit_failed`` with a message saying what went wrong. With
    ``refine``, ``fit_failed`` also covers a binary image that lost part of the wheel face (an
    outline dipping inside the rim above O), which would otherwise read as a wrong sinkage.
    Never raises for bad image content. The classic method has no uncertainty: the ``*_std_*``
    fields stay None. A result whose own outputs are implausible (:mod:`sinkjax.classic.plausible`:
    a boundary above O or short of the rim, a binary region that disagrees with the rim circle
    and soil line, a soil surface that goes on beyond the rim at neither end; with
    ``recording_radius_px``, the recording's rim radius, also a rim far from it) keeps its
    numbers under status ``implausible`` with the reason. Every frame that reaches step 2 says
    it was segmented by ``"hue+saturation"`` (``segmenter_features``), whatever its status.
    """
    result = _estimate(image, rig, name, refine, recording_radius_px)
    if result.status in (Status.BAD_IMAGE, Status.BAD_RECT):
        return result
    return dataclasses.replace(result, segmenter_features=FEATURE_CHOICES[FEATURES_HUE_SAT])


def _estimate(
    image: np.ndarray, rig: Rig, name: str, refine: bool, recording_radius_px: float | None
) -> FrameResult:
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        return failed(
            name,
            Status.BAD_IMAGE,
            f"expected an (H, W, 3) uint8 RGB image, got shape {img.shape} dtype {img.dtype}",
        )
    height, width = img.shape[:2]
    # Step 1: the confidence rectangle.
    try:
        rect = check_rect(rig.confidence_rect, img.shape)
    except ValueError as e:
        return failed(name, Status.BAD_RECT, str(e))
    # Step 2: HSI. Step 3: means, ranges, binary image, morphology.
    h_deg, s, _ = rgb_to_hsi_np(img)
    h_w, s_w = confidence_means_np(h_deg, s, rect)
    chroma = wheel_chroma_np(h_deg, s, rect)
    if chroma < MIN_WHEEL_CHROMA:
        # A black or bare-metal wheel: H_w is noise, and the H/S bands would select noise
        # that can still hold a circle, giving confidently wrong numbers.
        return failed(
            name,
            Status.NO_WHEEL,
            f"the wheel has no colour (mean chroma {chroma:.3f} < {MIN_WHEEL_CHROMA} at the "
            f"confidence rect {list(rect)}, S_w = {s_w:.3f}): the paper's hue/saturation test "
            "cannot see it; use the soft method (--method soft), which segments a black or "
            "metal wheel by intensity",
        )
    mask = hard_mask(h_deg, s, h_w, s_w, rig.segmentation)
    region = wheel_region(mask, rect)
    if region is None or np.count_nonzero(region) < _MIN_WHEEL_PIXELS:
        return failed(
            name,
            Status.NO_WHEEL,
            f"no wheel-coloured region at the confidence rect {list(rect)} (H_w = {h_w:.1f} deg, "
            f"S_w = {s_w:.3f}); check that the rectangle lies on the wheel face",
        )
    # Step 4: outline -> Hough rim -> boundary. Enclosed holes (lightening holes, hub,
    # highlights) are wheel: filled, they are no part of the outline.
    filled = fill_holes(region)
    contour, normals = wheel_outline(filled)
    inner = off_border(contour, img.shape)
    if np.count_nonzero(inner) < 50:
        return failed(
            name, Status.NO_WHEEL, "the wheel region's outline is too short to hold a rim"
        )
    m = min(height, width)
    # A rig's rim_radius_px hint replaces both the search window and the plausible range.
    hint = rim_hint_range_px(rig)
    window = hint or (HOUGH_WINDOW_FRAC[0] * m, HOUGH_WINDOW_FRAC[1] * m)
    r_min, r_max = hint or rim_radius_range_px(height, width)
    searched = _searched(r_min, r_max, hint is not None)
    coarse = hough_rim_np(contour[inner], normals[inner], (height, width), window)
    if coarse is None:
        return failed(
            name,
            Status.FIT_FAILED,
            f"the Hough transform found no rim circle in the outline ({searched})",
        )
    bc = hough_bin_px(height, width)
    cx, cy, r, n_in = refine_rim(
        contour[inner], normals[inner], coarse[0], coarse[1], coarse[2], band0_px=2.0 * bc
    )
    if not (np.isfinite([cx, cy, r]).all() and r_min <= r <= r_max):
        return failed(name, Status.FIT_FAILED, f"rim fit diverged (r = {r:.1f} px; {searched})")
    if n_in < 0.1 * 2.0 * math.pi * r:
        return failed(
            name,
            Status.FIT_FAILED,
            f"rim circle (r = {r:.1f} px) is supported by only {n_in} outline points; "
            f"the wheel's outline is not a circle (segmentation?) or not in range ({searched})",
        )
    rx, ry, rw, rh = rect
    if math.hypot(rx + 0.5 * (rw - 1) - cx, ry + 0.5 * (rh - 1) - cy) > r:
        return failed(
            name,
            Status.NO_WHEEL,
            f"the only circle in the outline of the region at the confidence rect (centre "
            f"({cx:.0f}, {cy:.0f}) px, r = {r:.0f} px) does not contain the rectangle; "
            "check that the rectangle lies on the wheel face",
        )
    if refine:
        pts, inner, cx, cy, r, sigma = refined_outline(img, region, cx, cy, r)
    else:
        pts, sigma = contour, rim_scatter_px(contour[inner], normals[inner], cx, cy, r)
    # Between lugs the outline runs along the rim, scattered by +-sigma: "closer than r" needs a
    # margin of a few sigma to leave those points out of the wheel-soil boundary.
    margin = min(max(BOUNDARY_MARGIN_PX, 4.0 * sigma), 3.0)
    sign = travel_sign(rig.travel)
    uv = np.column_stack([sign * (pts[:, 0] - cx), pts[:, 1] - cy])
    rho = np.hypot(uv[:, 0], uv[:, 1])
    inside = inner & (rho < r - margin)
    overlay = Overlay(centre_px=(cx, cy), radius_px=r)
    # Runs that barely dip inside the margin and are short are rim noise (a notch at a lug root,
    # a highlight on the rim edge), not soil: soil that reaches inside the rim either cuts in
    # deeper or spans a long chord.
    runs = [
        run
        for run in runs_of(inside)
        if r - rho[run].min() >= margin + 1.0 or np.ptp(uv[run, 0]) >= 0.05 * r
    ]
    if not runs:
        return no_contact(name, (cx, cy), r, overlay)
    idx = np.concatenate(runs)
    if refine:
        if uv[idx, 1].min() < 0.0:
            # Soil above the wheel centre: Eq. 1 (which takes |b|) would read it as less
            # sinkage, and the confidence rectangle, above the hub, would be buried. The binary
            # image has lost part of the wheel face instead; say so rather than report a number.
            return failed(
                name,
                Status.FIT_FAILED,
                "the wheel outline dips inside the rim above the wheel centre: the binary image "
                "lost part of the wheel face (shading, highlights or dust?); widen P_d/P_a or "
                "calibrate",
            )
        weight = x_extent_weights(pts, idx)
        a_uv, b_uv = ends_on_rim(uv, runs, r, reach_px=max(6.0 * margin, 0.1 * r))
    else:
        # Eq. 1 as written: every boundary point counts once. A and B: the boundary's ends, its
        # extreme points on the entry (+u) and exit (-u) sides.
        weight = np.ones(len(idx))
        a_uv = uv[idx[np.argmax(uv[idx, 0])]]
        b_uv = uv[idx[np.argmin(uv[idx, 0])]]
    geo = _geometry(pts[idx], weight, (cx, cy), r, a_uv, b_uv, rig.travel)
    z0 = float(geo.sinkage_px)
    t1 = math.degrees(float(geo.theta1_rad))
    t2 = math.degrees(float(geo.theta2_rad))
    if not all(math.isfinite(v) for v in (z0, t1, t2)):
        return failed(name, Status.FIT_FAILED, "Eqs. 1-3 gave a non-finite result")
    k, bb = float(geo.k), float(geo.b_px)

    line_uv = np.array([[b_uv[0], k * b_uv[0] + bb], [a_uv[0], k * a_uv[0] + bb]])
    to_img = lambda q: (float(sign * q[0] + cx), float(q[1] + cy))
    overlay = Overlay(
        centre_px=(cx, cy),
        radius_px=r,
        boundary_px=pts[idx].copy(),
        line_px=(to_img(line_uv[0]), to_img(line_uv[1])),
        a_px=to_img(a_uv),
        b_px=to_img(b_uv),
    )
    why = implausibility(uv[idx], a_uv, b_uv, r, margin, recording_radius_px)
    why = why or image_implausibility(img, filled, (cx, cy), r, (k, bb), a_uv, b_uv, sign)
    return FrameResult(
        image=name,
        status=Status.IMPLAUSIBLE if why else Status.OK,
        message=why,
        sinkage_mm=z0 * rig.wheel_radius_mm / r,
        theta1_deg=t1,
        theta2_deg=t2,
        center_x_px=cx,
        center_y_px=cy,
        radius_px=r,
        overlay=overlay,
    )


def recording_radius_px(results: list[FrameResult]) -> float | None:
    """The recording's rim radius: the median over its frames with a rim (None if none has)."""
    radii = [
        float(res.radius_px)
        for res in results
        if res.status in (Status.OK, Status.NO_CONTACT) and res.radius_px is not None
    ]
    return float(np.median(radii)) if radii else None
