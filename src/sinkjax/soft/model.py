"""Geometric model stage: rim circle + equivalent line + the two boundary ends, as residuals.

Parameters (one flat vector, image pixels / radians):
``cx, cy, r`` the rim circle; ``k, b`` the equivalent line y = k x + b in the wheel frame (Eq. 1);
``alpha_a, c_a`` and ``alpha_b, c_b`` the surface's tangents at the entry and exit ends (at the
end-most boundary point, ``end_clearance_px`` inside the rim; angle of the line, signed distance
from O), whose intersections with the rim are A and B (Eqs. 2-3); ``kappa_a, kappa_b`` (1/px) how
the surface bends away from each tangent over the end's window, so that a bump or a rut next to
the rim does not tilt the tangent (a straight line fitted over the window is the surface's mean
direction there, not its direction at the end). Every outline point
contributes to one residual slot per group, with a fixed weight that says how much it belongs to
that group:

- rim points pull on the circle with a redescending (Welsch) loss on d - r, so lug tips and
  stray edges outside the rim lose their influence;
- wheel-soil boundary points pull on the line with plain vertical residuals, so on clean data the
  line is exactly the paper's least-squares line of the boundary;
- boundary points near each end pull on that end's curve with orthogonal residuals under a
  Welsch loss (an edge of a lug or a hole next to the end loses its pull).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..geometry import entry_angle_rad, exit_angle_rad, sinkage_px
from .settings import SoftSettings

N_PARAMS = 11
PARAM_NAMES = ("cx", "cy", "r", "k", "b", "alpha_a", "c_a", "alpha_b", "c_b", "kappa_a", "kappa_b")


class Evidence(eqx.Module):
    """Outline points with their group weights, fixed during the solve (args of the residuals)."""

    x_px: Float[Array, " K"]
    y_px: Float[Array, " K"]
    w_rim: Float[Array, " K"]
    w_line: Float[Array, " K"]
    w_a: Float[Array, " K"]
    w_b: Float[Array, " K"]
    sign: Float[Array, ""]  # +1 travel right, -1 travel left
    start: Float[Array, " P"]
    # The loss scale and priors (``SoftSettings``); fixed during the solve, differentiable.
    settings: SoftSettings = eqx.field(default_factory=SoftSettings)
    # The recording's rim (cx, cy, r px) and the prior's weight (1/px^2) holding the circle to
    # it (soft.rim); weight 0: the frame's own rim, free.
    rim_px: Float[Array, " 3"] = eqx.field(default_factory=lambda: jnp.zeros(3))
    rim_weight: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros(()))
    # How far inside the rim (px) an edge must lie to count as soil (``fit.inner_margin_px``):
    # the boundary starts there, so its chord is the line's chord of a circle this much smaller.
    inner_px: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros(()))
    # Factor on each end's offset prior: 1 / (1 + the end's points), so that the prior holds an
    # end with no points to the equivalent line and leaves a well-measured end alone.
    end_prior_scale: Float[Array, " 2"] = eqx.field(default_factory=lambda: jnp.ones(2))
    # Image points (x, y px) each end's curve bends away from its tangent: the end-most point
    # of each end's window (``fit.build_evidence``); and the points of the equivalent line of
    # the boundary (least squares in the image, so it does not depend on the circle) below or
    # above them, which the ends' offset priors hold the end lines to. ``build_evidence`` sets
    # both; an Evidence made by hand with ends must set them too (zeros bend from the image's
    # corner).
    end_origin_px: Float[Array, "2 2"] = eqx.field(default_factory=lambda: jnp.zeros((2, 2)))
    end_anchor_px: Float[Array, "2 2"] = eqx.field(default_factory=lambda: jnp.zeros((2, 2)))
    # > 0 where the soil line is a shallow chord found against the recording's rim (soft.shallow):
    # a contact, however little weight its faint sub-pixel edge gives its points. Its value is
    # the margin (px, ``fit.inner_margin_px``) the chord's depth is known to (soft.checks).
    shallow_chord: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros(()))
    # The depth (px) of a soil chord the envelope saw (min_boundary_points on it), taken or not;
    # 0 where it saw none or without the recording's rim: with no contact, that much may hide.
    envelope_depth_px: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.zeros(()))


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
    p: Float[Array, " P"], ev: Evidence
) -> tuple[Float[Array, " K"], Float[Array, " K"]]:
    return ev.sign * (ev.x_px - p[0]), ev.y_px - p[1]


def residuals(p: Float[Array, " P"], ev: Evidence) -> Float[Array, " N"]:
    """Weighted residuals; weighted groups share slots where their members are disjoint."""
    s = ev.settings.astype(p.dtype)
    u, v = wheel_frame(p, ev)
    d = jnp.sqrt(u * u + v * v + 1e-12)
    rim = _sqrt_weight(ev.w_rim) * _welsch(d - p[2], s.rim_loss_scale_px)
    line = _sqrt_weight(ev.w_line) * (v - p[3] * u - p[4])
    origin = ev.end_origin_px.astype(p.dtype)
    end_a = _end_residual(u, v, ev, origin[0], p[5], p[6], p[9])
    end_b = _end_residual(u, v, ev, origin[1], p[7], p[8], p[10])
    end_a = _sqrt_weight(ev.w_a) * _welsch(end_a, s.end_loss_scale_px)
    end_b = _sqrt_weight(ev.w_b) * _welsch(end_b, s.end_loss_scale_px)
    prior = jnp.sqrt(s.prior_weight) * (p - ev.start)
    line_angle = jnp.arctan(p[3])
    lever = jnp.sqrt(s.end_angle_prior_points) * s.end_lever_px
    # Each end line's distance from the boundary's equivalent line below (or above) the end's
    # origin: not the difference of the offsets from O, which a steep end of a curved surface
    # makes large. Fixed image points: the prior pulls on neither the circle nor the line.
    anchor = ev.end_anchor_px.astype(p.dtype)
    on_a = jnp.stack([ev.sign * (anchor[0, 0] - p[0]), anchor[0, 1] - p[1]])
    on_b = jnp.stack([ev.sign * (anchor[1, 0] - p[0]), anchor[1, 1] - p[1]])
    end_prior = jnp.concatenate(
        [
            lever * jnp.stack([p[5] - line_angle, p[7] - line_angle]),
            jnp.sqrt(s.end_offset_prior_points * ev.end_prior_scale.astype(p.dtype))
            * jnp.stack(
                [
                    -jnp.sin(p[5]) * on_a[0] + jnp.cos(p[5]) * on_a[1] - p[6],
                    -jnp.sin(p[7]) * on_b[0] + jnp.cos(p[7]) * on_b[1] - p[8],
                ]
            ),
            jnp.sqrt(s.end_bend_prior_points) * 0.5 * s.end_lever_px**2 * p[9:11],
        ]
    )
    rim_prior = _sqrt_weight(ev.rim_weight.astype(p.dtype)) * (p[:3] - ev.rim_px.astype(p.dtype))
    # rim and line members are disjoint (outside / inside the rim), so are the two end windows.
    return jnp.concatenate([rim + line, end_a + end_b, prior, end_prior, rim_prior])


def _end_residual(
    u: Float[Array, " K"],
    v: Float[Array, " K"],
    ev: Evidence,
    origin: Float[Array, " 2"],
    alpha: Float[Array, ""],
    c: Float[Array, ""],
    kappa: Float[Array, ""],
) -> Float[Array, " K"]:
    """Offset of each point from the end's curve: the line -sin(a) u + cos(a) v = c bent by
    kappa (1/px) away from it with the square of the distance along it from ``origin`` (the
    image point nearest the end with evidence), so that the line is the surface's tangent at
    the end, not its mean direction over the window (which a curved surface, a rut or a bump,
    tilts by half the window's turn). A fixed image point: the ends do not pull on the circle."""
    along = jnp.cos(alpha) * ev.sign * (ev.x_px - origin[0]) + jnp.sin(alpha) * (
        ev.y_px - origin[1]
    )
    return -jnp.sin(alpha) * u + jnp.cos(alpha) * v - c - 0.5 * kappa * along * along


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
    p: Float[Array, " P"], wheel_radius_mm: float | Float[Array, ""] | None = None
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
