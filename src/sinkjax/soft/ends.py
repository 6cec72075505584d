"""The two ends of the wheel-soil boundary: where each lies, and which points hold its tangent.

A and B are where the soil surface meets the rim; the fit (``soft.model``) finds each as the
intersection of a short curve with the rim, fitted over a window of boundary next to the end,
its points down-weighted with their distance from the end (:func:`end_kernel`). The window's
length trades noise against bias: a long one averages the edge's noise, but a feature of the
terrain inside it (a rut's or a pile's edge, which the curve's single bend cannot follow) pulls
the end off the surface's own crossing. :func:`chosen_window` picks the length per end and per
frame from the data, by the rule of intersecting confidence intervals (Goldenshluger and
Nemirovski 1997; Katkovnik 1999): the crossing is estimated over a ladder of windows from short
to long, each with its standard error from its own residuals, and the longest window is kept
whose estimate still agrees with every shorter one's. On a straight or gently curved surface
that is the longest window; where a rut's edge enters the window the estimates drift by more
than their noise and the ladder stops before it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .model import end_point
from .settings import SoftSettings

WINDOW_STEPS = 5  # windows in the ladder, geometric from the shortest to the longest


def end_window_px(r_px: Array, settings: SoftSettings) -> Array:
    """The longest length of boundary used to find each end's tangent (:func:`chosen_window`
    picks each end's own, up to this): short enough to follow the surface.

    Whole pixels: the circle it scales with is found without a gradient (the Hough search), and
    the window's taper (:func:`end_kernel`) would otherwise move with it where ``jax.grad``
    cannot see."""
    s = settings.astype(r_px.dtype)
    return jnp.round(
        jnp.clip(s.end_window_fraction * r_px, s.end_window_min_px, s.end_window_max_px)
    )


def end_kernel(dist2_px2: Array, window_px: Array, taper: Array) -> Array:
    """Weight of a boundary point at squared distance ``dist2_px2`` from an end in that end's
    window: 0 beyond the window; inside it 1 - taper + taper * (1 - (d / window)^2)^2 (a
    biweight kernel for ``taper`` 1), so that the points next to the rim decide the end's
    tangent and a rut's or a bump's edge at the far side of the window pulls less. Squared
    distances: the end point's own distance is 0, where a norm's gradient is NaN."""
    w2 = window_px * window_px
    q2 = jnp.clip(dist2_px2 / w2, 0.0, 1.0)
    inside = (dist2_px2 < w2).astype(dist2_px2.dtype)
    return inside * (1.0 - taper + taper * (1.0 - q2) ** 2)


def boundary_ends(u: Array, present: Array, window_px: Array) -> tuple[Array, Array]:
    """Indices of the boundary's end-most points, A's (largest u) and B's (smallest u), among
    the ``present`` ones that start a stretch of boundary: at least half of the end's window
    (``window_px`` along u, towards the other end) holds present points (about one a pixel on
    an edge). A stray edge beyond a gap (a lug's or a hole's corner near the rim, a speck) would
    otherwise be the end, and the window's taper (:func:`end_kernel`) gives the end-most points
    the most say in the tangent. Where no point starts such a stretch (a boundary shorter than
    half a window), the plain extremes. Discrete choices: no gradient flows through them."""
    dt = u.dtype
    su = jnp.sort(jnp.where(present, u, jnp.inf))
    idx = jnp.arange(su.shape[0], dtype=jnp.int32)
    valid = idx < jnp.sum(present.astype(jnp.int32)).astype(jnp.int32)
    need = 0.5 * window_px.astype(dt)

    def count(a: Array, b: Array) -> Array:
        return (a - b).astype(dt)

    # Present points in [u_i, u_i + window) and in (u_i - window, u_i].
    ahead = count(jnp.searchsorted(su, su + window_px, side="left").astype(jnp.int32), idx)
    from_b = valid & (ahead >= need)
    u_b = jnp.where(jnp.any(from_b), su[jnp.argmax(from_b)], -jnp.inf)
    behind = count(idx + 1, jnp.searchsorted(su, su - window_px, side="right").astype(jnp.int32))
    to_a = valid & (behind >= need)
    last = su.shape[0] - 1 - jnp.argmax(to_a[::-1])
    u_a = jnp.where(jnp.any(to_a), su[last], jnp.inf)
    i_a = jnp.argmax(jnp.where(present & (u <= u_a), u, -jnp.inf))
    i_b = jnp.argmin(jnp.where(present & (u >= u_b), u, jnp.inf))
    return i_a, i_b


def _line_and_centroid(u: Array, v: Array, w: Array) -> tuple[Array, Array, Array, Array]:
    # Total least squares line through weighted points (angle, offset from O) and the points'
    # weighted centroid, which the line passes through.
    sw = jnp.maximum(jnp.sum(w), 1e-9)
    um, vm = jnp.sum(w * u) / sw, jnp.sum(w * v) / sw
    suu = jnp.sum(w * (u - um) ** 2)
    svv = jnp.sum(w * (v - vm) ** 2)
    suv = jnp.sum(w * (u - um) * (v - vm))
    alpha = 0.5 * jnp.arctan2(2 * suv, suu - svv + 1e-12)
    return alpha, -jnp.sin(alpha) * um + jnp.cos(alpha) * vm, um, vm


def orthogonal_line(u: Array, v: Array, w: Array) -> tuple[Array, Array]:
    """Total least squares line through weighted points: its angle and its offset from O."""
    alpha, c, _, _ = _line_and_centroid(u, v, w)
    return alpha, c


def _crossing_and_error(
    u: Float[Array, " K"],
    v: Float[Array, " K"],
    w: Float[Array, " K"],
    r_px: Float[Array, ""],
    side: float,
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Where the weighted points' straight line meets the rim on ``side`` (+1 A, -1 B), as the
    angle from the bottom of the rim (rad), and that angle's standard error from the points'
    scatter about the line (the offset's and the slope's errors carried to the crossing and
    along the rim). An infinite error where fewer than three points carry weight."""
    dt = u.dtype
    alpha, c, um, vm = _line_and_centroid(u, v, w)
    sw = jnp.sum(w)
    safe_sw = jnp.maximum(sw, 1e-9)
    ca, sa = jnp.cos(alpha), jnp.sin(alpha)
    t = ca * (u - um) + sa * (v - vm)
    res = -sa * u + ca * v - c
    var = jnp.maximum(jnp.sum(w * res * res) / jnp.maximum(sw - 2.0, 1.0), 0.05**2)
    stt = jnp.maximum(jnp.sum(w * t * t), 1e-9)
    var_offset = var * jnp.sum(w * w) / (safe_sw * safe_sw)
    var_slope = var * jnp.sum(w * w * t * t) / (stt * stt)
    # The crossing (line and circle about O), then how far it moves along the rim per pixel the
    # line moves across itself: 1 / |sin| of the angle between the line and the rim there.
    point = end_point(alpha, c, r_px, side)
    t_point = ca * (point[0] - um) + sa * (point[1] - vm)
    across = jnp.sqrt(var_offset + t_point * t_point * var_slope)
    tangent = jnp.stack([point[1], -point[0]]) / jnp.maximum(r_px, 1.0)
    sin_meet = jnp.maximum(jnp.abs(-sa * tangent[0] + ca * tangent[1]), 0.05)
    angle = jnp.arctan2(point[0], point[1])
    error = across / (jnp.maximum(r_px, 1.0) * sin_meet)
    return angle, jnp.where(sw >= 3.0, error, jnp.asarray(jnp.inf, dt))


