"""The soil's step (soft.soil_step) against the renderer's exact surface."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from sinkjax import synth
from sinkjax.soft.adaptive import AdaptiveSegmenter
from sinkjax.soft.estimator import rig_arrays
from sinkjax.soft.soil_step import soil_step
from sinkjax.synth.scene import surface_y_px


@jax.jit
def _masks(image_u8: jax.Array, rect: jax.Array, disc: jax.Array) -> tuple:
    image = image_u8.astype(jnp.float32) / 255.0
    d = (disc[0], disc[1], disc[2])
    mask = AdaptiveSegmenter().with_rim(image, rect, d)
    return (mask, *soil_step(image, mask, d))


def _soil_lines(mask: np.ndarray, truth: synth.Truth, surface: np.ndarray) -> np.ndarray:
    """Per column of the true contact chord (every 2 px, the true surface at least 4 px inside
    the rim): the first row of the mask's non-wheel run down to the rim, minus the surface's."""
    cx, cy, r = truth.center_x_px, truth.center_y_px, truth.radius_px
    out = []
    for c in range(int(cx - r) + 1, int(cx + r), 2):
        rim_y = cy + np.sqrt(max(r * r - (c - cx) ** 2, 0.0))
        if surface[c] > rim_y - 4 or surface[c] < cy:
            continue
        rows = np.nonzero(mask[int(cy) : int(rim_y) - 1, c] >= 0.5)[0]
        out.append(int(cy) + (rows.max() + 1 if rows.size else 0) - surface[c])
    return np.asarray(out)


def _frames(preset: str, seed: int) -> list[tuple]:
    rng = np.random.default_rng(seed)
    scenes = synth.recording_scenes(rng, 3, preset=preset, width=320, height=240)
    rig = synth.rig_for(scenes[0])
    rect = jnp.asarray(rig_arrays(rig).rect_px)
    out = []
    for i, scene in enumerate(scenes):
        image, truth = synth.render(scene, seed=seed * 10 + i)
        disc = jnp.asarray([truth.center_x_px, truth.center_y_px, truth.radius_px], jnp.float32)
        mask, stepped, moved = (np.asarray(a) for a in _masks(jnp.asarray(image), rect, disc))
        surface = surface_y_px(scene, np.arange(scene.width, dtype=np.float64))
        out.append((truth, mask, stepped, bool(moved), surface))
    return out


def test_dust_soil_line_moves_down_to_the_rendered_surface() -> None:
    """Soil-coloured dust on the lower wheel: the mask calls the faded face soil, its soil line
    lies well above the rendered surface; the step puts it at the surface."""
    n = 0
    for truth, mask, stepped, moved, surface in _frames("hard_dust", 2):
        if truth.sinkage_px < 8:
            continue
        n += 1
        before = _soil_lines(mask, truth, surface)
        after = _soil_lines(stepped, truth, surface)
        assert np.median(before) < -8.0  # the mask's line: tens of px above the soil
        assert moved
        # Rows are whole pixels: the first non-wheel row is the surface's, to a pixel.
        assert abs(np.median(after)) <= 1.0
        assert np.mean(np.abs(after) <= 2.0) >= 0.8
    assert n >= 2  # frames deep enough to tell were tested


def test_a_clean_frame_keeps_its_mask_bit_for_bit() -> None:
    """On the full mix (lugs, shadows, no dust) the mask's soil line is the soil's step: the
    mask is returned unchanged, so every number of the method is unchanged."""
    n = 0
    for truth, mask, stepped, moved, surface in _frames("full", 1):
        lines = _soil_lines(mask, truth, surface)
        assert not moved
        np.testing.assert_array_equal(stepped, mask)
        n += len(lines) > 0
    assert n >= 2  # frames with contact were tested
