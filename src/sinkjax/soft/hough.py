"""Hough stage: a robust initial rim circle from outline points, in JAX (jit/vmap-able).

As in the paper, the outline is transformed into (cx, cy, r) Hough space. Each point votes along
its inward normal for centres at a set of candidate radii (a 3-D transform summed over r for the
centre), then the radius is the peak of the histogram of outward-facing points' distances. Lugs
stick out beyond the rim, so their tips make a second peak at a larger radius: the rim is the
inner one whenever it is strong. A few algebraic (Kasa) refits on the inliers polish the result.
Nothing here needs gradients: it only chooses where the least-squares fit starts.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .outline import Outline
from .settings import SoftSettings


class Circle(eqx.Module):
    cx_px: Float[Array, ""]
    cy_px: Float[Array, ""]
    r_px: Float[Array, ""]
    support: Float[Array, ""]  # fraction of the circle's visible perimeter with rim evidence


def radius_range_px(height: int, width: int) -> tuple[float, float]:
    """Plausible rim radii: the wheel fills a good part of the frame but fits mostly inside it."""
    m = min(height, width)
    return 0.12 * m, 0.75 * m


def _kasa(x: Array, y: Array, w: Array) -> tuple[Array, Array, Array]:
    # Algebraic circle fit: minimise sum w (x^2 + y^2 + D x + E y + F)^2, centred for conditioning.
    sw = jnp.maximum(jnp.sum(w), 1e-9)
    xm, ym = jnp.sum(w * x) / sw, jnp.sum(w * y) / sw
    u, v = x - xm, y - ym
    z = u * u + v * v
    a = jnp.stack([u, v, jnp.ones_like(u)], -1) * jnp.sqrt(w)[:, None]
    sol = jnp.linalg.lstsq(a.T @ a + 1e-9 * jnp.eye(3, dtype=a.dtype), a.T @ (-z * jnp.sqrt(w)))[0]
    d, e, f = sol
    cx, cy = -d / 2, -e / 2
    r = jnp.sqrt(jnp.maximum(cx * cx + cy * cy - f, 1e-6))
    return cx + xm, cy + ym, r


def hough_rim(
    outline: Outline,
    height: int,
    width: int,
    settings: SoftSettings,
    rim_range_px: tuple[ArrayLike, ArrayLike] | None = None,
) -> Circle:
    """Initial rim circle (image pixels). ``height``/``width`` are static.

    ``rim_range_px``: the radii to search (a rig's ``rim_radius_px`` hint, traced: one compiled
    function serves every hint); None: :func:`radius_range_px` of the image size.
    """
    dt = outline.x_px.dtype
    bin_px = settings.centre_bin_px
    r_min: ArrayLike
    r_max: ArrayLike
    if rim_range_px is None:
        r_min, r_max = radius_range_px(height, width)
        # Candidate radii one centre bin apart: a rim point's vote then lands within half a bin
        # of the true centre for the nearest candidate (coarser steps smear the votes).
        n_radii = int(np.ceil((r_max - r_min) / bin_px)) + 1
        radii = jnp.linspace(r_min, r_max, n_radii, dtype=dt)
        nb = int(r_max) + 8
    else:
        # Sizes fixed by the image alone: enough radii to stay a bin apart over half the
        # diagonal, and radius histogram bins up to the diagonal.
        diagonal = float(np.hypot(height, width))
        r_min, r_max = (jnp.asarray(v, dt) for v in rim_range_px)
        n_radii = int(np.ceil(0.5 * diagonal / bin_px)) + 1
        radii = r_min + (r_max - r_min) * jnp.linspace(0.0, 1.0, n_radii, dtype=dt)
        nb = int(diagonal) + 8
    # Only edges with non-wheel beyond them can be the rim (or lug tips).
    w = outline.weight * jax.nn.sigmoid((0.3 - outline.mask_beyond) / 0.05)
    # Centre votes: p - n r (the normal points outwards on the rim).
    vx = outline.x_px[:, None] - outline.nx[:, None] * radii[None]
    vy = outline.y_px[:, None] - outline.ny[:, None] * radii[None]
    bw = (width + bin_px - 1) // bin_px
    bh = (height + bin_px - 1) // bin_px
    ix = jnp.floor(vx / bin_px).astype(jnp.int32)
    iy = jnp.floor(vy / bin_px).astype(jnp.int32)
    # A vote outside the image or of weight 0 (an empty outline slot) adds nothing: it goes to
    # an index past the end, which the scatter drops. (Sent to bin 0 instead, such votes, most
    # of them, queued on one address for their atomic adds on a GPU: 74 ms of a 640x480 batch
    # of 128 frames' 157 ms on an H200, experiments/gpu_profile.py.)
    inside = (ix >= 0) & (ix < bw) & (iy >= 0) & (iy < bh) & (w[:, None] > 0)
    lin = jnp.where(inside, iy * bw + ix, bh * bw)
    votes = jnp.broadcast_to(w[:, None], lin.shape)
    acc = jnp.zeros(bh * bw, dt).at[lin.ravel()].add(votes.ravel(), mode="drop")
    acc = acc.reshape(bh, bw)
    acc = jax.lax.reduce_window(acc, 0.0, jax.lax.add, (3, 3), (1, 1), "SAME")
    best = jnp.argmax(acc)
    cx = ((best % bw).astype(dt) + 0.5) * bin_px
    cy = ((best // bw).astype(dt) + 0.5) * bin_px

    def histogram(cx: Array, cy: Array) -> tuple[Array, Array]:
        dx, dy = outline.x_px - cx, outline.y_px - cy
        d = jnp.sqrt(dx * dx + dy * dy + 1e-9)
        align = (dx * outline.nx + dy * outline.ny) / d
        wr = w * jnp.clip(align, 0.0, 1.0) ** 4
        bins = jnp.where(wr > 0, jnp.clip(jnp.round(d).astype(jnp.int32), 0, nb - 1), nb)
        hist = jnp.zeros(nb, dt).at[bins].add(wr, mode="drop")  # weight 0: dropped, as above
        hist = jnp.convolve(hist, jnp.array([1.0, 2.0, 3.0, 2.0, 1.0], dt), mode="same")
        rb = jnp.arange(nb, dtype=dt)
        return jnp.where((rb >= r_min) & (rb <= r_max), hist, 0.0), rb

    def refine(carry: tuple[Array, Array, Array], band: Array) -> tuple[tuple, None]:
        cx, cy, r = carry
        dx, dy = outline.x_px - cx, outline.y_px - cy
        d = jnp.sqrt(dx * dx + dy * dy + 1e-9)
        align = (dx * outline.nx + dy * outline.ny) / d
        wi = w * (jnp.abs(d - r) < band).astype(dt) * (align > 0.8).astype(dt)
        ncx, ncy, nr = _kasa(outline.x_px, outline.y_px, wi)
        enough = jnp.sum(wi) > 20.0
        return (
            jnp.where(enough, ncx, cx).astype(dt),
            jnp.where(enough, ncy, cy).astype(dt),
            jnp.where(enough, nr, r).astype(dt),
        ), None

    # The Hough centre is only good to a few pixels (a degree of normal error moves a vote by
    # r * 1 deg), so first converge on the strongest circle with shrinking bands...
    hist, rb = histogram(cx, cy)
    r = rb[jnp.argmax(hist)]
    bands = jnp.array([25.0, 15.0, 10.0, 6.0, 4.0, 3.0, 2.0, 1.5], dt)
    (cx, cy, r), _ = jax.lax.scan(refine, (cx, cy, r), bands)
    # ...then, with a sharp histogram, prefer the inner envelope: lug tips make a peak up to
    # ~15% outside the rim, and the rim is the inner one whenever it is strong.
    hist, rb = histogram(cx, cy)
    inner = (rb >= 0.85 * r) & (rb <= r - 3.0)
    h_inner = jnp.where(inner, hist, 0.0)
    use_inner = jnp.max(h_inner) >= 0.35 * jnp.max(hist)
    r = jnp.where(use_inner, rb[jnp.argmax(h_inner)], r)
    (cx, cy, r), _ = jax.lax.scan(refine, (cx, cy, r), bands[5:])
    return Circle(cx_px=cx, cy_px=cy, r_px=r, support=circle_support(outline, cx, cy, r))


def circle_support(outline: Outline, cx: Array, cy: Array, r: Array) -> Float[Array, ""]:
    """Fraction of the circle's circumference with outward-facing outline points on it."""
    dt = outline.x_px.dtype
    w = outline.weight * jax.nn.sigmoid((0.3 - outline.mask_beyond) / 0.05)
    dx, dy = outline.x_px - cx, outline.y_px - cy
    d = jnp.sqrt(dx * dx + dy * dy + 1e-9)
    align = (dx * outline.nx + dy * outline.ny) / d
    on_rim = w * (jnp.abs(d - r) < 1.5).astype(dt) * (align > 0.8).astype(dt)
    return jnp.sum(on_rim) / (2 * jnp.pi * jnp.maximum(r, 1.0))
