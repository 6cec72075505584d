"""The soft outline stage (sinkjax.soft.outline) against analytic edges.

Masks and images are exact-coverage renderings (supersampled) of a disc or a half-plane, so the
edge each outline point should lie on is known in closed form.
"""

from __future__ import annotations

import dataclasses

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage

from sinkjax.soft.outline import (
    _bilinear_rgb,
    compact,
    default_capacity,
    extract_outline,
    refine_outline,
)
from sinkjax.soft.settings import SoftSettings

SETTINGS = SoftSettings()

H, W = 64, 72
CX, CY, R = 35.3, 31.6, 20.4  # a disc well inside the frame
WHEEL = np.array([0.80, 0.20, 0.15])  # inside colour
OUTSIDE = np.array([0.45, 0.50, 0.60])


# Compiled once for the (H, W) of this file: eager JAX compiles every primitive on first use,
# which costs more than the whole stage compiled.
_extract = jax.jit(
    lambda m, capacity=None: extract_outline(m, SETTINGS, capacity), static_argnames="capacity"
)
_refine = jax.jit(lambda image, o: refine_outline(image, o, SETTINGS))


def coverage(inside, ss: int = 8) -> np.ndarray:
    """(H, W) fraction of each pixel's area where ``inside(x, y)`` holds (pixel centres at
    integer coordinates), by ``ss`` x ``ss`` supersampling."""
    xs = (np.arange(W * ss) + 0.5) / ss - 0.5
    ys = (np.arange(H * ss) + 0.5) / ss - 0.5
    x, y = np.meshgrid(xs, ys)
    return inside(x, y).astype(np.float64).reshape(H, ss, W, ss).mean(axis=(1, 3))


def disc(r: float = R):
    return lambda x, y: np.hypot(x - CX, y - CY) <= r


def strong(o) -> np.ndarray:
    """Outline points that are confidently edge points."""
    return np.asarray(o.valid) & (np.asarray(o.weight) > 0.5)


def test_compact_is_nonzero_with_size() -> None:
    rng = np.random.default_rng(0)
    flags = jnp.asarray(rng.uniform(size=500) < 0.1)
    for size in (10, 45, 200):
        idx, count = jax.jit(compact, static_argnums=1)(flags, size)
        ref = jnp.nonzero(flags, size=size, fill_value=0)[0]
        np.testing.assert_array_equal(np.asarray(idx), np.asarray(ref))
        assert int(count) == int(np.sum(np.asarray(flags)))


def test_bilinear_rgb_is_scipy_map_coordinates() -> None:
    # Points inside, on the last row/column and beyond every side (clamped: mode "nearest").
    rng = np.random.default_rng(3)
    image = rng.uniform(size=(23, 31, 3))
    y = rng.uniform(-3.0, 26.0, size=(40, 7))
    x = rng.uniform(-3.0, 34.0, size=(40, 7))
    y[0, :3], x[0, :3] = [22.0, 0.0, 22.0], [30.0, 30.0, 0.0]  # exactly on the last row/column
    got = np.asarray(jax.jit(_bilinear_rgb)(jnp.asarray(image), jnp.asarray(y), jnp.asarray(x)))
    ref = np.stack(
        [
            scipy.ndimage.map_coordinates(image[..., c], [y, x], order=1, mode="nearest")
            for c in range(3)
        ],
        -1,
    )
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)


def test_disc_edge_is_subpixel_and_normals_radial() -> None:
    o = _extract(jnp.asarray(coverage(disc())))
    keep = strong(o)
    x, y = np.asarray(o.x_px)[keep], np.asarray(o.y_px)[keep]
    d = np.hypot(x - CX, y - CY)
    # One point per pixel step around the circumference, and nothing else.
    assert 0.9 * 2 * np.pi * R < keep.sum() < 1.6 * 2 * np.pi * R
    # The 50 % coverage contour is the circle itself: sub-pixel, not pixel-centre, accuracy.
    assert abs(np.median(d - R)) < 0.15
    assert np.max(np.abs(d - R)) < 0.5
    # Normals point from wheel to outside: along the outward radius.
    radial = ((x - CX) * np.asarray(o.nx)[keep] + (y - CY) * np.asarray(o.ny)[keep]) / d
    assert np.min(radial) > 0.97
    # Three pixels beyond a disc's edge there is no wheel; the disc is solid below its top edge.
    assert np.max(np.asarray(o.mask_beyond)[keep]) < 0.05
    top = keep & (np.asarray(o.ny) < -0.9)
    below = np.asarray(o.wheel_below_px)[top]
    chord = 2 * (CY - np.asarray(o.y_px)[top])  # wheel length under a top point, ~2 R
    np.testing.assert_allclose(below, chord - 3.0, atol=2.5)
    assert not bool(o.overflow)


