"""ONE synthetic camera set-up modelled on the paper's rig, and terrain placed under the wheel.

Every experiment shares :func:`paper_scene` (R = 140 mm, 28 lugs 15 mm high, a single lamp with
its cast shadow), so all share one confidence rectangle and the soft method compiles once per
image size; :func:`place` and :func:`bulldozing` set the soil (slip bulldozing: a pile ahead of
the wheel, a rut behind it) as :class:`sinkjax.synth.Scene` terrain fields. Millimetres for
sinkage; pixels only inside scene construction.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from sinkjax import synth as S

from .paper import WHEEL_RADIUS_MM
from .runs import Setup


def _hsv(h_deg: float, s: float, v: float) -> tuple[float, float, float]:
    import colorsys

    r, g, b = colorsys.hsv_to_rgb((h_deg % 360.0) / 360.0, s, v)
    return (r, g, b)


def paper_scene(setup: Setup) -> S.Scene:
    """The experiments' camera set-up (wheel on flat soil at 10 mm sinkage).

    The paper's wheel: R = 140 mm, 28 lugs 15 mm high; a single lamp above-left with the wheel's
    cast shadow on the soil, mild sensor noise, blur and JPEG. At 640x480 the rim radius is 140 px
    (1 px = 1 mm); at 320x240 everything is halved. Every experiment varies only the terrain,
    wheel phase and lighting of this scene, so :func:`sinkjax.synth.rig_for` gives one rig.
    """
    f = setup.width / 640.0
    r = 140.0 * f
    lamp = (-0.6, -0.8)
    base = S.Scene(
        width=setup.width,
        height=setup.height,
        centre_x_px=320.0 * f,
        centre_y_px=190.0 * f,
        radius_px=r,
        wheel_radius_mm=WHEEL_RADIUS_MM,
        wheel_rgb=_hsv(44, 0.85, 0.85),
        rim_rgb=_hsv(44, 0.85, 0.68),
        rim_width_px=9.0 * f,
        lug_rgb=_hsv(45, 0.8, 0.78),
        n_lugs=28,
        lug_height_px=15.0 * f,
        lug_width_px=6.0 * f,
        hub_radius_px=20.0 * f,
        hub_rgb=_hsv(40, 0.2, 0.45),
        n_holes=6,
        hole_radius_px=14.0 * f,
        hole_ring_px=85.0 * f,
        soil_rgb=_hsv(28, 0.32, 0.60),
        soil_rgb2=_hsv(24, 0.36, 0.55),
        soil_texture=0.12,
        pebbles=int(150 * f * f),
        wall_rgb=_hsv(210, 0.05, 0.55),
        light_dir=lamp,
        shading=0.25,
        shadow_factor=0.6,
        shadow_offset_px=(-lamp[0] * 0.2 * r, -lamp[1] * 0.2 * r),
        shadow_soft_px=5.0 * f,
        noise_std=2.0,
        blur_sigma_px=0.5 * f,
        jpeg_quality=90,
    )
    return place(base, 10.0)


def px_per_mm(scene: S.Scene) -> float:
    return scene.radius_px / scene.wheel_radius_mm


def place(scene: S.Scene, depth_mm: float, **terrain: Any) -> S.Scene:
    """``scene`` with the wheel's lowest point ``depth_mm`` below the FLAT soil level, plus the
    given terrain fields (bumps, ruts, roughness; see :class:`sinkjax.synth.Scene`). The flat
    level is what the paper's displacement sensor measured sinkage from."""
    level = scene.centre_y_px + scene.radius_px - depth_mm * px_per_mm(scene)
    return dataclasses.replace(scene, soil_level_px=level, **terrain)


def half_chord_px(scene: S.Scene, depth_mm: float) -> float:
    """Half the contact chord on flat soil at this depth (px)."""
    z = depth_mm * px_per_mm(scene)
    return math.sqrt(max(2.0 * scene.radius_px * z - z * z, 1.0))


def bulldozing(
    scene: S.Scene, depth_mm: float, slip: float, *, pile: bool = True, jitter: float = 0.0
) -> dict[str, Any]:
    """Slip bulldozing as terrain fields: a pile pushed up ahead of the wheel and a rut left behind
    it, both growing with slip (pile height (0.1 + 0.4 s) z, rut depth (0.2 + 0.5 s) z for
    sinkage z). ``pile=False`` leaves the scene's Gaussian bump free for a terrain feature.
    ``jitter`` in [-1, 1] shifts the features a little (frames of one run differ)."""
    r = scene.radius_px
    z = depth_mm * px_per_mm(scene)
    half = half_chord_px(scene, depth_mm)
    out: dict[str, Any] = {
        "rut_depth_px": (0.2 + 0.5 * slip) * z,
        "rut_dx_px": -(0.5 + 0.1 * jitter) * half,
        "rut_width_px": 0.06 * r,
        "rut_side": -1.0,
    }
    if pile:
        sigma = 0.12 * r
        out |= {
            "bump_height_px": (0.1 + 0.4 * slip) * z,
            "bump_dx_px": half + (0.5 + 0.2 * jitter) * sigma,
            "bump_sigma_px": sigma,
        }
    return out


def valid_contact(scene: S.Scene) -> bool:
    """Two rim crossings, with the entry end A ahead of and the exit end B behind the wheel's
    lowest point (Eqs. 2-3 assume x_A > 0 > x_B)."""
    if S.n_rim_crossings(scene) != 2:
        return False
    t = S.true_geometry(scene)
    return t.a_px[0] > 0.02 * scene.radius_px and t.b_end_px[0] < -0.02 * scene.radius_px
