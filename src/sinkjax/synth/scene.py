"""One synthetic frame's parameters (:class:`Scene`) and its exact soil surface.

A :class:`Scene` holds every parameter of one frame: camera set-up (wheel centre and rim radius in
the image), wheel (colours, rim ring, hub, lightening holes, lugs), terrain (the soil surface
``y = surface_y_px(scene, x)``, image coordinates, y down), soil and wall appearance, lighting and
sensor. :func:`mirrored` is the left-right mirror image with the same truth.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass, replace

import numpy as np
from jaxtyping import Float
from numpy.typing import NDArray

from ..geometry import travel_sign
from ..rig import ENCODINGS

F64 = NDArray[np.float64]  # the analytic geometry (surface, boundary, edges) is float64


@dataclass(frozen=True)
class Scene:
    """All parameters of one synthetic frame. Pixels, image coordinates (x right, y down).

    Colours are linear RGB triples in [0, 1]. The soil surface is
    ``soil_level_px + tilt*dx - bump + rut + rough`` with ``dx = x - centre_x_px`` (see
    :func:`surface_y_px`); terrain parameters are in image terms, so ``replace(scene,
    travel="left")`` keeps the picture and swaps entry and exit (use :func:`mirrored` to mirror
    the picture as well).
    """

    width: int = 640
    height: int = 480
    centre_x_px: float = 320.0
    centre_y_px: float = 200.0
    radius_px: float = 150.0  # RIM radius r; lugs stick out beyond it
    wheel_radius_mm: float = 140.0  # physical rim radius R
    travel: str = "right"
    # --- terrain
    terrain: str = "flat"
    soil_level_px: float = 330.0  # surface y at the wheel-centre column before the features
    tilt: float = 0.0  # dy/dx of the base level
    bump_height_px: float = 0.0  # Gaussian raise (mound, pile; < 0 digs a hollow)
    bump_dx_px: float = 0.0
    bump_sigma_px: float = 40.0
    rut_depth_px: float = 0.0  # smooth step lowering the surface on the ``rut_side`` of rut_dx
    rut_dx_px: float = 0.0
    rut_width_px: float = 20.0
    rut_side: float = -1.0  # -1: lowered on the left (behind a wheel travelling right)
    rough: tuple[tuple[float, float, float], ...] = ()  # (amplitude_px, signed wavelength_px, rad)
    # --- wheel
    wheel_rgb: tuple[float, float, float] = (0.85, 0.62, 0.10)
    rim_rgb: tuple[float, float, float] = (0.70, 0.50, 0.08)
    rim_width_px: float = 10.0
    lug_rgb: tuple[float, float, float] = (0.78, 0.58, 0.12)
    n_lugs: int = 0
    lug_height_px: float = 0.0
    lug_width_px: float = 0.0
    phase_rad: float = 0.0  # wheel rotation (lugs and holes), image angle atan2(dy, dx)
    hub_radius_px: float = 20.0
    hub_rgb: tuple[float, float, float] = (0.45, 0.43, 0.40)
    n_holes: int = 0
    hole_radius_px: float = 0.0
    hole_ring_px: float = 0.0  # distance of the hole centres from O
    hole_rgb: tuple[float, float, float] = (0.09, 0.09, 0.10)
    # --- soil and wall
    soil_rgb: tuple[float, float, float] = (0.62, 0.52, 0.40)
    soil_rgb2: tuple[float, float, float] = (0.55, 0.47, 0.38)  # hue variation partner
    soil_texture: float = 0.12  # relative intensity noise amplitude
    pebbles: int = 0
    wall_rgb: tuple[float, float, float] = (0.55, 0.56, 0.58)
    wall_gradient: float = 0.15
    wall_texture: float = 0.02  # relative low-frequency mottling of the wall
    face_texture: float = 0.02  # relative low-frequency variation on the wheel face
    # --- lighting
    light_dir: tuple[float, float] = (-0.6, -0.8)  # unit vector towards the lamp
    shading: float = 0.2  # relative intensity change across one rim radius
    lamp_white: float = 0.0  # additive white (desaturating) glow on the lamp side of the face
    specular: tuple[tuple[float, float, float, float], ...] = ()  # (dx, dy, sigma, amp) from O
    shadow_factor: float = 1.0  # cast shadow on soil multiplies by this (1: no shadow)
    shadow_offset_px: tuple[float, float] = (0.0, 0.0)
    shadow_soft_px: float = 4.0
    dust: float = 0.0  # max blend of the wheel face towards the soil colour
    dust_top_frac: float = 0.3  # dust starts at centre_y + dust_top_frac * r
    cast_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)  # per-channel gains (colour cast)
    gain: float = 1.0  # exposure
    black_level: float = 0.0  # sensor pedestal added to every channel, 8-bit units (desaturates)
    # --- sensor
    noise_std: float = 0.0  # 8-bit units
    blur_sigma_px: float = 0.0
    jpeg_quality: int = 0  # 0: lossless (PNG)
    # How pixel values store light: "linear" (proportional to it) or "srgb" (the sRGB tone curve
    # applied after blur and noise, as a camera does; the rig then says encoding = "srgb").
    encoding: str = "linear"
    supersample: int = 8  # supersample x supersample samples in pixels within 1 px of an edge

    def __post_init__(self) -> None:
        travel_sign(self.travel)
        if self.width < 8 or self.height < 8:
            raise ValueError(f"Scene needs width, height >= 8 px, got {self.width}x{self.height}")
        if not self.radius_px > 0 or not self.wheel_radius_mm > 0:
            raise ValueError(
                f"Scene needs radius_px > 0 and wheel_radius_mm > 0, got {self.radius_px} and "
                f"{self.wheel_radius_mm}"
            )
        if self.supersample < 1:
            raise ValueError(f"Scene.supersample must be >= 1, got {self.supersample}")
        if self.encoding not in ENCODINGS:
            raise ValueError(f'Scene.encoding must be "linear" or "srgb", got {self.encoding!r}')
        if not 0 <= self.jpeg_quality <= 100:
            raise ValueError(f"Scene.jpeg_quality must be 0 (PNG) to 100, got {self.jpeg_quality}")
        if self.n_lugs and not 0 < self.lug_width_px < math.pi * self.radius_px / self.n_lugs:
            # Labelling tests each point against its nearest lug only; that needs narrow lugs.
            raise ValueError(
                "Scene.lug_width_px must be > 0 and under half the lug pitch "
                f"(2 pi r / n_lugs / 2 = {math.pi * self.radius_px / self.n_lugs:.2f} px), "
                f"got {self.lug_width_px}"
            )


def surface_y_px(scene: Scene, x_px: Float[np.ndarray, "*n"]) -> Float[np.ndarray, "*n"]:
    """The exact soil surface: image y (px, down) at image x (px), any shape, float64."""
    dx = np.asarray(x_px, dtype=np.float64) - scene.centre_x_px
    y = scene.soil_level_px + scene.tilt * dx
    if scene.bump_height_px:
        y = y - scene.bump_height_px * np.exp(
            -0.5 * ((dx - scene.bump_dx_px) / scene.bump_sigma_px) ** 2
        )
    if scene.rut_depth_px:
        s = scene.rut_side * (dx - scene.rut_dx_px) / scene.rut_width_px
        y = y + scene.rut_depth_px * 0.5 * (1.0 + np.tanh(s))
    for amp, wavelength, phase in scene.rough:
        y = y + amp * np.sin(2.0 * np.pi * dx / wavelength + phase)
    return np.asarray(y)  # a 0-d array, not a NumPy scalar, for 0-d input


def mirrored(scene: Scene) -> Scene:
    """The left-right mirror image of ``scene``, travelling the other way (same truth)."""
    lx, ly = scene.light_dir
    sx, sy = scene.shadow_offset_px
    return replace(
        scene,
        centre_x_px=scene.width - 1 - scene.centre_x_px,
        travel="left" if scene.travel == "right" else "right",
        tilt=-scene.tilt,
        bump_dx_px=-scene.bump_dx_px,
        rut_dx_px=-scene.rut_dx_px,
        rut_side=-scene.rut_side,
        rough=tuple((a, -w, p) for a, w, p in scene.rough),
        phase_rad=math.pi - scene.phase_rad,
        light_dir=(-lx, ly),
        specular=tuple((-dx, dy, sg, am) for dx, dy, sg, am in scene.specular),
        shadow_offset_px=(-sx, sy),
    )


def hsv_rgb(h_deg: float, s: float, v: float) -> tuple[float, float, float]:
    """A colour from hue (degrees, wrapped), saturation and value (clipped to [0, 1]) as RGB."""
    r, g, b = colorsys.hsv_to_rgb(
        (h_deg % 360.0) / 360.0, min(max(s, 0.0), 1.0), min(max(v, 0.0), 1.0)
    )
    return (r, g, b)


def hue_gap_deg(a: float, b: float) -> float:
    """The circular distance between two hues, in degrees (0-180)."""
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)
