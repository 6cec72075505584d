"""The soft (differentiable) estimator: image -> z0, theta1, theta2 with one-sigma uncertainty.

``measure`` is the whole method for one frame as a pure JAX function (jit once per image size,
vmap over frames, grad with respect to the segmentation parameters), in two halves: ``prepare``
(mask -> outline -> the rim circle to measure with) and ``finish`` (joint fit, uncertainty,
checks), so that a recording's first frames can find its rim (``soft.rim``) without being
segmented twice. ``soft.batch`` is the NumPy-facing side the pipeline and CLI use.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from ..geometry import travel_sign
from ..result import FEATURES_INTENSITY, FEATURES_UNKNOWN
from ..rig import Rig, SegmentationParams, rim_hint_range_px, srgb_flag
from ..status import Status
from .adaptive import default_segmenter
from .below import has_contact, recounted
from .checks import line_shift_std, plausibility, steep_end_std
from .colour import linear_light
from .denoise import sigma_factor
from .fit import build_evidence, fit, rim_and_boundary_capacity
from .hough import Circle, hough_rim
from .model import end_point, measurements
from .outline import Outline, extract_outline, refine_outline
from .rim import RecordingRim, RimChoice, choose_circle
from .segmentation import Rect, soft_open
from .segmenter import Segmenter
from .settings import SoftSettings
from .shadow_cut import shadow_cut, spills
from .soil_step import soil_step
from .uncertainty import UncertaintyModel, covariance, measurement_std

# The default contact threshold as a number, for calibration's targets (SoftSettings has it).
MIN_BOUNDARY_POINTS = float(SoftSettings().min_boundary_points)


class SoftEstimate(eqx.Module):
    """One frame's soft estimate: sinkage in mm, angles in radians, each with one sigma.

    ``params`` are the fitted model (cx, cy, r px; k, b; end lines, see ``soft.model``) and
    ``params_std`` their sigmas before the uncertainty model's scaling; ``status`` is a
    :class:`sinkjax.Status` ``code``; the boundary arrays are the outline points and their
    boundary weights (for overlays). For no contact the measurements are 0 and the sigmas say how
    much sinkage (and angle) could hide below what the image shows (docs/conventions.md §1,
    :func:`hidden_contact_std`). ``features`` is which features the segmenter separated wheel
    from soil with (a ``FEATURES_*`` code of :data:`sinkjax.result.FEATURE_CHOICES`;
    ``FEATURES_UNKNOWN`` for a mask given to :func:`measure_from_mask`).
    """

    sinkage_mm: Float[Array, ""]
    sinkage_std_mm: Float[Array, ""]
    theta1_rad: Float[Array, ""]
    theta1_std_rad: Float[Array, ""]
    theta2_rad: Float[Array, ""]
    theta2_std_rad: Float[Array, ""]
    params: Float[Array, " P"]
    params_std: Float[Array, " P"]
    status: Int[Array, ""]
    boundary_weight: Float[Array, " K"]
    boundary_x_px: Float[Array, " K"]
    boundary_y_px: Float[Array, " K"]
    # A and B in the wheel frame (u, v) px: computed here so that turning a frame into a row
    # needs no JAX call outside the compiled function.
    ends_uv_px: Float[Array, "2 2"]
    check: Int[Array, ""]  # soft.checks: 0 plausible, else which test failed
    rim_code: Int[Array, ""]  # soft.rim: which rim the frame was measured with
    own_rim_px: Float[Array, " 3"]  # the frame's own rim (cx, cy, r) where it was searched
    rim_support: Float[Array, ""]  # fraction of the measured rim seen in this frame
    features: Int[Array, ""]  # the segmenter's choice of features (Segmenter.features)


class Prepared(eqx.Module):
    """A frame up to its rim choice (the first half of the method): the soft mask, its outline,
    and the rim to measure with (with the frame's own rim, where it was searched). Kept between
    the halves so that the first frames of a recording, measured once with their own rims to
    find the recording's, are not segmented twice where their masks do not depend on the rim
    (``Segmenter.uses_rim``). ``features``: which features made the mask
    (a ``FEATURES_*`` code), passed on to the :class:`SoftEstimate`; ``blur_px``: the blur the
    segmenter applied first (``Segmenter.blur_px``), which widens the sigmas."""

    mask: Float[Array, "H W"]
    outline: Outline
    choice: RimChoice
    features: Int[Array, ""]
    blur_px: Float[Array, ""]


def prepare(
    image: Float[Array, "H W 3"],
    mask: Float[Array, "H W"],
    rim: RecordingRim | None = None,
    settings: SoftSettings | None = None,
    rim_range_px: tuple[ArrayLike, ArrayLike] | None = None,
    features: ArrayLike = FEATURES_UNKNOWN,
    srgb: bool | Float[Array, ""] = False,
    blur_px: ArrayLike = 0.0,
) -> Prepared:
    """Outline of the mask, and the rim circle to measure with (``soft.rim.choose_circle``).
    ``features``: the code of the features that made ``mask`` (``Segmenter.features``; may be
    traced), kept for the estimate; by default unknown. ``srgb``: the image is sRGB-encoded
    (may be traced); its outline is then located in linear light (:func:`linear_light`)."""
    if image.ndim != 3 or image.shape[-1] != 3 or mask.shape != image.shape[:2]:
        raise ValueError(
            f"need image (H, W, 3) and mask (H, W) of the same H, W; got image {image.shape} "
            f"and mask {mask.shape}"
        )
    height, width = mask.shape
    s = (SoftSettings() if settings is None else settings).astype(mask.dtype)
    outline = refine_outline(linear_light(image, srgb), extract_outline(mask, s), s)

    def own_rim() -> Circle:
        # The starting circle is a discrete choice: no gradient flows through it.
        return jax.lax.stop_gradient(hough_rim(outline, height, width, s, rim_range_px))

    choice = choose_circle(outline, RecordingRim.per_frame() if rim is None else rim, own_rim, s)
    return Prepared(
        mask=mask,
        outline=outline,
        choice=choice,
        features=jnp.asarray(features, jnp.int32),
        blur_px=jnp.asarray(blur_px, mask.dtype),
    )


def rechoose(
    prepared: Prepared, rim: RecordingRim, settings: SoftSettings | None = None
) -> Prepared:
    """``prepared`` (made without a recording rim, so its own rim was searched) measured with
    ``rim`` instead: the same as :func:`prepare` with ``rim``, without segmenting again."""
    s = (SoftSettings() if settings is None else settings).astype(prepared.mask.dtype)
    choice = choose_circle(prepared.outline, rim, lambda: prepared.choice.own, s)
    return eqx.tree_at(lambda p: p.choice, prepared, choice)


def finish(
    image: Float[Array, "H W 3"],
    prepared: Prepared,
    *,
    travel: str | Float[Array, ""] = "right",
    wheel_radius_mm: float | Float[Array, ""] = 1.0,
    uncertainty: UncertaintyModel | None = None,
    settings: SoftSettings | None = None,
    srgb: bool | Float[Array, ""] = False,
    recount_in_disc: bool = False,
) -> SoftEstimate:
    """The second half of the method: the joint fit, its uncertainty and the checks.
    ``srgb``: as for :func:`prepare` (an outline taken again is located in linear light).
    ``recount_in_disc`` (static): where no boundary is found on a mask made from intensity,
    count the wheel below each outline point again inside the rim only, and take that if it
    finds one (the recording runner, ``soft.batch``, measures such frames again with it)."""
    mask, outline, choice = prepared.mask, prepared.outline, prepared.choice
    s = (SoftSettings() if settings is None else settings).astype(mask.dtype)
    sign = travel_sign(travel) if isinstance(travel, str) else travel
    # With the recording's rim, a soil line that the mask put above the soil's step (dust)
    # moves down to it (soft.soil_step); the outline is then taken again.
    c = choice.circle
    mask, moved = jax.lax.cond(
        choice.prior_weight > 0,
        lambda: soil_step(image, mask, (c.cx_px, c.cy_px, c.r_px)),
        lambda: (mask, jnp.zeros((), bool)),
    )
    # A mask that runs on from the face into the wheel's shadow on the soil is cut at the
    # shadow's top, the soil line (soft.shadow_cut; the cheap ring test first).
    stepped = moved
    disc = (c.cx_px, c.cy_px, c.r_px)
    mask, cut = jax.lax.cond(
        (choice.prior_weight > 0) & ~moved & spills(mask, disc),
        lambda: shadow_cut(image, mask, disc),
        lambda: (mask, jnp.zeros((), bool)),
    )
    moved = moved | cut
    outline = jax.lax.cond(
        moved,
        lambda: refine_outline(linear_light(image, srgb), extract_outline(mask, s), s),
        lambda: outline,
    )
    ev = build_evidence(outline, choice.circle, sign, s, rim_weight=choice.prior_weight)
    if recount_in_disc:
        ev = recounted(ev, outline, mask, choice, sign, s, prepared.features)
    res = fit(ev, capacity=rim_and_boundary_capacity(*mask.shape))
    p = res.params
    cov = covariance(p, ev)
    est = measurements(p, wheel_radius_mm)
    contact = has_contact(ev, s)
    # A wheel without colour: the soil's step found no soil inside the rim where the mask did
    # (soft.checks: the far edge of its cast shadow, as dark as its dusted face).
    stepped_out = stepped & ~contact & (prepared.features == FEATURES_INTENSITY)
    check = plausibility(image, mask, p, ev, contact, stepped_out)
    std = measurement_std(p, cov, wheel_radius_mm, uncertainty) * check.sigma_scale
    std = std * sigma_factor(prepared.blur_px)
    std = jnp.sqrt(std**2 + line_shift_std(p, check, wheel_radius_mm) ** 2 + steep_end_std(p) ** 2)
    measured = jnp.where(contact, Status.OK.code, Status.NO_CONTACT.code)
    # With the recording's rim, a soil boundary inside it is evidence enough of the wheel.
    seen = choice.seen | ((choice.prior_weight > 0) & contact)
    status = jnp.where(
        ~seen,
        Status.NO_WHEEL.code,
        jnp.where(
            ~res.ok,
            Status.FIT_FAILED.code,
            jnp.where(check.plausible, measured, Status.IMPLAUSIBLE.code),
        ),
    )
    zero_if_no_contact = jnp.where(contact, 1.0, 0.0)
    hidden = hidden_contact_std(p[2], ev.inner_px, wheel_radius_mm, s, ev.envelope_depth_px)
    std = jnp.where(contact, std, hidden)
    return SoftEstimate(
        sinkage_mm=est[0] * zero_if_no_contact,
        sinkage_std_mm=std[0],
        theta1_rad=est[1] * zero_if_no_contact,
        theta1_std_rad=std[1],
        theta2_rad=est[2] * zero_if_no_contact,
        theta2_std_rad=std[2],
        params=p,
        params_std=jnp.sqrt(jnp.maximum(jnp.diag(cov), 0.0)),
        status=status.astype(jnp.int32),
        boundary_weight=ev.w_line,
        boundary_x_px=ev.x_px,
        boundary_y_px=ev.y_px,
        ends_uv_px=jnp.stack([end_point(p[5], p[6], p[2], 1.0), end_point(p[7], p[8], p[2], -1.0)]),
        check=check.code,
        rim_code=choice.code,
        own_rim_px=jnp.stack([choice.own.cx_px, choice.own.cy_px, choice.own.r_px]),
        rim_support=choice.circle.support,
        features=prepared.features,
    )


def hidden_contact_std(
    r_px: Float[Array, ""],
    inner_px: Float[Array, ""],
    wheel_radius_mm: float | Float[Array, ""],
    settings: SoftSettings,
    envelope_px: float | Float[Array, ""] = 0.0,
) -> Float[Array, " 3"]:
    """One sigma of (sinkage mm, theta1 rad, theta2 rad) for a frame read as no contact.

    The soil may still touch the rim, too little to be seen: an edge counts as soil only
    ``inner_px`` inside the rim (``fit.inner_margin_px``), and a contact needs
    ``min_boundary_points`` columns of it, so a sinkage up to z_max = inner_px + (n / 2)^2 / (2 r)
    can hide. Where the envelope of rim and soil line (``soft.shallow``) saw a chord
    ``envelope_px`` deep, deeper than the margin and with ``min_boundary_points`` on it, but did
    not take it (its points do not fill its length), a chord that deep may hide, its depth known
    to about the margin: z_max is then at least envelope_px + inner_px. (On 4 seeds of
    ``experiments/shallow_contact.py`` this bound covers 6 of the 8 contacts of 0.5-0.7 px read
    as none; no frame without contact sees such a chord.) Reported as 0, the sinkage's error is
    then at most z_max; with no reason to prefer any depth below it, its root mean square is
    z_max / sqrt(3) (uniform on [0, z_max]), and that of each angle (theta ~ sqrt(2 z0 / r) on
    flat ground) acos(1 - z_max / r) / sqrt(2).
    """
    r = jnp.maximum(r_px, 1.0)
    z_max = inner_px + (0.5 * settings.min_boundary_points) ** 2 / (2.0 * r)
    seen = jnp.asarray(envelope_px, z_max.dtype)
    z_max = jnp.maximum(z_max, jnp.where(seen > inner_px, seen + inner_px, 0.0))
    # Inside (-1, 1): arccos has an infinite derivative at both ends (no wheel: r ~ 0).
    angle = jnp.arccos(jnp.clip(1.0 - z_max / r, -1.0 + 1e-6, 1.0 - 1e-6))
    z_mm = z_max * wheel_radius_mm / r
    return jnp.stack([z_mm / jnp.sqrt(3.0), angle / jnp.sqrt(2.0), angle / jnp.sqrt(2.0)])


def measure(
    image: Float[Array, "H W 3"],
    seg: SegmentationParams,
    *,
    rect: Rect,
    travel: str | Float[Array, ""] = "right",
    wheel_radius_mm: float | Float[Array, ""] = 1.0,
    uncertainty: UncertaintyModel | None = None,
    open_radius_px: int = 0,
    settings: SoftSettings | None = None,
    rim_range_px: tuple[ArrayLike, ArrayLike] | None = None,
    rim: RecordingRim | None = None,
    segmenter: Segmenter | None = None,
    srgb: bool | Float[Array, ""] = False,
) -> SoftEstimate:
    """The soft method on one image in [0, 1].

    ``image`` is (H, W, 3) RGB in [0, 1]; ``rect`` the confidence rectangle (x, y, w, h) in px;
    ``travel`` "right"/"left" or its sign (+1.0/-1.0); ``wheel_radius_mm`` the rim's physical
    radius R (sinkage is reported as z0 * R / r). Python values are static under ``jax.jit``;
    arrays (``rect`` an int array of 4, see :class:`RigArrays`) are traced, so one compiled
    function serves every rig of an image size. ``open_radius_px`` is always static.
    ``open_radius_px`` > 0 adds a grey-level opening of the mask (the paper's erosion/dilation
    as a differentiable min/max filter); by default only the outline's smoothing cleans the mask,
    which ``experiments/ablation_cleanup.py`` shows is enough. ``settings`` (None: the defaults)
    are the method's tuning settings, array leaves (not static: a new value does not recompile).
    ``rim_range_px``: the rim radii to search (px; may be traced), None for the default
    fractions of the image size. ``rim``: the recording's rim circle (``soft.rim``; traced), held
    as a strong prior, and given to the segmenter (``Segmenter.with_rim``); None: the frame's own
    rim. ``segmenter`` (a
    :class:`~sinkjax.soft.segmenter.Segmenter`) makes the mask; None: the default with the
    thresholds ``seg`` (:func:`~sinkjax.soft.adaptive.default_segmenter`: the paper's H/S test
    on a coloured wheel, intensity/chroma/texture on a black one); which features it chose is
    the estimate's ``features``. ``srgb`` (a bool or a traced 0/1 flag): the image's values are
    sRGB-encoded, as most cameras store them (the rig's ``encoding = "srgb"``); the outline's
    sub-pixel edges are then located in linear light, where a blurred edge mixes its two sides
    linearly (``experiments/encoding.py``). The segmentation sees the image as given.
    Never raises for image content: problems are reported in ``status``.
    """
    return measure_and_mask(
        image, seg, rect=rect, travel=travel, wheel_radius_mm=wheel_radius_mm,
        uncertainty=uncertainty, open_radius_px=open_radius_px, settings=settings,
        rim_range_px=rim_range_px, rim=rim, segmenter=segmenter, srgb=srgb,
    )[0]  # fmt: skip


def measure_and_mask(
    image: Float[Array, "H W 3"],
    seg: SegmentationParams,
    *,
    rect: Rect,
    travel: str | Float[Array, ""] = "right",
    wheel_radius_mm: float | Float[Array, ""] = 1.0,
    uncertainty: UncertaintyModel | None = None,
    open_radius_px: int = 0,
    settings: SoftSettings | None = None,
    rim_range_px: tuple[ArrayLike, ArrayLike] | None = None,
    rim: RecordingRim | None = None,
    segmenter: Segmenter | None = None,
    srgb: bool | Float[Array, ""] = False,
) -> tuple[SoftEstimate, Float[Array, "H W"]]:
    """:func:`measure`, and the soft wheel mask it measured (the calibration loss looks at it
    again; making it costs about a third of measuring a 640x480 frame)."""
    segmenter = default_segmenter(seg) if segmenter is None else segmenter
    mask = segmenter(image, rect) if rim is None else segmenter.with_rim(image, rect, rim.disc())
    if open_radius_px > 0:
        mask = soft_open(mask, open_radius_px)
    est = measure_from_mask(
        image,
        mask,
        travel=travel,
        wheel_radius_mm=wheel_radius_mm,
        uncertainty=uncertainty,
        settings=settings,
        rim_range_px=rim_range_px,
        rim=rim,
        features=segmenter.features(image, rect),
        srgb=srgb,
        blur_px=segmenter.blur_px(image, rect),
    )
    return est, mask


def measure_from_mask(
    image: Float[Array, "H W 3"],
    mask: Float[Array, "H W"],
    *,
    travel: str | Float[Array, ""] = "right",
    wheel_radius_mm: float | Float[Array, ""] = 1.0,
    uncertainty: UncertaintyModel | None = None,
    settings: SoftSettings | None = None,
    rim_range_px: tuple[ArrayLike, ArrayLike] | None = None,
    rim: RecordingRim | None = None,
    features: ArrayLike = FEATURES_UNKNOWN,
    srgb: bool | Float[Array, ""] = False,
    recount_in_disc: bool = False,
    blur_px: ArrayLike = 0.0,
) -> SoftEstimate:
    """Everything after segmentation, from a soft wheel mask in [0, 1] (1 = wheel) and its image.

    ``measure`` is ``measure_from_mask(image, segmenter(image, rect))``; a segmenter outside
    JAX (``sinkjax.torch``) supplies its own mask here. The image is still needed: the
    outline is located on its colours. Keyword arguments as for :func:`measure`; ``features``
    (the estimate's ``features``): the ``FEATURES_*`` code of what made the mask, if known;
    ``recount_in_disc`` (static): as for :func:`finish`; ``blur_px``: the blur the segmenter
    applied to the image first (``Segmenter.blur_px``), which widens the sigmas.
    Raises ValueError if the shapes disagree.
    """
    prepared = prepare(image, mask, rim, settings, rim_range_px, features, srgb, blur_px)
    return finish(
        image,
        prepared,
        travel=travel,
        wheel_radius_mm=wheel_radius_mm,
        uncertainty=uncertainty,
        settings=settings,
        srgb=srgb,
        recount_in_disc=recount_in_disc,
    )


class RigArrays(eqx.Module):
    """A rig's numbers as arrays: traced under ``jax.jit``, so one compiled function serves
    every rig of an image size (a new rig costs no compile). Built by :func:`rig_arrays`."""

    rect_px: Int[Array, " 4"]  # the confidence rectangle x, y, w, h
    travel_sign: Float[Array, ""]  # +1.0 travel right, -1.0 left
    wheel_radius_mm: Float[Array, ""]
    uncertainty: UncertaintyModel  # its leaves as arrays
    # The rig's rim_radius_px hint as the radii to search; None: the image size's default range
    # (hinted and unhinted rigs are two compiled functions per size, each serving all rigs).
    rim_range_px: tuple[Float[Array, ""], Float[Array, ""]] | None
    srgb: Float[Array, ""]  # 1.0: the frames are sRGB-encoded (rig encoding "srgb"), else 0.0


def rig_arrays(rig: Rig, uncertainty: UncertaintyModel | None = None) -> RigArrays:
    """``rig`` (and the uncertainty model, default :class:`UncertaintyModel`) as arrays of fixed
    dtypes, so that every rig gives the same abstract signature."""
    dtype = jax.dtypes.canonicalize_dtype(jnp.float64)
    model = UncertaintyModel() if uncertainty is None else uncertainty
    hint = rim_hint_range_px(rig)
    return RigArrays(
        rect_px=jnp.asarray(rig.confidence_rect, jnp.int32),
        travel_sign=jnp.asarray(travel_sign(rig.travel), dtype),
        wheel_radius_mm=jnp.asarray(rig.wheel_radius_mm, dtype),
        uncertainty=jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype), model),
        rim_range_px=None
        if hint is None
        else (jnp.asarray(hint[0], dtype), jnp.asarray(hint[1], dtype)),
        srgb=jnp.asarray(srgb_flag(rig.encoding), dtype),
    )
