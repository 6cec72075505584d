"""The segmenter interface: the threshold segmenter is exactly the paper's H/S mask, the
estimator takes any segmenter, and gradients reach a segmenter's leaves."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax import Segmenter, ThresholdSegmenter, measure
from sinkjax.rig import SegmentationParams
from sinkjax.soft.segmentation import BAND_WIDEN, wheel_mask


def _frame(draw_wheel) -> tuple[jnp.ndarray, tuple[int, int, int, int]]:
    img = jnp.asarray(draw_wheel(n_lugs=12, lug_h=4.0), dtype=jnp.float64) / 255.0
    return img, (140, 60, 40, 30)


def test_segmenter_is_abstract() -> None:
    with pytest.raises(TypeError):
        Segmenter()  # type: ignore[abstract]


def test_threshold_segmenter_equals_wheel_mask(draw_wheel) -> None:
    img, rect = _frame(draw_wheel)
    seg = SegmentationParams(p_d_sat=0.6, temperature_hue_deg=3.0)
    got = ThresholdSegmenter(seg)(img, rect)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(wheel_mask(img, seg, rect)))
    traced = jnp.asarray(rect, jnp.int32)
    # Under jit both ways compile the same computation (eager and jit differ in the last bit).
    got_t = jax.jit(lambda s, r: s(img, r))(ThresholdSegmenter(seg), traced)
    ref_t = jax.jit(lambda s, r: wheel_mask(img, s, r))(seg, traced)
    np.testing.assert_array_equal(np.asarray(got_t), np.asarray(ref_t))


@pytest.mark.slow
def test_default_segmenter_measures_a_coloured_wheel_as_the_threshold_mask(draw_wheel) -> None:
    # The default (adaptive) segmenter takes the H/S branch of a lax.cond on a coloured wheel:
    # the same computation, compiled in another context, so equal to float rounding.
    img, rect = _frame(draw_wheel)
    seg = SegmentationParams()
    a = measure(img, seg, rect=rect, wheel_radius_mm=100.0)
    b = measure(img, seg, rect=rect, wheel_radius_mm=100.0, segmenter=ThresholdSegmenter(seg))
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-12, atol=1e-12)
    assert int(a.status) == 0


def test_gradient_of_mask_statistic_matches_finite_differences(draw_wheel) -> None:
    img, rect = _frame(draw_wheel)

    def stat(p_a_sat: jnp.ndarray) -> jnp.ndarray:
        seg = SegmentationParams(p_a_sat=p_a_sat, temperature_sat=0.05)
        return jnp.mean(ThresholdSegmenter(seg)(img, rect))

    # The band's top at 1.3 S_w, where the drawn wheel's saturation gives the mean a slope
    # (the soft band is the paper's widened: its top is BAND_WIDEN * P_a * S_w).
    x0 = jnp.asarray(1.3 / BAND_WIDEN)
    g = float(jax.grad(stat)(x0))
    eps = 1e-5
    fd = float((stat(x0 + eps) - stat(x0 - eps)) / (2 * eps))
    assert abs(g) > 1e-6
    assert g == pytest.approx(fd, rel=1e-5)
