"""Plausibility checks (issue 12 item 5): the soft stage ``soft.checks`` and the classic one."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax import synth as S
from sinkjax.classic.estimator import estimate_classic, recording_radius_px
from sinkjax.classic.plausible import implausibility, ring_disagreement, soil_ends_beyond_rim
from sinkjax.result import FrameResult
from sinkjax.rig import Rig
from sinkjax.soft.checks import (
    MAX_HALF_RING_DISAGREEMENT,
    MAX_OUTER_WHEEL,
    NEAR_OUTER_RING,
    TESTS,
    message,
    outer_wheel,
    ring_disagreement as ring_disagreement_soft,
)
from sinkjax.soft.estimator import measure_from_mask
from sinkjax.soft.model import N_PARAMS
from sinkjax.soft.rim import RecordingRim
from sinkjax.soft.segmentation import wheel_mask
from sinkjax.status import Status

_measure = jax.jit(measure_from_mask, static_argnames=("travel", "wheel_radius_mm"))


def test_soft_checks_pass_a_clean_frame_and_flag_a_mask_that_lost_part_of_the_lower_rim() -> None:
    rng = np.random.default_rng(4)
    scenes = S.recording_scenes(rng, 1, preset="clean", width=200, height=150)
    img, truth = S.render(scenes[0], seed=1)
    rig = S.rig_for(scenes[0])
    image = jnp.asarray(img, jnp.float64) / 255.0
    mask = wheel_mask(image, rig.segmentation, rig.confidence_rect)
    good = _measure(image, mask, wheel_radius_mm=rig.wheel_radius_mm)
    assert int(good.check) == 0 and Status.from_code(int(good.status)) == Status.OK
    assert abs(float(good.sinkage_mm) - truth.sinkage_mm) < 0.1 * truth.sinkage_mm + 1.0
    yy, xx = np.mgrid[0:150, 0:200]
    ang = np.degrees(np.arctan2(yy - scenes[0].centre_y_px, xx - scenes[0].centre_x_px))
    sign = jnp.asarray(1.0)  # travel right
    held = lambda m: float(ring_disagreement_soft(m, good.params, sign, jnp.asarray(True)))
    assert held(mask) < 0.05
    # Erase a 45-degree wedge of the lower wheel above the soil line (the fitted rim meets the
    # soil 48 degrees below the horizontal; y down, so the lower left is 90-180 degrees): with
    # the fitted model held, the ring just inside the rim disagrees over 45 of its 180 degrees,
    # more than the test allows.
    wedge = (ang > 135) & (ang <= 180)
    share = held(jnp.where(jnp.asarray(wedge), 0.0, mask))
    assert share == pytest.approx(45.0 / 180.0, abs=0.02)
    assert share > MAX_HALF_RING_DISAGREEMENT
    # The upper half is not tested: a 70-degree wedge of the upper wheel (a lamp's glow that
    # no colour test calls wheel) moves no number; the frame stays ok and measures as before.
    glow = jnp.where(jnp.asarray((ang > -150) & (ang < -80)), 0.0, mask)
    assert held(glow) < 0.05
    lit = _measure(image, glow, wheel_radius_mm=140.0)
    assert Status.from_code(int(lit.status)) == Status.OK
    assert float(lit.sinkage_mm) == pytest.approx(float(good.sinkage_mm), abs=0.05)
    # The whole lower wheel lost (a mask that took it for soil): flagged, never ok.
    gone = jnp.where(jnp.asarray(ang > 0), 0.0, mask)
    bad = _measure(image, gone, wheel_radius_mm=140.0)
    assert Status.from_code(int(bad.status)) in (Status.IMPLAUSIBLE, Status.NO_WHEEL)
    if Status.from_code(int(bad.status)) == Status.IMPLAUSIBLE:
        assert int(bad.check) >= 1 and message(int(bad.check)).startswith(TESTS[int(bad.check) - 1])


def test_a_cast_shadow_taken_for_wheel_is_cut_at_the_soil_line_or_flagged() -> None:
    # The rendered wheel's own mask, plus a half-ellipse below the rim that the mask calls
    # wheel (a dark cast shadow on the soil under a black wheel): the soil no longer shows
    # inside the rim, so without the outer ring the frame would read "no contact, 0 mm".
    rng = np.random.default_rng(4)
    scenes = S.recording_scenes(rng, 1, preset="clean", width=200, height=150)
    sc = scenes[0]
    img, truth = S.render(sc, seed=1)
    assert truth.sinkage_px > 3.0
    rig = S.rig_for(sc)
    image = jnp.asarray(img, jnp.float64) / 255.0
    mask = wheel_mask(image, rig.segmentation, rig.confidence_rect)
    good = _measure(image, mask, wheel_radius_mm=rig.wheel_radius_mm)
    assert Status.from_code(int(good.status)) == Status.OK
    yy, xx = np.mgrid[0:150, 0:200]
    r, cx, cy = sc.radius_px, sc.centre_x_px, sc.centre_y_px
    shadow = ((xx - cx) / (1.3 * r)) ** 2 + ((yy - cy - 0.3 * r) / (1.2 * r)) ** 2 < 1.0
    shadow &= yy > cy
    # Measured as ``estimate`` measures a recording: with its rim held (soft.rim).
    rim = RecordingRim.fixed(cx, cy, r, 0.3)
    shadowed = jnp.where(jnp.asarray(shadow), 1.0, mask)
    # The image still shows the soil line (the soil's colour steps to the wheel's there): the
    # mask is cut at it (soft.shadow_cut) and the frame measures the rendered truth.
    cut = _measure(image, shadowed, wheel_radius_mm=140.0, rim=rim)
    assert Status.from_code(int(cut.status)) == Status.OK
    assert float(cut.sinkage_mm) == pytest.approx(truth.sinkage_mm, rel=0.03)
    assert math.degrees(float(cut.theta1_rad)) == pytest.approx(truth.theta1_deg, abs=1.0)
    assert math.degrees(float(cut.theta2_rad)) == pytest.approx(truth.theta2_deg, abs=1.0)
    # Where the image does not part them (each column's soil under the spill painted the
    # colour of its wheel just above the soil line: no step, no contrast), nothing is cut and
    # the outer ring flags the frame.
    wheel = np.asarray(mask) >= 0.5
    painted = np.asarray(image).copy()
    for c in range(painted.shape[1]):
        rows = np.nonzero(wheel[:, c])[0]
        if rows.size:
            below = shadow[:, c] & ~wheel[:, c] & (np.arange(painted.shape[0]) > rows.max())
            painted[below, c] = painted[max(rows.max() - 2, 0), c]
    bad = _measure(jnp.asarray(painted), shadowed, wheel_radius_mm=140.0, rim=rim)
    assert Status.from_code(int(bad.status)) == Status.IMPLAUSIBLE
    assert int(bad.check) == len(TESTS)
    assert message(int(bad.check)).startswith("the wheel mask reaches into the soil")


def test_outer_wheel_is_the_masks_excess_below_over_the_wheels_own_lugs() -> None:
    # A binary wheel of radius r with 24 lugs of 6 degrees (40 % of the circumference) reaching
    # 1.15 r, no soil. On the ring at NEAR_OUTER_RING * r the lugs are wheel all round: the lower
    # half's mean is their share, the upper half's the same, the excess 0. A shadow below the
    # rim that the mask calls wheel out to 1.12 r (short of the 1.2 r ring) covers the lower half
    # of that ring: the excess is then 1 - 0.4 (a frame read as no contact).
    height, width, cx, cy, r = 200, 240, 120.0, 80.0, 50.0
    yy, xx = np.mgrid[0:height, 0:width].astype(float)
    rad = np.hypot(xx - cx, yy - cy)
    ang = np.degrees(np.arctan2(yy - cy, xx - cx)) % 15.0
    wheel = (rad <= r) | ((rad <= 1.15 * r) & (ang >= 4.5) & (ang < 10.5))
    p = jnp.zeros(N_PARAMS).at[:5].set(jnp.asarray([cx, cy, r, 0.0, 2.0 * r]))
    sign, no_contact = jnp.asarray(1.0), jnp.asarray(False)
    plain = float(outer_wheel(jnp.asarray(wheel, jnp.float64), p, sign, no_contact))
    assert plain == pytest.approx(0.0, abs=0.03)
    ring = np.radians(np.linspace(0.0, 180.0, 721))
    x = np.round(cx + NEAR_OUTER_RING * r * np.cos(ring)).astype(int)
    y = np.round(cy + NEAR_OUTER_RING * r * np.sin(ring)).astype(int)
    assert wheel[y, x].mean() == pytest.approx(0.4, abs=0.03)  # the lugs' share, not 0
    shadow = (yy > cy) & (((xx - cx) / (1.1 * r)) ** 2 + ((yy - cy) / (1.12 * r)) ** 2 < 1.0)
    shaded = float(outer_wheel(jnp.asarray(wheel | shadow, jnp.float64), p, sign, no_contact))
    assert shaded == pytest.approx(0.6, abs=0.03)
    assert shaded > MAX_OUTER_WHEEL
    # With contact (a soil line 0.5 r below O) only the 1.2 r ring counts: the soil line has
    # parted wheel from soil, and this shadow does not reach that far.
    line, contact = p.at[4].set(0.5 * r), jnp.asarray(True)
    assert float(outer_wheel(jnp.asarray(wheel | shadow, jnp.float64), line, sign, contact)) < 0.01


def test_classic_implausibility() -> None:
    r = 100.0
    x = np.linspace(-60, 60, 121)
    flat = np.column_stack([x, np.full_like(x, 80.0)])
    a, b = np.array([60.0, 80.0]), np.array([-60.0, 80.0])  # on the rim: 60^2 + 80^2 = 100^2
    assert implausibility(flat, a, b, r, 1.0) == ""
    assert implausibility(flat, a, b, r, 1.0, recording_radius_px=101.0) == ""
    assert "recording" in implausibility(flat, a, b, r, 1.0, recording_radius_px=120.0)
    high = flat.copy()
    high[:, 1] = -10.0
    assert "above the wheel centre" in implausibility(high, a, b, r, 1.0)
    short = np.array([30.0, 80.0])  # 85 px from O: 15 px short of the rim
    assert "short of the rim" in implausibility(flat, short, b, r, 1.0)
    rows = [
        FrameResult(image="a", status=Status.OK, radius_px=100.0),
        FrameResult(image="b", status=Status.NO_WHEEL),
        FrameResult(image="c", status=Status.OK, radius_px=140.0),
        FrameResult(image="d", status=Status.NO_CONTACT, radius_px=101.0),
    ]
    assert recording_radius_px(rows) == pytest.approx(101.0)
    assert recording_radius_px(rows[1:2]) is None


def test_classic_flags_a_boundary_on_the_wheel_where_the_soil_does_not_go_on(draw_wheel) -> None:
    # draw_wheel's red wheel (conftest: centre (160.3, 100.6), r 85.4 px) in soil below y = 165.2.
    cx, cy, r, soil_y = 160.3, 100.6, 85.4, 165.2
    rig = Rig(wheel_radius_mm=140.0, confidence_rect=(150, 30, 24, 12))
    clean = draw_wheel()
    res = estimate_classic(clean, rig, "clean")
    assert res.status == Status.OK, res.message
    true_z0_mm = (cy + r - soil_y) * 140.0 / r
    assert res.sinkage_mm == pytest.approx(true_z0_mm, rel=0.1)
    # Soil-coloured dust on the wheel's lower face, 22 px above the soil: the binary image calls
    # it soil, and the classic boundary runs along the dust's top edge, on the wheel.
    dusty = clean.copy()
    yy, xx = np.mgrid[0 : dusty.shape[0], 0 : dusty.shape[1]]
    dust = (np.hypot(xx - cx, yy - cy) < r - 1.0) & (yy > soil_y - 22.0)
    dusty[dust] = clean[-1, 0]  # the soil's colour
    res = estimate_classic(dusty, rig, "dusty")
    assert res.status == Status.IMPLAUSIBLE
    assert "does not continue beyond the rim" in res.message
    # Its numbers are kept: 22 px more sinkage than the truth, to a pixel.
    assert res.sinkage_mm == pytest.approx(true_z0_mm + 22.0 * 140.0 / r, abs=140.0 / r)

    # The test itself, on the drawn geometry: A and B on the rim at a flat line at depth d.
    def ends(y_line: float) -> tuple[np.ndarray, np.ndarray]:
        v = y_line - cy
        u = math.sqrt(r * r - v * v)
        return np.array([u, v]), np.array([-u, v])

    assert not soil_ends_beyond_rim(clean, (cx, cy), r, 0.0, *ends(soil_y), 1.0)
    assert soil_ends_beyond_rim(dusty, (cx, cy), r, 0.0, *ends(soil_y - 22.0), 1.0)
    # Travel to the left mirrors u: the same frame, the same verdicts.
    assert not soil_ends_beyond_rim(clean, (cx, cy), r, 0.0, *ends(soil_y), -1.0)
    assert soil_ends_beyond_rim(dusty, (cx, cy), r, 0.0, *ends(soil_y - 22.0), -1.0)


def test_classic_ring_disagreement_is_the_share_of_the_rim_the_region_gets_wrong() -> None:
    # A filled wheel region (r 80 px at (150, 100)) cut by a flat soil line 40 px below O.
    cx, cy, r, depth = 150.0, 100.0, 80.0, 40.0
    yy, xx = np.mgrid[0:240, 0:300]
    ang = np.degrees(np.arctan2(yy - cy, xx - cx))
    region = (np.hypot(xx - cx, yy - cy) <= r) & (yy < cy + depth)
    for sign in (1.0, -1.0):
        assert ring_disagreement(region, (cx, cy), r, 0.0, depth, sign) == pytest.approx(
            0, abs=0.01
        )
    # A 72-degree wedge of the upper face lost (a highlight the band missed): a fifth of the
    # ring disagrees, to the ring's sampling (1/256) and the wedge's pixel edges.
    lost = region & (ang > -150) & (ang < -78)
    share = ring_disagreement(region & ~lost, (cx, cy), r, 0.0, depth, 1.0)
    assert share == pytest.approx(72 / 360, abs=0.01)
    # Soil taken for wheel below the line over the lower half: the arc below the line
    # (2 acos(depth / rho) of the ring at rho = r - 0.04 r) disagrees.
    rho = r - 0.04 * r
    below = 2 * math.degrees(math.acos(depth / rho)) / 360
    shadowed = np.hypot(xx - cx, yy - cy) <= r
    share = ring_disagreement(shadowed, (cx, cy), r, 0.0, depth, 1.0)
    assert share == pytest.approx(below, abs=0.01)


def test_implausible_status() -> None:
    s = Status.IMPLAUSIBLE
    assert str(s) == "implausible" and not s.measured and Status.from_code(s.code) is s
    assert "calibrate" in s.message and math.isfinite(s.code)


def test_line_shift_matches_a_pixel_count_of_the_mask_around_the_line() -> None:
    # A wheel of radius 100 px at (160, 120), soil line 40 px below O; the mask keeps wheel at
    # 0.4 in a 20 px band starting 3 px (the edge zone) below the line, as faded dust does.
    from sinkjax.soft.checks import _line_shift

    cx, cy, r, line, edge, band, level = 160.0, 120.0, 100.0, 40.0, 3.0, 20.0, 0.4
    yy, xx = np.mgrid[0:240, 0:320].astype(float)
    depth = yy - cy - line
    mask = np.where(depth < 0, 1.0, np.where((depth > edge) & (depth < edge + band), level, 0.0))
    p = jnp.asarray([cx, cy, r, 0.0, line, 0.0, 0.0, 0.0, 0.0])
    shift = jax.jit(_line_shift)
    mass, rms, fade = shift(jnp.asarray(mask), p, jnp.asarray(1.0), jnp.asarray(edge))
    # Reference: a sum over the pixels of the ring's disc below the edge zone (1 px^2 each).
    rho = r - max(2.0, 0.04 * r)
    inside = (np.hypot(xx - cx, yy - cy) < rho) & (depth > edge)
    chord = 2.0 * math.sqrt(rho**2 - line**2)
    ref_mass = float(np.sum(mask[inside])) / chord
    ref_rms = math.sqrt(2.0 * float(np.sum((mask * (depth - edge))[inside])) / chord)
    assert float(mass) == pytest.approx(ref_mass, rel=0.03)
    assert float(rms) == pytest.approx(ref_rms, rel=0.03)
    band_up = (np.hypot(xx - cx, yy - cy) < rho) & (depth < -edge) & (depth > -(rho - line))
    amb = mask * (1.0 - mask)
    ref_fade = float(np.sum(amb[inside]) + np.sum(amb[band_up])) / chord
    assert float(fade) == pytest.approx(ref_fade, rel=0.03)
    # Nothing below the edge zone: no shift (a clean frame keeps its sigma).
    clean = np.where(depth < 0, 1.0, 0.0)
    _, none, no_fade = shift(jnp.asarray(clean), p, jnp.asarray(1.0), jnp.asarray(edge))
    assert float(none) < 1e-3 and float(no_fade) < 1e-3


def test_line_shift_std_moves_z0_by_the_shift() -> None:
    # A flat soil line 40 px below O on a rim of 100 px: z0 = r - b, so moving the line down by
    # 2.5 px changes z0 by 2.5 px, i.e. 2.5 * R / r mm.
    from sinkjax.soft.checks import Plausibility, line_shift_std

    z = jnp.zeros(())
    check = Plausibility(z, z, z, z, z, z, z, z + 1.0, jnp.asarray(2.5), jnp.asarray(0))
    p = jnp.asarray([0.0, 0.0, 100.0, 0.0, 40.0, 0.0, 40.0, 0.0, 40.0])
    std = line_shift_std(p, check, 140.0)
    assert float(std[0]) == pytest.approx(2.5 * 140.0 / 100.0, rel=1e-6)
    # The ends at v = 40 on the rim: theta = acos(40 / 100); d theta / d v = 1 / (r sin theta).
    dtheta = 2.5 / (100.0 * math.sin(math.acos(0.4)))
    assert float(std[1]) == pytest.approx(dtheta, rel=1e-3)
    assert float(std[2]) == pytest.approx(dtheta, rel=1e-3)


def _rim_crossing_deg(direction_deg: float, through: tuple[float, float], end: str) -> float:
    """θ (deg) where the line through ``through`` (u, v) at ``direction_deg`` meets a rim of
    100 px about O, on the entry (larger u) or exit side: a quadratic solved by NumPy."""
    t = np.radians(direction_deg)
    d, q = np.array([np.cos(t), np.sin(t)]), np.asarray(through, float)
    points = [q + d * s for s in np.roots([1.0, 2.0 * q @ d, q @ q - 100.0**2]).real]
    u, v = max(points, key=lambda x: x[0]) if end == "A" else min(points, key=lambda x: x[0])
    return float(np.degrees(np.arctan2(u, v) if end == "A" else np.arctan2(-u, v)))


def test_a_steep_end_widens_its_angle_by_the_distance_to_the_equivalent_lines_end() -> None:
    # Rim r = 100 px about O; the equivalent line v = 40 px (k = 0). The entry end's tangent rises
    # towards the rim at 40 degrees (steeper than soil rests, as where the mask's edge runs up a
    # shaded rim ring) through (60, 42); the exit end's at 10 degrees through (-85, 42).
    from sinkjax.soft.checks import MAX_END_SLOPE_DEG, end_slopes_rad, steep_end_std

    def params(a_deg: float, b_deg: float) -> jax.Array:
        # The tangent -sin(a) u + cos(a) v = c through a point (u, v): c = -sin(a) u + cos(a) v.
        a, b = math.radians(a_deg), math.radians(b_deg)
        c_a = -math.sin(a) * 60.0 + math.cos(a) * 42.0
        c_b = -math.sin(b) * -85.0 + math.cos(b) * 42.0
        p = [0.0, 0.0, 100.0, 0.0, 40.0, a, c_a, b, c_b, 0.0, 0.0]
        assert len(p) == N_PARAMS
        return jnp.asarray(p)

    p = params(-40.0, 10.0)
    assert np.degrees(np.asarray(end_slopes_rad(p))) == pytest.approx([40.0, 10.0], abs=1e-9)
    std = np.degrees(np.asarray(steep_end_std(p)))
    on_line = math.degrees(math.atan2(math.sqrt(100.0**2 - 40.0**2), 40.0))
    on_curve = _rim_crossing_deg(-40.0, (60.0, 42.0), "A")
    assert on_curve > on_line + 15.0  # A lies well up the rim from the line's end
    assert std[1] == pytest.approx(on_curve - on_line, rel=1e-6)
    assert std[0] == 0.0 and std[2] == 0.0  # z0 is the line's; the exit end is no steeper
    # Just either side of the limit; and the same tangent the other way up is as steep.
    assert float(steep_end_std(params(-(MAX_END_SLOPE_DEG - 0.5), 10.0))[1]) == 0.0
    assert float(steep_end_std(params(-(MAX_END_SLOPE_DEG + 0.5), 10.0))[1]) > 0.0
    assert np.degrees(float(end_slopes_rad(params(140.0, 10.0))[0])) == pytest.approx(40.0)
    # Finite gradients, steep or not (calibration and training differentiate through sigma).
    for q in (p, params(-5.0, 3.0)):
        g = jax.grad(lambda x: jnp.sum(steep_end_std(x)))(q)
        assert bool(jnp.all(jnp.isfinite(g)))
