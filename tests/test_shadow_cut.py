"""The shadow's cut (soft.shadow_cut) against the renderer's exact soil surface."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from sinkjax import synth
from sinkjax.soft.adaptive import AdaptiveSegmenter
from sinkjax.soft.estimator import rig_arrays
from sinkjax.soft.settings import SoftSettings
from sinkjax.soft.shadow_cut import shadow_cut, spills
from sinkjax.synth.scene import surface_y_px


@jax.jit
def _masks(image_u8: jax.Array, rect: jax.Array, disc: jax.Array) -> tuple:
    image = image_u8.astype(jnp.float32) / 255.0
    d = (disc[0], disc[1], disc[2])
    mask = AdaptiveSegmenter().with_rim(image, rect, d)
    return (mask, spills(mask, d), *shadow_cut(image, mask, d))


def _frame(preset: str, seed: int, i: int) -> tuple:
    """Frame ``i`` of a 3-frame recording at 320x240: truth, mask, spills, cut mask, changed,
    the true soil surface per column."""
    rng = np.random.default_rng(seed)
    scenes = synth.recording_scenes(rng, 3, preset=preset, width=320, height=240)
    rect = jnp.asarray(rig_arrays(synth.rig_for(scenes[0])).rect_px)
    image, truth = synth.render(scenes[i], seed=seed * 10 + i)
    disc = jnp.asarray([truth.center_x_px, truth.center_y_px, truth.radius_px], jnp.float32)
    mask, spilt, cut, changed = (np.asarray(a) for a in _masks(jnp.asarray(image), rect, disc))
    surface = surface_y_px(scenes[i], np.arange(scenes[i].width, dtype=np.float64))
    return truth, mask, bool(spilt), cut, bool(changed), surface


def _soil_line_offsets(mask: np.ndarray, truth: synth.Truth, surface: np.ndarray) -> np.ndarray:
    """Per column of the true contact chord (the surface at least 4 px inside the rim): the
    row below the mask's lowest wheel pixel between the centre and the rim, minus the surface."""
    cx, cy, r = truth.center_x_px, truth.center_y_px, truth.radius_px
    out = []
    for c in range(int(cx - r) + 1, int(cx + r)):
        rim_y = cy + np.sqrt(max(r * r - (c - cx) ** 2, 0.0))
        if surface[c] > rim_y - 4 or surface[c] < cy:
            continue
        rows = np.nonzero(mask[int(cy) : int(rim_y), c] >= 0.5)[0]
        out.append(int(cy) + (rows.max() + 1 if rows.size else 0) - surface[c])
    return np.asarray(out)


def _cut_tops(removed: np.ndarray, truth: synth.Truth, surface: np.ndarray) -> np.ndarray:
    """Per column of the true contact chord where the cut removed anything: its first removed
    row minus the surface (the wheel's own holes may lie at the soil line, so the mask's
    lowest wheel pixel is no measure of where the cut is)."""
    cx, cy, r = truth.center_x_px, truth.center_y_px, truth.radius_px
    out = []
    for c in range(int(cx - r) + 1, int(cx + r)):
        rim_y = cy + np.sqrt(max(r * r - (c - cx) ** 2, 0.0))
        rows = np.nonzero(removed[:, c])[0]
        if surface[c] <= rim_y - 4 and surface[c] >= cy and rows.size:
            out.append(rows.min() - surface[c])
    return np.asarray(out)


def test_cast_shadow_taken_for_wheel_is_cut_at_the_rendered_surface() -> None:
    """A colour cast towards the wheel's hue: the mask runs on from the face into the wheel's
    shadow on the soil, past the rim; the cut puts its soil line on the rendered surface."""
    for i in (0, 1):
        truth, mask, spilt, cut, changed, surface = _frame("hard_cast", 14, i)
        assert spilt and changed and truth.sinkage_px > 8
        assert np.median(_soil_line_offsets(mask, truth, surface)) > 5.0  # the shadow's edge
        removed = cut != mask
        tops = _cut_tops(removed, truth, surface)
        assert tops.size > 30
        assert abs(np.median(tops)) < 1.0
        assert np.mean(np.abs(tops) <= 2.0) > 0.9
        # What it removes is the soil below the surface (the wheel above it keeps all but a
        # few pixels where the surface meets the rim), and below it no wheel is left.
        above = np.arange(mask.shape[0])[:, None] < surface[None, :] - 3
        assert np.sum(removed & above) < 0.01 * np.sum(removed)
        rows, cols = np.nonzero(cut >= 0.5)
        deep = rows > surface[cols] + 3 + 0.2 * truth.radius_px
        assert np.sum(deep) < 0.05 * np.sum(mask[rows, cols] >= 0.5)


def _wheel_cut_above(removed: np.ndarray, mask: np.ndarray, surface: np.ndarray) -> int:
    """Wheel pixels (mask >= 0.5) the cut removed more than 3 px above the rendered surface."""
    above = np.arange(mask.shape[0])[:, None] < surface[None, :] - 3
    return int(np.sum(removed & above & (mask >= 0.5)))