@pytest.mark.parametrize("slope", [0.0, 0.3, -1.7])
def test_half_plane_edge_is_the_line(slope: float) -> None:
    # Wheel above the line y = y0 + slope (x - W/2): the wheel-soil boundary of the model.
    y0 = 30.37
    o = _extract(jnp.asarray(coverage(lambda x, y: y <= y0 + slope * (x - W / 2))))
    keep = strong(o)
    x, y = np.asarray(o.x_px)[keep], np.asarray(o.y_px)[keep]
    inner = (x > 6) & (x < W - 7) & (y > 6) & (y < H - 7)  # away from the frame's edge
    dist = (y - y0 - slope * (x - W / 2)) / np.hypot(1.0, slope)
    assert inner.sum() > 25
    assert abs(np.median(dist[inner])) < 0.1 and np.max(np.abs(dist[inner])) < 0.3
    n_ref = np.array([-slope, 1.0]) / np.hypot(1.0, slope)  # wheel -> soil: down the line
    dots = np.asarray(o.nx)[keep][inner] * n_ref[0] + np.asarray(o.ny)[keep][inner] * n_ref[1]
    assert np.min(dots) > 0.99
    # Soil below the boundary: no wheel under it in its column.
    assert np.max(np.asarray(o.wheel_below_px)[keep][inner]) < 0.5


def test_capacity_overflow_is_flagged() -> None:
    o = _extract(jnp.asarray(coverage(disc())), capacity=20)
    assert bool(o.overflow) and int(np.sum(np.asarray(o.valid))) == 20
    assert o.x_px.shape == (20,)
    assert default_capacity(H, W) == 6 * (H + W)


def _speckled_disc() -> tuple[np.ndarray, np.ndarray]:
    """The disc's mask with 2x2 speckles of wheel (patches of the wheel's colour on the wall)
    on a 4 px grid around it and 2x2 pinholes in its face; and the clean disc's."""
    rng = np.random.default_rng(0)
    clean = coverage(disc())
    speckle = np.zeros((H, W))
    for y in range(0, H - 1, 4):
        for x in range(0, W - 1, 4):
            if rng.random() < 0.5:
                speckle[y : y + 2, x : x + 2] = 1.0
    holes = np.zeros((H, W))
    for y, x in ((25, 30), (36, 40), (30, 25)):
        holes[y : y + 2, x : x + 2] = 1.0
    return np.maximum(clean, speckle * (clean == 0)) * (1.0 - holes), clean


def rim_points(o) -> tuple[np.ndarray, np.ndarray]:
    """Which valid outline points lie on the disc's rim, and their y."""
    k = np.asarray(o.valid)
    x, y = np.asarray(o.x_px)[k], np.asarray(o.y_px)[k]
    return np.abs(np.hypot(x - CX, y - CY) - R) < 0.6, y


def test_crowded_outline_keeps_the_rim_not_the_speckle() -> None:
    # Points are stored in raster order: a ridge over capacity used to keep the top rows'
    # speckle and drop the rim below them. Here 772 ridge points, capacity 300.
    mask, clean = _speckled_disc()
    everything = _extract(jnp.asarray(mask), capacity=10**4)
    assert int(np.sum(np.asarray(everything.valid))) > 2 * 300
    on_clean, y_clean = rim_points(_extract(jnp.asarray(clean)))
    o = _extract(jnp.asarray(mask), capacity=300)
    assert not bool(o.overflow)
    on, y = rim_points(o)
    bottom = lambda yy: yy > CY + 0.7 * R  # below the rows where speckle filled the capacity
    assert on.sum() >= 0.95 * on_clean.sum()
    assert np.sum(on & bottom(y)) >= 0.95 * np.sum(on_clean & bottom(y_clean))
    assert np.sum(~on) <= 0.05 * on.sum()  # speckle and pinhole edges are gone
    # Uncrowded (the default capacity holds all 772): every point kept, as before, bit for bit.
    kept = _extract(jnp.asarray(mask))
    n = int(np.sum(np.asarray(kept.valid)))
    assert n == int(np.sum(np.asarray(everything.valid)))
    leaves = zip(
        jax.tree_util.tree_leaves(kept), jax.tree_util.tree_leaves(everything), strict=True
    )
    for a, b in leaves:
        if np.ndim(a):
            np.testing.assert_array_equal(np.asarray(a)[:n], np.asarray(b)[:n])


def test_refine_moves_a_biased_mask_edge_onto_the_image_edge() -> None:
    # The mask's edge sits 1.3 px inside the wheel's (a threshold that does not fire at 50 %
    # coverage); the image's colours, mixed by coverage, put the edge back on the circle.
    cov = coverage(disc())
    image = cov[..., None] * WHEEL + (1.0 - cov[..., None]) * OUTSIDE
    o = _extract(jnp.asarray(coverage(disc(R - 1.3))))
    keep = strong(o)
    d_mask = np.hypot(np.asarray(o.x_px) - CX, np.asarray(o.y_px) - CY)[keep]
    assert np.median(d_mask) == pytest.approx(R - 1.3, abs=0.15)
    ref = _refine(jnp.asarray(image), o)
    d = np.hypot(np.asarray(ref.x_px) - CX, np.asarray(ref.y_px) - CY)[keep]
    assert abs(np.median(d - R)) < 0.1 and np.percentile(np.abs(d - R), 90) < 0.25
    # Only the positions move.
    np.testing.assert_array_equal(np.asarray(ref.nx), np.asarray(o.nx))
    np.testing.assert_array_equal(np.asarray(ref.weight), np.asarray(o.weight))


