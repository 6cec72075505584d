"""A synthetic recording on disk: frames, ``rig.toml`` (:func:`rig_for`) and ``truth.csv``."""

from __future__ import annotations

import csv
import dataclasses
import math
import pathlib

import numpy as np

from ..rig import Rig, save_rig
from .presets import recording_scenes
from .raster import render_and_encode
from .scene import Scene

TRUTH_COLUMNS: tuple[str, ...] = (
    "image",
    "sinkage_mm",
    "theta1_deg",
    "theta2_deg",
    "terrain",
    "contact",
    "sinkage_px",
    "center_x_px",
    "center_y_px",
    "radius_px",
    "k",
    "b_px",
)


def rig_for(scene: Scene) -> Rig:
    """A rig for ``scene``'s camera set-up: R, travel and a confidence rectangle on the face.

    The rectangle lies above the hub, inside the band between the hub and the lightening-hole ring
    (or the rim ring without holes), so no wheel phase puts a hole, lug, hub or rim in it, and the
    soil (always below the hub) never covers it. It covers up to ~3 % of the rim disc.
    """
    cx, cy, r = scene.centre_x_px, scene.centre_y_px, scene.radius_px
    # Clearance from every other edge: blur, JPEG ringing and the pixels' own extent.
    gap = 1.5 + 0.015 * r
    inner = scene.hub_radius_px + gap
    if scene.n_holes:
        outer = scene.hole_ring_px - scene.hole_radius_px - gap
    else:
        outer = r - scene.rim_width_px - gap
    target = 0.03 * math.pi * r * r
    best = (0.0, 1.0, 1.0)
    for hgt in np.linspace(2, max(2.0, outer - inner), 64):
        top = inner + hgt
        if top >= outer:
            continue
        wid = 2 * math.sqrt(outer * outer - top * top)
        area = wid * hgt
        if area > best[0]:
            best = (area, float(wid), float(hgt))
    area, wid, hgt = best
    if area > target:  # keep the aspect, shrink to the target area
        f = math.sqrt(target / area)
        wid, hgt = wid * f, hgt * f
    # Integer pixel rectangle strictly within the continuous one (pixel j spans j-0.5..j+0.5).
    x0 = math.ceil(cx - wid / 2 + 0.5)
    x1 = math.floor(cx + wid / 2 - 0.5)
    y1 = math.floor(cy - inner - 0.5)
    y0 = math.ceil(cy - inner - hgt + 0.5)
    w, h = max(1, x1 - x0 + 1), max(1, y1 - y0 + 1)
    return Rig(
        wheel_radius_mm=float(scene.wheel_radius_mm),
        confidence_rect=(max(0, x0), max(0, y0), w, h),
        travel=scene.travel,
        encoding=scene.encoding,
    )


def _fmt(v: float) -> str:
    return repr(round(float(v), 9))


def frame_seed(seed: int, i: int) -> int:
    """Render seed of frame ``i`` of the recording written with ``seed``."""
    return int(np.random.SeedSequence([seed, i]).generate_state(1)[0])


def write_recording(
    out_dir: str | pathlib.Path,
    *,
    n_frames: int = 12,
    seed: int = 0,
    preset: str = "full",
    width: int = 640,
    height: int = 480,
    travel: str = "right",
    progress: bool = True,
    encoding: str = "linear",
) -> pathlib.Path:
    """Write a synthetic recording: frames, ``rig.toml`` and ``truth.csv``; returns the folder.

    Frames are ``frame_0000.png`` ... (``.jpg`` when the preset uses JPEG). ``truth.csv`` has the
    LABELS columns ``image,sinkage_mm,theta1_deg,theta2_deg`` then ``terrain,contact,sinkage_px,
    center_x_px,center_y_px,radius_px,k,b_px`` (no-contact frames: zeros, ``contact`` false).
    """
    from tqdm import tqdm

    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    scenes = recording_scenes(
        rng, n_frames, preset=preset, width=width, height=height, travel=travel
    )
    # The same scenes, stored with the camera's tone curve (the rig says so: rig_for).
    scenes = [dataclasses.replace(s, encoding=encoding) for s in scenes]
    if scenes:
        save_rig(
            rig_for(scenes[0]),
            out / "rig.toml",
            comment=f"sinkjax synthetic recording: preset={preset} seed={seed} frames={n_frames}",
        )
    with (out / "truth.csv").open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(TRUTH_COLUMNS)
        for i, scene in enumerate(tqdm(scenes, desc="synth", unit="frame", disable=not progress)):
            _, t, data = render_and_encode(scene, frame_seed(seed, i), encode=True)
            name = f"frame_{i:04d}.{'jpg' if scene.jpeg_quality else 'png'}"
            assert data is not None
            (out / name).write_bytes(data)
            writer.writerow(
                [
                    name,
                    _fmt(t.sinkage_mm),
                    _fmt(t.theta1_deg),
                    _fmt(t.theta2_deg),
                    t.terrain,
                    "true" if t.contact else "false",
                    _fmt(t.sinkage_px),
                    _fmt(t.center_x_px),
                    _fmt(t.center_y_px),
                    _fmt(t.radius_px),
                    _fmt(t.k),
                    _fmt(t.b_px),
                ]
            )
            fh.flush()
    return out
