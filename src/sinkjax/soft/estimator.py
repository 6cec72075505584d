"""The soft (differentiable) estimator: image -> z0, theta1, theta2 with one-sigma uncertainty.

``measure`` is the whole method for one frame as a pure JAX function (jit once per image size,
vmap over frames, grad with respect to the segmentation parameters). ``estimate_batch`` is the
NumPy-facing wrapper the pipeline and CLI use; it turns each frame into a results row.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ..geometry import from_wheel_frame, travel_sign
from ..result import FrameResult, Overlay, failed, no_contact
from ..rig import Rig, SegmentationParams, rect_problem, rim_hint_range_px
from ..status import Status
from .checks import message as check_message, plausibility
from .fit import build_evidence, fit
from .hough import hough_rim, radius_range_px
from .model import end_point, measurements
from .outline import extract_outline, refine_outline
from .segmentation import Rect, soft_open, wheel_mask
from .settings import SoftSettings
from .uncertainty import UncertaintyModel, covariance, measurement_std

# The default contact threshold as a number, for calibration's targets (SoftSettings has it).
MIN_BOUNDARY_POINTS = float(SoftSettings().min_boundary_points)


class SoftEstimate(eqx.Module):
    """One frame's soft estimate: sinkage in mm, angles in radians, each with one sigma.

    ``params`` are the fitted model (cx, cy, r px; k, b; end lines, see ``soft.model``) and
    ``params_std`` their sigmas before the uncertainty model's scaling; ``status`` is a
    :class:`sinkjax.Status` ``code``; the boundary arrays are the outline points and their
    boundary weights (for overlays). For no contact the measurements are 0 (docs/conventions.md §1).
    """

    sinkage_mm: Float[Array, ""]
    sinkage_std_mm: Float[Array, ""]
    theta1_rad: Float[Array, ""]
    theta1_std_rad: Float[Array, ""]
    theta2_rad: Float[Array, ""]
    theta2_std_rad: Float[Array, ""]
    params: Float[Array, " 9"]
    params_std: Float[Array, " 9"]
    status: Int[Array, ""]
    boundary_weight: Float[Array, " K"]
    boundary_x_px: Float[Array, " K"]
    boundary_y_px: Float[Array, " K"]
    # A and B in the wheel frame (u, v) px: computed here so that turning a frame into a row
    # needs no JAX call outside the compiled function.
    ends_uv_px: Float[Array, "2 2"]
    check: Int[Array, ""]  # soft.checks: 0 plausible, else which test failed


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
    fractions of the image size.
    Never raises for image content: problems are reported in ``status``.
    """
    mask = wheel_mask(image, seg, rect)
    if open_radius_px > 0:
        mask = soft_open(mask, open_radius_px)
    return measure_from_mask(
        image,
        mask,
        travel=travel,
        wheel_radius_mm=wheel_radius_mm,
        uncertainty=uncertainty,
        settings=settings,
        rim_range_px=rim_range_px,
    )


def measure_from_mask(
    image: Float[Array, "H W 3"],
    mask: Float[Array, "H W"],
    *,
    travel: str | Float[Array, ""] = "right",
    wheel_radius_mm: float | Float[Array, ""] = 1.0,
    uncertainty: UncertaintyModel | None = None,
    settings: SoftSettings | None = None,
    rim_range_px: tuple[ArrayLike, ArrayLike] | None = None,
) -> SoftEstimate:
    """Everything after segmentation, from a soft wheel mask in [0, 1] (1 = wheel) and its image.

    ``measure`` is ``measure_from_mask(image, wheel_mask(image, seg, rect))``; a learned
    segmenter (``sinkjax.torch``) supplies its own mask here. The image is still needed: the
    outline is located on its colours. Keyword arguments as for :func:`measure`.
    Raises ValueError if the shapes disagree.
    """
    if image.ndim != 3 or image.shape[-1] != 3 or mask.shape != image.shape[:2]:
        raise ValueError(
            f"need image (H, W, 3) and mask (H, W) of the same H, W; got image {image.shape} "
            f"and mask {mask.shape}"
        )
    height, width = mask.shape
    s = (SoftSettings() if settings is None else settings).astype(mask.dtype)
    outline = refine_outline(image, extract_outline(mask, s), s)
    # The starting circle is a discrete choice: no gradient flows through it.
    circle = jax.lax.stop_gradient(hough_rim(outline, height, width, s, rim_range_px))
    sign = travel_sign(travel) if isinstance(travel, str) else travel
    ev = build_evidence(outline, circle, sign, s)
    res = fit(ev)
    p = res.params
    cov = covariance(p, ev)
    est = measurements(p, wheel_radius_mm)
    contact = jnp.sum(ev.w_line) >= s.min_boundary_points
    check = plausibility(image, mask, p, ev, contact)
    std = measurement_std(p, cov, wheel_radius_mm, uncertainty) * check.sigma_scale
    measured = jnp.where(contact, Status.OK.code, Status.NO_CONTACT.code)
    status = jnp.where(
        circle.support < s.min_rim_support,
        Status.NO_WHEEL.code,
        jnp.where(
            ~res.ok,
            Status.FIT_FAILED.code,
            jnp.where(check.plausible, measured, Status.IMPLAUSIBLE.code),
        ),
    )
    zero_if_no_contact = jnp.where(contact, 1.0, 0.0)
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
    )


