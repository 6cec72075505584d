"""A soil line hidden by soil taken for wheel below it: the wheel below each point, recounted.

An outline point counts as wheel-soil boundary only as far as the mask has no wheel below it in
its column (``soft.outline``: the top edge of a lightening hole has wheel below it, the soil line
none). The intensity mask of a wheel without colour takes lit patches of grey sand, or shadows,
well below the rim for the wheel's face; counted down the whole column they made every point of a
plain soil line look like a hole's edge, and a whole recording read as no contact. Below the rim's
disc there is only soil, background and the wheel's cast shadow, so where the first count finds
no boundary on such a mask, :func:`recounted` counts inside the disc only.

The recording runner (``soft.batch``) measures a frame again with it (``finish``'s static
``recount_in_disc``) where the default ``finish`` found no contact on a mask made from intensity.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..result import FEATURES_INTENSITY
from .fit import build_evidence
from .model import Evidence
from .outline import Outline
from .rim import RimChoice
from .segmentation import smooth
from .settings import SoftSettings


def has_contact(ev: Evidence, s: SoftSettings) -> Array:
    # A shallow chord's edge is faint (the soil covers a sliver of a pixel or two), so its points
    # weigh little: it is a contact by its points' number and fill (soft.shallow), not weight.
    return (jnp.sum(ev.w_line) >= s.min_boundary_points) | (ev.shallow_chord > 0)


def recounted(
    ev: Evidence,
    outline: Outline,
    mask: Float[Array, "H W"],
    choice: RimChoice,
    sign: Float[Array, ""] | float,
    s: SoftSettings,
    features: Int[Array, ""],
) -> Evidence:
    """``ev``, or where it has no boundary on a mask made from intensity, the evidence with the
    wheel below each point counted inside the rim only, if that has one. A hue mask seldom takes
    the soil for wheel: there the first count stands (on the coloured hard presets the second
    found more false contacts, on dust and shading, than it recovered). Compiled apart from the
    default ``finish``: a branch that builds the evidence again changes how XLA rounds the
    whole graph, so that traced default settings no longer give the constants' numbers bit for
    bit (``tests/test_settings.py``)."""
    c = choice.circle

    def in_disc() -> Evidence:
        below = wheel_below_in_disc(outline, mask, c.cx_px, c.cy_px, c.r_px)
        again = build_evidence(below, c, sign, s, rim_weight=choice.prior_weight)
        found = has_contact(again, s)
        return jax.tree_util.tree_map(lambda a, b: jnp.where(found, a, b), again, ev)

    keep = has_contact(ev, s) | (features != FEATURES_INTENSITY)
    return jax.lax.cond(keep, lambda: ev, in_disc)


def wheel_below_in_disc(
    outline: Outline,
    mask: Float[Array, "H W"],
    cx_px: Float[Array, ""],
    cy_px: Float[Array, ""],
    r_px: Float[Array, ""],
) -> Outline:
    """``outline`` with each point's ``wheel_below_px`` counted inside the rim's disc only.

    Below a wheel-soil boundary point lies soil; below the top edge of a lightening hole or of
    a dark band across the face, wheel, and that wheel lies inside the rim. Below the disc
    there is only soil, background and the wheel's cast shadow: a mask that takes a grey soil
    for a bare-metal face there says nothing about the point above, yet counted down the whole
    column it took every point of a plain soil line for a hole's edge (a whole recording
    read as no contact). Counted from 3 px below the point (the edge's own blur), as
    :func:`extract_outline` counts; differentiable w.r.t. ``mask``.
    """
    height, width = mask.shape
    dt = mask.dtype
    solid = jax.nn.sigmoid((smooth(mask) - 0.5) / 0.1)
    # Exclusive prefix sums down each column: above[j] = solid rows 0 .. j-1.
    above = jax.lax.associative_scan(jnp.add, solid, axis=0)
    above = jnp.concatenate([jnp.zeros((1, width), dt), above], 0)
    cols = jnp.clip(jnp.round(outline.x_px).astype(jnp.int32), 0, width - 1)
    rows = jnp.clip(jnp.round(outline.y_px).astype(jnp.int32), 0, height - 1)
    # The disc's lowest row in each point's column (a discrete choice: no gradient through it).
    dx = jax.lax.stop_gradient(cols.astype(dt) - cx_px)
    half = jnp.sqrt(jnp.maximum(jax.lax.stop_gradient(r_px) ** 2 - dx * dx, 0.0))
    bottom = jnp.floor(jax.lax.stop_gradient(cy_px) + half).astype(jnp.int32)
    start = jnp.clip(rows + 3, 0, height)
    stop = jnp.clip(bottom + 1, start, height)
    return eqx.tree_at(lambda o: o.wheel_below_px, outline, above[stop, cols] - above[start, cols])
