"""The shadow's cut: where a mask runs from the wheel's face on into its shadow on the soil.

The mirror of :mod:`~sinkjax.soft.soil_step`. The wheel's shadow on the soil in front of and
below it is the soil's colour darkened; under a colour cast towards the wheel's hue, or for a
wheel whose hue the soil shares, its hue and saturation are the wheel's, so the H/S mask calls it
wheel, the wheel's region runs on through the soil line into the shadow, and the fit finds no
boundary inside the rim ("no contact", flagged: the mask reaches into the soil beyond the rim).
What the mask does not see, the image does: the shadow is far darker than the wheel, and the soil
line, where the soil hides the wheel, is a step in the image.

With the recording's rim known, a frame spills when the mask's mean on the lower half of a ring
just beyond the rim exceeds its mean on the upper half by more than ``MAX_SPILL`` (the
plausibility check's own test for a frame without contact: the wheel's lugs reach the ring all
round, a shadow only below), or on a ring further out, clear of the lugs, by more than
``MAX_SPARSE_SPILL`` (in a dim, noisy frame the shadow is only patches of wheel in the mask).
Then:

1. Colours (RGB blurred by about 1 px): the spill's (the mask's wheel beyond that ring), the
   face's (inside the rim above its centre) and the rim band's (``RIM_BAND`` of the radius just
   inside the rim, above the centre: a tyre or a painted band can look unlike the face). A pixel
   is the shadow's where it lies at most ``NEARER`` times as far from the spill's colour as from
   the wheel's nearest: the shaded lower rim band lies between the lit wheel and the shadow.
2. Each column under the rim: from the mask's lowest wheel pixel of the shadow's colour (no
   deeper than ``DEPTH`` radii below the centre) a run of shadow-coloured rows upwards, ended by
   two rows in a row that are not (one alone is pixel noise); its top is the column's soil line.
3. The soil is one surface: a line through the columns under the wheel's bottom (``CENTRAL``)
   whose run starts beyond the rim, then a quadratic through those within ``TRIM_PX`` of it, three
   times over. A column is cut where its own top lies within ``TOL_PX`` of that curve, or where it
   starts beyond the rim between such columns (cut at the curve: its run climbed a patch of rim
   band as dark as the shadow).
4. Only if the cut is believable: at least ``MIN_COLUMNS`` columns agree, the image has a step at
   the cut (the median ratio of the vertical colour edge there to the edge ``STEP_OFF_PX``
   further out is at least ``STEP_RATIO``, twice: a cut through the smooth shading of a wheel's
   dark side has none, a ratio about 1, and pixel noise in a dim frame holds a real step's ratio
   down to 2-3), and the soil line lies at least ``MIN_DEPTH_PX`` inside the rim somewhere (a
   shallower contact is not measured through a shadow; it stays flagged).

5. A second try where that cut is not believable: in strong light from one side the wheel's
   lower face (shaded, perhaps dusted) can be nearly as dark as its shadow, so the run climbs on
   through the soil line into the face and stops on its smooth shading (no step). The soil line
   is then the strongest step (the vertical colour edge) on the run's way up, from its top down
   to its lowest shadow pixel, in each column; steps 3 and 4 are taken again from there, and the
   cut is made only if it is believable by the same tests.

From each cut column's soil line down, the column is soil. A frame that does not spill, or whose
cuts are not believable, is returned unchanged, bit for bit; a frame whose first cut is
believable gets that cut, as before the second try existed. A choice, not a measurement: no
gradient flows through where the cut is; the outline taken again after it is refined on the
image, so the soil line is located by the image's own edge.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .probes import mean_where, on_ring
from .segmentation import smooth
from .soil_step import colour_edge, disc_grid

# The ring beyond the rim (x the radius) and the mask's excess on its lower half over its upper
# half above which a frame spills: the plausibility check's own (soft.checks NEAR_OUTER_RING,
# MAX_OUTER_WHEEL); samples on the half ring.
SPILL_RING, MAX_SPILL, N_RING = 1.08, 0.1, 90
# And rings further out, clear of the lugs (which put wheel on the near ring all round, so an
# excess there is the spill's alone): a sparse spill (a dim frame whose shadow is only patches
# of wheel in the mask) spills where its excess on any of them exceeds half MAX_SPILL.
OUTER_RINGS, MAX_SPARSE_SPILL = (1.12, 1.16, 1.2), 0.05
# The spill's colour must lie at least this far from the face's and the rim band's (RGB, 0-1
# units: about 13 of 255).
MIN_CONTRAST = 0.05
# The rim band: this fraction of the radius just inside the rim.
RIM_BAND = 0.12
# A pixel is the shadow's at most this many times as far from the spill's colour as from the
# wheel's nearest (the midpoint would be 1: the shaded lower rim band lies nearer the shadow).
NEARER = 0.5
# A column's run starts no further than this many radii below the centre.
DEPTH = 1.5
# The soil line's curve: the median of the columns within CENTRAL radii of the centre, then
# quadratics through the columns within TRIM_PX of the last; a column agrees within TOL_PX.
CENTRAL, TRIM_PX, TOL_PX = 0.3, 3.0, 2.0
# A believable cut: this many columns, and this share of those that cross the rim, cross it and
# agree; a step in the image at the cut (median ratio of the vertical colour edge at it to the
# edge STEP_OFF_PX further out on each side; rendered cast shadows 6-24 in good light, 2-3 in
# dim noisy frames, a cut through a wheel's smooth shading about 1); the soil line this far (px)
# inside the rim somewhere.
MIN_COLUMNS, MIN_AGREE = 8, 0.5
STEP_OFF_PX, STEP_RATIO = 4, 2.0
MIN_DEPTH_PX = 4.0


def _mean_colour(rgb: Float[Array, "H W 3"], where: Bool[Array, "H W"]) -> Array:
    w = where.astype(rgb.dtype)
    return jnp.sum(rgb * w[..., None], axis=(0, 1)) / jnp.maximum(jnp.sum(w), 1.0)


def _robust_curve(x: Array, t: Array, use: Array, cx: Array, r: Array) -> Array:
    """A curve through the points (x, t) where ``use``: the median of those under the wheel's
    bottom (within CENTRAL radii of its centre: the shadow's top is the soil line there),
    then a quadratic through all that lie within TRIM_PX of the last fit, three times over.
    Evaluated at every x, held at its value at the rim's side beyond it."""
    u = jnp.clip((x - cx) / jnp.maximum(r, 1.0), -1.0, 1.0)
    a = jnp.stack([jnp.ones_like(u), u, u * u], axis=-1)

    def solve(w: Array, n: int) -> Array:
        aw = a[:, :n] * w[:, None]
        reg = 1e-6 * jnp.eye(n, dtype=t.dtype)
        return a[:, :n] @ jnp.linalg.solve(aw.T @ a[:, :n] + reg, aw.T @ t)

    # The median, not a fit: a run that climbed a dark side must not tilt the start.
    central = use & (jnp.abs(u) < CENTRAL)
    curve = jnp.broadcast_to(jnp.nanmedian(jnp.where(central, t, jnp.nan)), t.shape)
    curve = jnp.where(jnp.isnan(curve), 0.0, curve)
    for _ in range(3):
        curve = solve((use & (jnp.abs(t - curve) <= TRIM_PX)).astype(t.dtype), 3)
    return curve


def spills(
    mask: Float[Array, "H W"], disc: tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""]]
) -> Bool[Array, ""]:
    """Whether the mask's wheel reaches beyond the rim below it (module docstring)."""
    cx, cy, r = disc
    m = jax.lax.stop_gradient(mask)
    phi = jnp.linspace(0.0, jnp.pi, N_RING, dtype=m.dtype)  # y down: the lower half
    centre = jnp.stack([cx, cy]).astype(m.dtype)

    def ring_mean(angles: Array, rho: Array) -> Array:
        v, seen, _, _ = on_ring(m, centre, jnp.asarray(1.0, m.dtype), rho, angles)
        return mean_where(v, seen)

    def excess(ring: float) -> Array:
        rho = ring * r
        return ring_mean(phi, rho) - ring_mean(phi + jnp.pi, rho)

    sparse = jnp.max(jnp.stack([excess(ring) for ring in OUTER_RINGS]))
    return (r > 0) & ((excess(SPILL_RING) > MAX_SPILL) | (sparse > MAX_SPARSE_SPILL))


