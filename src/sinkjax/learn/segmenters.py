"""Learned segmenters: a per-pixel colour MLP and a small CNN, both on rectangle-normalised inputs.

Each is a :class:`~sinkjax.soft.segmenter.Segmenter` (the estimator, ``SoftRecording`` and
``sinkjax estimate --segmenter`` take it like any other) with array leaves only (the parameters,
traced: one compile per image size serves any trained values) and a static ``hyper`` record,
called as ``segmenter(image, rect) -> mask``: image (H, W, 3) RGB in [0, 1], ``rect`` the
confidence rectangle (x, y, w, h) px (static ints or a traced int array), mask (H, W) in [0, 1]
(1 = wheel).

Inputs (:func:`normalised_inputs`): a learned segmenter should carry across wheels, soils and
lamps, and the one thing every rig says about its wheel is the confidence rectangle
(docs/conventions.md §2), a patch that is always wheel face. So each pixel's colour features
(:data:`FEATURE_NAMES`: R, G, B, the paper's intensity I and saturation S, and the chroma vector
(S cos H, S sin H), continuous where hue wraps and 0 for grey pixels) reach the networks relative
to that patch: ``(f - mean) / spread`` and ``f - mean``. A red wheel under a warm lamp and a grey
wheel in low light then look alike: "like the face" or "not", in the face's own units.

- :class:`ColourMLP`: pixel by pixel, inputs -> hidden -> hidden -> logit (~500 parameters).
- :class:`ConvSegmenter`: a 1x1 stem, then two depthwise-separable 3x3 blocks (the second
  dilated by 2) and a 1x1 head: 7 px of context (dust specks, lug edges, speculars) for about
  2 % of a dense 3x3 CNN's arithmetic (~1.2 thousand parameters at 16 channels).

Either may be built ``residual=1``: its log-odds are then the default segmenter's
(:func:`~sinkjax.soft.adaptive.default_segmenter` with the default thresholds, the rig's own
being out of a segmenter's sight) plus the network's correction, which also sees the default's
verdict as one more input. The correction's last layer starts at zero, so a new residual model
measures what the default method measures, and training through the fit (which keeps the best
model on held-out frames, its start included) can only move it where the labels say it is
better. A residual model also takes the default's use of the recording's rim, its low-light
blur and its choice of features (:meth:`with_rim`, :meth:`blur_px`, :meth:`features`), and the
correction is scaled by :data:`CORRECTION_SCALE` so that it can overturn a sure verdict.

Parameters are stored in float32 and cast to the image's dtype on use, so a model trained under
x64 runs in float32 and the other way round. Start from :func:`build` with ``residual=1`` (the
default mask), or without it (a random start) and :func:`sinkjax.learn.train.imitate` (a sensible
start: the default mask).
"""

from __future__ import annotations

import abc
import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int, PRNGKeyArray

from ..rig import SegmentationParams
from ..soft.adaptive import default_segmenter
from ..soft.colour import rgb_to_hsi
from ..soft.segmentation import Rect
from ..soft.segmenter import Disc, Segmenter, rect_weight

# ----------------------------------------------------------------------------- features

FEATURE_NAMES = ("r", "g", "b", "intensity", "saturation", "chroma_x", "chroma_y")
N_FEATURES = len(FEATURE_NAMES)
# Inputs to a network per pixel: the normalised features and the plain differences.
N_INPUTS = 2 * N_FEATURES
# The spread never drops below this (units of [0, 1] colour): a perfectly flat patch (a
# synthetic face, a saturated sensor) must not make every other pixel infinitely far away.
SPREAD_FLOOR = 0.01
# Normalised features are squashed to +-Z_LIMIT: beyond a few spreads "not the face" is all
# that matters, and bounded inputs keep a tiny network's activations in range.
Z_LIMIT = 6.0


def pixel_features(image: Float[Array, "H W 3"]) -> Float[Array, "H W F"]:
    """The :data:`FEATURE_NAMES` of every pixel of an RGB image in [0, 1]."""
    h_deg, s, i = rgb_to_hsi(image)
    h = jnp.radians(h_deg)
    return jnp.concatenate(
        [image, jnp.stack([i, s, s * jnp.cos(h), s * jnp.sin(h)], axis=-1)], axis=-1
    )


