"""Fit stage: assign outline points to rim / boundary / ends, then one optimistix solve.

Group membership is decided once, from the Hough circle, and then held fixed: that keeps the
problem an ordinary weighted least squares (so Levenberg-Marquardt converges quadratically) and
lets implicit differentiation carry gradients from the mask through the weights and the
sub-pixel point positions to the parameters.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Float

from ..geometry import equivalent_line
from .ends import end_weights, orthogonal_line
from .hough import Circle
from .model import Evidence, residuals
from .outline import Outline, compact
from .settings import SoftSettings
from .shallow import shallow_boundary


def _window_means(
    t: Float[Array, " K"], value: Float[Array, " K"], w: Float[Array, " K"], half: Array
) -> tuple[Float[Array, " K"], Float[Array, " K"]]:
    """Weighted mean of ``value`` over the points with weight ``w`` > 0 whose ``t`` lies within
    ``half`` of each point's, and the weight summed there (cumulative sums over sorted ``t``)."""
    key = jnp.where(w > 0, t, jnp.inf)
    order = jnp.argsort(key)
    ts = key[order]
    zero = jnp.zeros(1, value.dtype)
    cw = jnp.concatenate([zero, jnp.cumsum(w[order])])
    cv = jnp.concatenate([zero, jnp.cumsum((w * value)[order])])
    lo = jnp.searchsorted(ts, t - half, side="left")
    hi = jnp.searchsorted(ts, t + half, side="right")
    sw = cw[hi] - cw[lo]
    return (cv[hi] - cv[lo]) / jnp.maximum(sw, 1e-9), sw


def _weighted_median(a: Float[Array, " K"], w: Float[Array, " K"]) -> Float[Array, ""]:
    """Weighted median of ``a`` over the points with ``w`` > 0 (inf when there are none)."""
    a = jnp.where(w > 0, a, jnp.inf)
    order = jnp.argsort(a)
    cw = jnp.cumsum(w[order])
    idx = jnp.clip(jnp.searchsorted(cw, 0.5 * cw[-1]), 0, a.shape[0] - 1)
    return jnp.where(cw[-1] > 0, a[order][idx], jnp.inf)


def inner_margin_px(
    u: Float[Array, " K"],
    v: Float[Array, " K"],
    dr: Float[Array, " K"],
    w_rim: Float[Array, " K"],
    r_px: Float[Array, ""],
    rim_weight: float | Float[Array, ""],
    settings: SoftSettings,
) -> Float[Array, ""]:
    """How far inside the rim (px) the lower edge must lie, on average over a contact window, to
    be soil rather than the rim edge's own error.

    With the recording's rim (``rim_weight`` > 0: known to its sigma) the frame measures that
    error itself: the mean of d - r over windows of the same length along its rim points, whose
    spread (1.4826 x the weighted median of their absolute value; the known circle is the
    reference, so its own error is in it) includes what averaging does not remove (JPEG blocks,
    shading: neighbouring edge points err together). The margin is ``contact_z`` such spreads,
    with the rim's sigma added. Never more than ``rim_band_in_px``, the margin with a frame's own
    rim (found to about a pixel). A threshold, not a measurement: no gradient flows through it.
    """
    s = settings.astype(dr.dtype)
    u, v, dr, w_rim = (jax.lax.stop_gradient(a) for a in (u, v, dr, w_rim))
    arc = jnp.arctan2(u, v) * jax.lax.stop_gradient(r_px)
    mean, _ = _window_means(arc, dr, w_rim, s.contact_window_px)
    spread = 1.4826 * _weighted_median(jnp.abs(mean), w_rim)
    rim_weight = jnp.asarray(rim_weight, dr.dtype)
    known = (rim_weight > 0) & jnp.isfinite(spread)
    rim_var = jnp.where(known, 1.0 / jnp.where(known, rim_weight, 1.0), 0.0)
    margin = s.contact_z * jnp.sqrt(jnp.where(known, spread, 0.0) ** 2 + rim_var)
    return jnp.where(known, jnp.minimum(margin, s.rim_band_in_px), s.rim_band_in_px)


