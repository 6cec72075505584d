"""The one per-frame result that every estimator returns (docs/conventions.md §1, §4).

A :class:`FrameResult` is an ``eqx.Module`` (a pytree): the measured numbers are its leaves
(``None`` where not available), the frame's name, :class:`~sinkjax.Status` and message are static.
Both the soft and the classic estimator build it; the app layer turns it into a CSV row
(:func:`sinkjax.app.results.csv_row`) and an overlay (:func:`sinkjax.draw_overlay`), and counts
which features separated wheel from soil in each recording for the run summary.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import numpy as np

from .rig import rect_overexposed
from .status import Status

Point = tuple[float, float]

# Which features separated wheel from soil in a frame: the codes a soft segmenter reports from
# inside JAX (:meth:`sinkjax.Segmenter.features`) and their names, which a FrameResult carries
# and the run summary counts. The classic method is always FEATURES_HUE_SAT (the paper's H/S
# test); FEATURES_UNKNOWN (no name) is a mask made outside any segmenter (``measure_from_mask``).
# (Not sinkjax.learn.FEATURE_NAMES: those are the per-pixel inputs of the learned segmenters.)
FEATURES_UNKNOWN = -1
FEATURES_HUE_SAT = 0
FEATURES_INTENSITY = 1
FEATURES_LEARNED = 2
FEATURE_CHOICES = {
    FEATURES_HUE_SAT: "hue+saturation",
    FEATURES_INTENSITY: "intensity+texture",
    FEATURES_LEARNED: "learned",
}


class Overlay(eqx.Module):
    """What an overlay draws, in IMAGE pixels: rim circle, boundary, line ends, A and B."""

    centre_px: Point
    radius_px: float
    boundary_px: np.ndarray | None = None  # (n, 2) x, y
    line_px: tuple[Point, Point] | None = None
    a_px: Point | None = None
    b_px: Point | None = None


class FrameResult(eqx.Module):
    """One frame's measurement: sinkage (mm), angles (degrees), their one-sigma, the rim circle
    (image px), the status and a message. ``None`` = not available (``*_std_*`` for classic).

    ``segmenter_features``: which features separated wheel from soil (a :data:`FEATURE_CHOICES`
    name, e.g. ``"intensity+texture"``), for every frame that was segmented, whatever its
    status; None for one that never reached segmentation (unreadable, ``bad_rect``, ...). It
    is no column of the results CSV (docs/conventions.md §4): the run summary reports it.
    """

    image: str = eqx.field(static=True)
    status: Status = eqx.field(static=True, converter=Status)
    sinkage_mm: float | None = None
    sinkage_std_mm: float | None = None
    theta1_deg: float | None = None
    theta1_std_deg: float | None = None
    theta2_deg: float | None = None
    theta2_std_deg: float | None = None
    center_x_px: float | None = None
    center_y_px: float | None = None
    radius_px: float | None = None
    message: str = eqx.field(static=True, default="")
    overlay: Overlay | None = eqx.field(default=None, repr=False)
    segmenter_features: str | None = eqx.field(static=True, default=None)


def no_contact(
    image: str,
    centre_px: Point,
    radius_px: float,
    overlay: Overlay | None,
    std: tuple[float, float, float] | None = None,
) -> FrameResult:
    """docs/conventions.md §1: no contact is sinkage 0 and both angles 0. ``std``: one sigma of
    (sinkage mm, theta1 deg, theta2 deg), how much could hide below what the image shows; None
    for a method without one."""
    s = (None, None, None) if std is None else std
    return FrameResult(
        image=image,
        status=Status.NO_CONTACT,
        sinkage_mm=0.0,
        sinkage_std_mm=s[0],
        theta1_deg=0.0,
        theta1_std_deg=s[1],
        theta2_deg=0.0,
        theta2_std_deg=s[2],
        center_x_px=centre_px[0],
        center_y_px=centre_px[1],
        radius_px=radius_px,
        message=Status.NO_CONTACT.message,
        overlay=overlay,
    )


def failed(
    image: str,
    status: Status | str,
    message: str = "",
    *,
    segmenter_features: str | None = None,
) -> FrameResult:
    """A result for a frame that produced no measurement (``message``: the status's default;
    ``segmenter_features``: see :class:`FrameResult`, for a frame segmented in vain)."""
    status = Status(status)
    return FrameResult(
        image=image,
        status=status,
        message=message or status.message,
        segmenter_features=segmenter_features,
    )


_MEASURED = ("sinkage_mm", "theta1_deg", "theta2_deg")


def finite_or_failed(result: FrameResult) -> FrameResult:
    """``result``, or ``fit_failed`` if it claims a measurement that is not a finite number.

    A non-finite number would be written as an empty cell next to ``ok``: a row that looks
    measured and is not (e.g. R so large that z0 * R / r overflows)."""
    if not result.status.measured:
        return result
    bad = [
        f"{name} = {value!r}"
        for name in _MEASURED
        if (value := getattr(result, name)) is not None and not np.isfinite(value)
    ]
    if not bad:
        return result
    return failed(
        result.image,
        Status.FIT_FAILED,
        f"non-finite result ({', '.join(bad)})",
        segmenter_features=result.segmenter_features,
    )


def with_rect_hint(
    result: FrameResult, image_u8: np.ndarray, rect: tuple[int, int, int, int]
) -> FrameResult:
    """``result``, its message extended by why the confidence rectangle misleads the method
    where it is over-exposed and the frame was not measured ``ok``."""
    if result.status == Status.OK:
        return result
    hint = rect_overexposed(image_u8, rect)
    if hint is None:
        return result
    message = f"{result.message}; {hint}" if result.message else hint
    return dataclasses.replace(result, message=message)