def rect_statistics(
    features: Float[Array, "H W F"], rect: Rect
) -> tuple[Float[Array, " F"], Float[Array, " F"]]:
    """Mean and spread (standard deviation, floored at :data:`SPREAD_FLOOR`) of each feature
    over the confidence rectangle."""
    height, width, _ = features.shape
    w = rect_weight(rect, height, width, features.dtype)[..., None]
    n = jnp.maximum(jnp.sum(w), 1.0)
    mean = jnp.sum(w * features, axis=(0, 1)) / n
    var = jnp.sum(w * (features - mean[None, None, :]) ** 2, axis=(0, 1)) / n
    # sqrt(var + floor^2), not max(sqrt(var), floor): smooth, and finite gradient at var = 0.
    return mean, jnp.sqrt(var + SPREAD_FLOOR**2)


def normalised_inputs(image: Float[Array, "H W 3"], rect: Rect) -> Float[Array, "H W C"]:
    """The networks' per-pixel inputs: ``Z_LIMIT tanh(z / Z_LIMIT)`` of ``z = (f - mean) /
    spread`` and ``f - mean`` (both over the rectangle), channel-last."""
    f = pixel_features(image)
    mean, spread = rect_statistics(f, rect)
    d = f - mean[None, None, :]
    z = d / spread[None, None, :]
    return jnp.concatenate([Z_LIMIT * jnp.tanh(z / Z_LIMIT), d], axis=-1)


def colour_distance_mask(
    image: Float[Array, "H W 3"], rect: Rect, *, radius: float = 3.0, temperature: float = 0.5
) -> Float[Array, "H W"]:
    """A hand-made mask from the same inputs: how close (in rectangle spreads) a pixel's chroma
    and intensity are to the face's. The starting point learned segmenters imitate when no
    threshold mask is at hand; ``radius`` in spreads, ``temperature`` the sigmoid's width."""
    f = pixel_features(image)
    mean, spread = rect_statistics(f, rect)
    z = (f - mean[None, None, :]) / spread[None, None, :]
    # Chroma and intensity only: R, G, B repeat them. Guarded norm: no NaN gradient at 0.
    d2 = jnp.sum(z[..., 3:] ** 2, axis=-1)
    d = jnp.sqrt(d2 + 1e-12)
    return jax.nn.sigmoid((radius - d) / temperature)


# A residual model's base mask is clipped to [BASE_EPS, 1 - BASE_EPS] before its log-odds are
# taken (|log-odds| <= 13.8: the sigmoid gives the mask back to within 1e-6; a looser clip
# would leave every pixel a little uncertain, and the fit's sigma counts that), and reaches the
# network as tanh(log-odds / BASE_SCALE): "surely wheel", "surely not" and the doubt between.
# The network's correction is multiplied by CORRECTION_SCALE, so that the optimiser's steps
# can overturn a verdict of that size in tens of steps, not hundreds.
BASE_EPS = 1e-6
CORRECTION_SCALE = 8.0
BASE_SCALE = 4.0


def _base() -> Segmenter:
    """A residual model's base: the default segmenter at the default thresholds."""
    return default_segmenter(SegmentationParams())


def base_logits(
    image: Float[Array, "H W 3"], rect: Rect, disc: Disc | None = None
) -> Float[Array, "H W"]:
    """Log-odds of the default segmenter's mask with the default thresholds (with the
    recording's rim ``disc`` where known)."""
    seg = _base()
    m = seg(image, rect) if disc is None else seg.with_rim(image, rect, disc)
    m = jnp.clip(m, BASE_EPS, 1.0 - BASE_EPS)
    return jnp.log(m) - jnp.log1p(-m)


# ----------------------------------------------------------------------------- models

KINDS = ("mlp", "cnn")


def _init(key: PRNGKeyArray, shape: tuple[int, ...], fan_in: int) -> Float[Array, "..."]:
    # He initialisation for ReLU layers, stored as float32 (see the module docstring).
    return jax.random.normal(key, shape, jnp.float32) * math.sqrt(2.0 / fan_in)


def _conv(x: Float[Array, "H W C"], w: Array, b: Array) -> Float[Array, "H W O"]:
    """1x1 convolution (a per-pixel dense layer) of a channel-last image; ``w`` (C, O)."""
    return x @ w.astype(x.dtype) + b.astype(x.dtype)[None, None, :]


