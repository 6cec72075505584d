"""Shallow contact (issue 14, item 2): sinkage below 2 px against the recording's rim."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax import synth as S
from sinkjax.soft.adaptive import default_segmenter
from sinkjax.soft.checks import line_shift_std, plausibility
from sinkjax.soft.estimator import hidden_contact_std, measure, prepare
from sinkjax.soft.fit import boundary_side, build_evidence
from sinkjax.soft.model import measurements
from sinkjax.soft.rim import RecordingRim
from sinkjax.soft.settings import SoftSettings
from sinkjax.soft.shallow import envelope_line, shallow_boundary
from sinkjax.status import Status

CX, CY, R = 160.0, 100.0, 100.0


@functools.cache
def _frame(soil_level_px: float) -> tuple[np.ndarray, S.Truth]:
    # Lugs, JPEG, noise, blur and a cast shadow, as in the "full" preset.
    scene = S.Scene(
        width=320,
        height=240,
        centre_x_px=CX,
        centre_y_px=CY,
        radius_px=R,
        rim_width_px=6.0,
        n_lugs=12,
        lug_height_px=4.0,
        lug_width_px=8.0,
        phase_rad=0.3,
        hub_radius_px=14.0,
        soil_level_px=soil_level_px,
        pebbles=40,
        shadow_factor=0.5,
        shadow_offset_px=(-10.0, 15.0),
        noise_std=2.0,
        blur_sigma_px=0.5,
        jpeg_quality=85,
    )
    return S.render(scene, seed=3)


_measure = jax.jit(measure, static_argnames=("rect", "travel", "wheel_radius_mm"))


def _run(image: np.ndarray, **kw):
    # The recording's rim, known to 0.05 px (soft.rim), as SoftRecording measures frames.
    rig = S.rig_for(S.Scene(width=320, height=240, centre_x_px=CX, centre_y_px=CY, radius_px=R))
    return _measure(
        jnp.asarray(image, jnp.float64) / 255.0,
        rig.segmentation,
        rect=rig.confidence_rect,
        travel=rig.travel,
        wheel_radius_mm=rig.wheel_radius_mm,
        rim=RecordingRim.fixed(CX, CY, R, 0.05),
        **kw,
    )


@pytest.mark.parametrize("z0_px", [0.7, 1.2])
def test_shallow_contact_is_measured(z0_px: float) -> None:
    image, truth = _frame(CY + R - z0_px)
    assert truth.contact and truth.sinkage_px == pytest.approx(z0_px, abs=1e-6)
    est = _run(image)
    assert Status.from_code(int(est.status)) == Status.OK
    px_per_mm = R / S.Scene().wheel_radius_mm
    assert abs(float(est.sinkage_mm) * px_per_mm - truth.sinkage_px) < 0.3
    assert float(est.sinkage_std_mm) > 0


def test_a_shallow_chords_depth_is_known_to_its_margin() -> None:
    # The envelope measures the chord's depth against the rim's edge in this frame, which a
    # shadow or soil just below the rim pulls in by about the margin with no soil touching it
    # (no-contact frames of experiments/shallow_contact.py read 0.4-0.6 px "chords" under
    # margins of 0.35-0.45 px): the soil line's shift adds the margin in quadrature, and
    # line_shift_std turns it into z0's change for the line moved that far (finite difference).
    image, _ = _frame(CY + R - 0.7)
    est = _run(image)
    rig = S.rig_for(S.Scene(width=320, height=240, centre_x_px=CX, centre_y_px=CY, radius_px=R))
    img = jnp.asarray(image, jnp.float64) / 255.0
    rim = RecordingRim.fixed(CX, CY, R, 0.05)
    mask = default_segmenter(rig.segmentation).with_rim(img, rig.confidence_rect, rim.disc())
    prep = prepare(img, mask, rim)
    choice = prep.choice
    ev = build_evidence(prep.outline, choice.circle, 1.0, SoftSettings(), choice.prior_weight)
    margin = float(ev.shallow_chord)
    assert 0.2 < margin < 1.0  # a chord found, against the frame's own margin
    p, yes = est.params, jnp.asarray(True)
    shift = float(plausibility(img, mask, p, ev, yes).line_shift_px)
    bare = eqx.tree_at(lambda e: e.shallow_chord, ev, jnp.zeros(()))
    before = float(plausibility(img, mask, p, bare, yes).line_shift_px)
    assert shift**2 == pytest.approx(before**2 + margin**2, rel=1e-9)
    k, h = float(p[3]), 1e-4
    down = jnp.zeros_like(p).at[4].set(np.sqrt(1.0 + k * k)).at[6].set(1.0).at[8].set(1.0)
    dz = float(measurements(p + h * down, 140.0)[0] - measurements(p - h * down, 140.0)[0]) / (
        2 * h
    )
    check = plausibility(img, mask, p, ev, yes)
    assert float(line_shift_std(p, check, 140.0)[0]) == pytest.approx(abs(dz) * shift, rel=1e-5)


def test_no_contact_reports_the_sinkage_it_could_hide() -> None:
    image, truth = _frame(CY + R + 8.0)
    assert not truth.contact
    est = _run(image)
    assert Status.from_code(int(est.status)) == Status.NO_CONTACT
    assert float(est.sinkage_mm) == 0.0
    # z_max = sqrt(3) sigma (px): more than nothing, less than the 0.7 px contact seen above.
    z_max_px = np.sqrt(3.0) * float(est.sinkage_std_mm) * R / S.Scene().wheel_radius_mm
    assert 0.05 < z_max_px < 0.7
    # Each angle's sigma is that of a sinkage uniform on [0, z_max] on flat ground.
    theta = np.arccos(1.0 - z_max_px / R)
    assert float(est.theta1_std_rad) == pytest.approx(theta / np.sqrt(2.0), rel=1e-6)


def test_hidden_sigma_matches_uniform_sinkage() -> None:
    # Monte Carlo reference: RMS of reading 0 for z0 uniform on [0, z_max].
    s = SoftSettings()
    r, inner = jnp.asarray(120.0), jnp.asarray(0.4)
    std = np.asarray(hidden_contact_std(r, inner, 1.0, s))
    z_max = 0.4 + (0.5 * float(s.min_boundary_points)) ** 2 / (2 * 120.0)
    z = np.random.default_rng(0).uniform(0, z_max, 200_000)
    assert std[0] == pytest.approx(120.0**-1 * np.sqrt(np.mean(z**2)), rel=1e-2)
    theta = np.arccos(1 - z / 120.0)
    assert std[1] == pytest.approx(np.sqrt(np.mean(theta**2)), rel=2e-2)
    # A chord the envelope found 0.5 px deep but did not take: up to 0.5 px + the margin hides.
    seen = np.asarray(hidden_contact_std(r, inner, 1.0, s, jnp.asarray(0.5)))
    z = np.random.default_rng(1).uniform(0, 0.9, 200_000)
    assert seen[0] == pytest.approx(120.0**-1 * np.sqrt(np.mean(z**2)), rel=1e-2)
    # One no deeper than the margin (rim noise can draw such a line) changes nothing.
    low = np.asarray(hidden_contact_std(r, inner, 1.0, s, jnp.asarray(0.39)))
    np.testing.assert_allclose(low, std, rtol=1e-12)


def _lower_edge_uv(dip_at_deg: float, depth_px: float) -> tuple[np.ndarray, np.ndarray]:
    u, dr = (np.asarray(a) for a in _lower_edge(dip_at_deg, depth_px))
    phi = np.arctan2(u, np.sqrt(np.maximum((R + dr) ** 2 - u * u, 0.0)))
    return (R + dr) * np.sin(phi), (R + dr) * np.cos(phi)


def _with_lug_corners(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Two lug corners at the rim's bottom: 6 points each, 3 px inside the rim, 40 px either side.
    cu = np.concatenate([np.linspace(-42, -38, 6), np.linspace(38, 42, 6)])
    cv = np.sqrt(R * R - cu * cu) - 3.0
    return np.concatenate([u, cu]), np.concatenate([v, cv])


@pytest.mark.parametrize("dip_at_deg", [0.0, -4.0])
def test_envelope_finds_a_shallow_chord_beside_lug_corners(dip_at_deg: float) -> None:
    # Reference: the constructed edge, a chord 1 px deep with slope -tan(angle), 0.1 px noise.
    u, v = _lower_edge_uv(dip_at_deg, 1.0)
    depth_in = np.sqrt(np.maximum(R * R - u * u, 0.0)) - v  # before the noise
    chord, on_soil = depth_in > 0.25, depth_in > 0.05
    v = v + np.random.default_rng(1).normal(0.0, 0.1, v.shape)
    u, v = _with_lug_corners(u, v)
    lower = jnp.ones(u.shape)
    z, k, on = envelope_line(jnp.asarray(u), jnp.asarray(v), lower, jnp.asarray(R))
    assert float(z) == pytest.approx(1.0, abs=0.1)
    assert float(k) == pytest.approx(-np.tan(np.radians(dip_at_deg)), abs=0.01)
    on = np.asarray(on)
    assert not np.any(on[-12:])  # no lug corner
    assert np.all(on_soil[on[:-12]]) and np.sum(on[:-12]) >= 0.6 * np.sum(chord)
    use, _, depth = shallow_boundary(
        jnp.asarray(u), jnp.asarray(v), lower, jnp.asarray(R), jnp.asarray(4.0), jnp.asarray(0.3)
    )
    assert float(depth) == pytest.approx(float(z))  # a chord seen (and taken)
    assert bool(use)
    # The offset test takes lug corners (3 px inside the rim) for the soil: those of one side,
    # the deepest stretch it sees (the other side's lie beyond the rim edge from them).
    dr = np.hypot(u, v) - R
    inside = np.asarray(
        boundary_side(jnp.asarray(u), jnp.asarray(dr), lower, jnp.asarray(0.3), SoftSettings())
    )
    assert int(np.sum(inside[-12:])) == 6


@pytest.mark.parametrize("weight", [1.0, 0.2])
def test_a_faint_shallow_chord_counts_by_its_points(weight: float) -> None:
    # A chord 0.6 px deep moves the soft mask only partly: its edge points weigh about 0.2 each
    # (measured on rendered 800x600 frames), 2-3 in all over the chord's ~15 points, under
    # min_boundary_points (4). The envelope counts the points that lie on it instead.
    u, v = _lower_edge_uv(0.0, 0.6)
    v = v + np.random.default_rng(4).normal(0.0, 0.05, v.shape)
    u, v = _with_lug_corners(u, v)
    lower = jnp.full(u.shape, weight)
    args = (jnp.asarray(u), jnp.asarray(v), lower, jnp.asarray(R))
    z, _, on = envelope_line(*args)
    assert float(z) == pytest.approx(0.6, abs=0.1)
    assert float(jnp.sum(jnp.where(on, lower, 0.0))) < 4.0 or weight == 1.0
    use, _, _ = shallow_boundary(*args, jnp.asarray(4.0), jnp.asarray(0.3))
    assert bool(use)
    # A bare rim with the same faint weights stays no contact.
    phi = np.linspace(-np.pi / 2, np.pi / 2, int(np.pi * R))
    noise = np.random.default_rng(5).normal(0.0, 0.1, phi.shape)
    ub, vb = _with_lug_corners((R + noise) * np.sin(phi), (R + noise) * np.cos(phi))
    bare = (jnp.asarray(ub), jnp.asarray(vb), jnp.full(ub.shape, weight), jnp.asarray(R))
    assert not bool(shallow_boundary(*bare, jnp.asarray(4.0), jnp.asarray(0.3))[0])


def test_envelope_sees_no_contact_on_a_bare_rim_with_lug_corners() -> None:
    phi = np.linspace(-np.pi / 2, np.pi / 2, int(np.pi * R))
    noise = np.random.default_rng(2).normal(0.0, 0.1, phi.shape)
    u, v = _with_lug_corners((R + noise) * np.sin(phi), (R + noise) * np.cos(phi))
    args = (jnp.asarray(u), jnp.asarray(v), jnp.ones(u.shape), jnp.asarray(R))
    use, _, depth = shallow_boundary(*args, jnp.asarray(4.0), jnp.asarray(0.3))
    assert not bool(use) and float(depth) == 0.0  # no chord seen: nothing more can hide


def _lower_edge(dip_at_deg: float, depth_px: float) -> tuple[jnp.ndarray, jnp.ndarray]:
    # Lower half of a rim of radius R, one point per px of arc, with a straight soil chord of
    # the given depth whose middle is at the given angle from the bottom.
    phi = np.linspace(-np.pi / 2, np.pi / 2, int(np.pi * R))
    x, y = R * np.sin(phi), R * np.cos(phi)
    a = np.radians(dip_at_deg)
    normal = np.array([np.sin(a), np.cos(a)])
    along = x * normal[0] + y * normal[1]
    cut = along > R - depth_px
    # Project the points beyond the chord onto it (the soil hides the rim there).
    x = np.where(cut, x - (along - (R - depth_px)) * normal[0], x)
    y = np.where(cut, y - (along - (R - depth_px)) * normal[1], y)
    dr = np.hypot(x, y) - R
    return jnp.asarray(x), jnp.asarray(dr)


@pytest.mark.parametrize(("dip_at_deg", "contact"), [(0.0, True), (35.0, False)])
def test_a_dip_counts_as_contact_only_at_the_bottom(dip_at_deg: float, contact: bool) -> None:
    u, dr = _lower_edge(dip_at_deg, 0.8)
    inside = boundary_side(u, dr, jnp.ones_like(u), jnp.asarray(0.3), SoftSettings())
    # A dip of 0.8 px is a chord of 2 sqrt(2 R 0.8) = 25 px; the mean over +-5 px exceeds 0.3 px
    # over its middle.
    assert (int(jnp.sum(inside)) >= 4) == contact


@pytest.mark.heavy
@pytest.mark.slow
def test_gradients_are_finite_on_a_shallow_frame() -> None:
    image, _ = _frame(CY + R - 0.7)
    rig = S.rig_for(S.Scene(width=320, height=240, centre_x_px=CX, centre_y_px=CY, radius_px=R))
    rim = RecordingRim.fixed(CX, CY, R, 0.05)

    def loss(im: jnp.ndarray) -> jnp.ndarray:
        e = _measure(
            im,
            rig.segmentation,
            rect=rig.confidence_rect,
            travel=rig.travel,
            wheel_radius_mm=rig.wheel_radius_mm,
            rim=rim,
        )
        return e.sinkage_mm + e.theta1_rad + e.sinkage_std_mm

    # Jitted whole: the gradient of the jitted _measure called from Python would compile its
    # forward and its transpose separately.
    g = jax.jit(jax.grad(loss))(jnp.asarray(image, jnp.float64) / 255.0)
    assert np.all(np.isfinite(np.asarray(g))) and float(jnp.max(jnp.abs(g))) > 0
