"""Hard footage to develop against (issue 12): the ``hard_*`` presets and the ``hollow_ahead``
terrain.

Each hard camera set-up starts from a ``full`` one (lugs, holes, shadows, JPEG) and then makes
it worse, as unseen test-bed footage is: a wheel of any hue (a quarter of them grey-ish, barely
more saturated than the soil), strong specular highlights on the wheel, and per preset

- ``hard_dust``: soil-coloured dust over most of the lower wheel, up to nearly the soil's colour;
- ``hard_cast``: a colour cast towards the wheel's own hue, strong enough to tint the soil
  towards it (the hue gap between wheel and soil shrinks to a few tens of degrees);
- ``hard_shading``: strong one-sided shading (the far side of the face near black), a white lamp
  glow on the near side and a dark cast shadow on the soil;
- ``hard_lowlight``: 12-25 % exposure, a black-level pedestal and heavy sensor noise;
- ``hard_mix``: two of the above, drawn per set-up, at slightly milder strengths.

Recordings of hard presets add the ``hollow_ahead`` terrain to the cycle: a hollow behind the
wheel's lowest point, so the soil touches only the entry half of the rim and B lies ahead of O
(theta2 < 0 in the atan2 form of docs/conventions.md §1). The existing presets are untouched: a
hard set-up draws from the generator only after the ``full`` set-up it starts from.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import replace

import numpy as np

from .scene import Scene, hsv_rgb as _hsv, hue_gap_deg as _hue_gap, surface_y_px
from .truth import boundary_points, n_rim_crossings, true_geometry

HARD_PRESETS: tuple[str, ...] = (
    "hard_dust",
    "hard_cast",
    "hard_shading",
    "hard_lowlight",
    "hard_mix",
)
HOLLOW_AHEAD = "hollow_ahead"
# The wheel's hue keeps at least this gap (degrees) to the soil's before any cast.
_MIN_HUE_GAP_DEG = 25.0


def _paint(rng: np.random.Generator, soil_hue_deg: float) -> dict[str, object]:
    """Wheel, rim, lug and hub colours of any hue away from the soil's; 1 in 4 grey-ish."""
    u = rng.uniform
    hue = u(0, 360)
    for _ in range(100):
        if _hue_gap(hue, soil_hue_deg) >= _MIN_HUE_GAP_DEG:
            break
        hue = u(0, 360)
    sat = u(0.3, 0.45) if u(0, 1) < 0.25 else u(0.55, 0.95)
    val = u(0.5, 0.9)
    return {
        "wheel_rgb": _hsv(hue, sat, val),
        "rim_rgb": _hsv(hue, sat * u(0.95, 1.05), val * u(0.75, 0.85)),
        "lug_rgb": _hsv(hue + u(-3, 3), sat * u(0.85, 1.0), val * u(0.85, 0.95)),
        "hub_rgb": _hsv(hue, sat * u(0.1, 0.35), val * u(0.5, 0.75)),
        "_hue": hue,
    }


def harden(rng: np.random.Generator, base: Scene, preset: str) -> Scene:
    """``base`` (a ``full`` set-up) made into a ``preset`` set-up (one of :data:`HARD_PRESETS`)."""
    if preset not in HARD_PRESETS:
        raise ValueError(f"preset must be one of {HARD_PRESETS}, got {preset!r}")
    u = rng.uniform
    r = base.radius_px
    soil_h = colorsys.rgb_to_hsv(*base.soil_rgb)[0] * 360.0
    kw = _paint(rng, soil_h)
    hue = float(kw.pop("_hue"))  # type: ignore[arg-type]
    spec = []
    for _ in range(int(rng.integers(3, 9))):
        rr, aa = r * 0.9 * math.sqrt(u(0, 1)), u(0, 2 * math.pi)
        spec.append((rr * math.cos(aa), rr * math.sin(aa), u(2.0, max(3.0, 0.08 * r)), u(0.4, 0.9)))
    kw["specular"] = tuple(spec)
    effects = ("hard_dust", "hard_cast", "hard_shading", "hard_lowlight")
    mixed = (
        set(rng.choice(effects, size=2, replace=False).tolist()) if preset == "hard_mix" else set()
    )
    f = 0.85 if mixed else 1.0  # the mix combines two effects at slightly milder strengths
    if preset == "hard_dust" or "hard_dust" in mixed:
        kw["dust"], kw["dust_top_frac"] = f * u(0.65, 0.9), u(0.05, 0.3)
    if preset == "hard_cast" or "hard_cast" in mixed:
        c = np.asarray(_hsv(hue, 1.0, 1.0))
        d = 2 * c - 1 - (2 * c - 1).mean()
        kw["cast_rgb"] = tuple(float(g) for g in 1 + f * u(0.2, 0.35) * d)
    if preset == "hard_shading" or "hard_shading" in mixed:
        lx, ly = base.light_dir
        off = u(0.15, 0.35) * r
        kw.update(
            shading=f * u(0.7, 1.0),
            lamp_white=f * u(0.4, 0.7),
            shadow_factor=1 - f * u(0.55, 0.8),
            shadow_offset_px=(-lx * off, -ly * off),
            shadow_soft_px=u(2, 8),
        )
    if preset == "hard_lowlight" or "hard_lowlight" in mixed:
        kw.update(
            gain=u(0.12, 0.25) / f,
            noise_std=f * u(4.0, 9.0),
            black_level=f * u(6.0, 16.0),
        )
    return replace(base, **kw)  # type: ignore[arg-type]


def with_hollow_ahead(rng: np.random.Generator, base: Scene) -> Scene | None:
    """``base`` (travelling right) sunk into the front slope of a hollow: B ahead of O.

    A Gaussian hollow centred behind the lowest rim point drops the soil below the rim there;
    the soil re-enters the rim on the entry side. Returns None when no sample fits the image.
    """
    u = rng.uniform
    r, cy = base.radius_px, base.centre_y_px
    for _ in range(60):
        z = u(0.03, 0.2) * r  # how far the flat level stands above the rim's bottom
        sigma = u(0.25, 0.45) * r
        centre = -u(0.0, 0.3) * r
        depth = (z + u(0.02, 0.1) * r) / math.exp(-0.5 * (centre / sigma) ** 2)
        scene = replace(
            base,
            terrain=HOLLOW_AHEAD,
            phase_rad=float(u(0, 2 * math.pi)),
            soil_level_px=cy + r - z,
            tilt=u(-0.15, 0.05),
            bump_height_px=-depth,
            bump_dx_px=centre,
            bump_sigma_px=sigma,
        )
        if n_rim_crossings(scene) != 2:
            continue
        t = true_geometry(scene)
        _, y = boundary_points(scene)
        surf = surface_y_px(scene, np.arange(scene.width, dtype=np.float64))
        if (
            t.b_end_px[0] > 0.03 * r
            and t.a_px[0] > t.b_end_px[0] + 0.1 * r
            and y.min() > cy + 0.12 * r
            and surf.max() < scene.height - 3
        ):
            return scene
    return None