def _measure_u8(image_u8: Array, seg: SegmentationParams, rig: RigArrays) -> SoftEstimate:
    # The default float: float32, or float64 when jax_enable_x64 is on (one dtype throughout,
    # which the solver requires).
    image = image_u8.astype(jax.dtypes.canonicalize_dtype(jnp.float64)) / 255.0
    return measure(
        image,
        seg,
        rect=rig.rect_px,
        travel=rig.travel_sign,
        wheel_radius_mm=rig.wheel_radius_mm,
        uncertainty=rig.uncertainty,
        rim_range_px=rig.rim_range_px,
    )


# No static arguments: these compile once per image size (and batch size), whatever the rig.
_measure_one = jax.jit(_measure_u8)
_measure_batch = jax.jit(jax.vmap(_measure_u8, in_axes=(0, None, None)))

# (name, jitted function, example arguments) -> the callable to run on arguments of that shape.
CompiledProvider = Callable[[str, Any, tuple[Any, ...]], Callable[..., SoftEstimate]]
_provider: CompiledProvider | None = None


def set_compiled_provider(provider: CompiledProvider | None) -> None:
    """Let the application layer supply the compiled measuring functions (e.g. executables
    loaded from disk, :mod:`sinkjax.app.executables`); None: the jitted functions themselves."""
    global _provider
    _provider = provider


def compiled_measure(batched: bool, *args: Any) -> Callable[..., SoftEstimate]:
    """The measuring function (one frame, or a batch) for arguments shaped like ``args``."""
    name, fn = ("measure_batch", _measure_batch) if batched else ("measure_one", _measure_one)
    return fn if _provider is None else _provider(name, fn, args)


# Accelerator batches are padded to one of these sizes (then to a multiple of the largest), so
# that a run compiles a handful of shapes, not one per batch length.
BATCH_SIZES = (1, 8, 32, 128)


def padded_size(n: int) -> int:
    """The batch size ``n`` frames are padded to: the first of :data:`BATCH_SIZES` that holds
    them, else a multiple of the largest."""
    for size in BATCH_SIZES:
        if n <= size:
            return size
    top = BATCH_SIZES[-1]
    return -(-n // top) * top


def _use_vmap() -> bool:
    # On a CPU, vmap runs the Levenberg-Marquardt loops of all frames in lockstep until the
    # slowest converges, and XLA optimises a looped body (lax.map) worse than a plain one: frame
    # by frame through one compiled function is fastest. Accelerators want the whole batch.
    return jax.default_backend() != "cpu"


def estimate_batch(
    images: list[np.ndarray],
    rig: Rig,
    names: list[str],
    *,
    pad_to: int | None = None,
    uncertainty: UncertaintyModel | None = None,
) -> list[FrameResult]:
    """Soft estimates for frames of one size (uint8 RGB (H, W, 3) each), one row per frame.

    ``pad_to`` pads the batch (repeating a frame) so that every call has the same shape and the
    compiled function is reused; by default to :func:`padded_size`. The rig's numbers are
    traced (:class:`RigArrays`): a new rig of a size already seen compiles nothing.
    """
    if len(images) != len(names):
        raise ValueError(f"got {len(images)} images but {len(names)} names")
    if not images:
        return []
    shape = images[0].shape
    if any(im.shape != shape for im in images):
        raise ValueError("estimate_batch needs frames of one size; the pipeline groups them")
    height, width = shape[:2]
    problem = rect_problem(rig.confidence_rect, height, width)
    if problem is not None:
        return [failed(n, Status.BAD_RECT, problem) for n in names]
    n = len(images)
    # Fixed dtypes (not weak ones) for the thresholds too: a rig loaded from a file and one
    # built in Python must hit the same compiled function.
    dtype = jax.dtypes.canonicalize_dtype(jnp.float64)
    seg = jax.tree_util.tree_map(lambda v: jnp.asarray(v, dtype), rig.segmentation)
    args = (seg, rig_arrays(rig, uncertainty))
    hint = rim_hint_range_px(rig)
    if _use_vmap():
        size = max(pad_to or padded_size(n), n)
        batch = np.stack(images + [images[0]] * (size - n))
        frames = jnp.asarray(batch)
        out = compiled_measure(True, frames, *args)(frames, *args)
    else:
        one = compiled_measure(False, jnp.asarray(images[0]), *args)
        each = [one(jnp.asarray(im), *args) for im in images]
        # NumPy, not jnp.stack: eager JAX ops would each compile once per process.
        out = jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *each)
    out = jax.tree_util.tree_map(np.asarray, out)
    lo, hi = hint or radius_range_px(height, width)
    searched = f"{lo:.0f}-{hi:.0f} px, " + (
        "from the rig's rim_radius_px"
        if hint
        else "fractions of the image size; set rim_radius_px in the rig if the rim's radius "
        "is outside"
    )
    return [frame_result(out, i, names[i], rig, searched) for i in range(n)]


