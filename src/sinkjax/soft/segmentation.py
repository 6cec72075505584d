"""Segmentation stage: the paper's H/S range test as soft masks, and soft clean-up.

The hard test H_d <= H <= H_a and S_d <= S <= S_a becomes a product of sigmoids whose widths are
the temperatures in :class:`~sinkjax.SegmentationParams`; as they go to zero the mask becomes the
classic binary mask. Hue is compared circularly around the wheel's mean hue H_w.
:func:`wheel_mask` then vetoes the pixels whose chromaticity is clearly the soil's or the
background's (issue 12: a colour cast that tints the wall towards the wheel's hue passes the
paper's band).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..rig import CLIP_LEVEL, HUE_SCALE_DEG, SegmentationParams, rect_problem
from .colour import chromaticity, circular_mean_deg, rgb_to_hsi, wrap_deg
from .wheel_colour import column_median, wheel_colour

# The confidence rectangle (x, y, w, h) in px: static ints, or a traced array (see below).
Rect = tuple[int, int, int, int] | Int[Array, " 4"]


def confidence_means(
    h_deg: Float[Array, "H W"],
    s: Float[Array, "H W"],
    rect: Rect,
    weight: Float[Array, "H W"] | None = None,
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Eqs. 4-5: H_w (circular mean, degrees) and S_w over the confidence rectangle (x, y, w, h).

    ``rect`` is a tuple of ints (static: the rectangle is sliced out; raises ValueError if it
    does not lie inside the image) or an int array of 4 (traced: a masked mean over the image,
    so one compiled function serves every rectangle; the caller checks it with
    :func:`sinkjax.rig.rect_problem`). ``weight``: the pixels to average instead, 0/1 over the
    image (:func:`colour_weight`: the rectangle's pixels that show the wheel's colour).
    """
    height, width = h_deg.shape[-2:]
    check_rect(rect, height, width)
    if isinstance(rect, tuple | list):
        if weight is None:
            x, y, w, h = rect
            return circular_mean_deg(h_deg[y : y + h, x : x + w]), jnp.mean(s[y : y + h, x : x + w])
    if weight is None:
        weight = box_weight(jnp.asarray(rect, jnp.int32), height, width, s.dtype)
    count = jnp.maximum(jnp.sum(weight), 1.0)
    return circular_mean_deg(h_deg, weight), jnp.sum(weight * s) / count


def check_rect(rect: Rect, height: int, width: int) -> None:
    """Raise ValueError (saying how to fix it) where a static (tuple) ``rect`` does not lie inside
    a ``width`` x ``height`` image; a traced one is the caller's to check
    (:func:`sinkjax.rig.rect_problem`)."""
    if isinstance(rect, tuple | list) and (problem := rect_problem(tuple(rect), height, width)):
        raise ValueError(problem)


def box_weight(
    box: Int[Array, " 4"], height: int, width: int, dtype: jnp.dtype | type
) -> Float[Array, "H W"]:
    """1 inside the box (x, y, w, h) px (may be traced, may reach beyond the image), else 0."""
    x0, y0, w0, h0 = (box[i] for i in range(4))
    rows = jnp.arange(height, dtype=box.dtype)
    cols = jnp.arange(width, dtype=box.dtype)
    inside = ((rows >= y0) & (rows < y0 + h0))[:, None] & ((cols >= x0) & (cols < x0 + w0))[None, :]
    return inside.astype(dtype)


# A pixel with two or three channels at the sensor's top (a lamp's glow, a highlight) shows the
# light's colour, not the wheel's: its hue is that of the clipped channels, whatever the wheel's.
# (One clipped channel, a saturated wheel's own primary, keeps its hue.) Where fewer than this
# share of the confidence rectangle's pixels are unclipped, the wheel's colour is read from the
# rectangle grown by half its width and height on every side (the face around a glow), or by its
# whole width and height where that is still mostly clipped: from their unclipped pixels only.
# The smaller growth keeps to the face.
MIN_UNCLIPPED_SHARE = 0.25


def unclipped(image: Float[Array, "*n 3"]) -> Float[Array, "*n"]:
    """1 where at most one channel of a pixel reaches :data:`sinkjax.rig.CLIP_LEVEL`, else 0."""
    middle = jnp.sum(image, axis=-1) - jnp.max(image, axis=-1) - jnp.min(image, axis=-1)
    return (middle < CLIP_LEVEL).astype(image.dtype)


