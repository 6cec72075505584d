"""Low light (soft/denoise.py): the noise measured in the confidence rectangle, the blur against
OpenCV's, and the mask of a dim coloured wheel against the renderer's exact wheel."""

from __future__ import annotations

import math

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax import synth
from sinkjax.soft.adaptive import AdaptiveSegmenter
from sinkjax.soft.denoise import (
    RATIO_OFF,
    RATIO_ON,
    _gauss_axis,
    blur_sigma_px,
    denoise,
    noise_ratio,
    sigma_factor,
)
from sinkjax.soft.estimator import measure, measure_from_mask
from sinkjax.soft.segmentation import wheel_mask
from sinkjax.synth.hard import HARD_PRESETS
from sinkjax.synth.layers import WHEEL_LAYERS, coverage
from sinkjax.synth.recording import frame_seed


@pytest.mark.parametrize("sigma", [0.004, 0.02, 0.05])
def test_noise_ratio_against_the_noise_put_in(sigma: float) -> None:
    """A flat coloured face with Gaussian noise of known sigma: the ratio is sqrt(3/2) sigma over
    the face's opponent chroma, to the sampling error of 1024 differences (~5 %)."""
    rng = np.random.default_rng(3)
    colour = np.array([0.30, 0.22, 0.10])
    img = colour + sigma * rng.standard_normal((120, 160, 3))
    q1 = colour[0] - 0.5 * (colour[1] + colour[2])
    q2 = math.sqrt(3) / 2 * (colour[1] - colour[2])
    expected = math.sqrt(1.5) * sigma / math.hypot(q1, q2)
    got = float(noise_ratio(jnp.asarray(img), jnp.asarray([40, 30, 64, 32])))
    assert got == pytest.approx(expected, rel=0.1)


def test_blur_matches_opencv() -> None:
    rng = np.random.default_rng(0)
    img = rng.random((60, 80, 3))
    for s in (1.0, 2.5, 5.0):
        sig = jnp.asarray(s)
        ours = np.asarray(_gauss_axis(_gauss_axis(jnp.asarray(img), sig, 0), sig, 1))
        ref = cv2.GaussianBlur(img, (37, 37), s, borderType=cv2.BORDER_REPLICATE)
        np.testing.assert_allclose(ours, ref, atol=1e-6)


def test_clean_frame_is_returned_unchanged() -> None:
    rng = np.random.default_rng(1)
    sc = synth.recording_scenes(rng, 1, preset="full", width=320, height=240)[0]
    img, _ = synth.render(sc, 1)
    x = jnp.asarray(img, jnp.float64) / 255.0
    rect = jnp.asarray(synth.rig_for(sc).confidence_rect)
    assert float(noise_ratio(x, rect)) < 0.15
    np.testing.assert_array_equal(np.asarray(denoise(x, rect)), np.asarray(x))


def _dim_frame(seed: int) -> tuple[np.ndarray, jnp.ndarray, np.ndarray, object]:
    rng = np.random.default_rng(seed)
    sc = synth.recording_scenes(rng, 1, preset="hard_lowlight", width=320, height=240)[0]
    key = seed * 1000 + HARD_PRESETS.index("hard_lowlight") * 100
    img, t = synth.render(sc, seed=frame_seed(key, 0))
    truth = coverage(sc)[..., list(WHEEL_LAYERS)].sum(-1) > 0.5
    return img, jnp.asarray(synth.rig_for(sc).confidence_rect), truth, t


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def test_dim_wheel_mask_against_rendered_truth() -> None:
    """Dim coloured wheels (hard_lowlight, 320x240): where the noise turns the blur on, the default
    mask of the blurred frame matches the renderer's wheel at least as well as the H/S mask of
    the raw frame, clearly better where it is fully on; elsewhere it is that mask exactly."""
    seg = AdaptiveSegmenter()
    raw_mask = jax.jit(lambda x, r: wheel_mask(x, seg.seg, r))
    ours = jax.jit(lambda x, r: seg(x, r))
    gains, on = [], 0
    for seed in range(1, 13):
        img, rect, truth, _ = _dim_frame(seed)
        x = jnp.asarray(img, jnp.float64) / 255.0
        assert int(seg.features(x, rect)) == 0, seed  # the H/S test: a coloured wheel
        ratio = float(noise_ratio(x, rect))
        a, b = np.asarray(raw_mask(x, rect)), np.asarray(ours(x, rect))
        if ratio <= RATIO_OFF:
            np.testing.assert_array_equal(a, b)
            continue
        on += 1
        assert 1.0 <= float(blur_sigma_px(jnp.asarray(ratio))) <= 6.0
        before, after = _iou(a > 0.5, truth), _iou(b > 0.5, truth)
        assert after >= before, seed
        if ratio > RATIO_ON:
            gains.append(after - before)
    assert on >= 6 and len(gains) >= 3
    assert np.mean(gains) > 0.02, gains


@pytest.mark.heavy
def test_sigma_widens_with_the_blur() -> None:
    """The estimate of a blurred frame carries the blur's sigma factor (1 without a blur): the
    same mask measured as if unblurred has smaller sigmas, by at most that factor (the line's
    shift, which the blur does not touch, is added in quadrature after it)."""
    assert float(sigma_factor(jnp.asarray(0.0))) == 1.0
    seg = AdaptiveSegmenter()
    img, rect, _, _ = _dim_frame(5)
    x = jnp.asarray(img, jnp.float64) / 255.0
    blur = float(seg.blur_px(x, rect))
    assert blur > 1.0
    est = measure(x, seg.seg, rect=rect, segmenter=seg)
    plain = measure_from_mask(x, seg(x, rect), features=seg.features(x, rect))
    assert float(est.sinkage_mm) == pytest.approx(float(plain.sinkage_mm), abs=1e-9)
    names = ("sinkage_std_mm", "theta1_std_rad", "theta2_std_rad")
    ratio = np.array([float(getattr(est, n)) / float(getattr(plain, n)) for n in names])
    factor = (1.0 + blur * blur) ** 0.25
    assert np.all(ratio > 1.1) and np.all(ratio <= factor + 1e-9), (ratio, factor)


def test_vmap_of_a_clean_and_a_dim_frame_equals_each_alone() -> None:
    """Under vmap the blur's lax.cond becomes a select of both branches: a batch of a clean
    frame (no blur) and a dim one (blurred) gives each frame's own mask and blur."""
    seg = AdaptiveSegmenter()
    rng = np.random.default_rng(1)
    sc = synth.recording_scenes(rng, 1, preset="full", width=320, height=240)[0]
    clean, _ = synth.render(sc, 1)
    rect = jnp.asarray(synth.rig_for(sc).confidence_rect)
    dim, _, _, _ = _dim_frame(5)
    xs = jnp.asarray(np.stack([clean, dim]), jnp.float64) / 255.0
    masks = jax.vmap(seg, in_axes=(0, None))(xs, rect)
    blurs = jax.vmap(seg.blur_px, in_axes=(0, None))(xs, rect)
    for i in range(2):
        np.testing.assert_allclose(np.asarray(masks[i]), np.asarray(seg(xs[i], rect)), atol=1e-12)
        assert float(blurs[i]) == pytest.approx(float(seg.blur_px(xs[i], rect)), abs=1e-12)
    assert float(blurs[0]) == 0.0 < float(blurs[1])