def boundary_side(
    u: Float[Array, " K"],
    dr: Float[Array, " K"],
    lower: Float[Array, " K"],
    inner_px: Float[Array, ""],
    settings: SoftSettings,
) -> Bool[Array, " K"]:
    """Which outline points lie inside the rim as soil boundary (not rim evidence).

    A point clearly inside (``rim_band_in_px``) does where the deepest such stretch reaches it
    without crossing the rim edge (a candidate neither clearly inside nor in a dip): the soil is
    one curve from B to A, while a noisy rim edge (low light, a mask that stops short of the rim)
    dips inside it here and there beyond them. Nearer the rim one point's offset is
    mostly edge error, but a shallow soil edge is a long, smooth dip below the rim (a chord of
    2 sqrt(2 r z0) px): the mean offset d - r of the lower edge points within
    ``contact_window_px`` in u (weights ``lower``: facing down, soil below, one per column) must
    lie more than ``inner_px`` inside, and the dip must reach the rim's lowest point (u = 0)
    without a break. A wheel resting on the ground touches it first there (the camera is fixed
    to the rover, so the ground under the wheel is level in the wheel frame to within its local
    slope), while the rim edge's own errors (JPEG blocks, shading) sit anywhere along the rim.
    Points beyond the rim's outer band (lug tips) take no part.
    """
    s = settings.astype(dr.dtype)
    u, dr, lower = (jax.lax.stop_gradient(a) for a in (u, dr, lower))
    wc = jnp.where((lower > 0.1) & (dr <= s.rim_band_out_px), lower, 0.0)
    mean, sw = _window_means(u, dr, wc, s.contact_window_px)
    deep = dr < -s.rim_band_in_px
    dip = (wc > 0) & (sw > 0) & (mean < -inner_px)
    # Candidates that are not in the dip, counted between u = 0 and each point: none for a
    # point of the dip connected to the lowest point.
    gap = ((wc > 0) & ~(dip | deep)).astype(dr.dtype)
    key = jnp.where(wc > 0, u, jnp.inf)
    order = jnp.argsort(key)
    us = key[order]
    cg = jnp.concatenate([jnp.zeros(1, dr.dtype), jnp.cumsum(gap[order])])
    zero = jnp.zeros((), dr.dtype)

    def joined(anchor: Array) -> Array:
        at = jnp.searchsorted(us, jnp.minimum(u, anchor), side="left")
        to = jnp.searchsorted(us, jnp.maximum(u, anchor), side="right")
        return (cg[to] - cg[at]) < 0.5

    connected = joined(zero)
    # A deep boundary is one soil curve: the points clearly inside the rim that the deepest
    # stretch reaches without crossing the rim edge (a noisy rim edge beyond A or B dips inside
    # it here and there, apart from the soil's curve).
    depth = jnp.where((wc > 0) & deep, mean, jnp.inf)
    i_deep = jnp.argmin(depth)
    deep = deep & (joined(u[i_deep]) | ~jnp.isfinite(depth[i_deep]))
    # Where the soil is clearly inside the rim the dip adds only the corners where soil edge
    # and rim edge meet, which smoothing rounds and a thin wedge of background shifts: those
    # stay out, as the ends' tangents keep ``end_clearance_px`` from them.
    shallow = jnp.sum(jnp.where(deep, wc, 0.0)) < s.min_boundary_points
    return deep | (shallow & dip & connected)


