"""The default segmenter on wheels without hue, against the renderer's exact wheel mask; its
choice of features; its gradients against finite differences; the classic method's refusal."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax import Status, estimate_classic, synth
from sinkjax.rig import SegmentationParams
from sinkjax.soft.adaptive import AdaptiveSegmenter, texture
from sinkjax.soft.segmentation import wheel_mask
from sinkjax.soft.segmenter import FEATURES_HUE_SAT, FEATURES_INTENSITY
from sinkjax.synth.layers import WHEEL_LAYERS, coverage


def _scene(preset: str, seed: int = 3, width: int = 320, height: int = 240):
    rng = np.random.default_rng(seed)
    sc = synth.recording_scenes(rng, 1, preset=preset, width=width, height=height)[0]
    img, _ = synth.render(sc, seed)
    return sc, img, synth.rig_for(sc)


@pytest.mark.parametrize("preset", ["black_wheel", "metal_wheel"])
def test_mask_agrees_with_rendered_wheel(preset: str) -> None:
    sc, img, rig = _scene(preset)
    x = jnp.asarray(img, jnp.float64) / 255.0
    seg = AdaptiveSegmenter()
    mask = np.asarray(seg(x, rig.confidence_rect)) > 0.5
    truth = coverage(sc)[..., list(WHEEL_LAYERS)].sum(-1) > 0.5
    iou = (mask & truth).sum() / (mask | truth).sum()
    assert iou > 0.85
    assert int(seg.features(x, rig.confidence_rect)) == FEATURES_INTENSITY


def test_coloured_wheel_gets_the_paper_mask_exactly() -> None:
    _, img, rig = _scene("full")
    x = jnp.asarray(img, jnp.float64) / 255.0
    seg = SegmentationParams()
    rect = jnp.asarray(rig.confidence_rect, jnp.int32)
    got = jax.jit(lambda s, r: s(x, r))(AdaptiveSegmenter(seg), rect)
    ref = jax.jit(lambda s, r: wheel_mask(x, s, r))(seg, rect)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(ref))
    assert int(AdaptiveSegmenter(seg).features(x, rect)) == FEATURES_HUE_SAT


def test_texture_matches_numpy_windows() -> None:
    rng = np.random.default_rng(0)
    a = rng.uniform(size=(12, 14))
    got = np.asarray(texture(jnp.asarray(a), 3))
    pad = np.pad(a, 2, mode="edge")
    for i, j in [(0, 0), (5, 7), (11, 13), (3, 12)]:
        stds = [
            pad[2 + i + di : 2 + i + di + 3, 2 + j + dj : 2 + j + dj + 3].std()
            for di in (-2, 0)
            for dj in (-2, 0)
        ]
        assert got[i, j] == pytest.approx(min(stds), abs=1e-9)


@pytest.mark.parametrize("leaf", ["p_a_int", "p_chroma", "t_int"])
def test_gradient_of_mask_statistic_matches_finite_differences(leaf: str) -> None:
    _, img, rig = _scene("black_wheel")
    x = jnp.asarray(img[::2, ::2], jnp.float64) / 255.0
    rect = tuple(v // 2 for v in rig.confidence_rect)

    def stat(v: jnp.ndarray) -> jnp.ndarray:
        seg = AdaptiveSegmenter(**{leaf: v})
        return jnp.mean(seg(x, rect))

    x0 = jnp.asarray(float(getattr(AdaptiveSegmenter(), leaf)))
    g = float(jax.grad(stat)(x0))
    eps = 1e-6 * float(x0)
    fd = float((stat(x0 + eps) - stat(x0 - eps)) / (2 * eps))
    assert np.isfinite(g) and abs(g) > 1e-8
    assert g == pytest.approx(fd, rel=1e-4)


@pytest.mark.parametrize("preset", ["black_wheel", "metal_wheel"])
def test_classic_says_no_wheel_without_colour(preset: str) -> None:
    _, img, rig = _scene(preset)
    res = estimate_classic(img, rig, "f")
    assert res.status == Status.NO_WHEEL
    assert "no colour" in res.message and "soft" in res.message
    assert res.segmenter_features == "hue+saturation"  # what it tried