def _depthwise3(x: Float[Array, "H W C"], w: Array, b: Array, dilation: int) -> Array:
    """Depthwise 3x3 convolution ('same' size, zero padding), ``w`` (3, 3, C): nine shifted
    multiply-adds, which XLA's CPU backend runs far faster than a grouped convolution."""
    d = dilation
    height, width, _ = x.shape
    p = jnp.pad(x, ((d, d), (d, d), (0, 0)))
    wt = w.astype(x.dtype)
    out = jnp.broadcast_to(b.astype(x.dtype)[None, None, :], x.shape)
    for i in range(3):
        for j in range(3):
            out = out + wt[i, j][None, None, :] * p[i * d : i * d + height, j * d : j * d + width]
    return out


def _default_width(width: int | None, residual: int) -> int:
    """Hidden units or channels: 16 for a network on its own; 8 for a residual one, which runs
    the default segmenter too (a correction needs less, and 16 would cost 1.5-1.8x the default
    method per 640x480 frame against 1.2-1.3x at 8)."""
    return width if width is not None else (8 if residual else 16)


class LearnedSegmenter(Segmenter):
    """What the learned segmenters share: ``kind`` names the class in a saved file
    (:mod:`sinkjax.learn.io`) and ``hyper`` holds what rebuilds its skeleton."""

    kind: ClassVar[str]
    hyper: dict[str, int] = eqx.field(static=True)

    @property
    def residual(self) -> bool:
        """Whether the network corrects the default segmenter (see the module docstring)."""
        return bool(self.hyper.get("residual", 0))

    @abc.abstractmethod
    def _network(self, x: Float[Array, "H W C"]) -> Float[Array, "H W"]:
        """The network's log-odds (a residual model's correction) from its inputs."""

    def logits(
        self, image: Float[Array, "H W 3"], rect: Rect, disc: Disc | None = None
    ) -> Float[Array, "H W"]:
        """The mask before its sigmoid (log-odds of wheel); ``disc``: the recording's rim
        (a residual model's base uses it; the network itself does not)."""
        x = normalised_inputs(image, rect)
        if not self.residual:
            return self._network(x)
        base = base_logits(image, rect, disc)
        x = jnp.concatenate([x, jnp.tanh(base / BASE_SCALE)[..., None]], axis=-1)
        return base + CORRECTION_SCALE * self._network(x)

    def __call__(self, image: Float[Array, "H W 3"], rect: Rect) -> Float[Array, "H W"]:
        """Soft wheel mask in [0, 1] of an RGB image in [0, 1]."""
        return jax.nn.sigmoid(self.logits(image, rect))

    def with_rim(self, image: Float[Array, "H W 3"], rect: Rect, disc: Disc) -> Float[Array, "H W"]:
        """A residual model's base uses the recording's rim as the default segmenter does."""
        if not self.residual:
            return self(image, rect)
        return jax.nn.sigmoid(self.logits(image, rect, disc))

    def uses_rim(self, features: int) -> bool:
        return self.residual and _base().uses_rim(features)

    def features(self, image: Float[Array, "H W 3"], rect: Rect) -> Int[Array, ""]:
        """``learned``; a residual model reports the features its base chose, since the soft
        method's rules for a wheel without colour (soft.below, soft.soil_step) go by them."""
        if not self.residual:
            return super().features(image, rect)
        return _base().features(image, rect)

    def features_label(self, name: str) -> str:
        """``learned+`` the base's choice for a residual model (``learned+hue+saturation``)."""
        return f"learned+{name}" if self.residual else name

    def blur_px(self, image: Float[Array, "H W 3"], rect: Rect) -> Float[Array, ""]:
        """A residual model's base blurs a noisy frame as the default segmenter does."""
        if not self.residual:
            return jnp.zeros((), image.dtype)
        return _base().blur_px(image, rect)

    @property
    def n_parameters(self) -> int:
        leaves = jax.tree_util.tree_leaves(eqx.filter(self, eqx.is_array))
        return int(sum(leaf.size for leaf in leaves))


