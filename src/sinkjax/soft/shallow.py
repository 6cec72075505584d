"""Shallow contact: which outline points are the soil line, when the soil barely cuts the rim.

With the soil a pixel or two inside the rim, the wheel's lower outline is the rim circle except
along a chord of 2 sqrt(2 r z0) px, where the soil line cuts it off: the outline is the envelope
``v = min(v_rim(u), k u + b)`` (wheel frame, v down). Thresholding each point's offset from the
rim cannot find that chord: at z0 ~ 1 px the offsets are within the rim edge's own error over
most of it, while the corner of a lug or a hole in the rim sits a few pixels inside it and reads
as "clearly soil". The envelope is found as a whole instead: a grid search over the line's depth
z0 and slope k (coarse, then fine about the best) of the robust (Welsch) misfit of the lower
outline points near the rim's bottom to the envelope, with the rim held to the recording's
circle. The points that lie on the envelope's line part are the boundary; the joint fit then
measures the line from them as from any other boundary (Eq. 1), so the search decides only which
points count, not the numbers. A threshold, not a measurement: no gradient flows through it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

# The search: depth z0 in [0, MAX_DEPTH_PX] px and slope k within +-MAX_SLOPE (wheel frame), on a
# coarse grid then a fine one about the best; misfits under a Welsch loss of MISFIT_SCALE_PX.
MAX_DEPTH_PX = 4.0
MAX_SLOPE = 0.2
COARSE = (21, 9)  # depths, slopes
FINE = (11, 11)
MISFIT_SCALE_PX = 0.5
# A point is on the line part where the line runs this far inside the rim, within ON_LINE_PX of it.
CHORD_MARGIN_PX = 0.25
ON_LINE_PX = 1.0
# The envelope's points replace the offset test's where its line lies less deep than this (deeper,
# a curved surface, a rut or a hollow, is no longer a straight chord, and the offsets suffice),
# and where its line part holds at least MIN_CHORD_FILL outline points per px of its chord (a
# real soil edge runs all along it, one point per column; the edges of lugs at the rim's bottom
# do not: 0.5 on the one such frame seen, against 0.74 or more on 100 shallow contacts).
USE_BELOW_PX = 2.5
MIN_CHORD_FILL = 0.65
# The lower outline points nearest the rim's bottom that the search sees (a fixed size: jit).
MAX_POINTS = 512


def _misfit(
    z: Array, k: Array, u: Array, v: Array, w: Array, v_rim: Array, r: Array
) -> Float[Array, ""]:
    v_line = k * u + (r - z) * jnp.sqrt(1.0 + k * k)
    e = (v - jnp.minimum(v_rim, v_line)) / MISFIT_SCALE_PX
    return jnp.sum(w * (1.0 - jnp.exp(-0.5 * e * e)))


def _search(
    zs: Array, ks: Array, u: Array, v: Array, w: Array, v_rim: Array, r: Array
) -> tuple[Array, Array]:
    score = jax.vmap(lambda z: jax.vmap(lambda k: _misfit(z, k, u, v, w, v_rim, r))(ks))(zs)
    i, j = jnp.unravel_index(jnp.argmin(score), score.shape)
    return zs[i], ks[j]


def shallow_boundary(
    u: Float[Array, " K"],
    v: Float[Array, " K"],
    lower: Float[Array, " K"],
    r_px: Float[Array, ""],
    min_points: Float[Array, ""],
    min_depth_px: Float[Array, ""],
) -> tuple[Bool[Array, ""], Bool[Array, " K"], Float[Array, ""]]:
    """(whether the envelope's line part is a shallow soil edge to use, its points, and the
    line's depth z0 px where at least ``min_points`` points lie on it, used or not, else 0: a
    chord seen but not taken, which a frame read as no contact may hide): a line
    deeper than ``min_depth_px`` (what the rim edge's own error explains:
    ``fit.inner_margin_px``) and less deep than ``USE_BELOW_PX``, whose chord holds
    ``min_points`` or more outline points, and ``MIN_CHORD_FILL`` per px of its length. Points,
    not boundary weight: a sliver of soil a pixel deep moves the soft mask only partly, so the
    points of its edge weigh 0.2-0.4 each (measured on rendered 640x480 and 800x600 frames)."""
    # Only comparisons (booleans) leave here: no gradient to stop.
    z, _, on = envelope_line(u, v, lower, r_px)
    n_on = jnp.sum(on.astype(u.dtype))
    chord = 2.0 * jnp.sqrt(2.0 * r_px * jnp.maximum(z - CHORD_MARGIN_PX, 0.0))
    filled = n_on >= MIN_CHORD_FILL * chord
    use = (z > min_depth_px) & (z < USE_BELOW_PX) & (n_on >= min_points) & filled
    return use, on, jnp.where(n_on >= min_points, z, 0.0)


def envelope_line(
    u: Float[Array, " K"],
    v: Float[Array, " K"],
    lower: Float[Array, " K"],
    r_px: Float[Array, ""],
) -> tuple[Float[Array, ""], Float[Array, ""], Bool[Array, " K"]]:
    """(depth z0 px, slope k, which points lie on the line part) of the envelope of the rim
    (radius ``r_px`` about O) and a soil line that best explains the lower outline points
    (``lower``: their weight as soil-boundary candidates) near the rim's bottom."""
    u, v, lower, r = (jax.lax.stop_gradient(a) for a in (u, v, lower, r_px))
    dt = u.dtype
    dr = jnp.sqrt(u * u + v * v + 1e-12) - r
    cand = (lower > 0.1) & (v > 0) & (jnp.abs(u) < 0.5 * r)
    cand = cand & (dr > -MAX_DEPTH_PX - 1.5) & (dr < 1.5)
    n = min(MAX_POINTS, u.shape[0])
    # A line at depth z cuts the rim over a chord of half-length sqrt(2 r z) about the foot of
    # the perpendicular from O (within MAX_SLOPE r of the bottom): points beyond fit the rim
    # whatever the line, so they do not decide the search.
    reach = MAX_SLOPE * r + jnp.sqrt(2.0 * r * MAX_DEPTH_PX) + 2.0
    cand = cand & (jnp.abs(u) < reach)
    idx = jax.lax.top_k(jnp.where(cand, -jnp.abs(u), -jnp.inf), n)[1]
    uu, vv = u[idx], v[idx]
    ww = jnp.where(cand[idx], lower[idx], 0.0)
    v_rim = jnp.sqrt(jnp.maximum(r * r - uu * uu, 0.0))
    zs = jnp.linspace(0.0, MAX_DEPTH_PX, COARSE[0], dtype=dt)
    ks = jnp.linspace(-MAX_SLOPE, MAX_SLOPE, COARSE[1], dtype=dt)
    z, k = _search(zs, ks, uu, vv, ww, v_rim, r)
    dz, dk = zs[1] - zs[0], ks[1] - ks[0]
    zs = jnp.maximum(z + jnp.linspace(-dz, dz, FINE[0], dtype=dt), 0.0)
    ks = k + jnp.linspace(-dk, dk, FINE[1], dtype=dt)
    z, k = _search(zs, ks, uu, vv, ww, v_rim, r)
    v_line = k * u + (r - z) * jnp.sqrt(1.0 + k * k)
    v_rim_all = jnp.sqrt(jnp.maximum(r * r - u * u, 0.0))
    on = cand & (v_line < v_rim_all - CHORD_MARGIN_PX) & (jnp.abs(v - v_line) < ON_LINE_PX)
    return z, k, on
