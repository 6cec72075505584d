"""The classic pipeline's stages (sinkjax.classic.outline, sinkjax.classic.refine), one by one.

References: analytic circles and lines, SciPy (binary hole filling, geometric least squares) and
OpenCV's own morphology, all independent of the code under test.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy import ndimage
from scipy.optimize import least_squares

from sinkjax.classic.outline import (
    fit_circle,
    hough_rim_np,
    off_border,
    refine_rim,
    runs_of,
    wheel_outline,
)
from sinkjax.classic.refine import ends_on_rim, subpixel_edges, x_extent_weights
from sinkjax.classic.segmentation import fill_holes, wheel_region

H, W = 240, 320
CX, CY, R = 160.3, 100.6, 85.4  # conftest's draw_wheel default rim
WHEEL_RGB = (200, 40, 35)


def disc_mask(cx: float = CX, cy: float = CY, r: float = R) -> np.ndarray:
    """(H, W) bool: pixel centres inside the circle."""
    yy, xx = np.mgrid[0:H, 0:W]
    return np.hypot(xx - cx, yy - cy) <= r


def wheel_mask(draw_wheel, **kw) -> np.ndarray:
    """The binary image of a drawn wheel: pixels at least half covered by it (its colour is far
    from sky and soil in red, so the red channel measures coverage)."""
    img = draw_wheel(**kw).astype(np.float64)
    sky_r = 70.0
    return (img[..., 0] - sky_r) / (WHEEL_RGB[0] - sky_r) >= 0.5


# ----------------------------------------------------------------------------- binary image


def test_wheel_region_keeps_the_wheel_component() -> None:
    mask = disc_mask(r=60.0)
    mask[:, 158] = False  # a one-pixel crack through the wheel: closing bridges it
    mask[10:14, 10:14] = True  # a speck away from it: another component
    mask[100, 222] = True  # a one-pixel spur on the wheel's edge: the opening drops it
    region = wheel_region(mask, (150, 90, 20, 20))
    assert region is not None and region.dtype == bool
    # Reference: OpenCV's closing then opening of the mask, and its labelling, done here.
    k = np.ones((3, 3), np.uint8)
    ref = cv2.morphologyEx(
        cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, k), cv2.MORPH_OPEN, k
    )
    _, labels = cv2.connectedComponents(ref, connectivity=8)
    np.testing.assert_array_equal(region, labels == labels[100, 160])
    assert not region[10:14, 10:14].any() and region[:, 158].sum() > 100
    assert not region[100, 222]
    assert wheel_region(mask, (0, 200, 10, 10)) is None  # rectangle on no component
    assert wheel_region(np.zeros((H, W), bool), (150, 90, 20, 20)) is None


def test_fill_holes_matches_scipy() -> None:
    region = disc_mask(r=70.0)
    yy, xx = np.mgrid[0:H, 0:W]
    for k in range(5):  # lightening holes and a hub
        a = 2 * np.pi * k / 5
        region &= np.hypot(xx - CX - 45 * np.cos(a), yy - CY - 45 * np.sin(a)) > 9
    region &= np.hypot(xx - CX, yy - CY) > 12
    filled = fill_holes(region)
    np.testing.assert_array_equal(filled, ndimage.binary_fill_holes(region))
    np.testing.assert_array_equal(filled, disc_mask(r=70.0))


# ----------------------------------------------------------------------------- outline


def test_wheel_outline_is_the_border_with_inward_normals() -> None:
    region = disc_mask()
    pts, normals = wheel_outline(region)
    # Reference: the region's pixels with a 4-neighbour outside it (OpenCV erosion by a cross).
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    border = region & ~cv2.erode(region.astype(np.uint8), cross).astype(bool)
    got = {(int(x), int(y)) for x, y in pts}
    assert got == {(int(x), int(y)) for y, x in zip(*np.nonzero(border), strict=True)}
    d = np.hypot(pts[:, 0] - CX, pts[:, 1] - CY)
    assert np.all((d <= R) & (d > R - 1.5))  # border pixel centres: just inside the rim
    inward = -((pts[:, 0] - CX) * normals[:, 0] + (pts[:, 1] - CY) * normals[:, 1]) / d
    assert np.min(inward) > 0.9
    np.testing.assert_allclose(np.hypot(normals[:, 0], normals[:, 1]), 1.0, atol=1e-9)
    empty_pts, empty_n = wheel_outline(np.zeros((H, W), bool))
    assert empty_pts.shape == empty_n.shape == (0, 2)


def test_off_border() -> None:
    pts = np.array([[0, 5], [1, 5], [318, 5], [319, 5], [5, 0], [5, 1], [5, 238], [5, 239]])
    np.testing.assert_array_equal(
        off_border(pts.astype(float), (H, W)), [False, True, True, False] * 2
    )


@pytest.mark.parametrize(("n_lugs", "lug_h"), [(0, 0.0), (20, 6.0), (30, 8.0)])
def test_hough_then_refine_find_the_rim(draw_wheel, n_lugs: int, lug_h: float) -> None:
    soil_y = CY + 60.0
    region = wheel_mask(draw_wheel, n_lugs=n_lugs, lug_h=lug_h, soil=lambda x: soil_y + 0 * x)
    pts, normals = wheel_outline(region)
    inner = off_border(pts, region.shape)
    coarse = hough_rim_np(pts[inner], normals[inner], (H, W), (0.2 * H, 0.6 * H))
    assert coarse is not None
    cx, cy, r, votes = coarse
    bc = max(2.0, min(H, W) / 120.0)  # centre bin; radius bins are half that
    # The rim, not the lug tips (r + lug_h), to within a bin.
    assert abs(cx - CX) < bc and abs(cy - CY) < bc and abs(r - (R - 0.5)) < bc
    assert votes > 100
    cx, cy, r, n_in = refine_rim(pts[inner], normals[inner], cx, cy, r, 2 * bc)
    # Border pixel centres lie half a pixel inside the drawn edge on average.
    assert cx == pytest.approx(CX, abs=0.2) and cy == pytest.approx(CY, abs=0.2)
    assert r == pytest.approx(R - 0.5, abs=0.2)
    # Only rim points are inliers: the visible rim is above the soil, between the lugs.
    visible = 2 * np.pi - 2 * math.acos((soil_y - CY) / R)
    assert 0.3 * visible * R < n_in < 1.2 * visible * R


def test_hough_without_votes_is_none() -> None:
    pts = np.array([[5.0, 5.0]])
    away = np.array([[-1.0, 0.0]])  # votes land off the image
    assert hough_rim_np(pts, away, (H, W), (50.0, 60.0)) is None


def test_fit_circle_is_the_geometric_least_squares_circle() -> None:
    rng = np.random.default_rng(0)
    t = rng.uniform(-2.8, -0.3, 200)  # an arc, as the rim above the soil
    pts = np.stack([50 + 30 * np.cos(t), 40 + 30 * np.sin(t)], 1) + rng.normal(0, 0.4, (200, 2))
    got = fit_circle(pts, 52.0, 43.0, 27.0)
    fun = lambda p: np.hypot(pts[:, 0] - p[0], pts[:, 1] - p[1]) - p[2]
    ref = least_squares(fun, [52.0, 43.0, 27.0], xtol=1e-14, ftol=1e-14).x
    np.testing.assert_allclose(got, ref, atol=1e-6)
    np.testing.assert_allclose(got, [50, 40, 30], atol=0.5)


# ----------------------------------------------------------------------------- refinements


def test_subpixel_edges_lie_on_the_drawn_circle(draw_wheel) -> None:
    rgb = draw_wheel(soil=lambda x: 1e9 + 0 * x)  # no soil: the whole rim is visible
    region = wheel_mask(draw_wheel, soil=lambda x: 1e9 + 0 * x)
    pts, normals = wheel_outline(region)
    edge = subpixel_edges(rgb, pts, normals)
    d_pix = np.hypot(pts[:, 0] - CX, pts[:, 1] - CY)
    d = np.hypot(edge[:, 0] - CX, edge[:, 1] - CY)
    # Pixel centres are up to a pixel inside; the colour profile's half point is on the circle.
    assert np.median(R - d_pix) > 0.3
    assert abs(np.median(d - R)) < 0.05 and np.percentile(np.abs(d - R), 95) < 0.2
    # Points move only along their normals.
    step = edge - pts
    cross = step[:, 0] * normals[:, 1] - step[:, 1] * normals[:, 0]
    np.testing.assert_allclose(cross, 0.0, atol=1e-9)


def test_x_extent_weights_integrate_over_x() -> None:
    region = disc_mask(r=40.0)
    pts, _ = wheel_outline(region)
    idx = np.arange(len(pts))
    w = x_extent_weights(pts, idx)
    assert np.all(w > 0)
    # Every x-step of the closed outline is shared by its two ends: the weights add up to the
    # total x-travel around the outline, twice the disc's width in pixel centres.
    width = pts[:, 0].max() - pts[:, 0].min()
    assert w.sum() == pytest.approx(2 * width, abs=1e-3)
    # A vertical run of a staircase covers no x at all.
    stairs = np.array([[0, 0], [1, 0], [1, 1], [1, 2], [2, 2], [3, 2]], float)
    np.testing.assert_allclose(
        x_extent_weights(stairs, np.arange(6)),
        [0.5 * (3 + 1), 0.5, 0.0, 0.5, 1.0, 0.5 * (1 + 3)],
        atol=2e-6,
    )


@pytest.mark.parametrize("slope", [0.0, 0.2])
def test_ends_carried_onto_the_rim(slope: float) -> None:
    # Boundary v = b + slope u (wheel frame, y down), stopped 3 px short of the rim |q| = r.
    r, b = 80.0, 45.0
    qa, qb, qc = 1 + slope**2, 2 * slope * b, b * b - r * r
    u_a = (-qb + math.sqrt(qb * qb - 4 * qa * qc)) / (2 * qa)
    u_b = (-qb - math.sqrt(qb * qb - 4 * qa * qc)) / (2 * qa)
    u = np.linspace(u_b + 3, u_a - 3, 200)
    uv = np.stack([u, b + slope * u], 1)
    runs = [np.arange(0, 120), np.arange(120, 200)]  # a gap in the middle: two runs
    a, bb = ends_on_rim(uv, runs, r, reach_px=10.0)
    np.testing.assert_allclose(a, [u_a, b + slope * u_a], atol=1e-9)
    np.testing.assert_allclose(bb, [u_b, b + slope * u_b], atol=1e-9)
    # Beyond reach: the radial projection of the end instead.
    a_far, _ = ends_on_rim(uv, runs, r, reach_px=1.0)
    np.testing.assert_allclose(a_far, uv[-1] * r / np.hypot(*uv[-1]), atol=1e-9)


def test_runs_of_join_across_the_seam() -> None:
    flags = np.array([1, 1, 0, 0, 1, 1, 1, 0, 1], bool)
    assert [r.tolist() for r in runs_of(flags)] == [[4, 5, 6], [8, 0, 1]]
    assert runs_of(np.zeros(4, bool)) == [] and [r.tolist() for r in runs_of(np.ones(3, bool))] == [
        [0, 1, 2]
    ]
