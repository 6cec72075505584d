"""Rows of a batched soft estimate: frame ``i`` as the common :class:`~sinkjax.result.FrameResult`.

The compiled functions (``soft.batch``) return one :class:`SoftEstimate` of NumPy arrays for a
whole batch; turning a frame into a row (degrees, image px, the overlay geometry, the status
message) needs no JAX call, so a long run spends no time here outside the compiled method.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..geometry import travel_sign
from ..result import FEATURE_CHOICES, FrameResult, Overlay, failed, no_contact
from ..rig import Rig
from ..status import Status
from .checks import message as check_message
from .estimator import SoftEstimate
from .rim import RIM_HIDDEN, RIM_MOVED


def _rim_message(out: SoftEstimate, i: int) -> str:
    code = int(out.rim_code[i])
    if code == RIM_HIDDEN:
        return (
            f"the rim is hardly seen in this frame ({100 * float(out.rim_support[i]):.0f}% of it): "
            "measured with the recording's rim"
        )
    if code == RIM_MOVED:
        cx, cy, r = (float(v) for v in out.own_rim_px[i])
        return (
            f"this frame's own rim (centre {cx:.1f}, {cy:.1f} px, radius {r:.1f} px) is not the "
            "recording's: measured with its own rim (has the camera moved? --rim frame measures "
            "every frame with its own)"
        )
    return ""


def frame_result(out: SoftEstimate, i: int, name: str, rig: Rig, searched: str = "") -> FrameResult:
    """Frame ``i`` of a batched :class:`SoftEstimate` as the common :class:`FrameResult`
    (degrees, image px, the overlay geometry, which features the segmenter chose; every
    status). ``searched``: the rim radii searched, for the message of a frame without a rim."""
    result = _frame_result(out, i, name, rig, searched)
    features = FEATURE_CHOICES.get(int(out.features[i]))
    return dataclasses.replace(result, segmenter_features=features)


def _frame_result(out: SoftEstimate, i: int, name: str, rig: Rig, searched: str) -> FrameResult:
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
    # geometry.from_wheel_frame in plain floats: a JAX call per frame here would be an eager
    # dispatch and a device round trip per number on an accelerator.
    ax, ay = cx + sign * float(a[0]), cy + float(a[1])
    bx, by = cx + sign * float(b[0]), cy + float(b[1])
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
    rim_note = _rim_message(out, i)
    if status == Status.NO_CONTACT:
        hidden = (
            float(out.sinkage_std_mm[i]),
            float(np.degrees(out.theta1_std_rad[i])),
            float(np.degrees(out.theta2_std_rad[i])),
        )
        result = no_contact(name, (cx, cy), r, overlay, hidden)
        return (
            dataclasses.replace(result, message=f"{result.message}; {rim_note}")
            if rim_note
            else result
        )
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
        message="; ".join(m for m in (why, rim_note) if m),
    )