def chosen_window(
    u: Float[Array, " K"],
    v: Float[Array, " K"],
    w: Float[Array, " K"],
    dist2_px2: Float[Array, " K"],
    longest_px: Float[Array, ""],
    r_px: Float[Array, ""],
    side: float,
    settings: SoftSettings,
) -> Float[Array, ""]:
    """The length (whole px) of one end's window, chosen by intersecting confidence intervals.

    ``w``: the boundary points' weights (0 off the boundary), ``dist2_px2`` their squared
    distances from the end-most point; ``longest_px`` the longest window (``end_window_px``),
    ``side`` +1 for A, -1 for B. The ladder runs geometrically from ``end_window_min_px`` to
    ``longest_px`` in :data:`WINDOW_STEPS` steps; each window's tapered points give a straight
    line, its crossing with the rim and that crossing's standard error; the interval of each is
    the crossing ± ``end_window_z`` errors. The longest window whose interval meets every
    shorter window's is kept. A discrete choice: no gradient flows through it (nor did one
    through the fixed window, whose length follows the Hough circle)."""
    s = settings.astype(u.dtype)
    # Nothing here is differentiated: cut the inputs, so no derivative (a square root's at 0)
    # is formed at all.
    u, v, w, dist2_px2, r_px = jax.lax.stop_gradient((u, v, w, dist2_px2, r_px))
    shortest = jnp.minimum(s.end_window_min_px, longest_px)
    steps = jnp.arange(WINDOW_STEPS, dtype=u.dtype) / (WINDOW_STEPS - 1)
    ladder = jnp.round(shortest * (longest_px / jnp.maximum(shortest, 1.0)) ** steps)

    def estimate(window: Array) -> tuple[Array, Array]:
        return _crossing_and_error(u, v, w * end_kernel(dist2_px2, window, s.end_taper), r_px, side)

    angle, error = jax.vmap(estimate)(jax.lax.stop_gradient(ladder))
    half = s.end_window_z * error
    finite = jnp.isfinite(half)
    low = jax.lax.cummax(jnp.where(finite, angle - half, -jnp.inf))
    high = jax.lax.cummin(jnp.where(finite, angle + half, jnp.inf))
    agree = jnp.cumprod((low <= high).astype(jnp.int32))
    last: Int[Array, ""] = jnp.maximum(jnp.sum(agree) - 1, 0)
    return ladder[last]