def frame_result(out: SoftEstimate, i: int, name: str, rig: Rig, searched: str = "") -> FrameResult:
    """Frame ``i`` of a batched :class:`SoftEstimate` as the common :class:`FrameResult`
    (degrees, image px, the overlay geometry). ``searched``: the rim radii searched, for the
    message of a frame without a rim."""
    p = out.params[i].astype(float)
    status = Status.from_code(int(out.status[i]))
    cx, cy, r = float(p[0]), float(p[1]), float(p[2])
    if status == Status.NO_WHEEL:
        rim = f" (rim radii searched: {searched})" if searched else ""
        return failed(name, Status.NO_WHEEL, Status.NO_WHEEL.message + rim)
    if status == Status.FIT_FAILED or not np.all(np.isfinite(p)):
        return FrameResult(
            image=name,
            status=Status.FIT_FAILED,
            center_x_px=cx,
            center_y_px=cy,
            radius_px=r,
            message=Status.FIT_FAILED.message,
        )
    sign = travel_sign(rig.travel)
    a, b = out.ends_uv_px[i].astype(float)
    ax, ay = (float(t) for t in from_wheel_frame(a[0], a[1], cx, cy, rig.travel))
    bx, by = (float(t) for t in from_wheel_frame(b[0], b[1], cx, cy, rig.travel))
    keep = out.boundary_weight[i] > 0.25
    boundary = np.stack([out.boundary_x_px[i][keep], out.boundary_y_px[i][keep]], -1)
    k, bb = float(p[3]), float(p[4])
    line = None
    if status == Status.OK:
        u0, u1 = float(b[0]), float(a[0])
        line = (
            (cx + sign * u0, cy + k * u0 + bb),
            (cx + sign * u1, cy + k * u1 + bb),
        )
    overlay = Overlay(
        centre_px=(cx, cy),
        radius_px=r,
        boundary_px=boundary,
        line_px=line,
        a_px=(ax, ay) if status == Status.OK else None,
        b_px=(bx, by) if status == Status.OK else None,
    )
    if status == Status.NO_CONTACT:
        return no_contact(name, (cx, cy), r, overlay)
    # An implausible frame keeps its numbers (for review) under a non-ok status and its reason.
    why = check_message(int(out.check[i])) if status == Status.IMPLAUSIBLE else ""
    return FrameResult(
        image=name,
        status=status,
        sinkage_mm=float(out.sinkage_mm[i]),
        sinkage_std_mm=float(out.sinkage_std_mm[i]),
        theta1_deg=float(np.degrees(out.theta1_rad[i])),
        theta1_std_deg=float(np.degrees(out.theta1_std_rad[i])),
        theta2_deg=float(np.degrees(out.theta2_rad[i])),
        theta2_std_deg=float(np.degrees(out.theta2_std_rad[i])),
        center_x_px=cx,
        center_y_px=cy,
        radius_px=r,
        overlay=overlay,
        message=why,
    )