def shadow_cut(
    image: Float[Array, "H W 3"],
    mask: Float[Array, "H W"],
    disc: tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""]],
) -> tuple[Float[Array, "H W"], Bool[Array, ""]]:
    """(the mask with the shadow below its soil line cut away, whether it changed).
    ``disc``: the recording's rim (cx, cy, r) px; radius 0: nothing changes."""
    cx, cy, r, y, x, d2 = disc_grid(mask, disc)
    height = mask.shape[0]
    dt = mask.dtype
    wheel = jax.lax.stop_gradient(mask) >= 0.5
    rgb = jnp.stack([smooth(image[..., c]) for c in range(3)], axis=-1)
    face = wheel & (d2 < r * r) & (y < cy)
    spill = wheel & (d2 > (SPILL_RING * r) ** 2) & (y > cy)
    band = wheel & (d2 < (r - 2.0) ** 2) & (d2 > ((1.0 - RIM_BAND) * r) ** 2) & (y < cy)
    c_face, c_spill = _mean_colour(rgb, face), _mean_colour(rgb, spill)
    c_rim = _mean_colour(rgb, band)
    apart = jnp.sum((c_face - c_spill) ** 2) > MIN_CONTRAST**2
    apart = apart & (jnp.sum((c_rim - c_spill) ** 2) > MIN_CONTRAST**2)
    d_spill = jnp.sum((rgb - c_spill[None, None, :]) ** 2, axis=-1)
    d_wheel = jnp.minimum(
        jnp.sum((rgb - c_face[None, None, :]) ** 2, axis=-1),
        jnp.sum((rgb - c_rim[None, None, :]) ** 2, axis=-1),
    )
    shadowlike = d_spill < NEARER**2 * d_wheel
    window = (y > cy) & (jnp.abs(x - cx) < r)
    # The mask's lowest shadow-coloured wheel pixel in each column (a spill's ragged lower
    # edge mixes shadow and lit soil), and the run of shadow-coloured rows up from it, which
    # ends below the lowest wheel-coloured row above it.
    deep = window & wheel & shadowlike & (y < cy + DEPTH * r)
    in_run = jnp.any(deep, axis=0)
    lowest = height - 1 - jnp.argmax(deep[::-1], axis=0)
    # It ends at two rows in a row that are not the shadow's: one alone is noise (a dim frame's
    # pixel noise puts a few per cent of the shadow's pixels nearer the wheel's colour).
    other = window & ~shadowlike
    other = other & jnp.concatenate([jnp.zeros_like(other[:1]), other[:-1]], axis=0)
    stop = other & (y <= lowest[None, :].astype(dt))
    below_centre = jnp.floor(cy) + 1.0
    top = jnp.where(
        jnp.any(stop, axis=0), (height - jnp.argmax(stop[::-1], axis=0)).astype(dt), below_centre
    )
    # The soil line's curve from the columns where the mask crosses the rim into the shadow
    # (their run starts beyond the rim).
    crossing = in_run & ((lowest.astype(dt) - cy) ** 2 + (x[0] - cx) ** 2 > r * r)
    edge = colour_edge(image)
    found = spills(mask, (cx, cy, r)) & apart
    grid = (cx, cy, r, y, x, d2)
    cut, changed = _believable(top, crossing, in_run, edge, found, grid)
    # The run can climb on through the soil line into the wheel's own dark lower face (shaded,
    # dusted: as near the shadow's colour as the face's) and stop on its smooth shading, where
    # the image has no step. Then the soil line is the strongest step on the run's way up: the
    # occlusion edge between face and shadow. A second try from there.
    span = window & (y >= top[None, :] - 1.0) & (y <= lowest[None, :].astype(dt))
    strongest = jnp.argmax(jnp.where(span, edge, -1.0), axis=0).astype(dt)
    again, changed_again = _believable(
        jnp.where(in_run, strongest, top), crossing, in_run, edge, found, grid
    )
    # ``cut`` is empty unless the first try holds; the second is used only where it does not.
    return jnp.where(cut | (~changed & again), 0.0, mask), changed | changed_again


