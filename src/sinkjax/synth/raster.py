"""Appearance and rendering: wall, soil and wheel colours weighted by the layer coverages, then
lighting, sensor (blur, noise, black level) and encoding.

Everything is vectorised numpy (OpenCV for resizing, blur, pebbles and JPEG); one 640x480 frame
takes about 0.1 s on one core (``experiments/synth_speed.py``).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from jaxtyping import UInt8
from numpy.typing import NDArray

from .layers import BG, FACE, HOLE, HUB, LUG, N_LAYERS, RIM, SOIL, WHEEL_LAYERS, coverage_parts
from .scene import Scene, surface_y_px
from .truth import Truth, true_geometry


def _smooth_noise(
    rng: np.random.Generator, hgt: int, wid: int, cell_px: float
) -> NDArray[np.float32]:
    """Zero-mean, roughly unit-std noise smooth over ``cell_px``, (hgt, wid) float32."""
    gh, gw = max(2, round(hgt / cell_px) + 1), max(2, round(wid / cell_px) + 1)
    small = rng.standard_normal((gh, gw)).astype(np.float32)
    return np.asarray(cv2.resize(small, (wid, hgt), interpolation=cv2.INTER_CUBIC), np.float32)


def _layer_tables(
    scene: Scene,
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """Per-layer albedo (7, 3), specular weight (7,) and wheel membership (7,)."""
    alb = np.zeros((N_LAYERS, 3), dtype=np.float32)
    alb[FACE], alb[RIM], alb[LUG] = scene.wheel_rgb, scene.rim_rgb, scene.lug_rgb
    alb[HUB], alb[HOLE] = scene.hub_rgb, scene.hole_rgb
    spec = np.array([0, 1, 1, 0.8, 0.7, 0.05, 0], dtype=np.float32)
    wheel = np.zeros(N_LAYERS, dtype=np.float32)
    wheel[list(WHEEL_LAYERS)] = 1
    return alb, spec, wheel


def _soil_image(
    scene: Scene, rng: np.random.Generator, dyc: NDArray[np.float32], dxr: NDArray[np.float32]
) -> NDArray[np.float32]:
    """Textured soil colour on rows ``dyc`` (n, 1) x columns ``dxr`` (1, W), O-relative px: two-tone
    hue field, multi-scale intensity noise, lamp gradient, pebbles and the wheel's cast shadow."""
    hgt, wid = dyc.shape[0], dxr.shape[1]
    t = np.clip(0.5 + 0.35 * _smooth_noise(rng, hgt, wid, 90), 0, 1)[..., None]
    c1, c2 = np.asarray(scene.soil_rgb, np.float32), np.asarray(scene.soil_rgb2, np.float32)
    soil = c1 + t * (c2 - c1)
    tex = 0.5 * _smooth_noise(rng, hgt, wid, 40) + 0.35 * _smooth_noise(rng, hgt, wid, 10)
    tex += 0.3 * _smooth_noise(rng, hgt, wid, 2.5)
    lx, ly = scene.light_dir
    lit = 1 + 0.5 * scene.shading * (dxr * lx + dyc * ly) / scene.radius_px
    soil *= (lit * (1 + scene.soil_texture * tex))[..., None]
    if scene.pebbles:
        # Pebbles: a darker ellipse offset away from the lamp (the pebble's shadow), then the stone.
        n = round(scene.pebbles * hgt / scene.height)
        px, py = rng.uniform(0, wid, n), rng.uniform(0, hgt, n)
        ax = rng.uniform(0.8, 4.0, n)
        ay = ax * rng.uniform(0.5, 0.9, n)
        tone = rng.uniform(0.7, 1.4, n)
        ang = rng.uniform(0, 180, n)
        for i in range(n):
            c = (round(px[i]), round(py[i]))
            axes = (max(1, round(ax[i])), max(1, round(ay[i])))
            base = soil[min(hgt - 1, c[1]), min(wid - 1, c[0])]
            shadow_c = (round(px[i] - lx * 1.2), round(py[i] - ly * 1.2))
            cv2.ellipse(soil, shadow_c, axes, ang[i], 0, 360, (base * 0.7).tolist(), -1)
            cv2.ellipse(soil, c, axes, ang[i], 0, 360, (base * tone[i]).tolist(), -1)
    if scene.shadow_factor < 1:
        sx, sy = scene.shadow_offset_px
        ds = np.sqrt((dxr - sx) ** 2 + (dyc - sy) ** 2)
        reach = scene.radius_px + 0.6 * scene.lug_height_px
        mask = np.clip((reach - ds) / max(scene.shadow_soft_px, 1e-3) + 0.5, 0, 1)
        # Skylight fills the shadow: it darkens red most and blue least (a slight blue shift).
        dark = (1 - scene.shadow_factor) * mask[..., None]
        soil *= 1 - dark * np.array([1.0, 0.96, 0.8], np.float32)
    return soil


