"""Wheels without hue: black (rubber, 3D-printed) and bare-metal (aluminium) presets.

Flight and test-bed wheels are often black or bare aluminium, which the paper's hue/saturation
test cannot see. Each set-up here starts from a ``full`` one (placement, holes, lamp, sensor,
JPEG) and repaints it:

- ``black_wheel``: a near-black wheel (value 0.04-0.12, saturation under 0.05), grousered
  (always lugs), a weak broad sheen instead of sharp highlights, a mid-to-light wall;
- ``metal_wheel``: bare aluminium (value 0.6-0.85, saturation under 0.05, a cool tint), strong
  specular highlights, a darker backdrop (a bright wheel against a bright grey wall shows no
  rim at all, in any method);
- ``hard_black`` / ``hard_metal``: the same with strong one-sided shading, a dark cast shadow,
  heavier sensor noise and a little soil dust on the lower wheel.

Soils are grey (saturation under 0.08, a fine grain texture) or brown (the ``full`` preset's
brown and sand soils), half each; every set-up casts a shadow on the soil. Recordings of these
presets cycle the ordinary terrains. The existing presets are untouched: a set-up draws from
the generator only after the ``full`` set-up it starts from.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .scene import Scene, hsv_rgb as _hsv

MATERIAL_PRESETS: tuple[str, ...] = ("black_wheel", "metal_wheel", "hard_black", "hard_metal")
# Brown soils: (hue range, saturation range, value range), as the ``full`` preset's.
_BROWN_SOILS = (((22, 32), (0.32, 0.48), (0.35, 0.50)), ((33, 43), (0.25, 0.40), (0.55, 0.75)))


def _with_lugs(rng: np.random.Generator, base: Scene) -> Scene:
    """``base`` with grousers if it has none, as tall as its margins allow."""
    if base.n_lugs:
        return base
    u = rng.uniform
    r, cy, cx = base.radius_px, base.centre_y_px, base.centre_x_px
    n = int(rng.integers(12, 31))
    room = min(cy - r - 4, cx - r - 4, base.width - cx - r - 4)
    lug_h = min(u(0.03, 0.08) * r, max(room, 0.0))
    if lug_h < 1.0:
        return base
    pitch = 2 * math.pi * r / n
    lug_w = max(min(u(0.15, 0.35) * pitch, 0.12 * r), min(2.0, 0.4 * pitch))
    return replace(base, n_lugs=n, lug_height_px=lug_h, lug_width_px=lug_w)


def _soil(rng: np.random.Generator) -> dict[str, object]:
    u = rng.uniform
    if u(0, 1) < 0.5:
        hue, sat, val = u(0, 360), u(0.0, 0.08), u(0.3, 0.55)
        texture = u(0.15, 0.3)  # grey sand and regolith simulant: visible grain
    else:
        (h0, h1), (s0, s1), (v0, v1) = _BROWN_SOILS[int(rng.integers(len(_BROWN_SOILS)))]
        hue, sat, val = u(h0, h1), u(s0, s1), u(v0, v1)
        texture = u(0.1, 0.25)
    return {
        "soil_rgb": _hsv(hue, sat, val),
        "soil_rgb2": _hsv(hue + u(-6, 6), sat * u(0.8, 1.15), val * u(0.85, 1.05)),
        "soil_texture": texture,
    }


def _paint(rng: np.random.Generator, black: bool) -> dict[str, object]:
    """Wheel, rim, lug, hub and hole colours, and the highlights, of a black or metal wheel."""
    u = rng.uniform
    if black:
        hue, sat, val = u(0, 360), u(0.0, 0.05), u(0.04, 0.12)
        hub = _hsv(u(0, 360), u(0.0, 0.05), u(0.25, 0.45))  # a metal hub on a rubber wheel
        wall = _hsv(u(0, 360), u(0.02, 0.1), u(0.4, 0.8))
        n_spec, amp, size = int(rng.integers(0, 3)), (0.05, 0.2), (0.1, 0.25)
    else:
        hue, sat, val = u(190, 230), u(0.0, 0.05), u(0.6, 0.85)
        hub = _hsv(hue, sat, val * u(0.6, 0.8))
        wall = _hsv(u(0, 360), u(0.02, 0.15), u(0.12, 0.4))
        n_spec, amp, size = int(rng.integers(3, 9)), (0.3, 0.8), (0.01, 0.06)
    return {
        "wheel_rgb": _hsv(hue, sat, val),
        "rim_rgb": _hsv(hue, sat, val * u(0.85, 1.1)),
        "lug_rgb": _hsv(hue, sat, val * u(0.9, 1.15)),
        "hub_rgb": hub,
        "hole_rgb": _hsv(u(0, 360), u(0.0, 0.1), u(0.02, 0.08)),
        "wall_rgb": wall,
        "_spec": (n_spec, amp, size),
    }


def repaint(rng: np.random.Generator, base: Scene, preset: str) -> Scene:
    """``base`` (a ``full`` set-up) made into a ``preset`` set-up (one of
    :data:`MATERIAL_PRESETS`)."""
    if preset not in MATERIAL_PRESETS:
        raise ValueError(f"preset must be one of {MATERIAL_PRESETS}, got {preset!r}")
    u = rng.uniform
    r = base.radius_px
    scene = _with_lugs(rng, base)
    kw = _paint(rng, black=preset in ("black_wheel", "hard_black"))
    spec_kind: tuple[int, tuple[float, float], tuple[float, float]] = kw.pop("_spec")  # type: ignore[assignment]
    n_spec, amp, size = spec_kind
    spec = []
    for _ in range(n_spec):
        rr, aa = r * 0.9 * math.sqrt(u(0, 1)), u(0, 2 * math.pi)
        spec.append((rr * math.cos(aa), rr * math.sin(aa), u(*size) * r + 2.0, u(*amp)))
    kw["specular"] = tuple(spec)
    kw.update(_soil(rng))
    lx, ly = base.light_dir
    off = u(0.1, 0.3) * r
    kw.update(
        shadow_factor=u(0.4, 0.7),
        shadow_offset_px=(-lx * off, -ly * off),
        shadow_soft_px=u(2, 8),
        lamp_white=0.0,
    )
    if preset.startswith("hard_"):
        off = u(0.15, 0.35) * r
        kw.update(
            shading=u(0.5, 0.8),
            shadow_factor=u(0.25, 0.45),
            shadow_offset_px=(-lx * off, -ly * off),
            noise_std=u(3.0, 6.0),
            dust=u(0.15, 0.35),
            dust_top_frac=u(0.5, 0.8),
        )
    return replace(scene, **kw)  # type: ignore[arg-type]
