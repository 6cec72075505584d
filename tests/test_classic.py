"""The classic pipeline (sinkjax.classic.estimator) against independent references and drawn wheels.

The drawn wheels are supersampled analytic scenes (exact coverage anti-aliasing), so their rim,
soil line, z0 and angles are known exactly; no synthetic renderer is involved. Both modes are
tested: the paper's method (``refine=False``, the default) to integer-pixel tolerances, and the
sub-pixel refinement (``refine=True``) to tighter ones.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sinkjax.classic.estimator import _geometry_padded, estimate_classic
from sinkjax.classic.outline import hough_bin_px, hough_rim_np, rim_points, rim_scatter_px
from sinkjax.classic.segmentation import confidence_means_np, hard_mask, rgb_to_hsi_np
from sinkjax.geometry import rim_radius_range_px
from sinkjax.rig import Rig, SegmentationParams
from sinkjax.status import Status

BAD_IMAGE, BAD_RECT, FIT_FAILED = Status.BAD_IMAGE, Status.BAD_RECT, Status.FIT_FAILED
NO_CONTACT, NO_WHEEL, OK = Status.NO_CONTACT, Status.NO_WHEEL, Status.OK

# draw_wheel's (conftest) wheel colour, frame size and default rim.
WHEEL_RGB = (200, 40, 35)
W, H = 320, 240
CX, CY, R_PX = 160.3, 100.6, 85.4
R_MM = 140.0


def rig(travel: str = "right", rect=(150, 30, 24, 12)) -> Rig:
    return Rig(wheel_radius_mm=R_MM, confidence_rect=rect, travel=travel)


# --------------------------------------------------------------------------------------------
# Colour


def test_hsi_matches_per_pixel_reference(hsi_reference):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, size=(12, 17, 3), dtype=np.uint8)
    img[0, :3] = [[0, 0, 0], [128, 128, 128], [255, 255, 255]]
    h, s, i = rgb_to_hsi_np(img)
    assert h.dtype == s.dtype == i.dtype == np.float64
    for row in range(img.shape[0]):
        for col in range(img.shape[1]):
            ref = hsi_reference(*(float(v) / 255.0 for v in img[row, col]))
            got = (h[row, col], s[row, col], i[row, col])
            # Hue differences across 0/360 are the same angle.
            dh = (got[0] - ref[0] + 180.0) % 360.0 - 180.0
            assert abs(dh) < 1e-9 and got[1:] == pytest.approx(ref[1:], abs=1e-12)
    assert np.all((h >= 0) & (h < 360)) and np.all((s >= 0) & (s <= 1))


@pytest.mark.parametrize(
    ("rgb", "hue"),
    [
        ((1, 0, 0), 0.0),
        ((1, 1, 0), 60.0),
        ((0, 1, 0), 120.0),
        ((0, 1, 1), 180.0),
        ((0, 0, 1), 240.0),
        ((1, 0, 1), 300.0),
    ],
)
def test_hsi_primaries(rgb, hue):
    h, s, i = rgb_to_hsi_np(np.array([[rgb]], dtype=np.float64))
    assert h[0, 0] == pytest.approx(hue, abs=1e-9)
    assert s[0, 0] == pytest.approx(1.0)
    assert i[0, 0] == pytest.approx(sum(rgb) / 3)


def test_hsi_grey_and_black_are_finite_and_silent():
    img = np.array([[[0, 0, 0], [0.5, 0.5, 0.5], [1.0, 1.0, 1.0]]])
    with np.errstate(all="raise"):
        h, s, i = rgb_to_hsi_np(img)
    np.testing.assert_array_equal(h, 0.0)
    np.testing.assert_array_equal(s, 0.0)
    np.testing.assert_allclose(i, [[0.0, 0.5, 1.0]])


# --------------------------------------------------------------------------------------------
# Confidence means and the binary image


def test_confidence_means_is_circular_for_red():
    h = np.array([[350.0, 10.0, 355.0, 5.0]])
    s = np.array([[0.2, 0.4, 0.6, 0.8]])
    h_w, s_w = confidence_means_np(h, s, (0, 0, 4, 1))
    assert min(h_w, 360.0 - h_w) < 1e-9  # the arithmetic mean would be 180 (cyan)
    assert s_w == pytest.approx(0.5)


@pytest.mark.parametrize("rect", [(-1, 0, 2, 1), (3, 0, 2, 1), (0, 0, 4, 2), (0, 0, 0, 1)])
def test_confidence_means_rejects_rect_off_image(rect):
    with pytest.raises(ValueError, match="confidence rect"):
        confidence_means_np(np.zeros((1, 4)), np.zeros((1, 4)), rect)


def test_hard_mask_on_red_wheel(draw_wheel):
    img = draw_wheel(ss=1)
    h, s, _ = rgb_to_hsi_np(img)
    h_w, s_w = confidence_means_np(h, s, (150, 60, 24, 18))
    assert min(h_w, 360.0 - h_w) < 5.0
    mask = hard_mask(h, s, h_w, s_w, SegmentationParams())
    wheel = np.all(img == WHEEL_RGB, axis=-1)
    np.testing.assert_array_equal(mask, wheel)


def test_hard_mask_band_wraps_around_zero():
    h = np.array([[355.0, 5.0, 17.0, 19.0, 341.0, 343.0]])
    s = np.full_like(h, 0.5)
    mask = hard_mask(h, s, 0.0, 0.5, SegmentationParams())  # +-18 deg band
    np.testing.assert_array_equal(mask, [[True, True, True, False, False, True]])


# --------------------------------------------------------------------------------------------
# Rim points (shared by the Hough polish, the boundary margin and the refined rim)


def test_rim_points_keep_rim_drop_lug_tips_and_flanks():
    cx, cy, r = 50.0, 40.0, 30.0
    a = np.linspace(0.0, 2.0 * np.pi, 12, endpoint=False)
    out = np.column_stack([np.cos(a), np.sin(a)])
    # Residuals: inside the band, near its two ends, just beyond each end, a lug tip 3 px out.
    e = np.array([0.0, 0.4, -0.7, -1.49, 0.99, -1.51, 1.01, 3.0, 0.2, -0.3, 0.5, 0.1])
    pts = np.array([cx, cy]) + (r + e)[:, None] * out
    normals = -out
    # A lug flank: on the circle, but its normal 45 degrees off radial (cos 45 < 0.8).
    c, s_ = math.cos(math.pi / 4), math.sin(math.pi / 4)
    normals[8] = [c * normals[8, 0] - s_ * normals[8, 1], s_ * normals[8, 0] + c * normals[8, 1]]
    sel, res = rim_points(pts, normals, cx, cy, r)
    np.testing.assert_allclose(res, e, atol=1e-12)
    expected = [True, True, True, True, True, False, False, False, False, True, True, True]
    np.testing.assert_array_equal(sel, expected)
    # 8 rim points < 10: too few to tell, the default scatter.
    assert rim_scatter_px(pts, normals, cx, cy, r) == 0.5
    pts2 = np.concatenate([pts, pts[:5]])
    kept = np.concatenate([e[expected], e[:5]])
    mad = 1.4826 * np.median(np.abs(kept - np.median(kept)))
    normals2 = np.concatenate([normals, normals[:5]])
    assert rim_scatter_px(pts2, normals2, cx, cy, r) == pytest.approx(mad, abs=1e-12)


# --------------------------------------------------------------------------------------------
# Hough and the whole pipeline on drawn wheels

STRAIGHT_SOILS = [(165.2, 0.0), (150.7, 0.0), (160.4, 0.15), (170.9, -0.1)]


def straight_soil(y0: float, slope: float):
    return lambda x: y0 + slope * (x - CX)


def test_hough_spans_the_whole_plausible_radius_range():
    # 0.12-0.75 of min(H, W) in half-bin radius steps: more radius bins (152) than one OpenCV
    # filter call takes channels (128 in OpenCV 5). The rim, not the concentric lug tips 8 % out.
    a = np.linspace(0.0, 2.0 * np.pi, 720, endpoint=False)
    out = np.column_stack([np.cos(a), np.sin(a)])
    pts = np.concatenate([[CX, CY] + R_PX * out, [CX, CY] + 1.08 * R_PX * out])
    r_range = rim_radius_range_px(H, W)
    assert r_range == pytest.approx((0.12 * H, 0.75 * H))
    found = hough_rim_np(pts, -np.concatenate([out, out]), (H, W), r_range)
    assert found is not None
    bin_px = hough_bin_px(H, W)
    assert found[0] == pytest.approx(CX, abs=bin_px / 2)
    assert found[1] == pytest.approx(CY, abs=bin_px / 2)
    assert found[2] == pytest.approx(R_PX, abs=bin_px / 2)


@pytest.mark.parametrize(("n_lugs", "lug_h"), [(0, 0.0), (24, 8.0), (30, 3.0), (12, 8.5)])
@pytest.mark.parametrize("refine", [False, True])
def test_hough_finds_rim_not_lug_tips(n_lugs, lug_h, refine, draw_wheel):
    res = estimate_classic(
        draw_wheel(n_lugs=n_lugs, lug_h=lug_h, hole_r=40.0), rig(), refine=refine
    )
    assert res.status == OK, res.message
    # Lug tips are at r + lug_h (up to 10 % of r): the rim must come out, to well under a pixel.
    assert res.center_x_px == pytest.approx(CX, abs=0.25)
    assert res.center_y_px == pytest.approx(CY, abs=0.25)
    # The paper's rim goes through the outline's pixel centres, the last wheel pixels, which
    # lie half a pixel inside the drawn edge on average; the refined rim is on the edge itself.
    assert res.radius_px == pytest.approx(
        R_PX if refine else R_PX - 0.5, abs=0.25 if refine else 0.2
    )


def test_default_is_the_papers_method(draw_wheel):
    img = draw_wheel(soil=straight_soil(160.4, 0.15), n_lugs=20, lug_h=6.0)
    default, paper = estimate_classic(img, rig()), estimate_classic(img, rig(), refine=False)
    assert (default.sinkage_mm, default.theta1_deg, default.theta2_deg) == (
        paper.sinkage_mm,
        paper.theta1_deg,
        paper.theta2_deg,
    )
    refined = estimate_classic(img, rig(), refine=True)
    assert refined.sinkage_mm != paper.sinkage_mm
    # The paper's H/S test made the mask, in either mode (the run summary reports it).
    assert default.segmenter_features == refined.segmenter_features == "hue+saturation"


@pytest.mark.parametrize(("y0", "slope"), STRAIGHT_SOILS)
@pytest.mark.parametrize("travel", ["right", "left"])
def test_papers_method_on_straight_soil(y0, slope, travel, draw_wheel, line_truth):
    img = draw_wheel(soil=straight_soil(y0, slope), n_lugs=20, lug_h=6.0)
    res = estimate_classic(img, rig(travel))
    assert res.status == OK, res.message
    z0, t1, t2 = line_truth(CX, CY, R_PX, y0, slope)
    if travel == "left":
        t1, t2 = t2, t1
    # Integer pixels: the outline points of rim and soil both sit about half a pixel inside
    # their edges, which cancels in z0 to well under a pixel.
    assert res.sinkage_mm == pytest.approx(z0 * R_MM / R_PX, abs=0.5 * R_MM / R_PX)
    # A and B are the boundary's last points before the margin inside the rim (~1.3 px here)
    # plus the staircase: ~2 px inside it, which on this r = 85 px wheel, at 30-40 deg, is
    # up to ~2 deg short of where the soil meets the rim. Never long.
    for got, want in ((res.theta1_deg, t1), (res.theta2_deg, t2)):
        assert want - 2.0 <= got <= want + 0.3
    assert res.sinkage_std_mm is None and res.theta1_std_deg is None
    # What Eqs. 1-3 were given: integer outline points, every one counted once, and A, B the
    # boundary's extreme points on the entry and exit sides.
    ov = res.overlay
    assert ov is not None and ov.boundary_px is not None and ov.a_px and ov.b_px and ov.line_px
    pts = ov.boundary_px
    np.testing.assert_array_equal(pts, np.rint(pts))
    sign = 1.0 if travel == "right" else -1.0
    assert sign * ov.a_px[0] == max(sign * pts[:, 0])
    assert sign * ov.b_px[0] == min(sign * pts[:, 0])
    assert any(tuple(p) == ov.a_px for p in pts) and any(tuple(p) == ov.b_px for p in pts)
    k, b = np.polyfit(pts[:, 0], pts[:, 1], 1)
    for x, y in ov.line_px:
        assert y == pytest.approx(k * x + b, abs=1e-6)


@pytest.mark.parametrize(("y0", "slope"), STRAIGHT_SOILS)
@pytest.mark.parametrize("travel", ["right", "left"])
def test_refined_straight_soil_matches_analytic(y0, slope, travel, draw_wheel, line_truth):
    img = draw_wheel(soil=straight_soil(y0, slope), n_lugs=20, lug_h=6.0)
    res = estimate_classic(img, rig(travel), refine=True)
    assert res.status == OK, res.message
    z0, t1, t2 = line_truth(CX, CY, R_PX, y0, slope)
    if travel == "left":
        t1, t2 = t2, t1
    assert res.sinkage_mm == pytest.approx(z0 * R_MM / R_PX, rel=0.015)
    assert res.theta1_deg == pytest.approx(t1, abs=0.3)
    assert res.theta2_deg == pytest.approx(t2, abs=0.3)
    assert res.sinkage_std_mm is None and res.theta1_std_deg is None
    ov = res.overlay
    assert ov is not None and ov.boundary_px is not None and ov.boundary_px.shape[1] == 2
    assert ov.a_px is not None and res.center_x_px is not None and res.center_y_px is not None
    # A is on the entry side, on the rim.
    ax, ay = ov.a_px
    assert (ax - res.center_x_px) * (1 if travel == "right" else -1) > 0
    assert math.hypot(ax - res.center_x_px, ay - res.center_y_px) == pytest.approx(
        res.radius_px, abs=1e-6
    )


@pytest.mark.parametrize("y0", [155.3, 160.0])
def test_lightening_holes_cut_by_the_soil(y0, draw_wheel, line_truth):
    # The soil line crosses the lowest of six holes. The paper's method leaves it open: its
    # outline, above the soil line, counts as wheel-soil boundary and lifts the equivalent line
    # (4-8 % too much sinkage here). The refinement fills it from the intact holes' pattern.
    img = draw_wheel(soil=lambda x: y0 + 0.0 * x, n_holes=6, hole_r=9.0, ring=55.0)
    z0, t1, t2 = line_truth(CX, CY, R_PX, y0, 0.0)
    paper = estimate_classic(img, rig())
    assert paper.status == OK, paper.message
    assert paper.sinkage_mm > 1.02 * z0 * R_MM / R_PX
    res = estimate_classic(img, rig(), refine=True)
    assert res.status == OK, res.message
    assert res.sinkage_mm == pytest.approx(z0 * R_MM / R_PX, rel=0.01)
    assert res.theta1_deg == pytest.approx(t1, abs=0.3)
    assert res.theta2_deg == pytest.approx(t2, abs=0.3)


def test_boundary_equations_compile_once_per_bucket(draw_wheel):
    # Eqs. 1-3 run jitted on boundaries padded to a power of two: 3 soil levels -> 1-2 compiles.
    cache_size = _geometry_padded._cache_size  # type: ignore[attr-defined]
    before = cache_size()
    for y0 in (150.2, 150.6, 151.1):
        estimate_classic(draw_wheel(soil=lambda x, y0=y0: y0 + 0.0 * x, ss=2), rig())
    assert cache_size() - before <= 2


@pytest.mark.parametrize("refine", [False, True])
def test_no_contact(refine, draw_wheel):
    res = estimate_classic(draw_wheel(soil=lambda x: 200.0 + 0.0 * x), rig(), refine=refine)
    assert res.status == NO_CONTACT and res.message
    assert res.sinkage_mm == 0.0 and res.theta1_deg == 0.0 and res.theta2_deg == 0.0
    assert res.radius_px == pytest.approx(R_PX, abs=0.6)


def test_face_torn_above_the_centre(draw_wheel):
    # A washed-out patch on the upper rim (a lamp's glare) makes the outline dip inside the rim
    # above O; that is never soil. The refinement fails the frame instead of reporting a wrong
    # number; the paper's method takes the dip for boundary, and its plausibility check
    # (a boundary above the wheel centre) keeps that number from passing as ok.
    img = draw_wheel()
    yy, xx = np.mgrid[0:H, 0:W]
    glare = np.hypot(xx - 200.0, yy - 40.0) < 18.0
    img[glare] = (235, 225, 225)
    res = estimate_classic(img, rig(), refine=True)
    assert res.status == FIT_FAILED and "above the wheel centre" in res.message
    paper = estimate_classic(img, rig())
    assert paper.status == Status.IMPLAUSIBLE and paper.overlay is not None
    assert paper.overlay.boundary_px is not None
    assert paper.overlay.boundary_px[:, 1].min() < paper.center_y_px


def test_bad_rect(draw_wheel):
    res = estimate_classic(draw_wheel(ss=1), rig(rect=(310, 60, 24, 18)))
    assert res.status == BAD_RECT and "inside" in res.message
    assert res.segmenter_features is None  # never segmented


def test_no_wheel(draw_wheel):
    grey = np.full((H, W, 3), 120, np.uint8)
    res = estimate_classic(grey, rig())
    assert res.status == NO_WHEEL and res.message
    # The rectangle on the sky: a blob with no circular outline is not a wheel either.
    res = estimate_classic(draw_wheel(ss=1), rig(rect=(5, 5, 10, 10)))
    assert res.status not in (OK, NO_CONTACT) and res.message


def test_never_raises_on_bad_content(draw_wheel):
    rng = np.random.default_rng(1)
    images = [
        rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8),
        np.zeros((H, W, 3), np.uint8),
        np.full((H, W, 3), 255, np.uint8),
        np.zeros((40, 40, 3), np.uint8),
        draw_wheel(ss=1)[:, :170],  # half a wheel
    ]
    for img in images:
        res = estimate_classic(img, rig(rect=(20, 10, 8, 8)))
        assert res.status in (OK, NO_CONTACT, NO_WHEEL, FIT_FAILED, BAD_RECT)
        assert res.status == OK or res.message


@pytest.mark.parametrize("bad", [np.zeros((10, 10), np.uint8), np.zeros((10, 10, 3), np.float32)])
def test_bad_image(bad):
    res = estimate_classic(bad, rig(rect=(0, 0, 2, 2)))
    assert res.status == BAD_IMAGE and "uint8" in res.message