def _wheel_image(
    scene: Scene,
    rng: np.random.Generator,
    lab: NDArray[np.int8],
    edges: tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float32]],
    dyc: NDArray[np.float32],
    dxr: NDArray[np.float32],
) -> NDArray[np.float32]:
    """Coverage-weighted wheel colour (all wheel layers) on a window: albedo x shading + white
    (lamp glow, highlights), blended towards dust. ``lab`` and ``edges`` are window-relative."""
    hgt, wid = lab.shape
    r = scene.radius_px
    rows, cols, frac = edges
    alb_t, spec_t, wheel_t = _layer_tables(scene)
    alb, spec_w = alb_t[lab], spec_t[lab]
    alb[rows, cols] = frac @ alb_t
    spec_w[rows, cols] = frac @ spec_t
    lx, ly = scene.light_dir
    shade = np.maximum(1 + scene.shading * (dxr * lx + dyc * ly) / r, 0.12)
    shade = shade * (1 + scene.face_texture * _smooth_noise(rng, hgt, wid, 60))
    white = np.zeros((hgt, wid), dtype=np.float32)
    if scene.lamp_white:
        px, py, sg = 0.75 * r * lx, 0.75 * r * ly, 0.5 * r
        white += scene.lamp_white * np.exp(-((dxr - px) ** 2 + (dyc - py) ** 2) / (2 * sg * sg))
    for sdx, sdy, sg, amp in scene.specular:
        white += amp * np.exp(-((dxr - sdx) ** 2 + (dyc - sdy) ** 2) / (2 * sg * sg))
    wheel = alb * shade[..., None] + (spec_w * white)[..., None]
    if scene.dust:
        wheel_w = wheel_t[lab]
        wheel_w[rows, cols] = frac @ wheel_t
        ramp = np.clip((dyc - scene.dust_top_frac * r) / ((1 - scene.dust_top_frac) * r), 0, 1)
        patch = np.clip(1 + 0.35 * _smooth_noise(rng, hgt, wid, 25), 0, 1.5)
        dust = np.clip(scene.dust * ramp * patch, 0, 1)
        dust_rgb = np.asarray(scene.soil_rgb, np.float32) * 1.05
        # Linear in the layer fractions, so anti-aliased edges keep their 50 % crossing.
        wheel = wheel * (1 - dust)[..., None] + (wheel_w * dust * shade)[..., None] * dust_rgb
    return wheel


