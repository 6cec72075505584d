"""A black wheel's threshold from its shading-corrected face (soft.dark_face): the plane fit
against numpy's least squares, the valley against the mixture density it samples, and the
mask against the renderer's exact wheel."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_adaptive import _iou, _masks_with_and_without_rim, _with_rim

from sinkjax import synth
from sinkjax.soft.adaptive import AdaptiveSegmenter
from sinkjax.soft.dark_face import (
    _LOG_C_HI,
    _LOG_C_LO,
    corrected_histogram,
    face_plane,
    face_valley,
)
from sinkjax.synth.layers import SOIL, WHEEL_LAYERS, coverage


def _grid(h: int = 60, w: int = 80) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    return (xx - 40.0) / 30.0, (yy - 30.0) / 30.0


def test_face_plane_matches_numpy_least_squares() -> None:
    # Bounded noise (uniform: at most 1.73 RMS) is never trimmed: the fit is numpy's lstsq on
    # the weighted pixels.
    u, v = _grid()
    rng = np.random.default_rng(0)
    log_i = -2.3 + 0.2 * u - 0.3 * v + rng.uniform(-0.05, 0.05, u.shape)
    weight = (v < 0.2).astype(np.float64)
    args = (jnp.asarray(a) for a in (log_i, weight, u, v))
    plane, rms, used = face_plane(*args)
    sel = weight > 0
    design = np.column_stack([np.ones(sel.sum()), u[sel], v[sel]])
    coef, *_ = np.linalg.lstsq(design, log_i[sel], rcond=None)
    ref = coef[0] + coef[1] * u + coef[2] * v
    np.testing.assert_allclose(np.asarray(plane), ref, atol=1e-6)
    assert float(rms) == pytest.approx(np.std(log_i[sel] - ref[sel]), rel=1e-4)
    assert float(used) == sel.sum()


def test_face_plane_leaves_out_holes_and_a_hub() -> None:
    # Dark holes and a bright hub on one side of the face (a tenth of it): trimmed, the plane
    # is the face's; numpy's lstsq over everything is pulled far off.
    u, v = _grid()
    rng = np.random.default_rng(1)
    face = -2.3 + 0.2 * u - 0.3 * v
    log_i = face + rng.uniform(-0.05, 0.05, u.shape)
    spots = (rng.uniform(size=u.shape) < 0.2) & (u > 0.0)
    log_i[spots] += np.where(v[spots] < 0.0, -1.0, 1.2)
    weight = np.ones_like(u)
    args = (jnp.asarray(a) for a in (log_i, weight, u, v))
    plane, _, used = face_plane(*args)
    design = np.column_stack([np.ones(u.size), u.ravel(), v.ravel()])
    coef, *_ = np.linalg.lstsq(design, log_i.ravel(), rcond=None)
    naive = (coef[0] + coef[1] * u + coef[2] * v).reshape(u.shape)
    assert np.abs(np.asarray(plane) - face).max() < 0.01
    assert np.abs(naive - face).max() > 0.05
    assert float(used) == pytest.approx((~spots).sum(), rel=0.02)


def test_face_valley_is_the_dip_after_the_face() -> None:
    # Log corrected intensities: the face about 0 (4 % wide), its cast shadow on the soil at
    # 1.45 (10 %), the lit soil at 3 (15 %). The threshold is the mixture density's minimum
    # between face and shadow (numpy, on a fine grid), not the deeper one between shadow and lit
    # soil that a frame-wide valley search finds.
    rng = np.random.default_rng(2)
    pops = [(0.0, 0.04, 100_000), (np.log(1.45), 0.10, 8_000), (np.log(3.0), 0.15, 30_000)]
    log_c = np.concatenate([rng.normal(m, s, n) for m, s, n in pops])
    hist, centres = corrected_histogram(jnp.asarray(log_c[None, :]), jnp.ones((1, log_c.size)))
    found, ok = face_valley(hist, centres, jnp.asarray(0.1), jnp.asarray(_LOG_C_HI))
    grid = np.linspace(0.1, np.log(1.45), 2000)
    dens = sum(n / s * np.exp(-0.5 * ((grid - m) / s) ** 2) for m, s, n in pops)
    bin_width = (_LOG_C_HI - _LOG_C_LO) / hist.shape[0]
    assert bool(ok)
    assert np.log(float(found)) == pytest.approx(grid[np.argmin(dens)], abs=2 * bin_width)
    # One population only: no valley.
    one = 1e4 * jnp.exp(-0.5 * (centres / 0.04) ** 2)
    _, none = face_valley(one, centres, jnp.asarray(0.1), jnp.asarray(_LOG_C_HI))
    assert not bool(none)


def test_black_wheel_mask_with_rim_against_rendered_truth() -> None:
    """With the rim known, a black wheel's mask parts it from a cast shadow as dark as its lit
    side (hard_black: much better on several frames); on plain black wheels it loses at most a
    sliver of the edge (the threshold close above the face) and never a frame's worth."""
    gains = []
    for preset in ("black_wheel", "hard_black"):
        for seed in range(12):
            a, b, truth, inside = _masks_with_and_without_rim(preset, seed)
            frame = np.ones_like(inside)
            before, after = _iou(a, truth, frame), _iou(b, truth, frame)
            # Above the centre nothing changes.
            upper = np.arange(a.shape[0])[:, None] < np.nonzero(inside.any(axis=1))[0].mean()
            upper = np.broadcast_to(upper, a.shape)
            np.testing.assert_array_equal(a[upper], b[upper])
            if preset == "black_wheel":
                assert after >= before - 0.01, seed
            else:
                gains.append(after - before)
    assert sorted(gains)[-3] > 0.15 and np.mean(gains) > 0.05