def build_evidence(
    outline: Outline,
    circle: Circle,
    sign: float | Float[Array, ""],
    settings: SoftSettings,
    rim_weight: float | Float[Array, ""] = 0.0,
) -> Evidence:
    """Group weights for every outline point, and the solve's starting point.

    ``rim_weight`` (1/px^2) holds the fitted circle to ``circle`` (the recording's rim,
    ``soft.rim``); 0 leaves it free (``circle`` is then only where the solve starts).

    The bands around the rim decide which points are rim evidence, which may be boundary (well
    inside the rim, facing down, soil below them) and which may hold the ends' tangents (clear
    of the corner where the soil edge meets the rim edge); see :class:`SoftSettings`.
    """
    dt = outline.x_px.dtype
    s = settings.astype(dt)
    u = sign * (outline.x_px - circle.cx_px)
    v = outline.y_px - circle.cy_px
    d = jnp.sqrt(u * u + v * v + 1e-12)
    # Alignment of the (wheel -> outside) normal with the outward radial direction.
    align = (outline.x_px - circle.cx_px) * outline.nx + (outline.y_px - circle.cy_px) * outline.ny
    align = align / d
    w = outline.weight
    dr = d - circle.r_px
    outer = jax.nn.sigmoid((0.3 - outline.mask_beyond) / 0.05)
    faces_down = jax.nn.sigmoid((outline.ny - 0.3) / 0.1)
    soil_below = jnp.exp(-outline.wheel_below_px / s.wheel_below_scale_px)
    # Non-maximum suppression leaves one point per column on gentle edges and one per row on
    # steep ones; re-weight to one per unit x so the fit matches Eq. 1 on the true curve.
    per_x = jnp.minimum(1.0, jnp.abs(outline.ny) / jnp.maximum(jnp.abs(outline.nx), 1e-3))
    lower = w * faces_down * soil_below * per_x
    is_rim = (dr >= -s.rim_band_in_px) & (dr <= s.rim_band_out_px)
    rim_like = w * jax.nn.sigmoid((align - 0.75) / 0.05) * outer
    inner_px = inner_margin_px(u, v, dr, rim_like * is_rim.astype(dt), circle.r_px, rim_weight, s)
    inside = boundary_side(u, dr, lower, inner_px, s)
    # A shallow contact against the recording's rim: the envelope of rim and soil line says
    # which points are the soil (``soft.shallow``); offsets from the rim alone cannot.
    use_env, on_env, z_env = shallow_boundary(
        u, v, lower, circle.r_px, s.min_boundary_points, inner_px
    )
    with_rim = jnp.asarray(rim_weight, dt) > 0
    chord = with_rim & use_env
    chord_margin = jnp.where(chord, jnp.maximum(inner_px, 1e-3), 0.0)
    inside = jnp.where(chord, on_env, inside)
    # The margin the boundary actually starts at (the dip's only for a shallow contact).
    deep_weight = jnp.sum(jnp.where((dr < -s.rim_band_in_px) & (lower > 0.1), lower, 0.0))
    inner_px = jnp.where(deep_weight < s.min_boundary_points, inner_px, s.rim_band_in_px)
    w_rim = rim_like * (is_rim & ~inside).astype(dt)
    w_line = lower * inside.astype(dt)

    # The ends' tangents come from boundary points clear of the corner where the soil edge meets
    # the rim edge (smoothing rounds that corner over a few pixels and would bend them upward).
    clear = (dr < -s.end_clearance_px).astype(dt)
    w_end = w_line * clear
    w_a, w_b, i_a, i_b = end_weights(u, v, w_end, circle.r_px, s)

    k0, b0 = equivalent_line(u, v, w_line)
    # An end with too few points (a very short boundary) starts from the equivalent line.
    line_alpha = jnp.arctan(k0)
    line_c = b0 * jnp.cos(line_alpha)
    alpha_a, c_a = orthogonal_line(u, v, w_a)
    alpha_b, c_b = orthogonal_line(u, v, w_b)
    few_a = jnp.sum(w_a) < 3.0
    few_b = jnp.sum(w_b) < 3.0
    alpha_a, c_a = jnp.where(few_a, line_alpha, alpha_a), jnp.where(few_a, line_c, c_a)
    alpha_b, c_b = jnp.where(few_b, line_alpha, alpha_b), jnp.where(few_b, line_c, c_b)
    zero = jnp.zeros((), dt)
    start = jnp.stack(
        [circle.cx_px, circle.cy_px, circle.r_px, k0, b0, alpha_a, c_a, alpha_b, c_b, zero, zero]
    ).astype(dt)
    # Each end's curve bends away from its end-most point; the equivalent line's point in the
    # same column anchors its offset prior (the line is the same image line whatever circle it
    # was computed about: Eq. 1's least squares is invariant to shifting the frame).
    origin = jnp.stack(
        [
            jnp.stack([outline.x_px[i_a], outline.y_px[i_a]]),
            jnp.stack([outline.x_px[i_b], outline.y_px[i_b]]),
        ]
    )
    u_origin = sign * (origin[:, 0] - circle.cx_px)
    return Evidence(
        x_px=outline.x_px,
        y_px=outline.y_px,
        w_rim=w_rim,
        w_line=w_line,
        w_a=w_a,
        w_b=w_b,
        sign=jnp.asarray(sign, dt),
        start=start,
        settings=s,
        rim_px=start[:3],
        # The ends' priors matter only where an end has few points of its own.
        end_prior_scale=1.0 / (1.0 + jnp.stack([jnp.sum(w_a), jnp.sum(w_b)])),
        end_origin_px=origin,
        end_anchor_px=jnp.stack([origin[:, 0], circle.cy_px + k0 * u_origin + b0], axis=1),
        rim_weight=jnp.asarray(rim_weight, dt),
        inner_px=inner_px,
        shallow_chord=chord_margin.astype(dt),
        envelope_depth_px=jnp.where(with_rim, z_env, 0.0).astype(dt),
    )


