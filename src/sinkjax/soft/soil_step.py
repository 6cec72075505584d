"""The soil's step: where a mask's soil line lies above the image's sharpest edge inside the rim.

The soil occludes the wheel: where it meets the wheel face the image steps from one surface to
the other. Soil-coloured dust on the wheel's lower face is a fade, not a step, and a colour mask
calls the faded part soil, so its soil line rises tens of pixels above the true one (the frame is
then flagged, or read far too deep). With the recording's rim known, each column of the rim's
lower half whose non-wheel run reaches the rim has the mask's soil line where that run starts;
below it, down to just beyond the rim, the image's vertical colour edges (RGB blurred by about
1.4 px, central difference) say where the soil actually begins. ``experiments/dust_edges.py``
measures both against the renderer's surface: on dusty frames the mask's line lies a median
29 px above it, the strongest edge within 2 px in 89-95 % of the columns; on clean frames both
are the soil line.

A frame's mask moves only where its columns agree: the median over those columns of the strongest
edge's offset below the mask's line exceeds ``MIN_STEP_PX`` (a clean frame's is about 0: its mask
is returned unchanged, bit for bit). Then in each such column the rows from the mask's line down
to the peak of the lowest edge at least ``STRONG`` times as strong as the columns' typical
strongest (their median: a column's own strongest may be a hole in the face or a lug, above the
soil's step; where no soil crosses the rim, the rim's own edge is the lowest) become wheel, inside
the rim, and the outline, the fit and the checks see the soil line at the step. A choice, not a
measurement: no gradient flows through where the step is.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .segmentation import smooth

# The median offset (px) of the strongest edge below the mask's soil line over which the line
# moves to the edges: a clean frame's is about 0, a dusty one's tens of pixels.
MIN_STEP_PX = 4.0
# At least this many columns must show a soil run reaching the rim.
MIN_COLUMNS = 12
# The search starts this far above the mask's line and ends this far outside the rim: where no
# soil crosses the rim, the rim's own edge against what lies beyond it ends the column.
ABOVE_PX, RIM_OUT_PX = 3.0, 2.0
# A column's run counts when it is at least this long (px).
MIN_RUN_PX = 4.0
# The soil's step is the lowest edge at least this fraction of the columns' typical strongest
# (their median): a hole in the wheel face, or a lug's edge, can be stronger than the soil's
# step, above it.
STRONG = 0.5
# The step's peak lies within this many rows above the lowest row that is that strong.
PEAK_PX = 3.0


def colour_edge(image: Float[Array, "H W 3"]) -> Float[Array, "H W"]:
    """Vertical colour edge strength: |d/dy| of the blurred RGB image (central difference)."""
    blurred = jnp.stack([smooth(smooth(image[..., c])) for c in range(3)], axis=-1)
    pad = jnp.pad(blurred, ((1, 1), (0, 0), (0, 0)), mode="edge")
    d = 0.5 * (pad[2:] - pad[:-2])
    return jnp.sqrt(jnp.sum(d * d, axis=-1) + 1e-12)


def disc_grid(
    mask: Float[Array, "H W"],
    disc: tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""]],
) -> tuple[Array, Array, Array, Float[Array, "H 1"], Float[Array, "1 W"], Float[Array, "H W"]]:
    """The rim (cx, cy, r) without gradient, the pixel rows (H, 1) and columns (1, W) in the
    mask's dtype, and each pixel's squared distance from the rim's centre."""
    cx, cy, r = (jax.lax.stop_gradient(a) for a in disc)
    height, width = mask.shape
    y = jnp.arange(height, dtype=mask.dtype)[:, None]
    x = jnp.arange(width, dtype=mask.dtype)[None, :]
    return cx, cy, r, y, x, (x - cx) ** 2 + (y - cy) ** 2


def soil_step(
    image: Float[Array, "H W 3"],
    mask: Float[Array, "H W"],
    disc: tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""]],
) -> tuple[Float[Array, "H W"], Bool[Array, ""]]:
    """(the mask with its soil line moved down to the soil's step where the columns agree,
    whether it moved). ``disc``: the recording's rim (cx, cy, r) px; radius 0: nothing moves."""
    cx, cy, r, y, x, d2 = disc_grid(mask, disc)
    height = mask.shape[0]
    dt = mask.dtype
    reach = jnp.where(r > 0, r + RIM_OUT_PX, 0.0)
    lower = (y > cy) & (d2 < reach * reach)
    wheel = jax.lax.stop_gradient(mask) >= 0.5
    # A row's run of non-wheel rows down to the rim is broken by wheel anywhere below it: the
    # lowest wheel row per column (a cumulative maximum would be quadratic on a CPU).
    below = lower & wheel
    last = jnp.where(jnp.any(below, axis=0), height - 1 - jnp.argmax(below[::-1], axis=0), -1)
    run = lower & ~wheel & (y > last[None, :].astype(dt))
    has_run = jnp.any(run, axis=0)
    top = jnp.argmax(run, axis=0).astype(dt)  # first row of the run: the mask's soil line
    bottom = cy + jnp.sqrt(jnp.maximum(reach * reach - (x[0] - cx) ** 2, 0.0))
    use = has_run & (bottom - top >= MIN_RUN_PX)
    window = lower & (y >= top[None, :] - ABOVE_PX)
    strength = jnp.where(window, jax.lax.stop_gradient(colour_edge(image)), -1.0)
    strongest = jnp.argmax(strength, axis=0).astype(dt)
    offset = jnp.where(use, strongest - top, jnp.nan)
    n = jnp.sum(use)
    moved = (n >= MIN_COLUMNS) & (jnp.nanmedian(jnp.where(n > 0, offset, 0.0)) > MIN_STEP_PX)
    # The soil's step is about as strong in every column; a column's own strongest may be a
    # hole's edge. The reference is the median over the columns of their strongest.
    peak = jnp.nanmedian(jnp.where(use, jnp.max(strength, axis=0), jnp.nan))
    strong = window & (strength >= STRONG * peak)
    lowest = (height - 1 - jnp.argmax(strong[::-1], axis=0)).astype(dt)
    # The lowest strong edge's own peak (the blur spreads a step over a few rows).
    flank = window & (y >= lowest[None, :] - PEAK_PX) & (y <= lowest[None, :])
    step = jnp.argmax(jnp.where(flank, strength, -1.0), axis=0).astype(dt)
    # No edge that strong below the line: no soil step in the column, wheel down to the rim.
    step = jnp.where(jnp.any(strong, axis=0), step, float(height))
    fill = use[None, :] & (y >= top[None, :]) & (y < step[None, :]) & lower & (d2 < r * r)
    return jnp.where(moved & fill, 1.0, mask), moved