def colour_box(image: Float[Array, "H W 3"], rect: Rect) -> Int[Array, " 4"]:
    """The box (x, y, w, h) px the wheel's colour is read from: the confidence rectangle, or
    where it is mostly clipped (:data:`MIN_UNCLIPPED_SHARE`) that rectangle grown by half its
    size on every side, or by its whole size. A discrete choice: no gradient flows through it.
    A tuple ``rect`` is checked (ValueError if it does not lie inside the image)."""
    height, width = image.shape[:2]
    check_rect(rect, height, width)
    r = jnp.asarray(rect, jnp.int32)

    def mostly_clipped(box: Int[Array, " 4"]) -> Array:
        # The share over the box's grid of RECT_SAMPLES^2 pixels: a few hundred gathers, not
        # a pass over the whole image per box.
        return jnp.mean(unclipped(rect_values(image, box))) < MIN_UNCLIPPED_SHARE

    half = jnp.stack(
        [r[0] - r[2] // 2, r[1] - r[3] // 2, r[2] + r[2] // 2 * 2, r[3] + r[3] // 2 * 2]
    )
    whole = jnp.stack([r[0] - r[2], r[1] - r[3], 3 * r[2], 3 * r[3]])
    return jnp.where(mostly_clipped(r), jnp.where(mostly_clipped(half), whole, half), r)


def colour_weight(
    image: Float[Array, "H W 3"], rect: Rect, box: Int[Array, " 4"] | None = None
) -> Float[Array, "H W"]:
    """0/1 over the image: the unclipped pixels of :func:`colour_box` (``box``, where the caller
    has it), the pixels whose colour is the wheel's (the whole rectangle, as the paper has it,
    where none of them is unclipped). A rectangle without a clipped pixel gives exactly its own
    pixels. Where the rectangle's grid of RECT_SAMPLES^2 pixels shows none clipped, it is the
    rectangle's own pixels without looking further (``lax.cond``: a pass over the image saved)."""
    height, width = image.shape[:2]
    r = jnp.asarray(rect, jnp.int32)
    box = colour_box(image, rect) if box is None else box
    plain = box_weight(r, height, width, image.dtype)

    def unclipped_only() -> Float[Array, "H W"]:
        w = box_weight(box, height, width, image.dtype) * unclipped(image)
        return jnp.where(jnp.sum(w) > 0, w, plain)

    seen = jnp.any(unclipped(rect_values(image, r)) < 1.0)
    return jax.lax.cond(seen, unclipped_only, lambda: plain)


def band_limits(
    h_w_deg: Float[Array, ""], s_w: Float[Array, ""], seg: SegmentationParams
) -> tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""], Float[Array, ""]]:
    """(hue low, hue high) as offsets from H_w in degrees, and (S_d, S_a)."""
    return (
        (seg.p_d_hue - 1.0) * HUE_SCALE_DEG,
        (seg.p_a_hue - 1.0) * HUE_SCALE_DEG,
        seg.p_d_sat * s_w,
        seg.p_a_sat * s_w,
    )


def soft_mask(
    h_deg: Float[Array, "H W"],
    s: Float[Array, "H W"],
    h_w_deg: Float[Array, ""],
    s_w: Float[Array, ""],
    seg: SegmentationParams,
) -> Float[Array, "H W"]:
    """Soft wheel mask in [0, 1]: sigmoids of the distances to the four band limits."""
    h_lo, h_hi, s_lo, s_hi = band_limits(h_w_deg, s_w, seg)
    dh = wrap_deg(h_deg - h_w_deg)
    th = seg.temperature_hue_deg
    ts = seg.temperature_sat
    m_h = jax.nn.sigmoid((dh - h_lo) / th) * jax.nn.sigmoid((h_hi - dh) / th)
    m_s = jax.nn.sigmoid((s - s_lo) / ts) * jax.nn.sigmoid((s_hi - s) / ts)
    return m_h * m_s


HueSat = tuple[Float[Array, "H W"], Float[Array, "H W"]]


def paper_mask(
    image: Float[Array, "H W 3"],
    seg: SegmentationParams,
    rect: Rect,
    hs: HueSat | None = None,
    weight: Float[Array, "H W"] | None = None,
) -> Float[Array, "H W"]:
    """Image in [0, 1] -> the paper's steps (2)-(3) made differentiable: the H/S band alone.
    ``hs``: the image's hue (degrees) and saturation when the caller has them already
    (:func:`~sinkjax.soft.colour.rgb_to_hsi`; the same numbers, one conversion fewer).
    ``weight``: the pixels H_w and S_w are taken over (:func:`confidence_means`); None: the
    rectangle's, as the paper has it."""
    h, s = rgb_to_hsi(image)[:2] if hs is None else hs
    h_w, s_w = confidence_means(h, s, rect, weight)
    return soft_mask(h, s, h_w, s_w, seg)