def end_weights(
    u: Float[Array, " K"],
    v: Float[Array, " K"],
    w_end: Float[Array, " K"],
    r_px: Float[Array, ""],
    settings: SoftSettings,
) -> tuple[Float[Array, " K"], Float[Array, " K"], Int[Array, ""], Int[Array, ""]]:
    """Each end's weights on the boundary points (``w_end``: boundary points clear of the rim's
    corner, wheel frame ``u, v``) and the indices of the end-most points A's and B's curves bend
    from. One per point at the strongest, whatever scales the boundary's weights (a soft mask
    that leaves some wheel below the soil edge): the ends' priors are counted in boundary
    points. The two windows are disjoint (B's leaves out A's), as the residuals' shared slots
    need."""
    s = settings.astype(u.dtype)
    present = w_end > 0.5 * jnp.max(w_end)
    longest = end_window_px(r_px, s)
    i_a, i_b = boundary_ends(u, present, longest)
    w = w_end / jnp.maximum(jnp.max(w_end), 1e-6)
    dist2_a = (u - u[i_a]) ** 2 + (v - v[i_a]) ** 2
    window_a = chosen_window(u, v, w, dist2_a, longest, r_px, 1.0, s)
    w_a = w * end_kernel(dist2_a, window_a, s.end_taper)
    w = w * (dist2_a >= window_a * window_a).astype(u.dtype)
    dist2_b = (u - u[i_b]) ** 2 + (v - v[i_b]) ** 2
    window_b = chosen_window(u, v, w, dist2_b, longest, r_px, -1.0, s)
    return w_a, w * end_kernel(dist2_b, window_b, s.end_taper), i_a, i_b
