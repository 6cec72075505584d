"""A black wheel's intensity threshold from its shading-corrected face, once the recording's rim
is known.

A black wheel's face under one-sided light is a smooth gradient: across a 150 px rim its
brightness changes by a factor of 1.5 or more. The wheel's shadow on the soil in front of and
below it is the soil's colour darkened, and its darkest pixels can be as dark as the face's lit
side, although at the soil line, where the two meet, the soil is 1.2-2 times brighter than the
face just above it. A threshold on intensity alone (the paper-style ``p_a_int * I_w``, or a valley
of the frame's histogram, 9 % bins smoothed over five) then runs through the shadow's
population, the mask takes blotches of the shadow for wheel, and the frame is flagged.

With the rim known, the face is measured where it must be, the upper half of the disc:

1. Its shading, ``log I = a + b (x - cx) / r + c (y - cy) / r`` (a lamp's gradient is smooth
   across a flat face), fitted by least squares to the upper half's pixels that the frame's
   threshold calls wheel, three times over, each time without those more than ``TRIM`` times the
   residuals' RMS from the plane (holes, the hub, a sheen).
2. The corrected intensity ``c = I / exp(plane)`` is about 1 on the face everywhere, to within
   its RMS; the soil and its shadow lie above. The threshold goes to the first valley of the
   inside's histogram of ``log c`` (:func:`face_valley`; 2 % bins) above ``TRIM`` RMS and below
   the frame's own threshold on the lower half: the first dip that is deep against both the
   face's peak and the next population within ``_NEXT_LOG`` (so the dips of a dust's fade on the
   lower face do not count against a lit soil far beyond: the valley lies before the shadow).
3. Below the rim's centre (where the soil, the soil line and the shadow are; above it only the
   brighter background borders the wheel, and the frame's threshold stays), the threshold
   becomes ``min(frame's, corrected threshold * exp(plane))`` (it only takes pixels away from
   the wheel), where the fit held: enough pixels, a valley, and at least ``KEEP`` of the upper
   half the frame's threshold calls wheel still wheel at it. The sigmoid's width scales with the
   gap between the face and the threshold (``t_int / (p_a_int - 1)`` of it, the paper-style
   threshold's own sharpness), so that a threshold close above the face does not read the
   face's noise as grey.

``experiments/black_wheels.py`` measures the effect (README, "Wheels without hue").

The plane and the valley are choices, not measurements: no gradient flows through them; the
segmenter's ``p_valley`` scales the threshold, as the frame's own.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .histogram import _VALLEY_DEPTH, _VALLEY_MIN_SHARE, binned_histogram

TRIM = 2.5  # residuals beyond this many RMS are not the face (holes, hub, a sheen)
KEEP = 0.9  # the corrected threshold keeps at least this share of the upper half's wheel
MIN_FACE_PX = 400.0
_PLANE_ROUNDS = 3
# The corrected intensity's histogram: log c from half the face's to four times it, in bins of
# about 2 % (the face's own spread is 3-5 %; the frame's 9 % bins, smoothed over five, blur the
# face into a shadow 1.2 times brighter), smoothed over three.
_LOG_C_LO, _LOG_C_HI, _C_BINS = -0.7, 1.4, 96
# A valley's right side is the next population within this (log) of it: a soil's grain spreads
# its own population over about +-30 %.
_NEXT_LOG = 0.4


def face_plane(
    log_i: Float[Array, "H W"], weight: Float[Array, "H W"], u: Array, v: Array
) -> tuple[Float[Array, "H W"], Float[Array, ""], Float[Array, ""]]:
    """The face's shading plane (step 1 of the module docstring) over the pixels of 0/1
    ``weight``, with ``u``, ``v`` the offsets from the rim's centre in radii: the plane's log
    intensity everywhere, the residuals' RMS and how many pixels the last fit used."""
    dt = log_i.dtype
    basis = jnp.stack([jnp.ones_like(log_i), *jnp.broadcast_arrays(u, v, log_i)[:2]])

    def fit(w: Array) -> tuple[Array, Array, Array]:
        normal = jnp.einsum("khw,lhw->kl", basis * w[None], basis)
        rhs = jnp.einsum("khw,hw->k", basis * w[None], log_i)
        # A tiny ridge: an empty selection gives a zero plane, not a singular solve.
        coef = jnp.linalg.solve(normal + 1e-6 * jnp.eye(3, dtype=dt), rhs)
        plane = jnp.einsum("k,khw->hw", coef, basis)
        res = log_i - plane
        rms = jnp.sqrt(jnp.sum(w * res * res) / jnp.maximum(jnp.sum(w), 1.0) + 1e-12)
        return plane, rms, weight * (jnp.abs(res) < TRIM * rms).astype(dt)

    # Each round fits on the pixels the last left in (a loop: one compiled round, not three).
    w = jax.lax.fori_loop(0, _PLANE_ROUNDS - 1, lambda _, w: fit(w)[2], weight)
    plane, rms, _ = fit(w)
    return plane, rms, jnp.sum(w)