# The soft method's band beside its veto: the paper's band widened by this factor (the hue
# limits' offsets from H_w, H_w + BAND_WIDEN (P - 1) 180 deg, and the saturation's top,
# BAND_WIDEN P_a S_w: saturation is a ratio scale). The saturation's floor, which keeps the grey
# axis out (grey soil, shadows, speculars, the hub: not all of them are a reference's colour),
# stays the paper's.
BAND_WIDEN = 2.0


def widened(seg: SegmentationParams) -> SegmentationParams:
    """``seg`` with the H/S band widened as the soft method uses it beside its veto
    (:data:`BAND_WIDEN`): the same leaves, so gradients reach ``seg``'s P_a/P_d."""
    hue = lambda p: 1.0 + BAND_WIDEN * (p - 1.0)
    return eqx.tree_at(
        lambda q: (q.p_d_hue, q.p_a_hue, q.p_a_sat),
        seg,
        (hue(seg.p_d_hue), hue(seg.p_a_hue), BAND_WIDEN * seg.p_a_sat),
    )


def wheel_mask(
    image: Float[Array, "H W 3"],
    seg: SegmentationParams,
    rect: Rect,
    *,
    reference: bool = True,
    hs: HueSat | None = None,
    box: Int[Array, " 4"] | None = None,
) -> Float[Array, "H W"]:
    """Image in [0, 1] -> soft wheel mask: an H/S band (:func:`paper_mask`) with the pixels
    that are clearly soil or background vetoed (:func:`reference_mask`).

    The veto compares each pixel with the soil's and the background's own colours in this
    frame, so the band beside it need not separate the wheel from them too: it is the paper's
    widened (:func:`widened`). The paper's tight band cuts away what is still wheel on hard
    footage: the hue that soil-coloured dust or a colour cast pulls from H_w, the saturation
    that a confidence rectangle in a lamp's glow understates (the shaded face is more saturated
    than S_w). ``reference`` False: the paper's band alone, as the paper has it. ``hs``: as in
    :func:`paper_mask`. Both read the wheel's colour from the rectangle's unclipped pixels
    (:func:`colour_weight`; the face around it where a glow clips most of it); ``box``: the
    :func:`colour_box`, where the caller has it.
    """
    if not reference:
        return paper_mask(image, seg, rect, hs)
    box = colour_box(image, rect) if box is None else box
    weight = colour_weight(image, rect, box)
    return paper_mask(image, widened(seg), rect, hs, weight) * reference_mask(
        image, rect, seg.veto_fraction, box
    )


# Rows at the top and bottom of the image (fraction of its height) whose median colours are the
# background's and the soil's: a side view has the wall above the wheel and the soil below it,
# across the whole width (a wheel reaching into a strip covers far less than half of it).
EDGE_ROWS_FRACTION = 0.03
# A pixel is vetoed when it lies nearer the other reference by a fraction of the references'
# separation (SegmentationParams.veto_fraction, 0.25 by default): a blurred edge then stays with
# the band, which locates it to sub-pixel precision.
# Samples per side of the grid that stands for a traced confidence rectangle's pixels.
RECT_SAMPLES = 32
# The smallest spread of the wheel's chromaticity taken as real (1 % saturation: sensor noise).
MIN_SPREAD = 0.02


def rect_values(q: Float[Array, "H W C"], rect: Rect, dx: int = 0) -> Float[Array, "N C"]:
    """A RECT_SAMPLES^2 grid of nearest pixels spread evenly over the rectangle, static or traced
    alike (a traced rectangle has no static size; a median over a masked whole image would sort
    every pixel of the frame, 100+ ms at 640x480 on a CPU). A rectangle reaching beyond the
    image samples its edge pixels there. ``dx``: the pixels that many columns to the right."""
    height, width = q.shape[:2]
    r = jnp.asarray(rect, jnp.int32)
    x0, y0, w0, h0 = (r[i] for i in range(4))
    dt = q.dtype
    frac = (jnp.arange(RECT_SAMPLES, dtype=dt) + 0.5) / RECT_SAMPLES
    xs = jnp.clip(x0 + jnp.floor(frac * w0.astype(dt)).astype(r.dtype) + dx, 0, width - 1)
    ys = jnp.clip(y0 + jnp.floor(frac * h0.astype(dt)).astype(r.dtype), 0, height - 1)
    return q[ys[:, None], xs[None, :]].reshape(-1, q.shape[-1])


