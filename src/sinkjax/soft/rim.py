"""Rim stage for a recording: one rim circle from many frames, and each frame's use of it.

The camera is fixed to the wheel, so the rim is the same circle in every frame of a recording.
Found once from the recording's first frames (:func:`combine_rims`: a robust consensus of their
own fitted circles) it is known to a fraction of a pixel, and each frame is then measured with
that circle as a strong prior (:func:`choose_circle`): a frame whose own rim is hidden by dust
or shadow still measures, and the rim's per-frame noise no longer goes into A, B and the angles.

A frame disagrees with the recording only when its own rim evidence is strong and elsewhere (the
camera moved, or the "recording" is a folder of unrelated pictures); it is then measured with its
own rim and says so in its message, never silently. A moving camera turns the recording rim off
(``RecordingRim.per_frame``).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .hough import Circle, circle_support
from .outline import Outline
from .settings import SoftSettings

# How a frame's rim was chosen (``SoftEstimate.rim_code``).
RIM_OWN = 0  # per-frame rim: no recording rim given
RIM_RECORDING = 1  # the recording's rim, seen in this frame
RIM_HIDDEN = 2  # the recording's rim, hardly seen in this frame (its own evidence is weak)
RIM_MOVED = 3  # this frame's own strong rim is elsewhere: measured with its own rim

# A frame's rim agrees with the recording's within this many pixels (centre or radius), or this
# fraction of the radius if larger: well above the fit's per-frame rim noise (~0.1-0.3 px), well
# below any real displacement of a camera.
AGREE_PX = 2.0
AGREE_FRACTION = 0.015
# The recording's rim is known no better than this (px), whatever the consensus says: below it
# lie the outline's own systematic errors (blur, JPEG), shared by every frame.
MIN_RIM_STD_PX = 0.05
# A frame's own circle counts as the rim moved only within this fraction of the recording's radius.
MOVED_RADIUS_FRACTION = 0.2


class RecordingRim(eqx.Module):
    """The rim circle of a recording (image px) and how firmly frames are held to it.

    ``std_px`` is the one-sigma of each of cx, cy, r: the prior's width in every frame's fit, so
    the covariance (and the reported sigma) carries the recording rim's own uncertainty. ``use``
    is 1.0 to measure frames with this rim, 0.0 for each frame's own rim (a moving camera, or no
    consensus yet). All leaves are arrays: one compiled function serves both modes and every rim.
    """

    cx_px: Float[Array, ""]
    cy_px: Float[Array, ""]
    r_px: Float[Array, ""]
    std_px: Float[Array, ""]
    use: Float[Array, ""]

    @staticmethod
    def fixed(cx_px: float, cy_px: float, r_px: float, std_px: float) -> RecordingRim:
        dt = jax.dtypes.canonicalize_dtype(jnp.float64)
        v = (cx_px, cy_px, r_px, max(std_px, MIN_RIM_STD_PX), 1.0)
        return RecordingRim(*(jnp.asarray(x, dt) for x in v))

    @staticmethod
    def per_frame() -> RecordingRim:
        """No recording rim: each frame finds its own (the method as it was per frame)."""
        dt = jax.dtypes.canonicalize_dtype(jnp.float64)
        return RecordingRim(*(jnp.asarray(x, dt) for x in (0.0, 0.0, 1.0, 1.0, 0.0)))

    def disc(self) -> tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""]]:
        """The inside of the rim, (cx, cy, radius) px, up to the rim itself (a mask that
        changes its rule short of the rim would draw an edge of its own inside it); radius 0
        where the rim is not used."""
        return self.cx_px, self.cy_px, jnp.where(self.use > 0.5, self.r_px, 0.0)

    def describe(self) -> str:
        if float(self.use) < 0.5:
            return "per-frame rim"
        return (
            f"rim centre ({float(self.cx_px):.2f}, {float(self.cy_px):.2f}) px, radius "
            f"{float(self.r_px):.2f} px, +/- {float(self.std_px):.2f} px"
        )


def agree(a: Circle, b: Circle) -> Array:
    """Whether two circles are the same rim (see :data:`AGREE_PX`)."""
    tol = jnp.maximum(AGREE_PX, AGREE_FRACTION * b.r_px)
    return (jnp.hypot(a.cx_px - b.cx_px, a.cy_px - b.cy_px) <= tol) & (
        jnp.abs(a.r_px - b.r_px) <= tol
    )


def recording_circle(outline: Outline, rim: RecordingRim) -> Circle:
    """The recording's rim as a :class:`Circle`, with its support in this frame's outline."""
    dt = outline.x_px.dtype
    cx, cy, r = (jnp.asarray(v, dt) for v in (rim.cx_px, rim.cy_px, rim.r_px))
    return Circle(cx_px=cx, cy_px=cy, r_px=r, support=circle_support(outline, cx, cy, r))


def needs_own_rim(rec: Circle, rim: RecordingRim, settings: SoftSettings) -> Array:
    """Whether the frame's own rim must be searched: no recording rim, or it is hardly seen."""
    return (rim.use < 0.5) | (rec.support < settings.min_rim_support)