def corrected_histogram(
    log_c: Float[Array, "H W"], weight: Float[Array, "H W"]
) -> tuple[Float[Array, " B"], Float[Array, " B"]]:
    """The histogram of log corrected intensity over 0/1 ``weight`` (``_C_BINS`` bins from
    ``_LOG_C_LO`` to ``_LOG_C_HI``; outside that range not counted), smoothed over three bins,
    and the bins' centres."""
    span = (_LOG_C_LO, _LOG_C_HI, _C_BINS)
    return binned_histogram(log_c, weight, span, (1, 2, 1), clip=False)


def face_valley(
    hist: Float[Array, " B"],
    centres: Float[Array, " B"],
    lo: Float[Array, ""],
    hi: Float[Array, ""],
) -> tuple[Float[Array, ""], Bool[Array, ""]]:
    """The first valley of a log histogram between ``lo`` and ``hi`` (log): the first bin that
    is a local minimum and lies at least ``_VALLEY_DEPTH`` below the smaller of the highest bin
    on its left (the face's peak, below ``lo``) and the highest within ``_NEXT_LOG`` on its
    right (the next population: a far one, the lit soil, would make every dip of a dust's fade
    a valley), each at least ``_VALLEY_MIN_SHARE`` of the pixels in one bin; and whether there
    is one. Not differentiable (a choice of bin)."""
    n = hist.shape[0]
    reach = max(1, round(_NEXT_LOG * n / (_LOG_C_HI - _LOG_C_LO)))
    padded = jnp.concatenate([hist, jnp.zeros(reach, hist.dtype)])
    right = jnp.max(jnp.stack([padded[k : k + n] for k in range(reach + 1)]), axis=0)
    side = jnp.minimum(jax.lax.cummax(hist), right)
    span = (centres >= lo) & (centres <= hi) & (side >= _VALLEY_MIN_SHARE * jnp.sum(hist))
    lower_left = hist <= jnp.concatenate([hist[:1], hist[:-1]])
    lower_right = hist <= jnp.concatenate([hist[1:], hist[-1:]])
    bottom = span & lower_left & lower_right & (side - hist >= _VALLEY_DEPTH * side)
    return jnp.exp(centres[jnp.argmax(bottom)]), jnp.any(bottom)


def corrected_edge(
    intensity: Float[Array, "H W"],
    wheel: Float[Array, "H W"],
    edge: Float[Array, ""],
    disc: tuple[Array, Array, Array],
) -> tuple[Float[Array, "H W"], Float[Array, "H W"], Bool[Array, "H W"]]:
    """The corrected threshold map of step 3 (module docstring; the mask's is its minimum with
    ``edge``), the face's fitted intensity (the plane), both without gradient, and where the
    rule applies (below the rim's centre, where the fit held).

    ``intensity``: the frame's (smoothed); ``wheel``: the frame's own mask (its threshold
    ``edge``); ``disc``: the recording's rim (centre x, y, radius in px)."""
    cx, cy, rho = disc
    rows = jnp.arange(intensity.shape[0], dtype=intensity.dtype)[:, None]
    cols = jnp.arange(intensity.shape[1], dtype=intensity.dtype)[None, :]
    r = jnp.maximum(rho, 1.0)
    u, v = (cols - cx) / r, (rows - cy) / r
    inside = (u * u + v * v < 1.0) & (rho > 0.0)
    upper = inside & (v < 0.0) & (wheel > 0.5)
    still = jax.lax.stop_gradient(intensity)
    log_i = jnp.log(jnp.clip(still, 1.0 / 255.0, 1.0))
    plane, rms, used = face_plane(log_i, upper.astype(intensity.dtype), u, v)
    hist, centres = corrected_histogram(log_i - plane, inside.astype(intensity.dtype))
    # No higher than the frame's own threshold, where the soil line can be (the lower half).
    lower = (inside & (v > 0.0)).astype(intensity.dtype)
    face_low = jnp.sum(lower * plane) / jnp.maximum(jnp.sum(lower), 1.0)
    top = jnp.log(jnp.maximum(jax.lax.stop_gradient(edge), 1e-6)) - face_low
    found, parted = face_valley(hist, centres, TRIM * rms, top)
    face = jnp.exp(plane)
    corr = found * face
    edge_map = jnp.minimum(jax.lax.stop_gradient(edge), corr)
    upper_px = jnp.maximum(jnp.sum(upper.astype(intensity.dtype)), 1.0)
    kept = jnp.sum(jnp.where(upper, still < edge_map, False).astype(intensity.dtype)) / upper_px
    holds = parted & (used >= MIN_FACE_PX) & (kept >= KEEP)
    return corr, face, jnp.broadcast_to(holds & (v > 0.0), intensity.shape)
