"""Samples of the image and the mask at places the fitted model names (for ``soft.checks``).

The plausibility tests read the mask on rings about the fitted centre (:func:`on_ring`,
:func:`mean_where`) and the image's colour at a few points around each end of the soil line
(:func:`soil_lost`: does the soil surface go on beyond the rim?). Everything is pure JAX, jit-
and vmap-able; samples are bilinear (``jax.scipy.ndimage.map_coordinates``, as
``scipy.ndimage.map_coordinates`` with ``order=1``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .model import end_point

# Where the "soil goes on beyond the rim" test looks, at each end of the boundary (the classic
# method's plausibility test, sinkjax.classic.plausible, looks at the same places but the deep
# one): the soil just inside the rim, PROBE_INSIDE * r back along the line and PROBE_BELOW_PX
# below it; outside the rim, PROBE_OUTSIDE * r along the line's extension, PROBE_BELOW_PX and
# PROBE_BELOW_PX + PROBE_DROP * r below it (soil), PROBE_ABOVE_PX above it (what lies above the
# surface) and PROBE_BELOW_PX + PROBE_DEEP * r below it (the soil, in the light beyond the rim).
# The outside samples look like what is above when they are PROBE_NEARER times nearer to it in
# RGB (squared: twice as near) and apart from the soil inside by more than PROBE_MIN_RGB, and as
# much nearer to it than to the deep sample (where that is not the background too).
PROBE_INSIDE, PROBE_OUTSIDE, PROBE_DROP = 0.1, 0.15, 0.03
PROBE_BELOW_PX, PROBE_ABOVE_PX = 4.0, 6.0
PROBE_NEARER, PROBE_MIN_RGB = 4.0, 0.05
PROBE_DEEP = 0.2


def bilinear(a: Float[Array, "H W"], x: Array, y: Array) -> Array:
    return jax.scipy.ndimage.map_coordinates(a, [y, x], order=1, mode="nearest")


def on_ring(
    mask: Float[Array, "H W"], p: Float[Array, " P"], sign: Array, rho: Array, phi: Array
) -> tuple[Array, Array, Array, Array]:
    """The mask at angles ``phi`` on a circle of radius ``rho`` about the fitted centre: the
    values, whether each sample lies inside the image, and its wheel-frame (u, v) offsets."""
    height, width = mask.shape
    u, v = rho * jnp.cos(phi), rho * jnp.sin(phi)
    x, y = p[0] + sign * u, p[1] + v
    seen = (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
    return bilinear(mask, x, y), seen, u, v


def mean_where(values: Array, seen: Array) -> Array:
    n_seen = jnp.sum(seen.astype(values.dtype))
    return jnp.sum(jnp.where(seen, values, 0.0)) / jnp.maximum(n_seen, 1.0)


def patch_rgb(image: Float[Array, "H W 3"], x: Array, y: Array) -> Array:
    # Mean colour of a 5 x 5 px neighbourhood (sampled every 2 px): texture averages out.
    o = jnp.asarray([-2.0, 0.0, 2.0], image.dtype)
    xs, ys = jnp.broadcast_to(x + o[:, None], (3, 3)), jnp.broadcast_to(y + o[None, :], (3, 3))
    xs, ys = xs.ravel(), ys.ravel()
    return jnp.stack([jnp.mean(bilinear(image[..., c], xs, ys)) for c in range(3)])


def _nearer(c: Array, a: Array, b: Array, apart: float) -> Array:
    # c is PROBE_NEARER times nearer to a than to b (squared), and apart from b by ``apart``.
    return jnp.sum((c - b) ** 2) > PROBE_NEARER * jnp.sum((c - a) ** 2) + apart**2


def soil_lost(image: Float[Array, "H W 3"], p: Float[Array, " P"], sign: Array) -> Array:
    """True when, at both ends of the soil line of ``p``, the soil surface does not go on beyond
    the rim: the image below the line's extension outside the rim looks more like the
    background above it than like the soil inside the rim.

    Where the soil line is the soil's surface, the surface continues beyond the rim: just below
    its extension, past the lugs, there is soil (just below, or ``PROBE_DROP`` of the radius
    lower where the surface falls away from a berm the wheel pushed up). Where it is an edge
    on the wheel itself (soil-coloured dust on its lower part, a shadow line), the background
    lies there too.

    The wheel's cast shadow can darken the soil inside the rim only (a black wheel's shadow
    on the soil in front of it, lit soil beyond), and a bright background can be nearer in
    RGB to the lit soil than that dark soil is. So the outside samples are also compared with
    a second picture of the soil, well below the extension (``PROBE_DEEP`` of the radius:
    the soil wherever the surface goes on, and in the light beyond the rim), unless that
    sample is the background too (a line on the wheel far above the soil). ``sign`` is the
    travel sign of the wheel frame (+1: travel to the right)."""
    height, width = image.shape[:2]
    r, k = p[2], p[3]
    norm = jnp.sqrt(1.0 + k * k)
    n = jnp.stack([-k, 1.0]) / norm  # down, across the line
    lost = []
    for side, alpha, c in ((1.0, p[5], p[6]), (-1.0, p[7], p[8])):
        e = end_point(alpha, c, r, side)
        t = side * jnp.stack([1.0, k]) / norm  # along the line, away from the wheel
        # Below the extension, just under it and 3 % of the radius further down: a
        # surface that falls away beyond the rim (a berm the wheel pushed up) is soil there.
        out = e + PROBE_OUTSIDE * r * t
        pts = (
            e - PROBE_INSIDE * r * t + PROBE_BELOW_PX * n,  # the soil inside the rim
            out - PROBE_ABOVE_PX * n,  # above the extension: the background
            out + (PROBE_BELOW_PX + PROBE_DEEP * r) * n,  # well below it: the soil, lit
            out + PROBE_BELOW_PX * n,
            out + (PROBE_BELOW_PX + PROBE_DROP * r) * n,
        )
        xy = [(p[0] + sign * q[0], p[1] + q[1]) for q in pts]
        seen = [(x >= 2) & (x <= width - 3) & (y >= 2) & (y <= height - 3) for x, y in xy]
        rgb = [patch_rgb(image, x, y) for x, y in xy]
        c_in, c_up, c_deep = rgb[:3]
        # The deep sample is a second picture of the soil unless it is the background too.
        deep = seen[2] & (jnp.sum((c_deep - c_up) ** 2) > (2.0 * PROBE_MIN_RGB) ** 2)
        # Clearly more like the background than like either picture of the soil.
        looks_up = [
            _nearer(c, c_up, c_in, PROBE_MIN_RGB)
            & (~deep | _nearer(c, c_up, c_deep, PROBE_MIN_RGB))
            for c in rgb[3:]
        ]
        inside = seen[0] & seen[1] & seen[3] & seen[4]
        lost.append(inside & looks_up[0] & looks_up[1])
    return lost[0] & lost[1]
