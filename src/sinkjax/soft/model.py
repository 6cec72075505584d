"""Geometric model stage: rim circle + equivalent line + the two boundary ends, as residuals.

Parameters (one flat vector, image pixels / radians):
``cx, cy, r`` the rim circle; ``k, b`` the equivalent line y = k x + b in the wheel frame (Eq. 1);
``alpha_a, c_a`` and ``alpha_b, c_b`` short lines through the boundary's last few pixels at the
entry and exit ends (angle of the line, signed distance from O), whose intersections with the rim
are A and B (Eqs. 2-3). Every outline point contributes to one residual slot per group, with a
fixed weight that says how much it belongs to that group:

- rim points pull on the circle with a redescending (Welsch) loss on d - r, so lug tips and
  stray edges outside the rim lose their influence;
- wheel-soil boundary points pull on the line with plain vertical residuals, so on clean data the
  line is exactly the paper's least-squares line of the boundary;
- boundary points near each end pull on that end's line with orthogonal residuals.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..geometry import entry_angle_rad, exit_angle_rad, sinkage_px
from .settings import SoftSettings

N_PARAMS = 9
PARAM_NAMES = ("cx", "cy", "r", "k", "b", "alpha_a", "c_a", "alpha_b", "c_b")


class Evidence(eqx.Module):
    """Outline points with their group weights, fixed during the solve (args of the residuals)."""

    x_px: Float[Array, " K"]
    y_px: Float[Array, " K"]
    w_rim: Float[Array, " K"]
    w_line: Float[Array, " K"]
    w_a: Float[Array, " K"]
    w_b: Float[Array, " K"]
    sign: Float[Array, ""]  # +1 travel right, -1 travel left
    start: Float[Array, " 9"]
    # The loss scale and priors (``SoftSettings``); fixed during the solve, differentiable.
    settings: SoftSettings = eqx.field(default_factory=SoftSettings)
    # The recording's rim (cx, cy, r px) and the prior's weight (1/px^2) holding the circle to
    # it (soft.rim); weight 0: the frame's own rim, free.
    rim_px: Float[Array, " 3"] = eqx.field(default_factory=lambda: jnp.zeros(3))
    rim_weight: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros(()))
    # How far inside the rim (px) an edge must lie to count as soil (``fit.inner_margin_px``):
    # the boundary starts there, so its chord is the line's chord of a circle this much smaller.
    inner_px: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros(()))


def _welsch(res: Array, scale: Array) -> Array:
    # sqrt of Welsch's rho, signed: ~res for small res, -> bounded for large ones. Written as
    # res * sqrt(f(u)) with f(u) = (1 - exp(-u)) / u so that it is smooth (no sqrt at 0).
    u = 0.5 * (res / scale) ** 2
    small = u < 1e-6
    f = jnp.where(small, 1.0 - 0.5 * u, -jnp.expm1(-u) / jnp.where(small, 1.0, u))
    return res * jnp.sqrt(f)


def _sqrt_weight(w: Array) -> Array:
    # Double where: sqrt has an infinite derivative at 0, and most slots have weight 0 (padding,
    # other groups); inf * 0 would make the gradient with respect to the mask NaN.
    pos = w > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, w, 1.0)), 0.0)


def wheel_frame(
    p: Float[Array, " 9"], ev: Evidence
) -> tuple[Float[Array, " K"], Float[Array, " K"]]:
    return ev.sign * (ev.x_px - p[0]), ev.y_px - p[1]


def residuals(p: Float[Array, " 9"], ev: Evidence) -> Float[Array, " N"]:
    """Weighted residuals; weighted groups share slots where their members are disjoint."""
    s = ev.settings.astype(p.dtype)
    u, v = wheel_frame(p, ev)
    d = jnp.sqrt(u * u + v * v + 1e-12)
    rim = _sqrt_weight(ev.w_rim) * _welsch(d - p[2], s.rim_loss_scale_px)
    line = _sqrt_weight(ev.w_line) * (v - p[3] * u - p[4])
    end_a = _sqrt_weight(ev.w_a) * (-jnp.sin(p[5]) * u + jnp.cos(p[5]) * v - p[6])
    end_b = _sqrt_weight(ev.w_b) * (-jnp.sin(p[7]) * u + jnp.cos(p[7]) * v - p[8])
    prior = jnp.sqrt(s.prior_weight) * (p - ev.start)
    line_angle = jnp.arctan(p[3])
    lever = jnp.sqrt(s.end_angle_prior_points) * s.end_lever_px
    line_offset = p[4] * jnp.cos(line_angle)
    end_prior = jnp.concatenate(
        [
            lever * jnp.stack([p[5] - line_angle, p[7] - line_angle]),
            jnp.sqrt(s.end_offset_prior_points)
            * jnp.stack([p[6] - line_offset, p[8] - line_offset]),
        ]
    )
    rim_prior = _sqrt_weight(ev.rim_weight.astype(p.dtype)) * (p[:3] - ev.rim_px.astype(p.dtype))
    # rim and line members are disjoint (outside / inside the rim), so are the two end windows.
    return jnp.concatenate([rim + line, end_a + end_b, prior, end_prior, rim_prior])


def end_point(
    alpha: Float[Array | np.floating, ""],
    c: Float[Array | np.floating, ""],
    r: Float[Array | np.floating, ""],
    side: float,
) -> Float[Array, " 2"]:
    """Intersection of the line -sin(a) u + cos(a) v = c with the rim, on side +1 (A) or -1 (B).

    If the line misses the rim (|c| > r) the point nearest to it on the line's closest approach
    is returned, which keeps the angle continuous.
    """
    foot = c * jnp.stack([-jnp.sin(alpha), jnp.cos(alpha)])
    t = jnp.stack([jnp.cos(alpha), jnp.sin(alpha)])
    disc = r * r - c * c
    half = jnp.sqrt(jnp.where(disc > 1e-9, disc, 1e-9))
    # Orient the direction so that "+" goes towards the requested side (larger u for A).
    t = t * jnp.where(t[0] >= 0, 1.0, -1.0)
    return foot + side * half * t


def measurements(
    p: Float[Array, " 9"], wheel_radius_mm: float | Float[Array, ""] | None = None
) -> Float[Array, " 3"]:
    """(z0, theta1 rad, theta2 rad) from the model parameters (Eqs. 1-3).

    z0 is in pixels, or in mm (z0 * R / r) when the rim's physical radius R is given, so that the
    delta method carries the scale's own uncertainty too.
    """
    z0 = sinkage_px(p[3], p[4], p[2])
    if wheel_radius_mm is not None:
        # r is ~0 only when no wheel was found (reported as such); keep the value finite.
        z0 = z0 * wheel_radius_mm / jnp.maximum(p[2], 1.0)
    a = end_point(p[5], p[6], p[2], 1.0)
    b = end_point(p[7], p[8], p[2], -1.0)
    return jnp.stack([z0, entry_angle_rad(a[0], a[1]), exit_angle_rad(b[0], b[1])])