def reference_mask(
    image: Float[Array, "H W 3"],
    rect: Rect,
    veto_fraction: float | Float[Array, ""] = 0.25,
    box: Int[Array, " 4"] | None = None,
) -> Float[Array, "H W"]:
    """Soft veto in [0, 1]: 0 where a pixel's chromaticity is clearly nearer the soil's or the
    background's than the wheel's.

    In chromaticity (:func:`~sinkjax.soft.colour.chromaticity`, blind to shading and
    exposure) the background's and the soil's colours are medians (robust to pebbles) over the
    image's top and bottom rows; the wheel's is the median over the confidence rectangle's
    unclipped pixels (:func:`colour_box`), or where a glow or a highlight spreads them towards
    the light's colour, their saturated end (:func:`~sinkjax.soft.wheel_colour.wheel_colour`).
    Each pixel is compared with the perpendicular bisector of wheel and reference (the
    nearest-mean rule), so the soil's own colour, not a band around the wheel's, decides.
    A reference closer to the wheel than twice the wheel's own spread (MAD) is the wheel itself
    (a strip the wheel fills) and vetoes nothing. ``veto_fraction``: a pixel is vetoed once it
    lies nearer the other reference by that fraction of the two references' separation (a
    calibratable leaf: dust that blends the wheel's colour towards the soil's needs a larger
    one).
    """
    height = image.shape[0]
    # Sensor noise in the dark would scatter single pixels across the bisector: decide on
    # colours averaged over ~1 px (the veto need not be sharp, the band sets the edge).
    blurred = jnp.stack([smooth(image[..., c]) for c in range(3)], axis=-1)
    q = chromaticity(blurred)
    n = max(2, round(EDGE_ROWS_FRACTION * height))
    box = colour_box(image, rect) if box is None else box
    use = unclipped(rect_values(image, box))
    wheel = wheel_colour(rect_values(q, box), jnp.where(jnp.any(use > 0), use, 1.0))
    d_w = jnp.sum((q - wheel.centre[None, None, :]) ** 2, axis=-1)
    out = jnp.ones(image.shape[:2], image.dtype)
    for strip in (q[:n], q[-n:]):
        mu_c = column_median(strip.reshape(-1, 2))
        sep = jnp.sqrt(jnp.sum((mu_c - wheel.centre) ** 2) + 1e-12)
        d_c = jnp.sum((q - mu_c[None, None, :]) ** 2, axis=-1)
        margin = (d_c - d_w) / (2.0 * sep)
        m_c = jax.nn.sigmoid((margin + veto_fraction * sep) / (0.05 * sep + 1e-3))
        # A reference within two spreads of the wheel's is the wheel itself; the spread is at
        # least the chromaticity's sensor/JPEG noise, so a clean uniform wheel gates it fully off.
        spread = jnp.maximum(wheel.spread, MIN_SPREAD)
        gate = jax.nn.sigmoid((sep - 2.0 * spread) / (0.25 * spread))
        out = out * (1.0 - gate * (1.0 - m_c))
    return out


def _blur_axis(a: Float[Array, "H W"], axis: int) -> Float[Array, "H W"]:
    # Binomial [1, 4, 6, 4, 1]/16 (sigma = 1 px) with edge replication: cheap and separable.
    pad = [(0, 0), (0, 0)]
    pad[axis] = (2, 2)
    p = jnp.pad(a, pad, mode="edge")
    n = a.shape[axis]
    taps = (1.0, 4.0, 6.0, 4.0, 1.0)
    out = jnp.zeros_like(a)
    for i, t in enumerate(taps):
        out = out + t * jax.lax.slice_in_dim(p, i, i + n, axis=axis)
    return out / 16.0


def smooth(mask: Float[Array, "H W"]) -> Float[Array, "H W"]:
    """Gaussian-like smoothing (sigma ~ 1 px): the soft stand-in for dilation-then-erosion.

    Isolated mis-classified pixels (sensor noise, soil grains of wheel colour) drop below 0.5 and
    stop producing edges, while real edges keep their sub-pixel position (the blur is symmetric).
    """
    return _blur_axis(_blur_axis(mask, 0), 1)


def soft_open(mask: Float[Array, "H W"], radius_px: int = 1) -> Float[Array, "H W"]:
    """Grey-level opening (min filter then max filter) of a soft mask: removes thin spurs.

    The grey-level generalisation of the paper's erosion/dilation; piecewise differentiable.
    """
    size = 2 * radius_px + 1
    window = (size, size)
    er = -jax.lax.reduce_window(-mask, -jnp.inf, jax.lax.max, window, (1, 1), "SAME")
    return jax.lax.reduce_window(er, -jnp.inf, jax.lax.max, window, (1, 1), "SAME")
