"""Random scenes: camera set-ups per preset (wheel paint, soil and wall colours, lamp, sensor) and
terrains of each kind with a sampled sinkage; :func:`random_scene` and :func:`recording_scenes`.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ..geometry import travel_sign
from .hard import HARD_PRESETS, HOLLOW_AHEAD, harden, with_hollow_ahead
from .materials import MATERIAL_PRESETS, repaint
from .scene import Scene, hsv_rgb as _hsv, hue_gap_deg as _hue_gap, mirrored, surface_y_px
from .truth import boundary_points, n_rim_crossings, true_geometry

# The hard presets (synth/hard.py) and the black and metal wheels (synth/materials.py) come
# last; the others render as they always have.
PRESETS: tuple[str, ...] = (
    "clean",
    "full",
    "shading",
    "dust",
    "cast",
    "lowlight",
    *HARD_PRESETS,
    *MATERIAL_PRESETS,
)
TERRAINS: tuple[str, ...] = ("flat", "bulldozed", "raised", "hollow", "rough")

# Hue ranges (degrees) of the wheel paints; red straddles 0/360 on purpose (hue wrap-around).
_WHEEL_HUES = {
    "gold": (44, 56),
    "orange": (20, 32),
    "red": (-8, 8),
    "blue": (205, 230),
    "green": (100, 140),
}
# Soils: (hue range, saturation range, value range); all less saturated than any wheel paint.
_SOILS = {
    "sand": ((33, 43), (0.25, 0.40), (0.55, 0.75)),
    "brown": ((22, 32), (0.32, 0.48), (0.35, 0.50)),
    "grey-orange": ((16, 26), (0.15, 0.25), (0.50, 0.65)),
    "reddish-grey": ((2, 14), (0.18, 0.30), (0.45, 0.60)),
}
_MIN_HUE_GAP_DEG = 12.0


def camera_setup(rng: np.random.Generator, width: int, height: int, preset: str) -> Scene:
    """One camera set-up: wheel placement and paint, soil and wall colours, lamp, sensor."""
    if preset not in PRESETS:
        raise ValueError(f"preset must be one of {PRESETS}, got {preset!r}")
    if preset in HARD_PRESETS:
        return harden(rng, camera_setup(rng, width, height, "full"), preset)
    if preset in MATERIAL_PRESETS:
        return repaint(rng, camera_setup(rng, width, height, "full"), preset)
    if width < 64 or height < 64:
        raise ValueError(f"image must be at least 64x64 px, got {width}x{height}")
    u = rng.uniform
    m = min(width, height)
    clean = preset == "clean"
    n_lugs = 0 if clean else int(rng.integers(0, 31))
    soil_below = max(0.1 * height, 24.0)
    r = u(0.27, 0.4) * m
    lug_h = u(0.03, 0.1) * r if n_lugs else 0.0
    # Shrink until the wheel with lugs fits with a margin above and soil visible below.
    while 2 * r + lug_h + 4 + soil_below > height or 2 * (r + lug_h + 4) > width:
        r *= 0.95
        lug_h *= 0.95
    lug_w = 0.0
    if n_lugs:
        pitch = 2 * math.pi * r / n_lugs
        lug_w = min(u(0.15, 0.35) * pitch, 0.12 * r)
        lug_w = max(lug_w, min(2.0, 0.4 * pitch))
    cy = u(r + lug_h + 4, height - r - soil_below)
    x_lo, x_hi = r + lug_h + 4, width - r - lug_h - 4
    cx = float(np.clip(width / 2 + u(-0.12, 0.12) * width, x_lo, x_hi))

    paint = list(_WHEEL_HUES)[int(rng.integers(len(_WHEEL_HUES)))]
    hue = u(*_WHEEL_HUES[paint]) % 360.0
    sat, val = u(0.65, 0.95), u(0.6, 0.9)
    wheel = _hsv(hue, sat, val)
    rim = _hsv(hue, sat * u(0.95, 1.05), val * u(0.75, 0.85))
    lug = _hsv(hue + u(-3, 3), sat * u(0.85, 1.0), val * u(0.85, 0.95))
    hub = _hsv(hue, sat * u(0.1, 0.35), val * u(0.5, 0.75))
    hole = _hsv(u(0, 360), u(0.03, 0.15), u(0.06, 0.2))
    for _ in range(100):
        kind = list(_SOILS)[int(rng.integers(len(_SOILS)))]
        (h0, h1), (s0, s1), (v0, v1) = _SOILS[kind]
        soil_hue = u(h0, h1)
        if _hue_gap(soil_hue, hue) >= _MIN_HUE_GAP_DEG:
            break
    soil_s, soil_v = u(s0, s1), u(v0, v1)
    soil = _hsv(soil_hue, soil_s, soil_v)
    soil2 = _hsv(soil_hue + u(-6, 6), soil_s * u(0.8, 1.15), soil_v * u(0.85, 1.05))
    wall = _hsv(u(0, 360), u(0.02, 0.1), u(0.35, 0.8))

    rim_w = max(3.0, u(0.05, 0.09) * r)
    hub_r = u(0.1, 0.16) * r
    n_holes = int(rng.integers(0, 9))
    hole_r = hole_ring = 0.0
    if n_holes:
        # Holes in a ring leaving a clear band above the hub for the confidence rectangle.
        hole_r = u(0.07, 0.12) * r
        lo, hi = hub_r + 0.26 * r + hole_r, r - rim_w - 0.05 * r - hole_r
        hole_ring = u(lo, max(lo, hi))
        if n_holes > 1:
            hole_r = min(hole_r, hole_ring * math.sin(math.pi / n_holes) - 3)
        if hole_r < 2:
            n_holes, hole_r, hole_ring = 0, 0.0, 0.0

    ang = math.radians(u(200, 340))  # the lamp is above the wheel, left or right
    light = (math.cos(ang), math.sin(ang))
    shading = u(0.1, 0.25) if clean else u(0.1, 0.35)
    lamp_white = 0.0
    specular: tuple[tuple[float, float, float, float], ...] = ()
    shadow_factor, shadow_off, soft = 1.0, (0.0, 0.0), 4.0
    if not clean:
        spec = []
        for _ in range(int(rng.integers(0, 5))):
            rr, aa = r * 0.8 * math.sqrt(u(0, 1)), u(0, 2 * math.pi)
            spec.append(
                (rr * math.cos(aa), rr * math.sin(aa), u(2.0, max(2.5, 0.06 * r)), u(0.25, 0.7))
            )
        specular = tuple(spec)
        if u(0, 1) < 0.8:
            off = u(0.1, 0.3) * r
            shadow_factor, shadow_off, soft = (
                u(0.35, 0.7),
                (-light[0] * off, -light[1] * off),
                u(2, 8),
            )
    noise = u(0.5, 1.5) if clean else u(1.0, 4.0)
    blur = u(0.3, 0.6) if clean else u(0.0, 1.0)
    jpeg = 0 if clean else int(rng.integers(70, 96))
    dust, dust_top, cast, gain, black = 0.0, 0.3, (1.0, 1.0, 1.0), 1.0, 0.0
    if preset == "shading":
        shading, lamp_white = u(0.5, 0.8), u(0.35, 0.7)
    elif preset == "dust":
        dust, dust_top = u(0.6, 0.9), u(0.0, 0.35)
    elif preset == "cast":
        c = np.asarray(_hsv(u(0, 360), 1.0, 1.0))
        cast = tuple(float(g) for g in 1 + u(0.2, 0.4) * (2 * c - 1 - (2 * c - 1).mean()))  # type: ignore[assignment]
    elif preset == "lowlight":
        gain, noise, black = u(0.1, 0.25), u(4.0, 10.0), u(6.0, 16.0)
    return Scene(
        width=width,
        height=height,
        centre_x_px=cx,
        centre_y_px=cy,
        radius_px=r,
        wheel_rgb=wheel,
        rim_rgb=rim,
        rim_width_px=rim_w,
        lug_rgb=lug,
        n_lugs=n_lugs,
        lug_height_px=lug_h,
        lug_width_px=lug_w,
        hub_radius_px=hub_r,
        hub_rgb=hub,
        n_holes=n_holes,
        hole_radius_px=hole_r,
        hole_ring_px=hole_ring,
        hole_rgb=hole,
        soil_rgb=soil,
        soil_rgb2=soil2,
        soil_texture=u(0.08, 0.2),
        pebbles=int(u(50, 250) * width * height / (640 * 480)),
        wall_rgb=wall,
        wall_gradient=u(0.05, 0.3),
        face_texture=u(0.01, 0.04),
        light_dir=light,
        shading=shading,
        lamp_white=lamp_white,
        specular=specular,
        shadow_factor=shadow_factor,
        shadow_offset_px=shadow_off,
        shadow_soft_px=soft,
        dust=dust,
        dust_top_frac=dust_top,
        cast_rgb=cast,
        gain=gain,
        black_level=black,
        noise_std=noise,
        blur_sigma_px=blur,
        jpeg_quality=jpeg,
    )


def _sample_sinkage_mm(rng: np.random.Generator) -> float:
    """About 12 % of contact frames below 5 mm, the rest spread over 5-50 mm (R = 140 mm)."""
    return rng.uniform(0.5, 5.0) if rng.random() < 0.12 else rng.uniform(5.0, 50.0)


def _terrain_features(
    rng: np.random.Generator, kind: str, r: float, z0: float
) -> dict[str, object]:
    """Terrain parameters for a wheel travelling right (entry at +dx), heights in px."""
    u = rng.uniform
    half = math.sqrt(max(2 * r * z0 - z0 * z0, 1.0))  # half chord of the flat-ground contact
    if kind == "flat":
        return {}
    if kind == "bulldozed":
        return {
            "bump_height_px": u(0.03, 0.1) * r,
            "bump_dx_px": half + u(0.0, 0.3) * r,
            "bump_sigma_px": u(0.12, 0.25) * r,
            "rut_depth_px": u(0.3, 0.8) * z0,
            "rut_dx_px": -half * u(0.6, 1.1),
            "rut_width_px": u(0.05, 0.15) * r,
            "rut_side": -1.0,
        }
    if kind in ("raised", "hollow"):
        sign = 1.0 if kind == "raised" else -1.0
        return {
            "bump_height_px": sign * u(0.03, 0.12) * r,
            "bump_dx_px": u(-0.5, 0.5) * r,
            "bump_sigma_px": u(0.3, 0.8) * r,
        }
    if kind == "rough":
        n = int(rng.integers(3, 6))
        amps = u(0.3, 1.0, n) / np.arange(1, n + 1)
        amps *= u(0.015, 0.04) * r / amps.sum()
        return {
            "tilt": u(-0.05, 0.05),
            "rough": tuple(
                (float(a), float(u(0.25, 1.5) * r * rng.choice([-1, 1])), float(u(0, 2 * math.pi)))
                for a in amps
            ),
        }
    raise ValueError(f"terrain must be one of {TERRAINS}, got {kind!r}")


def _ok_contact(scene: Scene) -> bool:
    """A usable contact frame: two rim crossings, A and B on either side of the lowest point, soil
    below the hub (the confidence rectangle is above it) and above the image's bottom."""
    if n_rim_crossings(scene) != 2:
        return False
    t = true_geometry(scene)
    _, y = boundary_points(scene)
    surf = surface_y_px(scene, np.arange(scene.width, dtype=np.float64))
    # Eqs. 2-3 assume x_A > 0 > x_B: a contact patch entirely on one side of the lowest point
    # would give an exit angle near 180 deg that jumps to 0 as x_B crosses 0.
    straddles = t.a_px[0] > 0.02 * scene.radius_px and t.b_end_px[0] < -0.02 * scene.radius_px
    return bool(
        straddles
        and y.min() > scene.centre_y_px + 0.12 * scene.radius_px
        and surf.max() < scene.height - 3
    )