class ColourMLP(LearnedSegmenter):
    """Per-pixel MLP over rectangle-normalised colour: no spatial context, cheapest to run."""

    kind: ClassVar[str] = "mlp"
    weights: tuple[Array, ...]
    biases: tuple[Array, ...]

    def __init__(self, *, hidden: int | None = None, residual: int = 0, key: PRNGKeyArray) -> None:
        hidden = _default_width(hidden, residual)
        if hidden < 1:
            raise ValueError(f"hidden must be at least 1, got {hidden}")
        if residual not in (0, 1):
            raise ValueError(f"residual must be 0 or 1, got {residual}")
        sizes = (N_INPUTS + residual, hidden, hidden, 1)
        keys = jax.random.split(key, len(sizes) - 1)
        weights = [_init(k, (a, b), a) for k, a, b in zip(keys, sizes[:-1], sizes[1:], strict=True)]
        if residual:  # a correction that starts at zero: the default segmenter's mask
            weights[-1] = jnp.zeros_like(weights[-1])
        self.weights = tuple(weights)
        self.biases = tuple(jnp.zeros((b,), jnp.float32) for b in sizes[1:])
        self.hyper = {"hidden": hidden} | ({"residual": 1} if residual else {})

    def _network(self, x: Float[Array, "H W C"]) -> Float[Array, "H W"]:
        for w, b in zip(self.weights[:-1], self.biases[:-1], strict=True):
            x = jax.nn.relu(_conv(x, w, b))
        return _conv(x, self.weights[-1], self.biases[-1])[..., 0]


class ConvSegmenter(LearnedSegmenter):
    """Small depthwise-separable CNN (7 px receptive field) over rectangle-normalised colour."""

    kind: ClassVar[str] = "cnn"
    stem: tuple[Array, Array]
    blocks: tuple[tuple[Array, Array, Array, Array], ...]
    head: tuple[Array, Array]

    def __init__(
        self, *, channels: int | None = None, residual: int = 0, key: PRNGKeyArray
    ) -> None:
        channels = _default_width(channels, residual)
        if channels < 1:
            raise ValueError(f"channels must be at least 1, got {channels}")
        if residual not in (0, 1):
            raise ValueError(f"residual must be 0 or 1, got {residual}")
        c, n_in = channels, N_INPUTS + residual
        k_stem, k_head, *k_blocks = jax.random.split(key, 4)
        self.stem = (_init(k_stem, (n_in, c), n_in), jnp.zeros((c,), jnp.float32))
        blocks = []
        for k in k_blocks[:2]:
            kd, kp = jax.random.split(k)
            depthwise = _init(kd, (3, 3, c), 9)
            pointwise = _init(kp, (c, c), c)
            zeros = jnp.zeros((c,), jnp.float32)
            blocks.append((depthwise, zeros, pointwise, zeros))
        self.blocks = tuple(blocks)
        head = _init(k_head, (c, 1), c)
        if residual:  # a correction that starts at zero: the default segmenter's mask
            head = jnp.zeros_like(head)
        self.head = (head, jnp.zeros((1,), jnp.float32))
        self.hyper = {"channels": channels} | ({"residual": 1} if residual else {})

    def _network(self, x: Float[Array, "H W C"]) -> Float[Array, "H W"]:
        x = jax.nn.relu(_conv(x, *self.stem))
        for dilation, (wd, bd, wp, bp) in zip((1, 2), self.blocks, strict=True):
            # Residual: a block refines the per-pixel colour verdict with its neighbourhood.
            x = x + jax.nn.relu(_conv(_depthwise3(x, wd, bd, dilation), wp, bp))
        return _conv(x, *self.head)[..., 0]


_CLASSES: dict[str, type[ColourMLP] | type[ConvSegmenter]] = {
    "mlp": ColourMLP,
    "cnn": ConvSegmenter,
}


def build(kind: str, *, key: PRNGKeyArray | int = 0, **hyper: int) -> LearnedSegmenter:
    """A new segmenter of ``kind`` ("mlp" or "cnn") with random parameters from ``key``;
    ``hyper``: ``hidden=`` (mlp) or ``channels=`` (cnn), and ``residual=1`` for a model that
    corrects the default segmenter (see the module docstring). Raises ValueError for an unknown
    kind or hyper-parameter."""
    if kind not in _CLASSES:
        raise ValueError(f"unknown segmenter kind {kind!r}; choose one of {', '.join(KINDS)}")
    if isinstance(key, int):
        key = jax.random.PRNGKey(key)
    try:
        return _CLASSES[kind](key=key, **hyper)
    except TypeError as e:
        raise ValueError(f"bad hyper-parameters for a {kind!r} segmenter {hyper}: {e}") from e