class FitResult(eqx.Module):
    params: Float[Array, " P"]
    residuals: Float[Array, " N"]
    ok: Array
    steps: Array


def weighted_points(ev: Evidence, size: int) -> tuple[Evidence, Bool[Array, ""]]:
    """``ev`` with only its points of some weight (rim, boundary or an end), the first ``size``
    of them in outline order, padded with points of weight 0; and whether they all fit.

    Most outline slots carry no weight (padding, lugs, holes, texture edges: at 640x480 about
    a fifth of the slots are weighted, at most 0.28 on the full mix), yet each costs the solve a
    residual row at every step. The weighted points lie on the rim's band and the soil
    boundary, about one per pixel of their length: within an H x W image at most about
    3 (H + W) of them, half the outline's default capacity (:func:`rim_and_boundary_capacity`).
    """
    weighted = (ev.w_rim > 0) | (ev.w_line > 0) | (ev.w_a > 0) | (ev.w_b > 0)
    idx, count = compact(weighted, size)
    keep = (jnp.arange(size, dtype=count.dtype) < count).astype(ev.x_px.dtype)
    weights = tuple(w[idx] * keep for w in (ev.w_rim, ev.w_line, ev.w_a, ev.w_b))
    small = eqx.tree_at(
        lambda e: (e.x_px, e.y_px, e.w_rim, e.w_line, e.w_a, e.w_b),
        ev,
        (ev.x_px[idx], ev.y_px[idx], *weights),
    )
    return small, count <= size


def rim_and_boundary_capacity(height: int, width: int) -> int:
    """How many weighted points the solve makes room for in an H x W frame: an arc of the rim
    inside the image is at most about 1.6 (H + W) px long and the boundary at most 1.4 W, one
    point per pixel (non-maximum suppression)."""
    return 3 * (height + width)


def fit(ev: Evidence, *, max_steps: int = 256, capacity: int | None = None) -> FitResult:
    """The single joint Levenberg-Marquardt solve (implicit differentiation through it).

    Clean frames converge in a few tens of steps; a frame whose ends bend strongly under dust
    may need more than a hundred (the ends' robust loss), and a cap it hits reads as
    ``fit_failed``, so the cap is generous.

    ``capacity`` (static): the solve sees only the weighted points (:func:`weighted_points`),
    at most this many: the same least-squares problem at a fraction of the cost a step (the
    estimator passes :func:`rim_and_boundary_capacity`, half the outline's slots). A frame with
    more weighted points is solved on every slot instead, never on some of them: on the full mix
    none comes near, but a mask speckled inside the rim (strong one-sided shading) can give 3500-
    4200 weighted points at 640x480 against 3360. None: every slot. ``residuals`` are over all
    of ``ev``'s slots."""
    # Normal equations + Cholesky: the Jacobian is tall (thousands of points x 11 parameters) and
    # well conditioned, and this is several times faster than QR on the CPU.
    # Tolerances on the step and the objective: 1e-4 is far below anything measurable (0.02 px on
    # a 150 px offset, 0.006 deg on an angle), while tighter ones sit at float32 rounding noise of
    # a sum over thousands of residuals and make convergence a coin toss.
    solver: optx.LevenbergMarquardt = optx.LevenbergMarquardt(
        rtol=1e-4, atol=1e-4, linear_solver=lx.Normal(lx.Cholesky())
    )

    def solve(args: Evidence) -> tuple[Array, Array, Array]:
        sol: optx.Solution = optx.least_squares(
            residuals, solver, ev.start, args=args, max_steps=max_steps, throw=False
        )
        converged = jnp.asarray(sol.result == optx.RESULTS.successful)
        return sol.value, converged, sol.stats["num_steps"]

    if capacity is None or capacity >= ev.x_px.shape[0]:
        p, converged, steps = solve(ev)
    else:
        small, complete = weighted_points(ev, capacity)
        # More weighted points than the capacity (a speckled mask): the solve on every slot.
        # One branch runs on a CPU (frame by frame); under vmap both do.
        p, converged, steps = jax.lax.cond(complete, solve, lambda _: solve(ev), small)
    ok = converged & jnp.all(jnp.isfinite(p))
    return FitResult(params=p, residuals=residuals(p, ev), ok=ok, steps=steps)
