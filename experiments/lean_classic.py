"""A lean, independent OpenCV/NumPy implementation of the paper's classic pipeline (issue 13).

The speed reference for the soft method: the paper's steps with nothing added, written without
``sinkjax.classic`` (and without JAX), so that "soft costs X times the classic method" compares
against what a lab would write in an afternoon, not against our own careful classic code.

1. the confidence rectangle (from the rig);
2. RGB -> HSI: hue from OpenCV's HSV conversion (the same hue angle up to the hexagonal
   approximation, under a degree or two), saturation S = 1 - 3 min(R, G, B) / (R + G + B);
3. H_w, S_w over the rectangle (Eqs. 4-5; the hue mean circular, as docs/paper.md says sinkjax
   does), the P_d/P_a bands (hue circular, rig.HUE_SCALE_DEG = 180 degrees), then closing,
   opening (which also cuts off the lugs), the component reaching into the rectangle, its holes
   filled;
4. the region's outline (``cv2.findContours``), the rim circle by ``cv2.HoughCircles`` polished
   by a least-squares circle through the outline points near it, the outline points inside the
   rim (and off the image border) as the wheel-soil boundary;
5. Eq. 1 on a least-squares line through them, theta1 and theta2 by atan2 (docs/conventions.md §1).

    PYTHONPATH=src python experiments/lean_classic.py   # checks it against rendered truth
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

HUE_SCALE_DEG = 180.0  # the circular hue band's scale (docs/paper.md, "What sinkjax changes")
# The classic method's Hough window, as fractions of the image's shorter side (conventions §2).
RIM_WINDOW = (0.15, 0.6)


@dataclass(frozen=True)
class LeanRig:
    """What the lean pipeline needs of a rig: R (mm), rectangle (x, y, w, h px), travel, P's."""

    wheel_radius_mm: float
    rect: tuple[int, int, int, int]
    travel: str = "right"
    p_d_hue: float = 0.9
    p_a_hue: float = 1.1
    p_d_sat: float = 0.5
    p_a_sat: float = 1.8


@dataclass(frozen=True)
class LeanResult:
    """One frame: status "ok", "no_contact" or "no_wheel"; mm, degrees, image px."""

    status: str
    sinkage_mm: float = 0.0
    theta1_deg: float = 0.0
    theta2_deg: float = 0.0
    centre_px: tuple[float, float] = (0.0, 0.0)
    radius_px: float = 0.0


def hue_sat(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hue (degrees, [0, 360)) and HSI saturation of a uint8 RGB image, float32 (H, W) each."""
    x = rgb.astype(np.float32) * np.float32(1.0 / 255.0)
    hue = cv2.cvtColor(x, cv2.COLOR_RGB2HSV)[..., 0]
    low = cv2.min(cv2.min(x[..., 0], x[..., 1]), x[..., 2])
    total = cv2.add(cv2.add(x[..., 0], x[..., 1]), x[..., 2])
    sat = 1.0 - 3.0 * low / np.maximum(total, np.float32(1e-6))
    return hue, sat


def wheel_region(rgb: np.ndarray, rig: LeanRig) -> np.ndarray | None:
    """Steps 2-3: the wheel's filled region, uint8 (H, W) 0/1, or None without a wheel."""
    hue, sat = hue_sat(rgb)
    x, y, w, h = rig.rect
    hr = np.radians(hue[y : y + h, x : x + w])
    h_w = math.degrees(math.atan2(float(np.sin(hr).mean()), float(np.cos(hr).mean())))
    s_w = float(sat[y : y + h, x : x + w].mean())
    d = np.mod(hue - np.float32(h_w) + 180.0, 360.0) - 180.0
    lo, hi = (rig.p_d_hue - 1.0) * HUE_SCALE_DEG, (rig.p_a_hue - 1.0) * HUE_SCALE_DEG
    band = (d >= lo) & (d <= hi) & (sat >= rig.p_d_sat * s_w) & (sat <= rig.p_a_sat * s_w)
    # Closing bridges cracks; an opening wider than a lug drops the lugs and soil specks.
    size = max(5, round(0.02 * min(rgb.shape[:2])) | 1)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    m = cv2.morphologyEx(band.view(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    m = cv2.morphologyEx(m, cv2.MORPH_OPEN, disc)
    n, labels = cv2.connectedComponents(m, connectivity=8)
    counts = np.bincount(labels[y : y + h, x : x + w].ravel(), minlength=n)
    counts[0] = 0
    if n <= 1 or counts.max() == 0:
        return None
    region = (labels == int(np.argmax(counts))).view(np.uint8)
    contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    filled = np.zeros_like(region)
    cv2.drawContours(filled, contours, -1, 1, thickness=cv2.FILLED)
    return filled


def fit_circle(pts: np.ndarray) -> tuple[float, float, float]:
    """Least-squares (Kasa) circle through points (n, 2): centre x, y and radius, px."""
    xs, ys = pts[:, 0], pts[:, 1]
    a = np.stack([xs, ys, np.ones_like(xs)], 1)
    sol, *_ = np.linalg.lstsq(a, xs * xs + ys * ys, rcond=None)
    cx, cy = sol[0] / 2, sol[1] / 2
    return float(cx), float(cy), float(math.sqrt(max(sol[2] + cx * cx + cy * cy, 0.0)))


def rim(filled: np.ndarray, outline: np.ndarray) -> tuple[float, float, float] | None:
    """Step 4's rim circle (cx, cy, r px): Hough on the region, polished on the outline."""
    short = min(filled.shape)
    circles = cv2.HoughCircles(
        filled * np.uint8(255),
        cv2.HOUGH_GRADIENT,
        dp=2,
        minDist=short,
        param1=100,
        param2=30,
        minRadius=int(RIM_WINDOW[0] * short),
        maxRadius=int(RIM_WINDOW[1] * short),
    )
    if circles is None:
        return None
    cx, cy, r = (float(v) for v in circles[0, 0])
    # Polish on the outline points near it, then on the inner envelope only: lug stubs the
    # opening left stand outside the rim and must not pull it outwards.
    for lo, hi in ((-4.0, 4.0), (-2.0, 1.0), (-1.5, 0.5)):
        d = np.hypot(outline[:, 0] - cx, outline[:, 1] - cy) - r
        near = (d > lo) & (d < hi)
        if np.count_nonzero(near) < 10:
            break
        cx, cy, r = fit_circle(outline[near])
    return cx, cy, r + 0.5


def longest_run(flags: np.ndarray) -> np.ndarray:
    """Indices of the longest run of True in a closed sequence (the boundary is one stretch of
    the outline; stray pixels of the rim's staircase dipping inside r are not)."""
    if flags.all() or not flags.any():
        return np.flatnonzero(flags)
    start = int(np.argmin(flags))  # a False: no run wraps around from here
    rolled = np.roll(flags, -start).astype(np.int8)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], rolled, [0]])))
    begins, ends = edges[::2], edges[1::2]
    i = int(np.argmax(ends - begins))
    return (np.arange(begins[i], ends[i]) + start) % len(flags)


