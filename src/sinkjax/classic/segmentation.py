"""Classic pipeline, steps 2-3: HSI, the confidence means, the binary image and the wheel region.

Float64 NumPy and OpenCV, no gradients (the soft counterpart is :mod:`sinkjax.soft.segmentation`).
The paper's method as written: RGB -> HSI (:func:`rgb_to_hsi_np`), the wheel's mean hue and
saturation H_w, S_w over the confidence rectangle (Eqs. 4-5, :func:`confidence_means_np`), the
pixels whose H and S lie in the P_d/P_a ranges around them (:func:`hard_mask`), then "dilation,
erosion, area filtering and so on" (:func:`wheel_region`) and the enclosed holes filled
(:func:`fill_holes`). Hue is circular (``rig.HUE_SCALE_DEG``): a red wheel straddles 0/360
degrees, where the paper's arithmetic mean and P_a * H_w ranges would break.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from ..rig import HUE_SCALE_DEG, SegmentationParams, rect_problem


def rgb_to_hsi_np(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RGB -> the paper's HSI (textbook arccos hue), float64.

    ``rgb``: (H, W, 3) uint8, or float in [0, 1]. Returns H in degrees [0, 360), S and I in [0, 1],
    each (H, W). Grey pixels (R = G = B) get H = 0, black pixels S = 0; never NaN, never warns.
    Raises ValueError if the last axis is not 3.
    """
    a = np.asarray(rgb)
    if a.ndim < 1 or a.shape[-1] != 3:
        raise ValueError(f"rgb must have shape (..., 3), got {a.shape}")
    x = a.astype(np.float64) / 255.0 if a.dtype == np.uint8 else a.astype(np.float64)
    r, g, b = np.moveaxis(x, -1, 0).copy()  # contiguous planes: faster than strided channels
    rg, rb = r - g, r - b
    num = 0.5 * (rg + rb)
    # (R-G)^2 + (R-B)(G-B) = R^2+G^2+B^2-RG-RB-GB >= 0, zero only for grey.
    den = np.sqrt(np.maximum(rg * rg + rb * (g - b), 0.0))
    grey = den <= 1e-12
    theta = np.degrees(np.arccos(np.clip(num / np.where(grey, 1.0, den), -1.0, 1.0)))
    h = np.where(b <= g, theta, 360.0 - theta)
    h[grey | (h >= 360.0)] = 0.0
    total = r + g + b
    dark = total <= 1e-12
    s = 1.0 - 3.0 * np.minimum(np.minimum(r, g), b) / np.where(dark, 1.0, total)
    s[dark] = 0.0
    return h, np.clip(s, 0.0, 1.0), total / 3.0


def check_rect(
    rect: tuple[int, int, int, int], shape: tuple[int, ...]
) -> tuple[int, int, int, int]:
    """The confidence rectangle (x, y, w, h) as ints; ValueError (with the fix) unless it lies
    inside an image of ``shape`` (the one rule, :func:`sinkjax.rig.rect_problem`)."""
    problem = rect_problem(rect, int(shape[0]), int(shape[1]))
    if problem is not None:
        raise ValueError(problem)
    x, y, w, h = (int(v) for v in rect)
    return x, y, w, h


def confidence_means_np(
    h_deg: np.ndarray, s: np.ndarray, rect: tuple[int, int, int, int]
) -> tuple[float, float]:
    """Eqs. 4-5: mean hue H_w (degrees, [0, 360)) and saturation S_w over ``rect`` = (x, y, w, h).

    ``h_deg``, ``s``: (H, W). The hue mean is circular (a red wheel straddles 0/360, where the
    arithmetic mean of Eq. 4 would land on cyan). Raises ValueError if ``rect`` is not fully inside
    the image.
    """
    x, y, w, h = check_rect(rect, np.shape(h_deg))
    hh = np.radians(np.asarray(h_deg, dtype=np.float64)[y : y + h, x : x + w])
    h_w = math.degrees(math.atan2(float(np.mean(np.sin(hh))), float(np.mean(np.cos(hh)))))
    s_w = float(np.mean(np.asarray(s, dtype=np.float64)[y : y + h, x : x + w]))
    return h_w % 360.0, s_w


def wheel_chroma_np(h_deg: np.ndarray, s: np.ndarray, rect: tuple[int, int, int, int]) -> float:
    """The length of the mean (S cos H, S sin H) over ``rect``: how much colour the wheel has, in
    saturation units (noise in the hue of a grey wheel averages out; S_w alone would not)."""
    x, y, w, h = check_rect(rect, np.shape(h_deg))
    hh = np.radians(np.asarray(h_deg, dtype=np.float64)[y : y + h, x : x + w])
    ss = np.asarray(s, dtype=np.float64)[y : y + h, x : x + w]
    return math.hypot(float(np.mean(ss * np.cos(hh))), float(np.mean(ss * np.sin(hh))))


def hard_mask(
    h_deg: np.ndarray, s: np.ndarray, h_w_deg: float, s_w: float, seg: SegmentationParams
) -> np.ndarray:
    """The paper's binary image: pixels whose H and S lie in the P_d/P_a ranges. (H, W) bool.

    Hue: wrap(H - H_w) in [(p_d_hue - 1) * 180, (p_a_hue - 1) * 180] degrees (circular band, see
    ``rig.HUE_SCALE_DEG``). Saturation: S in [p_d_sat * S_w, p_a_sat * S_w].
    """
    d = np.mod(np.asarray(h_deg, dtype=np.float64) - h_w_deg + 180.0, 360.0) - 180.0
    lo_h = (float(seg.p_d_hue) - 1.0) * HUE_SCALE_DEG
    hi_h = (float(seg.p_a_hue) - 1.0) * HUE_SCALE_DEG
    s = np.asarray(s, dtype=np.float64)
    return (
        (d >= lo_h)
        & (d <= hi_h)
        & (s >= float(seg.p_d_sat) * s_w)
        & (s <= float(seg.p_a_sat) * s_w)
    )


def wheel_region(mask: np.ndarray, rect: tuple[int, int, int, int]) -> np.ndarray | None:
    """Dilation, erosion and area filtering: the wheel's connected component (holes not filled).

    ``mask``: (H, W) bool. Returns a (H, W) bool mask, or None when no component reaches into the
    confidence rectangle. Closing bridges one-pixel cracks (noise, anti-aliasing); the component
    with the most pixels in the rectangle is the wheel. Its holes (lightening holes, hub, specular
    highlights) are no part of its outline; :func:`fill_holes` fills them.
    """
    k3 = np.ones((3, 3), np.uint8)
    closed = cv2.erode(cv2.dilate(mask.astype(np.uint8), k3), k3)
    # An opening after the closing drops one-pixel spurs and soil specks touching the wheel.
    opened = cv2.dilate(cv2.erode(closed, k3), k3)
    n, labels = cv2.connectedComponents(opened, connectivity=8)
    if n <= 1:
        return None
    x, y, w, h = rect
    counts = np.bincount(labels[y : y + h, x : x + w].ravel(), minlength=n)
    counts[0] = 0
    best = int(np.argmax(counts))
    if counts[best] == 0:
        return None
    return labels == best


def fill_holes(region: np.ndarray) -> np.ndarray:
    """``region`` (H, W) bool with its enclosed holes filled (inside its external contour)."""
    contours, _ = cv2.findContours(
        region.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE
    )
    out = np.zeros(region.shape, np.uint8)
    cv2.drawContours(out, contours, -1, 1, thickness=cv2.FILLED)
    return out.astype(bool) | region
