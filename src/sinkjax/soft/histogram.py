"""Log-intensity histograms and their valleys: where the default segmenter puts the intensity
threshold of a wheel without colour (:mod:`sinkjax.soft.adaptive`).

A histogram is over log intensity (shading scales intensity, so a population keeps its width in
log units), every second pixel each way, 64 bins from one 8-bit step to 1, smoothed over five
bins. The thresholds found are not differentiable (each is a choice of bin); the segmenter's
leaves scale them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

_HIST_BINS = 64
_LOG_I_MIN = float(np.log(1.0 / 255.0))  # one 8-bit step: the darkest intensity binned
# Pixels are counted into this many copies of the histogram (pixel i into copy i % _COPIES), then
# the copies are summed: on a GPU every count is an atomic add, and neighbouring pixels (of one
# intensity) into one bin wait for each other; spread over the copies they do not (on a batch
# of 128 frames of 640x480, 6.3 ms a histogram before, 0.2 ms after, on an H200:
# experiments/gpu_profile.py). Counts of 0/1 weights are whole numbers, so the sum is exact
# whatever the order.
_COPIES = 32
# A valley parts two populations when it lies at least this far (relative) below the smaller
# of them, each holding at least this share of the pixels in one bin.
_VALLEY_DEPTH = 0.25
_VALLEY_MIN_SHARE = 2e-4
# A valley this deep parts two real populations (not a ripple of one).
_CLEAR_DEPTH = 0.5


def binned_histogram(
    values: Float[Array, "H W"],
    weight: Float[Array, "H W"],
    span: tuple[float, float, int],
    kernel: tuple[int, ...],
    clip: bool,
) -> tuple[Float[Array, " B"], Float[Array, " B"]]:
    """The histogram of ``values`` over ``span`` = (lo, hi, bins), each pixel counted with its
    ``weight`` (0: left out), smoothed by ``kernel`` (integer weights, normalised here), and the
    bins' centres. ``clip``: values outside the span count in the end bins, else not at all."""
    lo, hi, bins = span
    scale = bins / (hi - lo)
    idx = jnp.floor((values - lo) * scale).astype(jnp.int32)
    keep = weight.ravel() > 0
    if clip:
        idx = jnp.clip(idx, 0, bins - 1)
    else:
        keep = keep & (idx.ravel() >= 0) & (idx.ravel() < bins)
    copy = jnp.arange(idx.size, dtype=jnp.int32) % _COPIES
    # A pixel left out adds nothing: its index lies past the end and is dropped.
    slot = jnp.where(keep, copy * bins + idx.ravel(), _COPIES * bins)
    counts = (
        jnp.zeros(_COPIES * bins, values.dtype)
        .at[slot]
        .add(weight.ravel(), mode="drop")
        .reshape(_COPIES, bins)
        .sum(axis=0)
    )
    k = jnp.asarray(kernel, values.dtype) / sum(kernel)
    centres = lo + (jnp.arange(bins, dtype=values.dtype) + 0.5) / scale
    return jnp.convolve(counts, k, mode="same"), centres


def log_histogram(
    intensity: Float[Array, "H W"], weight: Float[Array, "H W"] | None = None
) -> tuple[Float[Array, " B"], Float[Array, " B"]]:
    """The frame's histogram of log intensity (every second pixel each way, 64 bins from one
    8-bit step to 1, smoothed over five bins; each pixel counted with its ``weight``, 1 by
    default) and the bins' centres (log intensity)."""
    log_i = jnp.log(jnp.clip(intensity[::2, ::2], 1.0 / 255.0, 1.0))
    w = jnp.ones_like(log_i) if weight is None else weight[::2, ::2]
    return binned_histogram(log_i, w, (_LOG_I_MIN, 0.0, _HIST_BINS), (1, 2, 3, 2, 1), clip=True)