def with_terrain(rng: np.random.Generator, base: Scene, kind: str, contact: bool) -> Scene:
    """``base`` with a sampled terrain of ``kind``, sinkage and wheel phase (travel right)."""
    r, cy = base.radius_px, base.centre_y_px
    scene = base
    for attempt in range(30):
        z0 = _sample_sinkage_mm(rng) * r / base.wheel_radius_mm
        feats = _terrain_features(rng, kind, r, z0) if attempt < 25 else {}
        scene = replace(
            base,
            terrain=kind,
            phase_rad=float(rng.uniform(0, 2 * math.pi)),
            soil_level_px=cy + r - z0,
            **feats,  # type: ignore[arg-type]
        )
        if not contact:
            # Lower the whole surface until it clears the rim by a few pixels.
            xs = np.linspace(base.centre_x_px - r, base.centre_x_px + r, 801)
            rim_bottom = cy + np.sqrt(np.maximum(r * r - (xs - base.centre_x_px) ** 2, 0))
            clearance = float(np.min(surface_y_px(scene, xs) - rim_bottom))
            scene = replace(
                scene, soil_level_px=scene.soil_level_px - clearance + rng.uniform(1.5, 15)
            )
            surf = surface_y_px(scene, np.arange(scene.width, dtype=np.float64))
            if n_rim_crossings(scene) == 0 and surf.max() < scene.height - 3:
                return scene
            continue
        # Newton-like steps on the level: lowering the surface by d lowers z0 by about d.
        for _ in range(6):
            t = true_geometry(scene)
            step = t.sinkage_px - z0 if t.contact else -max(1.0, z0)
            scene = replace(scene, soil_level_px=scene.soil_level_px + step)
            if abs(step) < 1e-3:
                break
        if _ok_contact(scene):
            return scene
    raise RuntimeError(
        "could not sample a valid terrain; the wheel leaves too little room for soil"
    )


