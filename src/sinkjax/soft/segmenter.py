"""The segmenter interface: anything that maps an image and its confidence rectangle to a soft
wheel mask.

A :class:`Segmenter` is an ``eqx.Module`` whose array leaves are its trainable parameters (so
``jax.grad`` of any loss of the mask, or of the whole fitted measurement through
:func:`sinkjax.measure`, reaches them) and whose static fields are its structure. The estimator,
calibration and training take any segmenter; :class:`ThresholdSegmenter` is the paper's H/S
range test (:func:`~sinkjax.soft.segmentation.wheel_mask`) behind this interface.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..result import (
    FEATURE_CHOICES as FEATURE_CHOICES,
    FEATURES_HUE_SAT as FEATURES_HUE_SAT,
    FEATURES_INTENSITY as FEATURES_INTENSITY,
    FEATURES_LEARNED as FEATURES_LEARNED,
    FEATURES_UNKNOWN as FEATURES_UNKNOWN,
)
from ..rig import SegmentationParams
from .segmentation import Rect, box_weight, check_rect, wheel_mask

# The inside of a recording's rim: (cx, cy, radius) px, radius 0 where no rim is known.
Disc = tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""]]

# The FEATURES_* codes that Segmenter.features reports, and FEATURE_CHOICES their names, live in
# sinkjax.result (the classic method and the run summary use them too); re-exported here.


def rect_weight(
    rect: Rect, height: int, width: int, dtype: jnp.dtype | type
) -> Float[Array, "H W"]:
    """1 inside the confidence rectangle (x, y, w, h), 0 outside; a tuple is checked (raises
    ValueError if it does not lie inside the image), an int array of 4 may be traced."""
    check_rect(rect, height, width)
    return box_weight(jnp.asarray(rect, jnp.int32), height, width, dtype)


class Segmenter(eqx.Module):
    """A soft wheel segmenter: ``segmenter(image, rect) -> mask``.

    ``image`` is (H, W, 3) RGB in [0, 1]; ``rect`` the confidence rectangle (x, y, w, h) in px,
    a tuple of ints (static) or an int array of 4 (traced, see
    :func:`~sinkjax.soft.segmentation.confidence_means`); the result is (H, W) in [0, 1],
    1 = wheel. Implementations must be jit-able and vmap-able, branch on no traced value in
    Python, and have finite gradients with respect to every array leaf.
    """

    @abc.abstractmethod
    def __call__(self, image: Float[Array, "H W 3"], rect: Rect) -> Float[Array, "H W"]:
        raise NotImplementedError

    def with_rim(self, image: Float[Array, "H W 3"], rect: Rect, disc: Disc) -> Float[Array, "H W"]:
        """The mask when the recording's rim is known: ``disc`` (cx, cy, radius px; traced)
        is the inside of the rim, where only wheel and soil can be (radius 0: no rim known).
        A segmenter may use it (:class:`~sinkjax.soft.adaptive.AdaptiveSegmenter` does for a
        wheel without colour, and says so with :meth:`uses_rim`); by default the mask ignores
        it."""
        del disc
        return self(image, rect)

    def uses_rim(self, features: int) -> bool:
        """Whether :meth:`with_rim` may differ from the plain mask for a frame whose
        :meth:`features` are ``features``: a recording's first frames, segmented before its
        rim is known, are segmented again only then. False unless a segmenter overrides it."""
        del features
        return False

    def blur_px(self, image: Float[Array, "H W 3"], rect: Rect) -> Float[Array, ""]:
        """The Gaussian blur (sigma, px) this segmenter applied to ``image`` before segmenting
        it, beyond the mask's own smoothing: the estimate's sigma widens with it
        (:func:`~sinkjax.soft.denoise.sigma_factor`). 0 unless a segmenter overrides it."""
        del rect
        return jnp.zeros((), image.dtype)

    def features(self, image: Float[Array, "H W 3"], rect: Rect) -> Int[Array, ""]:
        """Which features separate wheel from soil in this frame (a ``FEATURES_*`` code of
        :data:`FEATURE_CHOICES`): jit-able and vmap-able like the mask. The soft method reports
        it per frame (``SoftEstimate.features``, then ``FrameResult.segmenter_features``) and
        the run summary counts it per recording.

        A fixed-form segmenter reports its one choice; learned ones report FEATURES_LEARNED.
        """
        del image, rect
        return jnp.asarray(FEATURES_LEARNED, jnp.int32)

    def features_label(self, name: str) -> str:
        """The run summary's name for a frame whose :meth:`features` code is called ``name``
        (a :data:`FEATURE_CHOICES` value): that name, unless a segmenter says more."""
        return name


class ThresholdSegmenter(Segmenter):
    """The paper's H/S range test as a soft mask: exactly :func:`wheel_mask` with ``seg``.

    ``seg``'s fields (P_d/P_a for hue and saturation, the temperatures) are the leaves that
    calibration tunes.
    """

    seg: SegmentationParams = SegmentationParams()

    def __call__(self, image: Float[Array, "H W 3"], rect: Rect) -> Float[Array, "H W"]:
        return wheel_mask(image, self.seg, rect)

    def features(self, image: Float[Array, "H W 3"], rect: Rect) -> Int[Array, ""]:
        del image, rect
        return jnp.asarray(FEATURES_HUE_SAT, jnp.int32)