def valley(
    hist: Float[Array, " B"],
    centres: Float[Array, " B"],
    lo: Float[Array, ""],
    hi: Float[Array, ""],
    bright: Bool[Array, ""],
) -> Float[Array, ""]:
    """The intensity threshold in the histogram's valley between the wheel and the background.

    ``lo``, ``hi`` (log intensity) bound the search. The background's population is the
    histogram's highest peak on the background's side (below ``hi`` for a ``bright`` wheel,
    above ``lo`` for a dark one); the search stops there, so that the valley found lies between
    the wheel and the background nearest to it. The threshold is the middle of the emptiest
    bins (within 0.001 % of the pixels of the minimum: ties); ``exp(hi)`` when the range holds
    no bin. Not differentiable (a choice of bin). :class:`~sinkjax.soft.adaptive.AdaptiveSegmenter`
    searches the bright side (a metal wheel)."""
    beyond = jnp.where(bright, centres < hi, centres > lo)
    mode = centres[jnp.argmax(jnp.where(beyond, hist, -1.0))]
    a = jnp.where(bright, jnp.maximum(mode, lo), lo)
    b = jnp.where(bright, hi, jnp.minimum(mode, hi))
    inside = (centres >= a) & (centres <= b)
    lowest = jnp.min(jnp.where(inside, hist, jnp.inf))
    emptiest = inside & (hist <= lowest + 1e-5 * jnp.sum(hist))
    n = jnp.sum(emptiest.astype(centres.dtype))
    middle = jnp.sum(jnp.where(emptiest, centres, 0.0)) / jnp.maximum(n, 1.0)
    return jnp.exp(jnp.where(jnp.any(inside), middle, hi))


def deepest_valley(
    hist: Float[Array, " B"],
    centres: Float[Array, " B"],
    lo: Float[Array, ""],
    hi: Float[Array, ""],
    reach: Float[Array, ""] | None = None,
) -> tuple[Float[Array, ""], Bool[Array, ""]]:
    """The intensity threshold at the deepest valley between two populations of the histogram
    within ``lo``-``hi`` (log intensity): the bin whose count lies furthest below the smaller of
    the highest bins on either side of it in that range, relative to that smaller one, where
    it is at least ``_VALLEY_DEPTH`` below and the smaller side holds at least
    ``_VALLEY_MIN_SHARE`` of the pixels in one bin; ``exp(lo)`` where no bin is (one
    population: nothing to part). Also whether a valley was found. Not differentiable.

    ``reach`` (log intensity, above ``hi``): the populations on either side are looked for up
    to it (the valley still lies in ``lo``-``hi``), and the highest valley at least
    ``_CLEAR_DEPTH`` deep wins over a deeper one below it: the valley just under the brightest
    population (a metal wheel's face), not one between two darker ones (holes and soil)."""
    top = hi if reach is None else reach
    span = (centres >= lo) & (centres <= top)
    inside = span & (centres <= hi)
    h = jnp.where(span, hist, 0.0)
    side = jnp.minimum(jax.lax.cummax(h), jax.lax.cummax(h, reverse=True))
    real = inside & (side >= _VALLEY_MIN_SHARE * jnp.sum(hist))
    depth = jnp.where(real, (side - h) / jnp.maximum(side, 1e-9), 0.0)
    best = jnp.argmax(depth)
    if reach is not None:
        # The highest run of clear bins, and its deepest bin (the valley's floor).
        clear = depth >= _CLEAR_DEPTH
        last = hist.shape[0] - 1 - jnp.argmax(clear[::-1])
        gaps = jnp.cumsum(~clear)
        run = clear & (gaps == gaps[last]) & (jnp.arange(hist.shape[0]) <= last)
        best = jnp.where(jnp.any(clear), jnp.argmax(jnp.where(run, depth, -1.0)), best)
    found = depth[best] >= _VALLEY_DEPTH
    return jnp.exp(jnp.where(found, centres[best], lo)), found


def log_quantile(
    hist: Float[Array, " B"], centres: Float[Array, " B"], q: float
) -> Float[Array, ""]:
    """The log intensity below which a share ``q`` of a histogram's pixels lie (the first bin
    whose cumulative count reaches it; the top bin of an empty histogram)."""
    cum = jnp.cumsum(hist)
    i = jnp.argmax(cum >= q * cum[-1])
    return jnp.where(cum[-1] > 0, centres[i], centres[-1])


def valley_depth(
    hist: Float[Array, " B"],
    centres: Float[Array, " B"],
    at: Float[Array, ""],
    top: Float[Array, ""],
) -> Float[Array, ""]:
    """How many times the histogram's highest bin between intensity ``at`` and ``top`` outnumbers
    the bin at ``at``: above 1 where a population rises beyond the valley, 1 on a falling tail."""
    log_at = jnp.log(at)
    i = jnp.argmin(jnp.abs(centres - log_at))
    span = (centres >= log_at) & (centres <= jnp.log(top))
    peak = jnp.max(jnp.where(span, hist, 0.0))
    return peak / jnp.maximum(hist[i], 1e-9)