def test_a_sky_lit_shadow_on_grey_soil_is_not_taken_for_a_black_wheel() -> None:
    """A black wheel's shadow on the soil inside its rim is lit by the tinted sky alone: its
    chroma (0.02-0.05) is several times the wheel's own, which is only the wheel's few percent of
    albedo times that tint. The chroma radius's floor (3 x 0.008, former 3 x 0.012; the
    sigmoid's width 0.0053, former 0.008) parts them: against the renderer's exact masks over
    twelve plain black-wheel frames, the soil inside the rim called wheel falls to under a tenth
    (the frame with most: 216 px -> under 10), and the wheel inside the rim lost to the tighter
    radius stays under 0.5 % of it."""
    former = AdaptiveSegmenter(chroma_floor=0.012, t_chroma_dark=0.008)
    with_former = jax.jit(lambda x, r, d: former.with_rim(x, r, d))
    soil_as_wheel, wheel_missed, wheel_px = np.zeros(2), np.zeros(2), 0
    for seed in range(12):
        rng = np.random.default_rng(seed)
        sc = synth.recording_scenes(rng, 1, preset="black_wheel", width=320, height=240)[0]
        img, t = synth.render(sc, seed)
        x = jnp.asarray(img, jnp.float64) / 255.0
        rect = jnp.asarray(synth.rig_for(sc).confidence_rect)
        disc = tuple(jnp.asarray(v) for v in (t.center_x_px, t.center_y_px, t.radius_px))
        cov = coverage(sc)
        wheel = cov[..., list(WHEEL_LAYERS)].sum(-1) > 0.5
        yy, xx = np.mgrid[: img.shape[0], : img.shape[1]]
        inside = (xx - t.center_x_px) ** 2 + (yy - t.center_y_px) ** 2 < t.radius_px**2
        soil_in, wheel_in = (cov[..., SOIL] > 0.5) & inside, wheel & inside
        masks = [np.asarray(f(x, rect, disc)) > 0.5 for f in (with_former, _with_rim)]
        counts = np.array([(m & soil_in).sum() for m in masks])
        if seed == 0:
            assert counts[0] > 150 and counts[1] < 10, counts
        soil_as_wheel += counts
        wheel_missed += [(~m & wheel_in).sum() for m in masks]
        wheel_px += int(wheel_in.sum())
    assert soil_as_wheel[1] < 0.1 * soil_as_wheel[0], soil_as_wheel
    assert wheel_missed[1] - wheel_missed[0] < 0.005 * wheel_px, (wheel_missed, wheel_px)


@pytest.mark.heavy
@pytest.mark.parametrize(
    ("preset", "seed", "leaves"),
    [
        # A cast shadow the corrected threshold parts from the face.
        ("hard_black", 6, ("p_valley", "t_int")),
        # Lit grey sand beyond a metal wheel's rim (tests/test_metal_rim.py).
        ("metal_wheel", 16_000, ("p_tex_rim",)),
    ],
)
def test_gradient_through_the_rim_rules_matches_finite_differences(
    preset: str, seed: int, leaves: tuple[str, ...]
) -> None:
    rng = np.random.default_rng(seed)
    sc = synth.recording_scenes(rng, 1, preset=preset, width=320, height=240)[0]
    img, t = synth.render(sc, seed)
    x = jnp.asarray(img, jnp.float64) / 255.0
    rect = tuple(synth.rig_for(sc).confidence_rect)
    disc = tuple(jnp.asarray(v) for v in (t.center_x_px, t.center_y_px, t.radius_px))
    for leaf in leaves:

        def stat(v: jnp.ndarray, leaf: str = leaf) -> jnp.ndarray:
            return jnp.mean(AdaptiveSegmenter(**{leaf: v}).with_rim(x, rect, disc))

        x0 = jnp.asarray(float(getattr(AdaptiveSegmenter(), leaf)))
        assert float(jnp.mean(AdaptiveSegmenter().with_rim(x, rect, disc))) != pytest.approx(
            float(jnp.mean(AdaptiveSegmenter()(x, rect))), abs=1e-3
        )  # the rule is in use on this frame
        g = float(jax.grad(stat)(x0))
        eps = 1e-6 * float(x0)
        fd = float((stat(x0 + eps) - stat(x0 - eps)) / (2 * eps))
        assert np.isfinite(g) and abs(g) > 1e-8
        assert g == pytest.approx(fd, rel=1e-4)
