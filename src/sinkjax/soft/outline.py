"""Outline stage: sub-pixel edge points of the soft wheel mask, in fixed-size arrays.

The paper takes the wheel's outline from the binary image. Here the outline is the ridge of the
soft mask's gradient magnitude, thinned by non-maximum suppression (one point per pixel step along
the edge) and located to sub-pixel precision by a parabola through the ridge. Each point carries
its unit normal (pointing from wheel to non-wheel), a soft selection weight, and how much wheel
lies below it in its column (a wheel-soil boundary point has only soil below).
Shapes are static: at most ``capacity`` points, padded with zero weight, so it jit-compiles once
per image size and vmaps over frames.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .segmentation import smooth
from .settings import SoftSettings

# A ridge must be at least this strong (mask units per pixel) to count as an edge point at all;
# the soft weight then ramps up around ``SoftSettings.edge_level``.
_EDGE_MIN = 0.03


class Outline(eqx.Module):
    """Edge points of one frame (padded to a fixed capacity; ``weight`` 0 = absent)."""

    x_px: Float[Array, " K"]
    y_px: Float[Array, " K"]
    nx: Float[Array, " K"]
    ny: Float[Array, " K"]
    weight: Float[Array, " K"]
    wheel_below_px: Float[Array, " K"]
    mask_beyond: Float[Array, " K"]
    valid: Bool[Array, " K"]
    overflow: Bool[Array, ""]


def default_capacity(height: int, width: int) -> int:
    """Room for every edge point a wheel image plausibly has (rim, lugs, holes, boundary)."""
    return int(6 * (height + width))


def _shift(a: Float[Array, "H W"], dy: int, dx: int) -> Float[Array, "H W"]:
    # out[i, j] = a[i + dy, j + dx] with edge replication.
    n = max(1, abs(dy), abs(dx))
    p = jnp.pad(a, n, mode="edge")
    h, w = a.shape
    return p[n + dy : n + dy + h, n + dx : n + dx + w]


def compact(flags: Bool[Array, " N"], size: int) -> tuple[Array, Array]:
    """Indices of the true entries (first ``size`` of them, padded with 0) and their count.

    ``jnp.nonzero(size=...)`` does the same; a parallel prefix sum for the output positions is
    about twice as fast on a CPU (XLA's cumsum of a long vector is sequential there).
    """
    f = flags.astype(jnp.int32)
    pos = jax.lax.associative_scan(jnp.add, f) - 1
    slot = jnp.where(flags, pos, size)
    idx = (
        jnp.zeros(size + 1, jnp.int32)
        .at[slot]
        .set(jnp.arange(f.shape[0], dtype=jnp.int32), mode="drop")
    )
    return idx[:size], pos[-1] + 1


# Where the ridge holds more points than the capacity, a ridge point is kept only where the mask
# a few pixels inside it (along the gradient) exceeds the mask as far outside it by at least
# CROWD_CONTRAST, each averaged over a box: the edge between a solid region and an empty one,
# not a speckle's, a patch's or a pinhole's. Each level is (pixels each side, box half-size);
# the next level applies where the last still leaves more points than the capacity.
CROWD_LEVELS = ((3, 2), (8, 5))
CROWD_CONTRAST = 0.5


# (dy, dx) of the quantised gradient directions 0, 45, 90, 135 degrees.
STEPS = ((0, 1), (1, 1), (1, 0), (1, -1))


def _gradients(m: Float[Array, "H W"]) -> tuple[Array, Array, Array, Array]:
    """Sobel gx, gy of the smoothed mask, their magnitude, and the direction's index in STEPS."""
    # Sobel derivatives, normalised so a unit step blurred over n pixels has slope ~1/n.
    gx = (
        _shift(m, -1, 1)
        + 2 * _shift(m, 0, 1)
        + _shift(m, 1, 1)
        - _shift(m, -1, -1)
        - 2 * _shift(m, 0, -1)
        - _shift(m, 1, -1)
    ) / 8.0
    gy = (
        _shift(m, 1, -1)
        + 2 * _shift(m, 1, 0)
        + _shift(m, 1, 1)
        - _shift(m, -1, -1)
        - 2 * _shift(m, -1, 0)
        - _shift(m, -1, 1)
    ) / 8.0
    mag2 = gx * gx + gy * gy
    mag = jnp.sqrt(jnp.where(mag2 > 0, mag2, 1.0)) * (mag2 > 0).astype(mag2.dtype)
    # Quantise the gradient direction to 0/45/90/135 degrees for non-maximum suppression, by
    # comparisons (tan 22.5 deg) rather than an arctangent of every pixel.
    ax, ay = jnp.abs(gx), jnp.abs(gy)
    t22 = 0.41421356
    q = jnp.where(
        ay <= t22 * ax, 0, jnp.where(ax <= t22 * ay, 2, jnp.where(gx * gy > 0, 1, 3))
    ).astype(jnp.int32)
    return gx, gy, mag, q


def _edge_contrast(
    m: Float[Array, "H W"],
    gx: Float[Array, "H W"],
    gy: Float[Array, "H W"],
    q: Array,
    side_px: int,
    half_px: int,
) -> Float[Array, "H W"]:
    # The mask's mean over a (2 half_px + 1)^2 box centred side_px pixels from each pixel along
    # its quantised gradient towards the higher mask (the wheel's side of an edge), minus the
    # same as far the other way.
    size = 2 * half_px + 1
    box = jax.lax.reduce_window(m, 0.0, jax.lax.add, (size, size), (1, 1), "SAME") / size**2
    out = jnp.zeros_like(m)
    for i, (dy, dx) in enumerate(STEPS):
        n = side_px if dy == 0 or dx == 0 else max(round(side_px / 1.41421356), 1)
        ahead = _shift(box, n * dy, n * dx) - _shift(box, -n * dy, -n * dx)
        forward = (gx * dx + gy * dy) >= 0
        out = jnp.where(q == i, jnp.where(forward, ahead, -ahead), out)
    return out


def _ridge(mag: Float[Array, "H W"], q: Array) -> Bool[Array, "H W"]:
    """Non-maximum suppression: where the gradient magnitude peaks across the edge."""

    def along(sign: int) -> Array:
        shifted = [_shift(mag, sign * dy, sign * dx) for dy, dx in STEPS]
        return jnp.where(
            q == 0,
            shifted[0],
            jnp.where(q == 1, shifted[1], jnp.where(q == 2, shifted[2], shifted[3])),
        )

    ridge = (mag >= along(1)) & (mag > along(-1)) & (mag > _EDGE_MIN)
    return ridge.at[:2].set(False).at[-2:].set(False).at[:, :2].set(False).at[:, -2:].set(False)


def _thin(mask: Float[Array, "H W"], weak: Float[Array, ""], capacity: int) -> Bool[Array, "H W"]:
    """The ridge of ``mask``'s outline thinned to fit ``capacity`` points.

    Points are stored in raster order, so an overflowing ridge would keep the top of the image
    and drop the rest: a dim frame whose textured wall has patches of the wheel's colour
    filled the capacity above the wheel, and the rim was lost in every frame of the recording.
    First the weak ridges go (gradient at most ``weak``: a soft mask's ripples in textured
    soil or wall, points of hardly any weight). Then, a speckle's or a patch's edge has no solid
    wheel a few pixels inside it, a pinhole's in the wheel's face no empty space a few pixels
    outside it; the wheel's outline (rim, lugs, boundary) has both. So while the ridge stays
    crowded only points with that contrast stay, judged further out and over larger boxes at
    each level of :data:`CROWD_LEVELS`. Called only on a crowded ridge: an uncrowded one is
    kept whole, bit for bit.
    """

    m = smooth(mask)
    gx, gy, mag, q = _gradients(m)
    kept = _ridge(mag, q) & (mag > weak)
    for side_px, half_px in CROWD_LEVELS:
        sharp = _edge_contrast(m, gx, gy, q, side_px, half_px) > CROWD_CONTRAST
        kept = kept & ((jnp.sum(kept) <= capacity) | sharp)
    return kept


def extract_outline(
    mask: Float[Array, "H W"], settings: SoftSettings, capacity: int | None = None
) -> Outline:
    """Sub-pixel outline points of a soft mask. ``capacity`` is static."""
    s = settings.astype(mask.dtype)
    height, width = mask.shape
    k = default_capacity(height, width) if capacity is None else capacity
    m = smooth(mask)
    gx, gy, mag, q = _gradients(m)
    ridge = _ridge(mag, q)
    flat, count = compact(ridge.ravel(), k)
    # Crowded (more ridge points than the capacity): thinned (see _thin), all of it done again
    # from the mask in a lax.cond, so an uncrowded frame (on a CPU, frame by frame) pays
    # nothing more.
    flat, count = jax.lax.cond(
        count > k,
        lambda: compact(_thin(mask, s.edge_level - 2.0 * s.edge_softness, k).ravel(), k),
        lambda: (flat, count),
    )
    valid = jnp.arange(k, dtype=count.dtype) < count
    rows = flat // width
    cols = flat % width
    e0 = mag[rows, cols]
    qq = q[rows, cols]
    # The magnitude one step ahead and behind across the edge (edge-replicated).
    dy_, dx_ = (jnp.array([st[i] for st in STEPS], jnp.int32)[qq] for i in (0, 1))
    ef = mag[jnp.clip(rows + dy_, 0, height - 1), jnp.clip(cols + dx_, 0, width - 1)]
    eb = mag[jnp.clip(rows - dy_, 0, height - 1), jnp.clip(cols - dx_, 0, width - 1)]
    # Parabola through (-1, eb), (0, e0), (1, ef): vertex offset in steps along the direction.
    curv = eb - 2.0 * e0 + ef
    ok = curv < -1e-9
    off = jnp.where(ok, 0.5 * (eb - ef) / jnp.where(ok, curv, -1.0), 0.0)
    off = jnp.clip(off, -0.5, 0.5)
    step = jnp.array(STEPS, dtype=mask.dtype)[qq]  # (K, 2) as (dy, dx)
    x = cols.astype(mask.dtype) + off * step[:, 1]
    y = rows.astype(mask.dtype) + off * step[:, 0]
    g_x = gx[rows, cols]
    g_y = gy[rows, cols]
    norm = jnp.where(e0 > 0, e0, 1.0)
    # Normal from wheel (high mask) to non-wheel: minus the gradient.
    nx = -g_x / norm
    ny = -g_y / norm
    weight = jnp.where(valid, jax.nn.sigmoid((e0 - s.edge_level) / s.edge_softness), 0.0)
    # Wheel mass strictly below each pixel in its column, starting 3 px down (past the edge's
    # own blur): a wheel-soil boundary point has ~0, the top edge of a hole has a lot.
    solid = jax.nn.sigmoid((m - 0.5) / 0.1)
    below = jax.lax.associative_scan(jnp.add, solid, axis=0, reverse=True)
    below = jnp.concatenate([below[3:], jnp.zeros((3, width), mask.dtype)], 0)
    # Mask 3 px beyond the edge: ~0 on the wheel's true outline (rim, lug tips, boundary), high
    # on a partial edge inside the wheel (a darker rim ring, shading), which must not be the rim.
    bx = jnp.clip(jnp.round(x + 3.0 * nx).astype(jnp.int32), 0, width - 1)
    by = jnp.clip(jnp.round(y + 3.0 * ny).astype(jnp.int32), 0, height - 1)
    return Outline(
        x_px=x,
        y_px=y,
        nx=nx,
        ny=ny,
        weight=weight,
        wheel_below_px=below[rows, cols],
        mask_beyond=m[by, bx],
        valid=valid,
        overflow=count > k,
    )


# Luma and the two chroma axes (BT.601). Video and JPEG keep luma at full resolution but halve
# chroma, so chroma edges are smeared: the profile leans on luma where luma has contrast.
_YCC = ((0.299, 0.587, 0.114), (-0.169, -0.331, 0.5), (0.5, -0.419, -0.081))


def refine_outline(
    image: Float[Array, "H W 3"], outline: Outline, settings: SoftSettings
) -> Outline:
    """Move each outline point along its normal to where the image is halfway between its sides.

    The mask finds edges but is a poor ruler: a hue/saturation threshold on a blurred or JPEG-ed
    pixel that mixes wheel and soil does not fire at 50 % coverage, so mask edges sit up to a
    pixel or two inside the darker or less saturated side. Colours mix linearly under blur and
    anti-aliasing, so along the normal the image goes from the inner colour c_in to the outer
    c_out; projecting onto (c_in - c_out) gives a profile from 1 to 0 whose integral over the
    window is the distance from the window's start to the edge, for any symmetric blur. That
    integral is linear in the pixels (noise averages out) and differentiable.

    The integral is the edge's place only when the window's ends lie on the plateaus beyond the
    edge's blur. Where the mask edge is well off the image edge (a colour cast that makes the
    background half wheel-coloured puts it 2-3 px outside the rim), the window's inner end lies
    on the edge itself and one profile stops short (rendered cast footage: 2.4 px -> 0.8 px,
    and the rim's radius 0.7 px too large). So where the first profile moved a point by more
    than a third of its half length, further profiles (``settings.refine_passes`` in all) are
    taken, each centred where the last put the edge; each removes most of the remaining offset
    (2.5 px on an edge blurred by a Gaussian of 1 px: 1.0, 0.25, 0.05 px after one, two, three).
    A further profile moves a point at most as far as the last one did (the offsets of a clean
    edge shrink from pass to pass; one that drifted onto another edge, such as a dark contact
    shadow's far side, cannot run away). Points the first profile placed within a pixel keep it
    (the further passes fade in between 1 and 1.5 px, so the result stays continuous in the
    image and the mask): there the first window already straddles the edge, and recentring on
    small, crowded frames (the corners where soil meets rim) added noise, not accuracy. No point
    moves further than the profile's half length.

    Three profiles are the default (``SoftSettings.refine_passes``; 1 is the former method).
    Measured, one profile against three: the rim points of colour-cast footage 0.8 -> 0.04 px off
    the rim; the benchmark's 90th percentile angle errors (seed 2026) 0.83 / 0.96 -> 0.73 / 0.78
    deg, at about 3 ms more per 640x480 frame.
    A mask that lies well inside the wheel (a learned segmenter's start, logits - 2) now meets a
    rim placed on the wheel's edge, so the ring check flags more of its frames.
    """
    if settings.refine_passes == 0:
        return outline
    reach = settings.refine_half_width_px
    t = _edge_offset(image, outline, jnp.zeros_like(outline.x_px), settings)
    t = jnp.clip(t, -reach, reach)
    # 0 where the first profile moved a point by at most a third of its half length, 1 beyond half.
    far = jnp.clip((jnp.abs(t) - reach / 3.0) / (reach / 6.0), 0.0, 1.0)
    last = jnp.abs(t)
    for _ in range(settings.refine_passes - 1):
        step = far * jnp.clip(_edge_offset(image, outline, t, settings), -last, last)
        t = jnp.clip(t + step, -reach, reach)
        last = jnp.abs(step)
    return eqx.tree_at(
        lambda o: (o.x_px, o.y_px),
        outline,
        (outline.x_px + t * outline.nx, outline.y_px + t * outline.ny),
    )


def _bilinear_rgb(
    image: Float[Array, "H W 3"], y: Float[Array, "*n"], x: Float[Array, "*n"]
) -> Float[Array, "*n 3"]:
    """The image's three channels at (y, x), interpolated bilinearly, coordinates clamped to the
    image: ``jax.scipy.ndimage.map_coordinates(channel, [y, x], order=1, mode="nearest")`` for
    each channel, with the same arithmetic in the same order (equal to float rounding: XLA may
    fuse it differently), but one gather of all three channels per corner instead of one per
    channel (0.7 of the refinement's cost per 640x480 frame: 4.1 -> 2.9 ms a profile)."""
    height, width = image.shape[:2]
    y0f, x0f = jnp.floor(y), jnp.floor(x)
    wy1, wx1 = y - y0f, x - x0f
    wy0, wx0 = 1 - wy1, 1 - wx1
    y0, x0 = y0f.astype(jnp.int32), x0f.astype(jnp.int32)
    ys = (jnp.clip(y0, 0, height - 1), jnp.clip(y0 + 1, 0, height - 1))
    xs = (jnp.clip(x0, 0, width - 1), jnp.clip(x0 + 1, 0, width - 1))
    terms = [
        (wy * wx)[..., None] * image[yi, xi]
        for yi, wy in zip(ys, (wy0, wy1), strict=True)
        for xi, wx in zip(xs, (wx0, wx1), strict=True)
    ]
    return terms[0] + terms[1] + terms[2] + terms[3]


def _edge_offset(
    image: Float[Array, "H W 3"], outline: Outline, t: Float[Array, " K"], settings: SoftSettings
) -> Float[Array, " K"]:
    """The edge's offset along each normal from the outline point moved ``t`` px along it, by
    one profile centred there (0 where the two sides do not differ)."""
    half, step = settings.refine_half_width_px, settings.refine_step_px
    x0 = outline.x_px + t * outline.nx
    y0 = outline.y_px + t * outline.ny
    chroma = settings.astype(image.dtype).chroma_weight
    ts = jnp.arange(-half, half + 0.5 * step, step, dtype=image.dtype)
    px = x0[:, None] + ts[None] * outline.nx[:, None]
    py = y0[:, None] + ts[None] * outline.ny[:, None]
    samples = _bilinear_rgb(image, py, px)
    ycc = (
        jnp.asarray(_YCC, image.dtype)
        * jnp.stack([jnp.ones((), image.dtype), chroma, chroma])[:, None]
    )
    samples = samples @ ycc.T
    c_in = jnp.mean(samples[:, :3], axis=1)
    c_out = jnp.mean(samples[:, -3:], axis=1)
    diff = c_in - c_out
    contrast2 = jnp.sum(diff * diff, -1)
    ok = contrast2 > 0.02**2
    proj = (
        jnp.einsum("ktc,kc->kt", samples - c_out[:, None], diff)
        / jnp.where(ok, contrast2, 1.0)[:, None]
    )
    # Trapezoid integral of the profile from the window's start: the edge's offset from -half.
    t_edge = -half + step * (jnp.sum(proj, 1) - 0.5 * (proj[:, 0] + proj[:, -1]))
    return jnp.where(ok, t_edge, 0.0)