def measure(rgb: np.ndarray, rig: LeanRig) -> LeanResult:
    """The paper's pipeline on one (H, W, 3) uint8 RGB frame."""
    filled = wheel_region(rgb, rig)
    if filled is None:
        return LeanResult("no_wheel")
    contours, _ = cv2.findContours(filled, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    outline = max(contours, key=len)[:, 0, :].astype(np.float64)
    circle = rim(filled, outline)
    if circle is None:
        return LeanResult("no_wheel")
    cx, cy, r = circle
    hh, ww = filled.shape
    inside = np.hypot(outline[:, 0] - cx, outline[:, 1] - cy) < r - 2.0
    off_edge = (
        (outline[:, 0] > 0)
        & (outline[:, 0] < ww - 1)
        & (outline[:, 1] > 0)
        & (outline[:, 1] < hh - 1)
    )
    pts = outline[longest_run(inside & off_edge & (outline[:, 1] > cy))]
    if len(pts) < 10:
        return LeanResult("no_contact", centre_px=(cx, cy), radius_px=r)
    sign = 1.0 if rig.travel == "right" else -1.0
    u, v = sign * (pts[:, 0] - cx), pts[:, 1] - cy  # wheel frame: u towards the entry side
    k, b = np.polyfit(u, v, 1)
    z0_px = r - abs(b) / math.hypot(k, 1.0)
    ia, ib = int(np.argmax(u)), int(np.argmin(u))
    return LeanResult(
        "ok",
        sinkage_mm=z0_px * rig.wheel_radius_mm / r,
        theta1_deg=math.degrees(math.atan2(u[ia], v[ia])),
        theta2_deg=math.degrees(math.atan2(-u[ib], v[ib])),
        centre_px=(cx, cy),
        radius_px=r,
    )


def lean_rig(rig: object) -> LeanRig:
    """A :class:`LeanRig` from a ``sinkjax.Rig`` (read by attribute: no sinkjax import here)."""
    seg = rig.segmentation  # type: ignore[attr-defined]
    return LeanRig(
        wheel_radius_mm=float(rig.wheel_radius_mm),  # type: ignore[attr-defined]
        rect=tuple(int(v) for v in rig.confidence_rect),  # type: ignore[attr-defined]
        travel=str(rig.travel),  # type: ignore[attr-defined]
        p_d_hue=float(seg.p_d_hue),
        p_a_hue=float(seg.p_a_hue),
        p_d_sat=float(seg.p_d_sat),
        p_a_sat=float(seg.p_a_sat),
    )


def main() -> None:
    """Against the renderer's exact truth on a few synthetic frames of two camera set-ups."""
    from sinkjax import synth as S

    for seed, (w, h) in ((7, (640, 480)), (11, (1024, 768))):
        scenes = S.recording_scenes(np.random.default_rng(seed), 6, width=w, height=h)
        rig = lean_rig(S.rig_for(scenes[0]))
        for i, sc in enumerate(scenes):
            image, t = S.render(sc, seed=i)
            res = measure(image, rig)
            print(
                f"{w}x{h} {sc.terrain:10s} {res.status:10s} z0 {res.sinkage_mm:6.2f} "
                f"(true {t.sinkage_mm:6.2f}) mm, th1 {res.theta1_deg:6.2f} ({t.theta1_deg:6.2f}), "
                f"th2 {res.theta2_deg:6.2f} ({t.theta2_deg:6.2f}) deg, r {res.radius_px:6.1f} "
                f"({t.radius_px:6.1f}) px"
            )


if __name__ == "__main__":
    main()
