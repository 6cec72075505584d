"""The paper's sinkage model (Fig. 1, Eqs. 1-3), made exact per docs/conventions.md §1.

All functions are pure JAX, jit- and vmap-able, and work in the *wheel frame*: origin at the rim
centre O, x to the entry side, y DOWN, pixels. :func:`to_wheel_frame` maps image pixels there,
mirroring x when the wheel travels left so that the entry point A is always at +x.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

_TINY = 1e-12


# Pixel coordinates (any shape, the same for x and y) and a scalar, e.g. the rim centre.
Points = Float[ArrayLike, "*n"]
Scalar = Float[ArrayLike, ""]


def travel_sign(travel: str) -> float:
    """+1 for ``travel="right"`` (entry on the right), -1 for ``"left"``. Raises ValueError."""
    if travel == "right":
        return 1.0
    if travel == "left":
        return -1.0
    raise ValueError(f"travel must be 'right' or 'left', got {travel!r}")


def rim_radius_range_px(height: int, width: int) -> tuple[float, float]:
    """Plausible rim radii (px) in a ``height`` x ``width`` image: 0.12 to 0.75 of min(H, W).

    The camera set-up this tool is for (docs/paper.md) shows the wheel filling a good part of the
    frame while fitting mostly inside it; a circle outside this range is not the rim.
    """
    m = min(height, width)
    return 0.12 * m, 0.75 * m


def to_wheel_frame(
    x_px: Points, y_px: Points, centre_x_px: Scalar, centre_y_px: Scalar, travel: str = "right"
) -> tuple[Float[Array, "*n"], Float[Array, "*n"]]:
    """Image pixels -> wheel frame (O-centred, y down, entry side at +x)."""
    s = travel_sign(travel)
    return s * (jnp.asarray(x_px) - centre_x_px), jnp.asarray(y_px) - centre_y_px


def from_wheel_frame(
    u_px: Points, v_px: Points, centre_x_px: Scalar, centre_y_px: Scalar, travel: str = "right"
) -> tuple[Float[Array, "*n"], Float[Array, "*n"]]:
    """Inverse of :func:`to_wheel_frame`."""
    s = travel_sign(travel)
    return s * jnp.asarray(u_px) + centre_x_px, jnp.asarray(v_px) + centre_y_px


def equivalent_line(
    x_px: Float[ArrayLike, " n"],
    y_px: Float[ArrayLike, " n"],
    weight: Float[ArrayLike, " n"] | None = None,
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Least-squares line y = k x + b with vertical residuals (Eq. 1's k and b).

    With ``weight`` (>= 0) it is the weighted fit; zero weights drop points, which keeps shapes
    static under jit. Written in centred form (algebraically equal to Eq. 1, better conditioned).
    Degenerate input (fewer than two distinct x) gives k = 0 and b = mean y, with finite gradients.
    """
    x = jnp.asarray(x_px)
    y = jnp.asarray(y_px)
    w = jnp.ones_like(x) if weight is None else jnp.asarray(weight)
    sw = jnp.sum(w)
    sw_safe = jnp.where(sw > _TINY, sw, 1.0)
    xm = jnp.sum(w * x) / sw_safe
    ym = jnp.sum(w * y) / sw_safe
    dx = x - xm
    sxx = jnp.sum(w * dx * dx)
    sxy = jnp.sum(w * dx * (y - ym))
    # Double where: the untaken branch must not divide by zero either, or its NaN leaks into grads.
    ok = sxx > _TINY * jnp.maximum(sw_safe, 1.0)
    k = jnp.where(ok, sxy / jnp.where(ok, sxx, 1.0), 0.0)
    return k, ym - k * xm


def sinkage_px(
    k: Float[ArrayLike, "*b"], b_px: Float[ArrayLike, "*b"], radius_px: Float[ArrayLike, "*b"]
) -> Float[Array, "*b"]:
    """Eq. 1: z0 = r - |b| / sqrt(k^2 + 1), the rim radius minus the distance from O to the line."""
    k = jnp.asarray(k)
    return jnp.asarray(radius_px) - jnp.abs(b_px) / jnp.sqrt(k * k + 1.0)


def _safe_atan2(num: Array, den: Array) -> Array:
    """atan2(num, den), 0 at (0, 0), with finite gradients there.

    Double where: atan2's gradient divides by num^2 + den^2, so the untaken branch at the origin
    must see a harmless point too, or its NaN leaks into grads.
    """
    origin = (num == 0) & (den == 0)
    return jnp.where(origin, 0.0, jnp.arctan2(num, jnp.where(origin, 1.0, den)))