@pytest.mark.parametrize("shift", [2.5, -2.5, 0.6])
def test_refine_recentres_only_a_mask_edge_a_few_pixels_off(shift: float) -> None:
    # A colour cast that makes the background half wheel-coloured puts the mask's edge 2-3 px
    # outside the rim (dust, inside it). One profile centred there has a plateau on the edge's
    # own blur (here a Gaussian of 1 px) and stops short; each further profile, centred where the
    # last put the edge, closes most of the rest. A mask edge within a pixel keeps one profile.
    cov = cv2.GaussianBlur(coverage(disc()), (0, 0), 1.0)
    image = cov[..., None] * WHEEL + (1.0 - cov[..., None]) * OUTSIDE
    o = _extract(jnp.asarray(coverage(disc(R + shift))))
    keep = strong(o)

    def offset(passes: int) -> np.ndarray:
        settings = dataclasses.replace(SETTINGS, refine_passes=passes)
        ref = jax.jit(lambda im, o: refine_outline(im, o, settings))(jnp.asarray(image), o)
        return np.hypot(np.asarray(ref.x_px) - CX, np.asarray(ref.y_px) - CY)[keep] - R

    assert np.median(offset(0)) == pytest.approx(shift, abs=0.15)
    d = offset(3)
    if abs(shift) > 1.5:
        assert abs(np.median(offset(1))) > 0.8  # one profile: short by a third of the shift
        assert abs(np.median(d)) < 0.1 and np.percentile(np.abs(d), 90) < 0.12
    else:
        np.testing.assert_array_equal(d, offset(1))
        assert abs(np.median(d)) < 0.1


def test_refine_without_contrast_leaves_points() -> None:
    o = _extract(jnp.asarray(coverage(disc())))
    flat = jnp.full((H, W, 3), 0.4)
    ref = _refine(flat, o)
    np.testing.assert_array_equal(np.asarray(ref.x_px), np.asarray(o.x_px))
    np.testing.assert_array_equal(np.asarray(ref.y_px), np.asarray(o.y_px))


@pytest.mark.slow
def test_jit_equals_eager_and_vmap_equals_loop() -> None:
    masks = jnp.asarray(np.stack([coverage(disc()), coverage(disc(R - 3.1))]))
    cov = np.asarray(masks)[..., None]
    images = jnp.asarray(cov * WHEEL + (1.0 - cov) * OUTSIDE)

    def stage(image, mask):
        return refine_outline(image, extract_outline(mask, SETTINGS, capacity=400), SETTINGS)

    eager = stage(images[0], masks[0])
    jitted = jax.jit(stage)(images[0], masks[0])
    jax.tree.map(
        lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12), eager, jitted
    )
    batched = jax.vmap(stage)(images, masks)
    for i in range(2):
        one = stage(images[i], masks[i])
        jax.tree.map(
            lambda a, b, i=i: np.testing.assert_allclose(a[i], b, rtol=1e-12, atol=1e-12),
            batched,
            one,
        )


def test_gradients_finite_and_match_finite_differences() -> None:
    cov = coverage(disc())
    image = jnp.asarray(cov[..., None] * WHEEL + (1.0 - cov[..., None]) * OUTSIDE)
    mask = jnp.asarray(coverage(disc(R - 1.0)))

    def loss(image, mask):
        o = refine_outline(image, extract_outline(mask, SETTINGS, capacity=400), SETTINGS)
        return jnp.sum(o.weight * (o.x_px - CX) ** 2 + o.weight * (o.y_px - CY) ** 2)

    g_img, g_mask = jax.jit(jax.grad(loss, argnums=(0, 1)))(image, mask)
    loss = jax.jit(loss)
    assert np.all(np.isfinite(np.asarray(g_img))) and np.all(np.isfinite(np.asarray(g_mask)))
    assert np.abs(np.asarray(g_img)).max() > 0 and np.abs(np.asarray(g_mask)).max() > 0
    # The refined positions are linear in the pixels (a trapezoid integral): directional
    # derivative along a random image perturbation against central differences.
    direction = jnp.asarray(np.random.default_rng(2).normal(size=image.shape))
    eps = 1e-6
    fd = (loss(image + eps * direction, mask) - loss(image - eps * direction, mask)) / (2 * eps)
    ad = jnp.sum(g_img * direction)
    assert float(ad) == pytest.approx(float(fd), rel=1e-5)