def test_a_run_that_climbs_into_the_dark_lower_face_is_cut_at_the_step() -> None:
    """Strong light from one side: the wheel's lower face is nearly as dark as its shadow on the
    soil, so the run of shadow-coloured rows climbs on through the soil line into the face and
    ends on its smooth shading (no step there: that cut is refused). The second try takes the
    strongest step on the run's way up, the occlusion edge, and cuts on the rendered surface,
    within the outline's refinement window (which then finds the edge to a fraction of a px)."""
    window = SoftSettings().refine_half_width_px
    for i in (0, 1, 2):
        truth, mask, spilt, cut, changed, surface = _frame("hard_shading", 27, i)
        assert spilt and changed and truth.sinkage_px > 8
        removed = cut != mask
        tops = _cut_tops(removed, truth, surface)
        assert tops.size > 50
        assert abs(np.median(tops)) < 1.0
        assert np.mean(np.abs(tops) <= window) > 0.95
        assert _wheel_cut_above(removed, mask, surface) < 0.02 * np.sum(removed & (mask >= 0.5))


def test_shaded_wheel_over_its_shadow_is_not_cut_through_its_face() -> None:
    """One-sided light: the wheel's shaded side is as dark as its shadow on the soil, and the
    mask spills into the shadow; colour alone would cut half the wheel away. The cut needs a
    step in the image (the soil line is an occlusion edge; shading is smooth): the colour run's
    top has none and is refused; what is cut is cut at the soil line's step, and not one wheel
    pixel above the rendered surface goes."""
    window = SoftSettings().refine_half_width_px
    for i in (0, 1):
        truth, mask, spilt, cut, changed, surface = _frame("hard_shading", 0, i)
        assert spilt and truth.sinkage_px > 4
        removed = cut != mask
        assert _wheel_cut_above(removed, mask, surface) == 0
        if changed:
            tops = _cut_tops(removed, truth, surface)
            assert abs(np.median(tops)) < 1.0
            assert np.mean(np.abs(tops) <= window) > 0.8


def test_a_mask_that_does_not_spill_is_returned_unchanged() -> None:
    truth, mask, spilt, cut, changed, _ = _frame("full", 3, 0)
    assert truth.sinkage_px > 3 and not spilt and not changed
    np.testing.assert_array_equal(cut, mask)


def _dim_frame(seed: int) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float], int]:
    """A dim, noisy frame drawn here (not by the renderer): a lugged wheel lit from above over
    flat soil at row 165, its shadow on the soil of nearly the wheel's colour; the mask has the
    face, runs 12 px on under the soil line inside the rim, and holds 8x8 patches (JPEG blocks)
    of the shadow beyond it, too sparse for the near ring among the lugs."""
    h, w, cx, cy, r, soil = 240, 320, 160.0, 100.0, 85.0, 165
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    rho, angle = np.hypot(x - cx, y - cy), np.arctan2(y - cy, x - cx)
    lugs = (rho <= 1.1 * r) & (np.abs((angle * 24 / (2 * np.pi)) % 1.0 - 0.5) < 0.12)
    wheel = (rho <= r) | lugs
    shadow = (np.hypot(x - cx - 12, y - cy - 25) <= r) & (y >= soil)
    image = np.empty((h, w, 3))
    image[:] = (0.08, 0.08, 0.08)
    shade = np.clip(1.0 - 0.15 * (y - cy) / r, 0.85, 1.0)[..., None]
    image[wheel] = (shade * np.array([0.115, 0.105, 0.143]))[wheel]
    image[y >= soil] = (0.10, 0.09, 0.085)
    image[shadow] = (0.079, 0.072, 0.084)
    image += rng.normal(0.0, 0.02, image.shape)
    mask = (wheel & (y < soil)).astype(np.float64)
    blocks = np.kron(rng.random((h // 8, w // 8)) < 0.15, np.ones((8, 8))).astype(bool)
    mask[blocks & shadow & (rho > r)] = 1.0
    mask[shadow & (rho <= r) & (y < soil + 12)] = 1.0
    return image, mask, (cx, cy, r), soil


def test_a_sparse_spill_in_a_dim_noisy_frame_is_cut_at_the_soil_line() -> None:
    """Low light: the shadow is only patches of wheel in the mask, and pixel noise breaks up
    its run of shadow-coloured rows; the rings clear of the lugs see the spill, runs end at two
    rows that are not the shadow's, and the cut lands on the drawn soil line."""
    for seed in (0, 2, 3):
        image, mask, disc, soil = _dim_frame(seed)
        d = tuple(jnp.asarray(v) for v in disc)
        assert bool(spills(jnp.asarray(mask), d))
        cut, changed = (np.asarray(a) for a in shadow_cut(jnp.asarray(image), jnp.asarray(mask), d))
        assert changed
        removed = cut != mask
        cx, cy, r = disc
        tops = [
            np.nonzero(removed[:, c])[0].min() - soil
            for c in range(int(cx - r), int(cx + r))
            if removed[:, c].any() and (c - cx) ** 2 + (soil + 5 - cy) ** 2 < r * r
        ]
        assert len(tops) > 80 and np.mean(np.abs(tops) <= 1) > 0.95
        below = np.arange(mask.shape[0])[:, None] >= soil
        assert np.sum((cut >= 0.5) & below) < 0.02 * np.sum((mask >= 0.5) & below)