def entry_angle_rad(
    x_a_px: Float[ArrayLike, "*b"], y_a_px: Float[ArrayLike, "*b"]
) -> Float[Array, "*b"]:
    """theta1 = atan2(x_A, y_A) (docs/conventions.md §1; wheel frame, y down).

    The angle from the downward vertical through O to A, positive towards the entry side and
    continuous through x_A = 0 (negative when A lies past the bottom of the rim). Where
    x_A > 0 it equals the paper's Eq. 2, pi/2 - atan(y_A / x_A). 0 at A = O.
    """
    return _safe_atan2(jnp.asarray(x_a_px), jnp.asarray(y_a_px))


def exit_angle_rad(
    x_b_px: Float[ArrayLike, "*b"], y_b_px: Float[ArrayLike, "*b"]
) -> Float[Array, "*b"]:
    """theta2 = atan2(-x_B, y_B) (docs/conventions.md §1; wheel frame, y down).

    Positive towards the exit side, continuous through x_B = 0 (negative when B lies ahead of O).
    Where x_B < 0 it equals the paper's Eq. 3, pi/2 + atan(y_B / x_B). 0 at B = O.
    """
    return _safe_atan2(-jnp.asarray(x_b_px), jnp.asarray(y_b_px))


def flat_ground_angle_rad(
    sinkage_px_: Float[ArrayLike, "*b"], radius_px: Float[ArrayLike, "*b"]
) -> Float[Array, "*b"]:
    """theta1 = theta2 = acos(1 - z0/r) on flat ground (the identity the model must satisfy)."""
    c = jnp.clip(1.0 - jnp.asarray(sinkage_px_) / jnp.asarray(radius_px), -1.0, 1.0)
    return jnp.arccos(c)


class SinkageGeometry(eqx.Module):
    """Everything Fig. 1 defines, for one frame, in pixels and radians (wheel frame for k, b, A, B).

    ``sinkage_px`` and the angles are 0 when there is no contact (``contact`` false).
    """

    centre_x_px: Float[Array, ""]
    centre_y_px: Float[Array, ""]
    radius_px: Float[Array, ""]
    k: Float[Array, ""]
    b_px: Float[Array, ""]
    a_px: Float[Array, " 2"]
    b_end_px: Float[Array, " 2"]
    sinkage_px: Float[Array, ""]
    theta1_rad: Float[Array, ""]
    theta2_rad: Float[Array, ""]
    contact: Array


def geometry_from_boundary(
    x_px: Float[ArrayLike, " n"],
    y_px: Float[ArrayLike, " n"],
    centre_x_px: Float[ArrayLike, ""],
    centre_y_px: Float[ArrayLike, ""],
    radius_px: Float[ArrayLike, ""],
    *,
    travel: str = "right",
    weight: Float[ArrayLike, " n"] | None = None,
    a_px: Float[ArrayLike, " 2"] | None = None,
    b_end_px: Float[ArrayLike, " 2"] | None = None,
) -> SinkageGeometry:
    """Eqs. 1-3 from wheel-soil boundary points given in IMAGE pixels.

    A and B default to the boundary's extreme points on the entry and exit sides (the boundary's
    ends); pass ``a_px``/``b_end_px`` (wheel frame) to use exact ends, e.g. rim intersections.
    Points with zero ``weight`` are ignored; no points at all means no contact.
    """
    u, v = to_wheel_frame(x_px, y_px, centre_x_px, centre_y_px, travel)
    w = jnp.ones_like(u) if weight is None else jnp.asarray(weight)
    present = w > 0
    contact = jnp.any(present)
    k, b = equivalent_line(u, v, w)
    if a_px is None:
        i_a = jnp.argmax(jnp.where(present, u, -jnp.inf))
        a = jnp.stack([u[i_a], v[i_a]])
    else:
        a = jnp.asarray(a_px)
    if b_end_px is None:
        i_b = jnp.argmin(jnp.where(present, u, jnp.inf))
        be = jnp.stack([u[i_b], v[i_b]])
    else:
        be = jnp.asarray(b_end_px)
    r = jnp.asarray(radius_px, dtype=u.dtype)
    z0 = jnp.where(contact, sinkage_px(k, b, r), 0.0)
    t1 = jnp.where(contact, entry_angle_rad(a[0], a[1]), 0.0)
    t2 = jnp.where(contact, exit_angle_rad(be[0], be[1]), 0.0)
    return SinkageGeometry(
        centre_x_px=jnp.asarray(centre_x_px, dtype=u.dtype),
        centre_y_px=jnp.asarray(centre_y_px, dtype=u.dtype),
        radius_px=r,
        k=k,
        b_px=b,
        a_px=a,
        b_end_px=be,
        sinkage_px=z0,
        theta1_rad=t1,
        theta2_rad=t2,
        contact=contact,
    )