def _compose(scene: Scene, rng: np.random.Generator) -> NDArray[np.float32]:
    """Noise-free linear RGB image (H, W, 3) in about [0, 1].

    Each layer's colour is only computed where it can appear: the wall above the lowest surface
    point, the soil below the highest, the wheel in its bounding box.
    """
    hgt, wid = scene.height, scene.width
    cx, cy, r = scene.centre_x_px, scene.centre_y_px, scene.radius_px
    lab, rows, cols, frac = coverage_parts(scene)
    bg_w = (lab == BG).astype(np.float32)
    soil_w = (lab == SOIL).astype(np.float32)
    bg_w[rows, cols] = frac[:, BG]
    soil_w[rows, cols] = frac[:, SOIL]
    surf = surface_y_px(scene, np.arange(wid, dtype=np.float64))
    dxr = np.arange(wid, dtype=np.float32)[None, :] - np.float32(cx)
    dyc = np.arange(hgt, dtype=np.float32)[:, None] - np.float32(cy)
    img = np.zeros((hgt, wid, 3), dtype=np.float32)

    y_wall = int(np.clip(math.ceil(surf.max()) + 2, 1, hgt))
    lx = scene.light_dir[0]
    shade = 1 - scene.wall_gradient * ((dyc[:y_wall] + cy) / hgt + 0.3 * dxr * lx / wid)
    shade = shade + scene.wall_texture * _smooth_noise(rng, y_wall, wid, 30)
    img[:y_wall] = (bg_w[:y_wall] * shade)[..., None] * np.asarray(scene.wall_rgb, np.float32)

    y_soil = int(np.clip(math.floor(surf.min()) - 2, 0, hgt - 1))
    soil = _soil_image(scene, rng, dyc[y_soil:], dxr)
    img[y_soil:] += soil_w[y_soil:, :, None] * soil

    reach = r + scene.lug_height_px + 0.5 * scene.lug_width_px + 3
    y0, y1 = max(0, math.floor(cy - reach)), min(hgt, math.ceil(cy + reach) + 1)
    x0, x1 = max(0, math.floor(cx - reach)), min(wid, math.ceil(cx + reach) + 1)
    if y0 < y1 and x0 < x1:
        sel = (rows >= y0) & (rows < y1) & (cols >= x0) & (cols < x1)
        edges = (rows[sel] - y0, cols[sel] - x0, frac[sel])
        img[y0:y1, x0:x1] += _wheel_image(
            scene, rng, lab[y0:y1, x0:x1], edges, dyc[y0:y1], dxr[:, x0:x1]
        )
    return img * (scene.gain * np.asarray(scene.cast_rgb, np.float32))


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1] as sRGB-encoded values (IEC 61966-2-1), clipped to [0, 1]."""
    x = np.clip(linear, 0.0, 1.0)
    high = 1.055 * np.power(x, np.float32(1 / 2.4)) - 0.055
    return np.where(x <= 0.0031308, 12.92 * x, high).astype(np.float32)


def render_and_encode(
    scene: Scene, seed: int, *, encode: bool
) -> tuple[UInt8[np.ndarray, "H W 3"], Truth, bytes | None]:
    """:func:`render` plus the file bytes: the JPEG when the scene uses one, else the PNG if
    ``encode``, else None."""
    rng = np.random.default_rng(seed)
    img = _compose(scene, rng) * np.float32(255)
    if scene.black_level:
        img += np.float32(scene.black_level)
    if scene.blur_sigma_px > 0.05:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), scene.blur_sigma_px), np.float32)
    if scene.noise_std > 0:
        img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(scene.noise_std)
    if scene.encoding == "srgb":
        img = np.float32(255) * srgb_encode(img / np.float32(255))
    # Round half up: +0.5 then truncate (one pass fewer than rint, same result after clipping).
    img += np.float32(0.5)
    out = np.clip(img, 0, 255, out=img).astype(np.uint8)
    data = None
    if scene.jpeg_quality:
        ok, buf = cv2.imencode(
            ".jpg", out[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(scene.jpeg_quality)]
        )
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        data = buf.tobytes()
        decoded = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        if decoded is None:
            raise RuntimeError("JPEG decoding failed")
        out = np.ascontiguousarray(decoded[..., ::-1], dtype=np.uint8)
    elif encode:
        ok, buf = cv2.imencode(".png", out[..., ::-1])
        if not ok:
            raise RuntimeError("PNG encoding failed")
        data = buf.tobytes()
    return out, true_geometry(scene), data


def render(scene: Scene, seed: int) -> tuple[UInt8[np.ndarray, "H W 3"], Truth]:
    """Render one frame: uint8 RGB (height, width, 3) and its exact :class:`Truth`.

    ``seed`` drives the soil texture, pebbles and sensor noise; the same (scene, seed) gives the
    same bytes. With ``scene.jpeg_quality`` > 0 the image is the decoded JPEG.
    """
    img, truth, _ = render_and_encode(scene, seed, encode=False)
    return img, truth
