"""Plausibility stage: does the fitted model explain the picture? (issue 12, item 5)

A fit always returns numbers; on footage the segmentation did not understand (a colour cast that
makes the wall wheel-coloured, dust that makes the lower wheel soil-coloured, a shadow that eats
half of the face) they can be far off while the fit's own covariance stays small. This stage
weighs the model against its own inputs, with no threshold taken from the renderer:

- **mask vs rim circle**: on the lower half of a ring just inside the fitted rim (below O, where
  the boundary and its ends are), the part above the fitted soil line is wheel by the model's
  own account, the part below it soil. The fraction of that half ring where the mask says
  otherwise is the disagreement. Lugs, holes, hub and highlights never reach this ring on a
  wheel the mask understood, so a disagreement over more than a tenth of the rim (36 degrees, a
  fifth of the half ring) means the mask and the model describe different pictures. The upper
  half moves no number (a lamp's glow there, which no colour test calls wheel, is harmless) and
  is not tested.
- **no wheel in the soil beyond the rim**: on the lower half of a ring at 1.2 times the rim
  radius (beyond lugs of up to a fifth of the radius), below the equivalent line's extension
  (all of the half ring without contact), only soil can be. A mask that is wheel there took a
  cast shadow or the soil itself for wheel, and the boundary it implies (or its absence: "no
  contact") is that mistake's. Over more than a tenth of those samples, the frame fails. A
  frame read as no contact is held to a nearer ring too, at 1.08 times the radius (clear of the
  rim's edge zone), where a shadow that ends short of 1.2 r shows: there the wheel's own lugs
  are wheel too, so the mask's mean on the lower half counts only by its excess over its mean on
  the upper half, the lugs' share (a wheel's lugs go all round it; a shadow on the soil, or soil
  taken for wheel, lies only below). With contact the soil line has parted wheel from soil, and
  a shadow beyond it moves no number. Above the line the background may take the wheel's colour
  (a colour cast) without harm.
- **residuals vs the outline's own noise**: the rim points' residual variance against the
  variance of the boundary points around the two short end tangents (the same mask's edge noise,
  measured where the model is a straight line over a few pixels). Their ratio, an F statistic,
  inflates sigma by its square root whenever it exceeds one (a Birge ratio). It is reported with
  its 99.9 % point (log-normal approximation, degrees of freedom reduced by the outline's
  correlation length) but sets no status: lugs and JPEG make rim and boundary noise differ.
- **a plausible soil curve**: the boundary must lie below O (the soil cannot cover the hub: the
  confidence rectangle is above it) and reach the rim at both ends: its extreme points may stop
  short of the rim by the end clearance plus a few pixels, not by a tenth of the radius, or A and
  B are extrapolations the data never saw. Its span in x must also be the chord that z0 implies
  on the equivalent line (the boundary is the line's stretch inside the rim), to within half
  (a shallow chord is held to its own depth when ``soft.shallow`` finds it instead).
- **the soil goes on beyond the rim**: the soil surface does not end at the wheel. Just outside
  the rim, past the lugs, below the equivalent line's extension, the image must look more like
  the soil just inside the rim below the line than like what lies above the extension, either
  just below the extension or 3 % of the radius lower (a berm that the wheel pushed up falls
  away beyond the rim). When at both ends it looks like what is above (the background) at
  both depths, the "boundary" is an edge on the wheel itself (soil-coloured dust on its lower
  part, a shadow line). The wheel's cast shadow can darken the soil inside the rim only, so
  the samples are also compared with the soil a fifth of the radius below the extension
  (``soft.probes.soil_lost``).
- **the soil's step stays inside the rim** (a wheel without colour): a step ``soft.soil_step`` finds
  at the rim's edge below the mask's soil (no contact) is the far edge of a dark cast shadow.

- **where the soil line could be** (a sigma, not a test): dust that fades the wheel towards the
  soil's colour, or noise, leaves the mask neither wheel nor soil over a band around the line,
  and the line sits somewhere in it. Outside the outline's own edge zone, the wheel the mask
  keeps below the line (read as the probability that the line is deeper) and the width of the
  mask's fade across it give how far the line could be, in px; the measurements' change for a
  line moved that far (:func:`line_shift_std`) adds to sigma in quadrature. On a frame whose
  mask has a sharp soil edge both are about zero and sigma is unchanged. A shallow chord's depth
  (``soft.shallow``) adds its margin: a shadow or soil just below the rim pulls the edge in as far.
- **an end steeper than soil stands** (a sigma, not a test): an end tangent more than
  :data:`MAX_END_SLOPE_DEG` steeper than the equivalent line is more likely the mask's edge
  running up the inside of the rim than the soil; that end's angle gets the difference to where
  the equivalent line meets the rim in its sigma (:func:`steep_end_std`).

Frames failing any test get status ``implausible`` (their message names the test) instead of a
confident number. Everything is pure JAX, jit- and vmap-able.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ..geometry import entry_angle_rad, exit_angle_rad
from .model import Evidence, end_point, measurements, residuals
from .probes import bilinear, mean_where, on_ring, soil_lost

N_RING_SAMPLES = 256
N_BAND_DEPTH, N_BAND_ALONG = 48, 64  # samples of the disc segment below the soil line
# 99.9 % one-sided normal quantile: the tests' false-alarm rate on a frame the model explains.
_Z_999 = 3.09
# Correlation length of neighbouring outline points, in points: the uncertainty model's sigma
# scales (1.4-3.1 as standard deviations, soft.uncertainty.UncertaintyModel) are of its
# square root's order.
CORRELATION_POINTS = 1.6**2


class Plausibility(eqx.Module):
    """The evidence and the verdict for one frame (all scalars).

    ``ring_disagreement`` (fraction of the ring inside the rim where mask and model disagree),
    ``outer_wheel`` (fraction of the soil beyond the rim, on a ring, that the mask calls wheel),
    ``rim_f`` (rim residual variance over the boundary's local edge noise variance) and
    ``rim_f_limit`` (its 99.9 % point), ``above_centre`` (fraction of boundary weight above O),
    ``end_gap_px`` (the larger distance from a boundary end to the rim), ``chord_ratio``
    (boundary x-span over the chord z0 implies); ``sigma_scale`` multiplies sigma;
    ``line_shift_px`` (how far from the fitted soil line the mask says the line could be, root
    mean square, px) adds to sigma in quadrature (:func:`line_shift_std`); ``code``
    is 0 when plausible, else 1 + the index of the first failed test in :data:`TESTS`.
    """

    ring_disagreement: Float[Array, ""]
    outer_wheel: Float[Array, ""]
    rim_f: Float[Array, ""]
    rim_f_limit: Float[Array, ""]
    above_centre: Float[Array, ""]
    end_gap_px: Float[Array, ""]
    chord_ratio: Float[Array, ""]
    sigma_scale: Float[Array, ""]
    line_shift_px: Float[Array, ""]
    code: Array

    @property
    def plausible(self) -> Bool[Array, ""]:
        return self.code == 0


TESTS: tuple[str, ...] = (
    "the wheel mask disagrees with the fitted rim circle over more than a tenth of the rim",
    "the wheel-soil boundary reaches above the wheel centre",
    "the wheel-soil boundary stops short of the rim (A or B would be extrapolated)",
    "the wheel-soil boundary does not span the chord its sinkage implies",
    "the soil surface does not continue beyond the rim at the boundary's ends",
    "the soil's step lies at the rim where the mask saw soil inside it (a cast shadow's edge)",
    "the wheel mask reaches into the soil beyond the rim (a shadow or the soil taken for wheel)",
)
MAX_RING_DISAGREEMENT = 0.1
# The soft method's ring is the half below O: the same 36 degrees of rim are a fifth of it.
MAX_HALF_RING_DISAGREEMENT = 2 * MAX_RING_DISAGREEMENT
# The ring lies RING_INSET * r (at least RING_INSET_PX) inside the rim: clear of the rim's own
# edge zone.
RING_INSET, RING_INSET_PX = 0.04, 2.0
OUTER_RING = 1.2  # x the rim radius: beyond lugs of up to 0.2 r
NEAR_OUTER_RING = 1.08  # x the rim radius: clear of the rim's edge zone, not of the lugs
MAX_OUTER_WHEEL = 0.1
MAX_ABOVE_CENTRE = 0.05
END_GAP_FRACTION = 0.1
CHORD_RATIO_RANGE = (0.5, 1.5)


def ring_disagreement(
    mask: Float[Array, "H W"], p: Float[Array, " P"], sign: Array, contact: Array
) -> Array:
    """Mean disagreement, in [0, 1], of the mask with the fitted model on the lower half of a
    ring just inside the rim (module docstring): 1 - mask above the equivalent line (all of it
    without ``contact``), the mask below it. Differentiable w.r.t. ``mask``; the check fails
    above ``MAX_HALF_RING_DISAGREEMENT``."""
    r = p[2]
    rho = r - jnp.maximum(RING_INSET_PX, RING_INSET * r)
    phi = jnp.linspace(0.0, jnp.pi, N_RING_SAMPLES // 2, dtype=mask.dtype)  # y down: lower half
    m, seen, u, v = on_ring(mask, p, sign, rho, phi)
    # Wheel above the equivalent line (y down); without contact the whole half ring is wheel.
    wheel_side = ~contact | (v < p[3] * u + p[4])
    return mean_where(jnp.where(wheel_side, 1.0 - m, m), seen)


def outer_wheel(
    mask: Float[Array, "H W"], p: Float[Array, " P"], sign: Array, contact: Array
) -> Array:
    """What the mask calls wheel where only soil can be, in [0, 1]: its mean on the lower half
    of a ring at ``OUTER_RING`` times the rim radius (the part inside the image), below the
    equivalent line's extension where there is contact; without contact, the larger of that and
    the mask's excess on the lower half of a ring at ``NEAR_OUTER_RING`` times the radius over
    its mean on the upper half of that ring (the wheel's own lugs reach that far all round, a
    shadow on the soil or soil taken for wheel only below; with contact the soil line has
    already parted wheel from soil, and wheel in the soil beyond it moves no number).
    Differentiable w.r.t. ``mask``; the check fails above ``MAX_OUTER_WHEEL``."""
    phi = jnp.linspace(0.0, jnp.pi, N_RING_SAMPLES // 2, dtype=mask.dtype)  # y down: lower half
    m, seen, u, v = on_ring(mask, p, sign, OUTER_RING * p[2], phi)
    far = mean_where(m, seen & (~contact | (v > p[3] * u + p[4])))
    m, seen, _, _ = on_ring(mask, p, sign, NEAR_OUTER_RING * p[2], phi)
    m_up, seen_up, _, _ = on_ring(mask, p, sign, NEAR_OUTER_RING * p[2], phi + jnp.pi)
    excess = mean_where(m, seen) - mean_where(m_up, seen_up)
    return jnp.where(contact, far, jnp.maximum(far, excess))


def _segment(
    mask: Float[Array, "H W"], p: Float[Array, " P"], sign: Array, start_px: Array, side: float
) -> tuple[Array, Array, Array]:
    """The mask sampled on the disc (inside the ring of :func:`ring_disagreement`) from
    ``start_px`` on below (``side`` +1) or above (-1) the equivalent line, as deep as the segment
    below it reaches: (mask, depth beyond ``start_px``, area px^2 per chord px) per sample."""
    height, width = mask.shape
    dt = mask.dtype
    r, k = p[2], p[3]
    rho = r - jnp.maximum(RING_INSET_PX, RING_INSET * r)
    norm = jnp.sqrt(1.0 + k * k)
    d0 = p[4] / norm  # the line's distance below O along its downward normal
    n, t = jnp.stack([-k, 1.0]) / norm, jnp.stack([1.0, k]) / norm
    depth = jnp.maximum(rho - d0 - start_px, 0.0)
    frac_s = (jnp.arange(N_BAND_DEPTH, dtype=dt) + 0.5) / N_BAND_DEPTH
    frac_a = (jnp.arange(N_BAND_ALONG, dtype=dt) + 0.5) / N_BAND_ALONG * 2.0 - 1.0
    s = start_px + frac_s * depth  # distance from the line, px
    off = d0 + side * s
    half = jnp.sqrt(jnp.maximum(rho * rho - off**2, 1e-12))
    a = frac_a[None, :] * half[:, None]
    x = p[0] + sign * (a * t[0] + off[:, None] * n[0])
    y = p[1] + a * t[1] + off[:, None] * n[1]
    seen = (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
    m = jnp.where(seen, bilinear(mask, x.ravel(), y.ravel()).reshape(x.shape), 0.0)
    chord = 2.0 * jnp.sqrt(jnp.maximum(rho * rho - d0 * d0, 1.0))
    area = (2.0 * half / N_BAND_ALONG * depth / N_BAND_DEPTH)[:, None] / chord
    return m, jnp.broadcast_to((s - start_px)[:, None], m.shape), jnp.broadcast_to(area, m.shape)


def _line_shift(
    mask: Float[Array, "H W"], p: Float[Array, " P"], sign: Array, edge_px: Array
) -> tuple[Array, Array, Array]:
    """How far the soil line could be from the fitted one by the mask's own account, px:
    (mass, rms, fade).

    Mask structure within ``edge_px`` (the outline's own search half-width) of the equivalent
    line is the edge itself and is left out. Below that zone, read the soft mask at depth s as
    the probability that the soil line lies deeper than s (wheel there means the line is below
    it): ``mass``, the mask's integral per unit of chord, is then the expected depth D of the
    true line below the fitted one and ``rms`` = sqrt(E[D^2]) = sqrt(2 * integral of s * mask)
    (E[D^2] = 2 * integral of s P(D > s) ds). ``fade`` is the width of the mask's transition
    across the line on both sides of the edge zone (as deep above as the segment reaches
    below), as the integral of mask * (1 - mask) per unit of chord: a mask that fades from wheel
    to soil over a band of width L (soil-coloured dust, noise) gives L / 6, a sharp edge 0.
    """
    m, s, area = _segment(mask, p, sign, edge_px, 1.0)
    m_up, _, area_up = _segment(mask, p, sign, edge_px, -1.0)
    mass = jnp.sum(m * area)
    second = 2.0 * jnp.sum(m * area * s)
    fade = jnp.sum(m * (1.0 - m) * area) + jnp.sum(m_up * (1.0 - m_up) * area_up)
    # A mask pushed a little below 0 (a gradient check, a learned segmenter) must not make the
    # second moment negative: a NaN sigma.
    return mass, jnp.sqrt(jnp.maximum(second, 0.0) + 1e-12), fade


def _variance(res: Array, w: Array) -> tuple[Array, Array]:
    # Residual variance of a group (res carries sqrt(w)) and its effective degrees of freedom.
    sw = jnp.sum(w)
    dof = jnp.maximum(sw - 3.0, 1.0)
    return jnp.sum(res * res) / dof, jnp.maximum(dof / CORRELATION_POINTS, 1.0)


def plausibility(
    image: Float[Array, "H W 3"],
    mask: Float[Array, "H W"],
    p: Float[Array, " P"],
    ev: Evidence,
    contact: Array,
    stepped_out: Array | bool = False,
) -> Plausibility:
    """The plausibility tests for the fitted ``p`` of one frame (see the module docstring).
    ``stepped_out``: the soil's step moved the mask's soil line down out of the rim."""
    dt = p.dtype
    n = ev.x_px.shape[0]
    res = residuals(p, ev)
    var_rim, dof_rim = _variance(jnp.where(ev.w_rim > 0, res[:n], 0.0), ev.w_rim)
    var_end, dof_end = _variance(res[n : 2 * n], ev.w_a + ev.w_b)
    floor = jnp.asarray(0.05**2, dt)  # as soft.uncertainty: no edge is better than 0.05 px
    rim_f = jnp.maximum(var_rim, floor) / jnp.maximum(var_end, floor)
    rim_f_limit = jnp.exp(_Z_999 * jnp.sqrt(2.0 / dof_rim + 2.0 / dof_end))
    has_ends = jnp.sum(ev.w_a + ev.w_b) >= 6.0

    u = ev.sign * (ev.x_px - p[0])
    v = ev.y_px - p[1]
    w = ev.w_line
    sw = jnp.maximum(jnp.sum(w), 1e-9)
    above = jnp.sum(jnp.where(v < 0, w, 0.0)) / sw
    present = w > 0.5 * jnp.max(w)
    d = jnp.sqrt(u * u + v * v + 1e-12)
    i_a = jnp.argmax(jnp.where(present, u, -jnp.inf))
    i_b = jnp.argmin(jnp.where(present, u, jnp.inf))
    gap = jnp.maximum(p[2] - d[i_a], p[2] - d[i_b])
    dist = jnp.abs(p[4]) / jnp.sqrt(p[3] ** 2 + 1.0)
    # Edges count as boundary from ``ev.inner_px`` inside the rim, and the soil/rim corner can
    # add points up to the rim itself: the span lies between the chords of the two circles
    # (for a shallow contact they differ by half or more, so neither alone is the reference).
    r_in = p[2] - ev.inner_px.astype(dt)
    slope = jnp.sqrt(p[3] ** 2 + 1.0)
    chord = 2.0 * jnp.sqrt(jnp.maximum(r_in**2 - dist**2, 1.0)) / slope
    chord_full = 2.0 * jnp.sqrt(jnp.maximum(p[2] ** 2 - dist**2, 1.0)) / slope
    span = u[i_a] - u[i_b]
    chord_ratio = span / chord
    chord_wrong = (chord_ratio < CHORD_RATIO_RANGE[0]) | (span / chord_full > CHORD_RATIO_RANGE[1])
    # A shallow chord (soft.shallow) passed this test against its own depth when found; the
    # chord 2 sqrt(2 r (z0 - margin)) halves or doubles as a sub-pixel z0 moves by its sigma.
    chord_wrong = chord_wrong & ~(ev.shallow_chord > 0)

    ring = ring_disagreement(mask, p, ev.sign, contact)
    outer = outer_wheel(mask, p, ev.sign, contact)
    # The ends' points start where the boundary does, or the clearance further in if larger.
    clearance = jnp.maximum(ev.settings.end_clearance_px.astype(dt), ev.inner_px.astype(dt))
    fails = jnp.stack(
        [
            ring > MAX_HALF_RING_DISAGREEMENT,
            contact & (above > MAX_ABOVE_CENTRE),
            contact & (gap > clearance + jnp.maximum(3.0, END_GAP_FRACTION * p[2])),
            contact & chord_wrong,
            contact & soil_lost(image, p, ev.sign),
            jnp.asarray(stepped_out),
            outer > MAX_OUTER_WHEEL,
        ]
    )
    code = jnp.where(jnp.any(fails), 1 + jnp.argmax(fails), 0).astype(jnp.int32)
    sigma_scale = jnp.sqrt(jnp.where(has_ends, jnp.maximum(rim_f, 1.0), 1.0))
    edge_px = jnp.asarray(ev.settings.refine_half_width_px, dt)
    _, shift_rms, fade = _line_shift(mask, p, ev.sign, edge_px)
    # The line may sit anywhere in a fade of width L = 6 fade: a uniform spread of L / sqrt(12)
    # = sqrt(3) fade about it, on top of the one-sided shift the mask's wheel below it implies.
    shift = jnp.sqrt(shift_rms**2 + 3.0 * fade**2)
    # A shallow chord's depth is known to its margin (fit.build_evidence; module docstring).
    shift = jnp.sqrt(shift**2 + ev.shallow_chord**2)
    return Plausibility(
        ring_disagreement=ring,
        outer_wheel=outer,
        rim_f=rim_f,
        rim_f_limit=rim_f_limit,
        above_centre=above,
        end_gap_px=gap,
        chord_ratio=chord_ratio,
        sigma_scale=sigma_scale,
        line_shift_px=jnp.where(contact, shift, 0.0),
        code=code,
    )


def line_shift_std(
    p: Float[Array, " P"], check: Plausibility, wheel_radius_mm: float | Float[Array, ""]
) -> Float[Array, " 3"]:
    """The sigma (z0 mm, theta1 rad, theta2 rad) of the soil line's ambiguity: the measurements'
    change when the equivalent line and both end lines move down by ``check.line_shift_px``."""
    k = p[3]
    down = jnp.zeros_like(p).at[4].set(jnp.sqrt(1.0 + k * k)).at[6].set(1.0).at[8].set(1.0)
    g = jax.jacfwd(measurements)(p, wheel_radius_mm)
    return jnp.abs(g @ down) * check.line_shift_px


# A soil surface at rest is no steeper than its angle of repose: 30-35 degrees for dry sand and
# most regolith simulants. An end tangent steeper than this against the equivalent line is more
# likely the mask's edge running up the inside of the rim (a shaded or dusted rim ring taken for
# soil) than the soil (experiments/end_steepness.py).
MAX_END_SLOPE_DEG = 30.0


def end_slopes_rad(p: Float[Array, " P"]) -> Float[Array, " 2"]:
    """The acute angle (rad, in [0, pi/2]) between each end's tangent (A, B) and the
    equivalent line, both in the wheel frame (``soft.model``)."""
    d = p[jnp.asarray([5, 7])] - jnp.arctan(p[3])
    return jnp.arctan2(jnp.abs(jnp.sin(d)), jnp.abs(jnp.cos(d)))


def line_end_angles_rad(p: Float[Array, " P"]) -> Float[Array, " 2"]:
    """(theta1, theta2) rad where the equivalent line meets the rim (the paper's A and B)."""
    alpha = jnp.arctan(p[3])
    c = p[4] * jnp.cos(alpha)  # the line y = k x + b as -sin(a) u + cos(a) v = c
    a, b = end_point(alpha, c, p[2], 1.0), end_point(alpha, c, p[2], -1.0)
    return jnp.stack([entry_angle_rad(a[0], a[1]), exit_angle_rad(b[0], b[1])])


def steep_end_std(p: Float[Array, " P"]) -> Float[Array, " 3"]:
    """The sigma (z0 mm, theta1 rad, theta2 rad) of an end whose tangent is steeper than soil
    rests (:data:`MAX_END_SLOPE_DEG`) against the equivalent line: the difference between that
    end's angle and the angle at which the equivalent line meets the rim (the paper's A or B).
    Two models of the end that disagree that much say the end lies somewhere between them; 0
    for an end no steeper (its curve is trusted, as its own sigma says)."""
    steep = end_slopes_rad(p) > jnp.radians(MAX_END_SLOPE_DEG)
    apart = jnp.where(steep, jnp.abs(measurements(p)[1:] - line_end_angles_rad(p)), 0.0)
    return jnp.concatenate([jnp.zeros((1,), p.dtype), apart])


def message(code: int) -> str:
    """Words for a :class:`Plausibility` ``code`` (empty for 0)."""
    if code <= 0:
        return ""
    return TESTS[code - 1] + "; the numbers are not trustworthy (check the segmentation: calibrate)"