class RimChoice(eqx.Module):
    """What a frame is measured with: ``circle``; ``prior_weight`` (1/px^2) holding the fit's
    circle to it (0: free); ``code`` one of the ``RIM_*`` values; ``seen`` whether the frame
    shows a wheel at all (else it is ``no_wheel``); ``own`` the frame's own rim where it was
    searched, else the recording's."""

    circle: Circle
    own: Circle
    prior_weight: Float[Array, ""]
    code: Array
    seen: Array


def choose_circle(
    outline: Outline,
    rim: RecordingRim,
    own_rim: Callable[[], Circle],
    settings: SoftSettings,
) -> RimChoice:
    """The circle a frame is measured with (see :class:`RimChoice`).

    ``own_rim`` finds the frame's own rim (the Hough stage); it runs only when needed: without a
    recording rim, or where the recording's rim has less support in this frame than a rim needs
    (then the frame's own evidence decides between "hidden" and "moved").
    """
    rec = recording_circle(outline, rim)
    need = needs_own_rim(rec, rim, settings)
    own = jax.lax.cond(need, own_rim, lambda: rec)
    strong_own = own.support >= settings.min_rim_support
    recorded = rim.use >= 0.5
    # A bumped camera shifts the rim; it hardly changes its size (the wheel stays at the same
    # distance). A circle of another size is some other round edge (hub, hole, a lug's arc), so
    # the rim is hidden, not moved.
    same_size = jnp.abs(own.r_px - rec.r_px) <= MOVED_RADIUS_FRACTION * rec.r_px
    moved = recorded & need & strong_own & same_size & ~agree(own, rec)
    use_rec = recorded & ~moved
    circle = jax.tree_util.tree_map(lambda a, b: jnp.where(use_rec, a, b), rec, own)
    # A hidden rim keeps the recording's circle; the frame shows no wheel only when its own rim
    # is missing too and hardly any of the recording's rim is seen.
    seen = jnp.where(
        use_rec, strong_own | (rec.support >= 0.25 * settings.min_rim_support), strong_own
    )
    dt = outline.x_px.dtype
    weight = jnp.where(use_rec, 1.0 / jnp.asarray(rim.std_px, dt) ** 2, 0.0)
    code = jnp.where(
        ~recorded,
        RIM_OWN,
        jnp.where(moved, RIM_MOVED, jnp.where(need, RIM_HIDDEN, RIM_RECORDING)),
    ).astype(jnp.int32)
    return RimChoice(circle=circle, own=own, prior_weight=weight, code=code, seen=seen)


def combine_rims(
    circles_px: np.ndarray, supports: np.ndarray, *, min_support: float
) -> RecordingRim | None:
    """The recording's rim from its frames' own fitted circles ((n, 3) cx, cy, r px), or None.

    Frames with too little rim evidence are left out; the rest vote: the consensus is the
    median circle, its inliers those that :func:`agree` with it, and the rim is their mean, with
    the standard error of that mean (at least :data:`MIN_RIM_STD_PX`) as its sigma. None when
    no frame saw a rim, or when fewer than half of those that did agree with each other: the
    camera is not fixed to the wheel, and each frame keeps its own rim.
    """
    c = np.asarray(circles_px, float).reshape(-1, 3)
    good = np.all(np.isfinite(c), axis=1) & (np.asarray(supports, float) >= min_support)
    c = c[good]
    if len(c) == 0:
        return None
    med = np.median(c, axis=0)
    tol = max(AGREE_PX, AGREE_FRACTION * med[2])
    inlier = (np.hypot(c[:, 0] - med[0], c[:, 1] - med[1]) <= tol) & (
        np.abs(c[:, 2] - med[2]) <= tol
    )
    if 2 * int(inlier.sum()) < len(c) or (len(c) >= 2 and inlier.sum() < 2):
        return None
    c = c[inlier]
    mean = c.mean(axis=0)
    # The spread of one frame's circle; a single frame's is unknown: assume a third of a pixel.
    spread = float(np.max(c.std(axis=0, ddof=1))) if len(c) >= 2 else 0.3
    cx, cy, r = (float(v) for v in mean)
    return RecordingRim.fixed(cx, cy, r, std_px=spread / np.sqrt(len(c)))