def _believable(
    top: Float[Array, " W"],
    crossing: Bool[Array, " W"],
    in_run: Bool[Array, " W"],
    edge: Float[Array, "H W"],
    found: Bool[Array, ""],
    grid: tuple[Array, Array, Array, Array, Array, Array],
) -> tuple[Bool[Array, "H W"], Bool[Array, ""]]:
    """(where to cut, whether to) for the soil line at row ``top`` of each column (the module
    docstring's steps 3 and 4); ``found``: the frame spills and its shadow is apart from the
    wheel's colours."""
    cx, cy, r, y, x, d2 = grid
    height, width = edge.shape
    dt = top.dtype
    cols = jnp.arange(width)
    # Another column than the crossing ones is cut only where its own run's top agrees with
    # their curve (a shaded side's run, say, climbs far above it).
    line = _robust_curve(x[0], top, crossing, cx, r)
    agree = in_run & (jnp.abs(top - line) <= TOL_PX)
    # A crossing column between agreeing ones whose run climbed off the curve (a patch of the
    # shaded rim band as dark as the shadow) is cut at the curve.
    left = jnp.min(jnp.where(agree, cols, width))
    right = jnp.max(jnp.where(agree, cols, -1))
    use = agree | (crossing & (cols >= left) & (cols <= right))
    top = jnp.clip(top, line - TOL_PX, line + TOL_PX)
    # Most of the crossing columns must agree on the soil line.
    n_cross = jnp.sum(crossing.astype(dt))
    n_agree = jnp.sum((crossing & agree).astype(dt))
    enough = n_agree >= jnp.maximum(MIN_COLUMNS, MIN_AGREE * n_cross)
    changed = found & enough
    # The soil line is an occlusion edge, a step in the image; where the cut runs through a
    # smooth shading gradient instead (a wheel's own shaded side as dark as its shadow), the
    # colours were no guide: no cut.
    row = jnp.clip(top.astype(jnp.int32), 0, height - 1)

    def at(k: int) -> Array:
        return edge[jnp.clip(row + k, 0, height - 1), cols]

    step = jnp.maximum(jnp.maximum(at(-1), at(0)), jnp.maximum(at(1), at(-2)))
    off = 0.5 * (at(-2 - STEP_OFF_PX) + at(1 + STEP_OFF_PX))
    ratio = jnp.nanmedian(jnp.where(agree, step / (off + 1e-3), jnp.nan))
    # Cut to about a pixel or two, the soil line must lie well inside the rim to be measured
    # through the shadow: a shallower contact stays as the mask had it (and is flagged).
    rim_y = cy + jnp.sqrt(jnp.maximum(r * r - (x[0] - cx) ** 2, 0.0))
    depth = jnp.max(jnp.where(agree, rim_y - top, 0.0))
    changed = changed & (ratio >= STEP_RATIO) & (depth >= MIN_DEPTH_PX)
    # Below the soil line and outside the rim only soil can be (what is left of the spill in
    # columns whose own run did not reach the soil line: a paler penumbra, the shadow beside
    # the wheel).
    beyond = (d2 > r * r) & (y > cy) & (y > line[None, :] + TOL_PX)
    return changed & ((use[None, :] & (y >= top[None, :])) | beyond), changed