def random_scene(
    rng: np.random.Generator,
    *,
    width: int = 640,
    height: int = 480,
    preset: str = "full",
    travel: str = "right",
) -> Scene:
    """One random frame: its own camera set-up, terrain kind, sinkage (~3 % no contact), phase."""
    base = camera_setup(rng, width, height, preset)
    kinds = _terrain_kinds(preset)
    kind = kinds[int(rng.integers(len(kinds)))]
    scene = _frame(rng, base, kind, contact=rng.random() >= 0.03)
    return mirrored(scene) if travel_sign(travel) < 0 else scene


def _terrain_kinds(preset: str) -> tuple[str, ...]:
    return (*TERRAINS, HOLLOW_AHEAD) if preset in HARD_PRESETS else TERRAINS


def _frame(rng: np.random.Generator, base: Scene, kind: str, contact: bool) -> Scene:
    """:func:`with_terrain`, plus the hard presets' ``hollow_ahead`` (a plain hollow where the
    image leaves no room for one, or without contact)."""
    if kind != HOLLOW_AHEAD:
        return with_terrain(rng, base, kind, contact)
    scene = with_hollow_ahead(rng, base) if contact else None
    return scene if scene is not None else with_terrain(rng, base, "hollow", contact)


def recording_scenes(
    rng: np.random.Generator,
    n_frames: int,
    *,
    preset: str = "full",
    width: int = 640,
    height: int = 480,
    travel: str = "right",
) -> list[Scene]:
    """Frames of ONE camera set-up (same wheel, centre, radius, colours, lamp, sensor).

    Terrain kinds cycle flat, bulldozed, raised, hollow, rough (and ``hollow_ahead`` for the
    hard presets); sinkage, terrain details and the wheel phase vary per frame; about 3 % of
    frames have no contact.
    """
    s = travel_sign(travel)
    base = camera_setup(rng, width, height, preset)
    kinds = _terrain_kinds(preset)
    scenes = []
    for i in range(n_frames):
        scene = _frame(rng, base, kinds[i % len(kinds)], contact=rng.random() >= 0.03)
        scenes.append(mirrored(scene) if s < 0 else scene)
    return scenes
