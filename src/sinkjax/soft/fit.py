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
from jaxtyping import Array, Float

from ..geometry import equivalent_line
from .hough import Circle
from .model import Evidence, residuals
from .outline import Outline
from .settings import SoftSettings


def end_window_px(r_px: Array, settings: SoftSettings) -> Array:
    """Length of boundary used to find each end's tangent: short enough to follow the surface."""
    s = settings.astype(r_px.dtype)
    return jnp.clip(s.end_window_fraction * r_px, s.end_window_min_px, s.end_window_max_px)


def _orthogonal_line(u: Array, v: Array, w: Array) -> tuple[Array, Array]:
    # Total least squares line through weighted points: angle of the main axis, offset from O.
    sw = jnp.maximum(jnp.sum(w), 1e-9)
    um, vm = jnp.sum(w * u) / sw, jnp.sum(w * v) / sw
    suu = jnp.sum(w * (u - um) ** 2)
    svv = jnp.sum(w * (v - vm) ** 2)
    suv = jnp.sum(w * (u - um) * (v - vm))
    alpha = 0.5 * jnp.arctan2(2 * suv, suu - svv + 1e-12)
    return alpha, -jnp.sin(alpha) * um + jnp.cos(alpha) * vm


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
    in_band = ((dr >= -s.rim_band_in_px) & (dr <= s.rim_band_out_px)).astype(dt)
    outer = jax.nn.sigmoid((0.3 - outline.mask_beyond) / 0.05)
    w_rim = w * in_band * jax.nn.sigmoid((align - 0.75) / 0.05) * outer

    inside = (dr < -s.rim_band_in_px).astype(dt)
    faces_down = jax.nn.sigmoid((outline.ny - 0.3) / 0.1)
    soil_below = jnp.exp(-outline.wheel_below_px / s.wheel_below_scale_px)
    # Non-maximum suppression leaves one point per column on gentle edges and one per row on
    # steep ones; re-weight to one per unit x so the fit matches Eq. 1 on the true curve.
    per_x = jnp.minimum(1.0, jnp.abs(outline.ny) / jnp.maximum(jnp.abs(outline.nx), 1e-3))
    w_line = w * inside * faces_down * soil_below * per_x

    # The ends' tangents come from boundary points clear of the corner where the soil edge meets
    # the rim edge (smoothing rounds that corner over a few pixels and would bend them upward).
    clear = (dr < -s.end_clearance_px).astype(dt)
    w_end = w_line * clear
    present = w_end > 0.5 * jnp.max(w_end)
    i_a = jnp.argmax(jnp.where(present, u, -jnp.inf))
    i_b = jnp.argmin(jnp.where(present, u, jnp.inf))
    win = end_window_px(circle.r_px, s)
    near_a = jnp.hypot(u - u[i_a], v - v[i_a]) < win
    near_b = jnp.hypot(u - u[i_b], v - v[i_b]) < win
    w_a = w_end * near_a.astype(dt)
    w_b = w_end * near_b.astype(dt) * (~near_a).astype(dt)

    k0, b0 = equivalent_line(u, v, w_line)
    # An end with too few points (a very short boundary) starts from the equivalent line.
    line_alpha = jnp.arctan(k0)
    line_c = b0 * jnp.cos(line_alpha)
    alpha_a, c_a = _orthogonal_line(u, v, w_a)
    alpha_b, c_b = _orthogonal_line(u, v, w_b)
    few_a = jnp.sum(w_a) < 3.0
    few_b = jnp.sum(w_b) < 3.0
    alpha_a, c_a = jnp.where(few_a, line_alpha, alpha_a), jnp.where(few_a, line_c, c_a)
    alpha_b, c_b = jnp.where(few_b, line_alpha, alpha_b), jnp.where(few_b, line_c, c_b)
    start = jnp.stack(
        [circle.cx_px, circle.cy_px, circle.r_px, k0, b0, alpha_a, c_a, alpha_b, c_b]
    ).astype(dt)
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
        rim_weight=jnp.asarray(rim_weight, dt),
    )


class FitResult(eqx.Module):
    params: Float[Array, " 9"]
    residuals: Float[Array, " N"]
    ok: Array
    steps: Array


def fit(ev: Evidence, *, max_steps: int = 64) -> FitResult:
    """The single joint Levenberg-Marquardt solve (implicit differentiation through it)."""
    # Normal equations + Cholesky: the Jacobian is tall (thousands of points x 9 parameters) and
    # well conditioned, and this is several times faster than QR on the CPU.
    # Tolerances on the step and the objective: 1e-4 is far below anything measurable (0.02 px on
    # a 150 px offset, 0.006 deg on an angle), while tighter ones sit at float32 rounding noise of
    # a sum over thousands of residuals and make convergence a coin toss.
    solver: optx.LevenbergMarquardt = optx.LevenbergMarquardt(
        rtol=1e-4, atol=1e-4, linear_solver=lx.Normal(lx.Cholesky())
    )
    sol: optx.Solution = optx.least_squares(
        residuals, solver, ev.start, args=ev, max_steps=max_steps, throw=False
    )
    p = sol.value
    ok = (sol.result == optx.RESULTS.successful) & jnp.all(jnp.isfinite(p))
    return FitResult(params=p, residuals=residuals(p, ev), ok=ok, steps=sol.stats["num_steps"])
