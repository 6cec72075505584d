"""The wheel's colour as the soil/background veto sees it, in chromaticity, and its spread.

Light reflected by a painted or plastic wheel is the sum of a body part (the paint's colour) and
a surface part (the light's own colour: highlights, a lamp's glow). In chromaticity
(:func:`~sinkjax.soft.colour.chromaticity`, blind to brightness) its pixels therefore lie on a
segment from the body colour (where the surface part is small: shaded or matte parts) towards
the light's colour (near grey). A confidence rectangle in a glow holds pixels spread along that
segment: read as their median with their spread, the wheel's colour is a desaturated average
whose spread swallows the soil's colour, and the veto
(:func:`~sinkjax.soft.segmentation.reference_mask`) turns itself off.

:func:`wheel_colour` therefore looks at the shape of the rectangle's cloud of chromaticities.
Round (sensor noise, texture): the median and its spread, as always. Stretched along the wheel's
hue direction (:data:`GLOW_ELONGATION` times wider along it than across it: the signature of a
surface part that varies over the rectangle): the body colour, the cloud's saturated end
(:data:`BODY_QUANTILE` along the hue direction, the median across it), with the spread across
the hue direction, which a glow does not widen. A wall of the wheel's hue but paler stays apart
from it (a segment reaching towards the light's colour would take it for wheel).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

# The quantile of the rectangle's saturation (along the wheel's hue) taken as its body colour:
# the saturated end of its pixels, robust to a few saturated specks.
BODY_QUANTILE = 0.75
# How many times wider the cloud must be along the hue direction than across it to be read as a
# glow's segment: sensor noise is round (ratio about 1), a glow's a few tens.
GLOW_ELONGATION = 4.0
_MAD_TO_SD = 1.4826


class WheelColour(eqx.Module):
    """The wheel's colour in chromaticity and the normal-equivalent spread around it."""

    centre: Float[Array, " 2"]
    spread: Float[Array, ""]


def column_median(q: Float[Array, "N C"]) -> Float[Array, " C"]:
    """Median of each column: the values of ``jnp.median(q, axis=0)``, and like it a gradient
    on the middle one or two entries (among tied entries, perhaps another one), at half its cost
    on a CPU: only the lower half is ordered (``lax.top_k``), not every value (a full sort of a
    640 x 14 strip takes about 1 ms there)."""
    n = q.shape[0]
    low = -jax.lax.top_k(-q.T, n // 2 + 1)[0]  # (C, n // 2 + 1), ascending
    if n % 2:
        return low[:, n // 2]
    return 0.5 * (low[:, n // 2 - 1] + low[:, n // 2])


def weighted_quantile(
    x: Float[Array, " N"], w: Float[Array, " N"], level: float
) -> Float[Array, ""]:
    """The lower weighted ``level`` quantile of ``x`` over weights ``w`` >= 0 (some > 0): the
    first value, in order, at which the cumulative weight reaches ``level`` of the total. Its
    gradient is one on that entry (as a median's)."""
    order = jnp.argsort(x)
    cw = jnp.cumsum(w[order])
    idx = jnp.argmax(cw >= level * cw[-1])
    return x[order[idx]]


def _median(q: Float[Array, "N 2"], w: Float[Array, " N"]) -> Float[Array, " 2"]:
    # Every sample (all weights 1): exactly the median; else the lower weighted median.
    weighted = lambda: jnp.stack([weighted_quantile(q[:, c], w, 0.5) for c in range(2)])
    return jax.lax.cond(jnp.all(w > 0), lambda: column_median(q), weighted)


def wheel_colour(q: Float[Array, "N 2"], w: Float[Array, " N"]) -> WheelColour:
    """The wheel's colour from the rectangle's chromaticities ``q`` and 0/1 weights ``w`` (the
    unclipped samples; some 1): their median and spread, or where the cloud is a glow's segment
    its body colour and the spread across the hue direction (the module's docstring). Which of
    the two is a discrete choice; the gradient flows through the chosen one."""
    med = _median(q, w)
    dev = jnp.abs(q - med[None, :])
    mad = _median(dev, w)
    round_spread = _MAD_TO_SD * jnp.sqrt(jnp.sum(mad * mad) + 1e-12)
    norm2 = jnp.sum(med * med)
    grey = norm2 < 1e-12
    u = jnp.where(grey, jnp.array([1.0, 0.0], q.dtype), med / jnp.sqrt(jnp.where(grey, 1.0, norm2)))
    along = q[:, 0] * u[0] + q[:, 1] * u[1]
    across = -q[:, 0] * u[1] + q[:, 1] * u[0]
    t_mid, offset = weighted_quantile(along, w, 0.5), weighted_quantile(across, w, 0.5)
    mad_along = weighted_quantile(jnp.abs(along - t_mid), w, 0.5)
    mad_across = weighted_quantile(jnp.abs(across - offset), w, 0.5)
    glow = jax.lax.stop_gradient(mad_along > GLOW_ELONGATION * mad_across) & ~grey
    t = weighted_quantile(along, w, BODY_QUANTILE)
    body = jnp.stack([t * u[0] - offset * u[1], t * u[1] + offset * u[0]])
    across_spread = _MAD_TO_SD * jnp.sqrt(mad_across * mad_across + 1e-12)
    return WheelColour(
        centre=jnp.where(glow, body, med), spread=jnp.where(glow, across_spread, round_spread)
    )
