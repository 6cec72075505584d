"""Colour and segmentation stages against independent references (math.acos, the classic
pipeline's NumPy code), with the limits and gradients the soft method relies on."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax.classic.estimator import hard_mask, rgb_to_hsi_np
from sinkjax.rig import SegmentationParams
from sinkjax.soft.adaptive import AdaptiveSegmenter
from sinkjax.soft.colour import chromaticity, circular_mean_deg, rgb_to_hsi
from sinkjax.soft.segmentation import (
    box_weight,
    colour_weight,
    column_median,
    confidence_means,
    paper_mask,
    reference_mask,
    smooth,
    soft_mask,
    soft_open,
    wheel_mask,
)


def test_hsi_matches_textbook_and_classic(hsi_reference) -> None:
    rng = np.random.default_rng(0)
    px = rng.uniform(size=(400, 3))
    h, s, i = (np.asarray(a) for a in rgb_to_hsi(jnp.asarray(px)))
    ref = np.array([hsi_reference(*p) for p in px])
    np.testing.assert_allclose(h, ref[:, 0], atol=1e-7)
    np.testing.assert_allclose(s, ref[:, 1], atol=1e-10)
    np.testing.assert_allclose(i, ref[:, 2], atol=1e-12)
    hc, sc, _ = rgb_to_hsi_np(px.reshape(20, 20, 3))
    np.testing.assert_allclose(h / 360.0, hc.ravel() / 360.0, atol=1e-5)
    np.testing.assert_allclose(s, sc.ravel(), atol=1e-5)


@pytest.mark.parametrize(
    ("rgb", "hue"),
    [((1, 0, 0), 0), ((1, 1, 0), 60), ((0, 1, 0), 120), ((0, 1, 1), 180), ((0, 0, 1), 240)],
)
def test_primary_hues(rgb: tuple[int, int, int], hue: float) -> None:
    h, s, _ = rgb_to_hsi(jnp.asarray(rgb, dtype=float))
    assert float(h) == pytest.approx(hue, abs=1e-9)
    assert float(s) == pytest.approx(1.0)


def test_hsi_gradients_finite_at_grey_black_and_wrap() -> None:
    px = jnp.asarray(
        [[0.5, 0.5, 0.5], [0.0, 0.0, 0.0], [0.8, 0.1, 0.1 + 1e-9], [0.8, 0.1 + 1e-9, 0.1]]
    )
    for k in range(3):
        g = jax.jacrev(lambda p, k=k: rgb_to_hsi(p)[k])(px)
        assert np.all(np.isfinite(np.asarray(g)))


def test_circular_mean_of_red() -> None:
    hues = jnp.asarray([350.0, 355.0, 5.0, 10.0])
    m = float(circular_mean_deg(hues))
    assert min(m, 360 - m) == pytest.approx(0.0, abs=1e-9)


def test_soft_mask_tends_to_classic_mask() -> None:
    rng = np.random.default_rng(3)
    img = rng.uniform(size=(40, 50, 3))
    img[5:20, 5:30] = np.array([0.8, 0.15, 0.12]) + rng.normal(
        0, 0.03, (15, 25, 3)
    )  # a red wheel patch
    img = np.clip(img, 0, 1)
    rect = (8, 8, 15, 8)
    h, s, _ = rgb_to_hsi(jnp.asarray(img))
    h_w, s_w = confidence_means(h, s, rect)
    base = SegmentationParams()
    hc, sc, _ = rgb_to_hsi_np(img)
    hard = hard_mask(hc, sc, float(h_w), float(s_w), base)
    assert hard.sum() > 100  # the patch is found, across the 0/360 wrap
    cold = SegmentationParams(
        p_d_hue=base.p_d_hue,
        p_a_hue=base.p_a_hue,
        p_d_sat=base.p_d_sat,
        p_a_sat=base.p_a_sat,
        temperature_hue_deg=1e-6,
        temperature_sat=1e-8,
    )
    soft = np.asarray(soft_mask(h, s, h_w, s_w, cold))
    np.testing.assert_array_equal(soft > 0.5, hard)
    assert np.all((soft < 1e-6) | (soft > 1 - 1e-6))


def test_soft_mask_gradients_finite() -> None:
    rng = np.random.default_rng(4)
    img = jnp.asarray(rng.uniform(size=(12, 12, 3)))

    def total(seg: SegmentationParams) -> jnp.ndarray:
        h, s, _ = rgb_to_hsi(img)
        h_w, s_w = confidence_means(h, s, (2, 2, 4, 4))
        return jnp.sum(soft_mask(h, s, h_w, s_w, seg))

    g = jax.grad(total)(SegmentationParams())
    assert all(np.isfinite(float(v)) for v in jax.tree_util.tree_leaves(g))
    assert abs(float(g.p_a_sat)) > 0


def test_traced_rect_equals_sliced_rect_with_one_trace() -> None:
    # Hues on both sides of 0/360, so a plain (non-circular) mean would be far off.
    rng = np.random.default_rng(8)
    img = np.clip(rng.uniform(size=(20, 30, 3)), 0, 1)
    img[3:15, 4:25] = np.clip(np.array([0.8, 0.12, 0.14]) + rng.normal(0, 0.05, (12, 21, 3)), 0, 1)
    h, s, _ = rgb_to_hsi(jnp.asarray(img))
    traces = []

    @jax.jit
    def traced(rect):
        traces.append(1)
        return confidence_means(h, s, rect)

    for rect in [(4, 3, 21, 12), (0, 0, 30, 20), (10, 5, 1, 1), (29, 19, 1, 1)]:
        want = confidence_means(h, s, rect)
        got = traced(jnp.asarray(rect, jnp.int32))
        h_rad = np.radians(np.asarray(h)[rect[1] : rect[1] + rect[3], rect[0] : rect[0] + rect[2]])
        ref = math.degrees(math.atan2(np.sin(h_rad).mean(), np.cos(h_rad).mean())) % 360.0
        assert float(want[0]) == pytest.approx(ref, abs=1e-9)
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-9, atol=1e-9)
    assert len(traces) == 1


def test_confidence_rect_off_image_raises() -> None:
    z = jnp.zeros((10, 10))
    with pytest.raises(ValueError, match="extends beyond the 10x10 image"):
        confidence_means(z, z, (5, 5, 10, 2))


def test_smoothing_and_opening() -> None:
    m = jnp.ones((9, 9)) * 0.7
    np.testing.assert_allclose(np.asarray(smooth(m)), 0.7, atol=1e-12)
    spur = jnp.zeros((9, 9)).at[4, :].set(1.0).at[0:3, 0:3].set(1.0)
    opened = np.asarray(soft_open(spur, 1))
    assert opened[4].max() == 0.0  # a one-pixel line is removed
    assert opened[1, 1] == 1.0  # a 3x3 block survives


def test_chromaticity_is_the_hsi_hue_and_blind_to_brightness() -> None:
    rng = np.random.default_rng(11)
    px = rng.uniform(0.05, 1.0, size=(200, 3))
    q = np.asarray(chromaticity(jnp.asarray(px)))
    h, _, _ = rgb_to_hsi(jnp.asarray(px))
    np.testing.assert_allclose(
        np.degrees(np.arctan2(q[:, 1], q[:, 0])) % 360.0, np.asarray(h), atol=1e-7
    )
    np.testing.assert_allclose(np.asarray(chromaticity(jnp.asarray(0.3 * px))), q, atol=1e-12)
    g = jax.grad(lambda x: jnp.sum(chromaticity(x)))(jnp.zeros((2, 3)))
    assert np.all(np.isfinite(np.asarray(g)))


def _cast_scene() -> tuple[np.ndarray, tuple[int, int, int, int], np.ndarray]:
    # A wall tinted towards the wheel's hue (inside the paper's band), a wheel disc, soil below.
    rng = np.random.default_rng(5)
    img = np.empty((60, 80, 3))
    img[:] = (0.4, 0.62, 0.47)  # greenish wall, saturation about half the wheel's
    img[45:] = (0.55, 0.45, 0.35)  # soil
    yy, xx = np.mgrid[:60, :80]
    wheel = (yy - 30) ** 2 + (xx - 40) ** 2 < 14**2
    img[wheel] = (0.25, 0.7, 0.35)
    img = np.clip(img + rng.normal(0, 0.01, img.shape), 0, 1)
    return img, (34, 20, 12, 5), wheel


@pytest.mark.parametrize("n", [8960, 1023, 2])
def test_column_median_is_numpy_median_with_its_gradient(n: int) -> None:
    # Rounded values: many ties, as in a strip of 8-bit pixels.
    rng = np.random.default_rng(n)
    q = np.round(rng.normal(size=(n, 2)), 1)
    got = np.asarray(jax.jit(column_median)(jnp.asarray(q)))
    np.testing.assert_array_equal(got, np.median(q, axis=0))
    # The gradient is the sort-based median's: the middle one or two entries of each column.
    g = np.asarray(jax.grad(lambda a: jnp.sum(column_median(a)))(jnp.asarray(q)))
    g_ref = np.asarray(jax.grad(lambda a: jnp.sum(jnp.median(a, axis=0)))(jnp.asarray(q)))
    np.testing.assert_allclose(g.sum(axis=0), [1.0, 1.0])
    np.testing.assert_allclose(g.sum(axis=0), g_ref.sum(axis=0))
    for c in range(2):
        middle = np.sort(q[:, c])[[(n - 1) // 2, n // 2]]
        assert np.all(np.isin(q[g[:, c] > 0, c], middle))


def test_reference_veto_removes_a_cast_wall_and_keeps_the_wheel() -> None:
    img, rect, _ = _cast_scene()
    seg = SegmentationParams(p_d_sat=0.3)
    band = np.asarray(paper_mask(jnp.asarray(img), seg, rect))
    mask = np.asarray(wheel_mask(jnp.asarray(img), seg, rect))
    # Away from the wheel's edge (3 px), whose blurred pixels are mixtures.
    far = np.hypot(*np.mgrid[-30:30, -40:40]) > 17
    wall, soil = far.copy(), far.copy()
    wall[42:], soil[:48] = False, False
    assert band[wall].mean() > 0.8  # the paper's band takes the tinted wall for wheel
    assert mask[wall].max() < 0.05 and mask[soil].max() < 0.05
    inner = np.hypot(*np.mgrid[-30:30, -40:40]) < 12
    assert mask[inner].min() > 0.95
    traced = wheel_mask(jnp.asarray(img), seg, jnp.asarray(rect, jnp.int32))
    np.testing.assert_allclose(np.asarray(traced), mask, atol=1e-12)
    np.testing.assert_allclose(
        np.asarray(wheel_mask(jnp.asarray(img), seg, rect, reference=False)), band, atol=0
    )


def test_wheel_mask_gradients_finite_jit_and_vmap() -> None:
    img, rect, _ = _cast_scene()
    imgs = jnp.stack([jnp.asarray(img), jnp.asarray(img[:, ::-1])])
    r = jnp.asarray(rect, jnp.int32)

    def total(seg: SegmentationParams, x: jnp.ndarray) -> jnp.ndarray:
        return jnp.sum(jax.vmap(wheel_mask, in_axes=(0, None, None))(x, seg, r))

    gs, gx = jax.jit(jax.grad(total, argnums=(0, 1)))(SegmentationParams(p_d_sat=0.3), imgs)
    leaves = jax.tree_util.tree_leaves(gs)
    assert all(np.isfinite(float(v)) for v in leaves) and abs(float(gs.p_a_hue)) > 0
    assert np.all(np.isfinite(np.asarray(gx)))


def test_veto_fraction_keeps_dust_blends_when_relaxed() -> None:
    """Soil-coloured dust on the lower wheel blends the wheel's colour towards the soil's: the
    default veto removes it, a relaxed one (calibration's leaf) keeps it, and the veto's edge is
    where the rule puts it (NumPy: the blend's distance past the bisector, in separations)."""
    wall, soil, green = (
        np.array([0.5, 0.5, 0.5]),
        np.array([0.55, 0.42, 0.3]),
        np.array([0.25, 0.7, 0.35]),
    )
    dust = 0.15 * green + 0.85 * soil
    img = np.empty((60, 80, 3))
    img[:] = wall
    img[45:] = soil
    yy, xx = np.mgrid[:60, :80]
    wheel = (yy - 30) ** 2 + (xx - 40) ** 2 < 14**2
    img[wheel] = green
    img[wheel & (yy >= 36)] = dust
    rect = (34, 20, 12, 5)

    def chroma(rgb: np.ndarray) -> np.ndarray:
        r, g, b = rgb
        return np.array([2 * r - g - b, np.sqrt(3) * (g - b)]) / (r + g + b)

    def beyond(ref: np.ndarray) -> float:
        # How far past the bisector of wheel and ``ref`` the blend lies, in their separations.
        qw, qr, qd = chroma(green), chroma(ref), chroma(dust)
        sep = np.linalg.norm(qr - qw)
        return float((np.sum((qd - qw) ** 2) - np.sum((qd - qr) ** 2)) / (2 * sep) / sep)

    past = max(beyond(soil), beyond(wall))
    assert 0.3 < past < 0.9
    inside = wheel & (yy >= 38) & (yy <= 41) & (np.abs(xx - 40) < 6)  # away from every edge
    x = jnp.asarray(img)

    def veto(fraction: float) -> np.ndarray:
        return np.asarray(reference_mask(x, rect, fraction))

    assert veto(0.25)[inside].max() < 0.05
    assert veto(1.0)[inside].min() > 0.95
    assert veto(past - 0.05)[inside].max() < 0.5 < veto(past + 0.05)[inside].min()
    g = jax.grad(lambda f: jnp.sum(reference_mask(x, rect, f) * jnp.asarray(inside, x.dtype)))(past)
    assert np.isfinite(float(g)) and float(g) > 0
    assert float(SegmentationParams().veto_fraction) == 0.25


def _glow_scene(glow_cols: int) -> tuple[np.ndarray, tuple[int, int, int, int], np.ndarray]:
    """A wheel (a disc of radius 30, a saturated blue-green) on a grey wall over brown soil,
    its confidence rectangle (20 x 8) in a lamp's glow: white (every channel at the sensor's
    top) over the rectangle's first ``glow_cols`` columns, and 3 px around them."""
    face = np.array([0.15, 0.55, 0.6])
    img = np.empty((90, 120, 3))
    img[:] = 0.5
    img[70:] = (0.55, 0.42, 0.3)
    yy, xx = np.mgrid[:90, :120]
    img[(yy - 40) ** 2 + (xx - 60) ** 2 < 30**2] = face
    rect = (50, 25, 20, 8)
    if glow_cols:
        img[22:36, 47 : 50 + glow_cols + 3] = 1.0
    return img, rect, face


@pytest.mark.parametrize("glow_cols", [12, 20])
def test_a_glow_on_the_rectangle_does_not_give_the_wheel_its_colour(
    glow_cols: int, hsi_reference
) -> None:
    """H_w and S_w are the face's own (Gonzalez & Woods' HSI of its colour) whether the glow
    clips 60 % of the rectangle (its unclipped pixels are the face) or all of it (the face
    around the rectangle, grown by its own size); the default segmenter then sees the wheel by
    its hue, not as a grey one."""
    img, rect, face = _glow_scene(glow_cols)
    x = jnp.asarray(img)
    h, s, _ = rgb_to_hsi(x)
    h_w, s_w = confidence_means(h, s, rect, colour_weight(x, rect))
    h_ref, s_ref, _ = hsi_reference(*face)
    assert float(h_w) == pytest.approx(h_ref, abs=1e-3)
    assert float(s_w) == pytest.approx(s_ref, abs=1e-4)
    # As the paper has it (the rectangle's own pixels) the glow's white decides.
    assert float(confidence_means(h, s, rect)[1]) < 0.6 * s_ref
    seg = AdaptiveSegmenter()
    assert bool(seg.coloured(x, rect))
    mask = np.asarray(seg(x, jnp.asarray(rect, jnp.int32)))
    yy, xx = np.mgrid[:90, :120]
    d = np.hypot(yy - 40, xx - 60)
    assert mask[(d < 26) & (yy > 40)].min() > 0.9  # the face below the glow
    assert mask[d > 34].max() < 0.1  # wall and soil


@pytest.mark.parametrize("face", [(0.15, 0.55, 0.6), (0.1, 0.25, 1.0)])
def test_a_rectangle_without_a_glow_is_read_as_before(face: tuple[float, ...]) -> None:
    """No pixel clipped, or one channel only (a saturated blue wheel's own primary at the
    sensor's top keeps its hue): the rectangle's own pixels, exactly."""
    img, rect, _ = _glow_scene(0)
    img[(np.hypot(*np.mgrid[-40:50, -60:60]) < 30)] = face
    x = jnp.asarray(img)
    np.testing.assert_array_equal(
        np.asarray(colour_weight(x, rect)),
        np.asarray(box_weight(jnp.asarray(rect), 90, 120, x.dtype)),
    )
