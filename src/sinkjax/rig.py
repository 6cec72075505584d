"""The rig file (docs/conventions.md §2): wheel radius, confidence rectangle, travel, thresholds."""

from __future__ import annotations

import difflib
import math
import tomllib
from pathlib import Path
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

# The hue band is circular: H_d = H_w + (P_d - 1) * HUE_SCALE_DEG, likewise H_a with P_a.
# The paper writes H_a = P_a * H_w, which depends on where hue's zero happens to be (a red wheel at
# H_w ~ 0 would get an empty band, at H_w ~ 359 a huge one). Using a fixed half-turn as the scale
# keeps the paper's P_a/P_d meaning ("percent around the wheel's mean") for every wheel colour.
HUE_SCALE_DEG = 180.0
# Largest rim radius accepted (mm): sinkage is z0 * R / r, which must stay a finite number; no
# wheel is 100 m in radius, but 1.7e308 mm would make every sinkage infinite.
MAX_WHEEL_RADIUS_MM = 1e5


class RigError(ValueError):
    """A rig file or rig argument is unusable; the message says what to fix."""


class SegmentationParams(eqx.Module):
    """The paper's P_d/P_a for H and S, plus the soft method's temperatures and the strength of
    its soil/background veto.

    Every field is a scalar array leaf so that ``jax.grad`` reaches it (calibration tunes them).
    H band: H_w + (P - 1) * 180 deg (circular); S band: [P_d * S_w, P_a * S_w] (the paper's).
    Temperatures set the width of the soft masks' sigmoids: degrees of hue, units of saturation.
    """

    p_d_hue: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.9)
    p_a_hue: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=1.1)
    p_d_sat: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.5)
    p_a_sat: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=1.8)
    temperature_hue_deg: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=2.0)
    temperature_sat: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.02)
    # The soil/background veto (soft.segmentation.reference_mask): a pixel is vetoed when it lies
    # nearer the soil's or the background's chromaticity than the wheel's by this fraction of
    # their separation. Larger keeps more blends of wheel and soil colour (dust on the wheel);
    # from 0.5 on only pixels beyond the other reference itself are vetoed.
    veto_fraction: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.25)

    def as_dict(self) -> dict[str, float]:
        return {name: float(getattr(self, name)) for name in SEGMENTATION_KEYS}


# The paper's H/S test needs a wheel with colour: below this mean chroma (saturation units, the
# length of the confidence rectangle's mean (S cos H, S sin H)) H_w is noise. A black or bare-metal
# wheel sits at ~0.02-0.04, the least coloured painted wheels of the synthetic presets at > 0.05.
MIN_WHEEL_CHROMA = 0.05

SEG_FIELDS = (
    "p_d_hue",
    "p_a_hue",
    "p_d_sat",
    "p_a_sat",
    "temperature_hue_deg",
    "temperature_sat",
)
# The H/S band's fields above, and the rig file's [segmentation] keys: the band and the veto.
SEGMENTATION_KEYS = (*SEG_FIELDS, "veto_fraction")


class Rig(eqx.Module):
    """One camera set-up. ``confidence_rect`` is (x, y, w, h) in pixels on the wheel face."""

    wheel_radius_mm: float = eqx.field(static=True)
    confidence_rect: tuple[int, int, int, int] = eqx.field(static=True)
    travel: str = eqx.field(static=True, default="right")
    segmentation: SegmentationParams = SegmentationParams()
    # Optional: the rim's radius in image pixels, roughly; the rim search then looks within
    # RIM_HINT_TOLERANCE of it instead of over the default fractions of the image size.
    rim_radius_px: float | None = eqx.field(static=True, default=None)
    # How the camera stored brightness: "linear" (proportional to light) or "srgb" (the sRGB
    # tone curve of most cameras' JPEG/PNG output). The soft method locates edges in linear light.
    encoding: str = eqx.field(static=True, default="linear")

    def __check_init__(self) -> None:
        validate_rig_fields(self.wheel_radius_mm, self.confidence_rect, self.travel)
        _check_rim_hint(self.rim_radius_px, "rig")
        _check_encoding(self.encoding, "rig")


# A rim_radius_px hint is searched from (1 - t) to (1 + t) times itself: it need only be rough.
RIM_HINT_TOLERANCE = 0.25
# Largest rim_radius_px accepted: bigger than any image a camera makes.
MAX_RIM_RADIUS_PX = 1e5


def rim_hint_range_px(rig: Rig) -> tuple[float, float] | None:
    """The rim radii (px) to search given the rig's ``rim_radius_px`` hint; None without one
    (each method then uses its default range, fractions of the image's shorter side)."""
    if rig.rim_radius_px is None:
        return None
    r = float(rig.rim_radius_px)
    return (1.0 - RIM_HINT_TOLERANCE) * r, (1.0 + RIM_HINT_TOLERANCE) * r


# The rig file's encoding values: how pixel values relate to light (docs/conventions.md §2).
ENCODINGS = ("linear", "srgb")


def srgb_flag(encoding: str) -> float:
    """The encoding as the compiled functions take it: 1.0 for "srgb", 0.0 for "linear"."""
    return 1.0 if encoding == "srgb" else 0.0


def _check_encoding(value: Any, source: str) -> None:
    if value not in ENCODINGS:
        raise RigError(
            f'{source}: encoding must be "linear" or "srgb", got {value!r}; "srgb" for '
            'camera footage stored with the sRGB tone curve, "linear" (the default) for '
            "values proportional to light"
        )


def _check_rim_hint(value: Any, source: str) -> None:
    if value is None:
        return
    if (
        not isinstance(value, int | float)
        or isinstance(value, bool)
        or not math.isfinite(value)
        or not 4.0 <= value <= MAX_RIM_RADIUS_PX
    ):
        raise RigError(
            f"{source}: rim_radius_px must be a number of pixels from 4 to "
            f"{MAX_RIM_RADIUS_PX:g} (the rim's radius in the image, roughly), got {value!r}; "
            "e.g. rim_radius_px = 180, or leave it out"
        )


def validate_rig_fields(
    wheel_radius_mm: Any, confidence_rect: Any, travel: Any, source: str = "rig"
) -> None:
    """Raise RigError with a fix-it message if any field is unusable."""
    if (
        not isinstance(wheel_radius_mm, int | float)
        or isinstance(wheel_radius_mm, bool)
        or not math.isfinite(wheel_radius_mm)
        or wheel_radius_mm <= 0
    ):
        raise RigError(
            f"{source}: wheel_radius_mm must be a positive number (the rim radius R in mm), "
            f"got {wheel_radius_mm!r}; e.g. wheel_radius_mm = 140.0"
        )
    if wheel_radius_mm > MAX_WHEEL_RADIUS_MM:
        raise RigError(
            f"{source}: wheel_radius_mm = {wheel_radius_mm!r} is more than "
            f"{MAX_WHEEL_RADIUS_MM:g} mm ({MAX_WHEEL_RADIUS_MM / 1000:g} m); write the rim "
            "radius R in millimetres, e.g. wheel_radius_mm = 140.0"
        )
    if (
        not isinstance(confidence_rect, tuple | list)
        or len(confidence_rect) != 4
        or not all(isinstance(v, int) and not isinstance(v, bool) for v in confidence_rect)
    ):
        raise RigError(
            f"{source}: confidence_rect must be four integers [x, y, w, h] in pixels, "
            f"got {confidence_rect!r}; e.g. confidence_rect = [300, 120, 40, 30]"
        )
    x, y, w, h = confidence_rect
    if x < 0 or y < 0 or w < 1 or h < 1:
        raise RigError(
            f"{source}: confidence_rect [x, y, w, h] needs x, y >= 0 and w, h >= 1, "
            f"got {list(confidence_rect)!r}"
        )
    if travel not in ("right", "left"):
        raise RigError(f'{source}: travel must be "right" or "left", got {travel!r}')


# A channel this close to the sensor's top (of 1) is clipped. A pixel with two or three clipped
# channels has lost its colour (it shows the light's): the default segmenter reads the wheel's
# colour without such pixels, and a rectangle full of them is named. One clipped channel alone
# is a saturated colour (a bright blue wheel), not a glow.
CLIP_LEVEL = 0.97
# The share of a confidence rectangle's pixels clipped above which its statistics are the
# light's, not the wheel's.
MAX_CLIPPED_SHARE = 0.5


def rect_overexposed(image_u8: Any, rect: tuple[int, int, int, int]) -> str | None:
    """Why a frame's confidence rectangle cannot tell the wheel's colour, or None: more than
    :data:`MAX_CLIPPED_SHARE` of its pixels have two or three channels at the sensor's top (a
    lamp's glow, a highlight), so the wheel's hue, saturation and brightness there are the
    light's. ``image_u8`` is the (H, W, 3) uint8 frame; ``rect`` lies inside it
    (:func:`rect_problem`)."""
    x, y, w, h = rect
    patch = np.asarray(image_u8)[y : y + h, x : x + w]
    if patch.ndim != 3 or patch.dtype != np.uint8 or patch.size == 0:
        return None
    # The middle channel of three is at the top where two or three are (soft.segmentation's
    # ``unclipped``, on uint8).
    middle = np.sort(patch, axis=-1)[..., 1]
    share = float(np.mean(middle >= CLIP_LEVEL * 255.0))
    if share <= MAX_CLIPPED_SHARE:
        return None
    return (
        f"the confidence rectangle is over-exposed ({100 * share:.0f} % of its pixels have two "
        "or three channels at the sensor's top, so its colour is the light's, not the wheel's): "
        "move it to a part of the wheel face that is not blown out, or lower the exposure"
    )


def rect_problem(rect: Any, height: int, width: int) -> str | None:
    """None if ``rect`` = (x, y, w, h) px lies inside a ``width`` x ``height`` image; else why not.

    The one rule for a confidence rectangle: four integers with x, y >= 0, w, h >= 1,
    x + w <= width and y + h <= height. The message says how to fix it (rig file or flag).
    """
    if (
        not isinstance(rect, tuple | list)
        or len(rect) != 4
        or not all(isinstance(v, int) and not isinstance(v, bool) for v in rect)
    ):
        return f"confidence_rect must be four integers [x, y, w, h] in pixels, got {rect!r}"
    x, y, w, h = rect
    fix = "fix confidence_rect in the rig or pass --confidence-rect X,Y,W,H"
    if x < 0 or y < 0 or w < 1 or h < 1:
        return (
            f"the confidence rectangle [x, y, w, h] = [{x}, {y}, {w}, {h}] needs x, y >= 0 and "
            f"w, h >= 1 to lie inside the image; {fix}"
        )
    if x + w > width or y + h > height:
        return (
            f"the confidence rectangle [x, y, w, h] = [{x}, {y}, {w}, {h}] extends beyond the "
            f"{width}x{height} image: it must lie inside it (needs x+w <= {width} and "
            f"y+h <= {height}); {fix}"
        )
    return None


def rig_from_dict(data: dict[str, Any], source: str = "rig") -> Rig:
    """Build a Rig from parsed TOML; raises RigError naming the field and the fix."""
    if "wheel_radius_mm" not in data:
        raise RigError(
            f"{source}: missing wheel_radius_mm (the physical rim radius R in mm); "
            "add e.g. wheel_radius_mm = 140.0 or pass --wheel-radius-mm"
        )
    if "confidence_rect" not in data:
        raise RigError(
            f"{source}: missing confidence_rect = [x, y, w, h] (pixels of a rectangle that always "
            "shows the wheel face); add it or pass --confidence-rect X,Y,W,H"
        )
    _check_keys(data, RIG_KEYS, source, "")
    radius = data["wheel_radius_mm"]
    if isinstance(radius, int) and not isinstance(radius, bool):
        radius = float(radius)
    rect = data["confidence_rect"]
    rect = tuple(rect) if isinstance(rect, list) else rect
    travel = data.get("travel", "right")
    validate_rig_fields(radius, rect, travel, source)
    seg_data = data.get("segmentation", {})
    if not isinstance(seg_data, dict):
        raise RigError(f"{source}: [segmentation] must be a table")
    _check_keys(seg_data, SEGMENTATION_KEYS, source, "[segmentation] ")
    seg_kwargs: dict[str, Any] = {}
    for name, value in seg_data.items():
        if (
            not isinstance(value, int | float)
            or isinstance(value, bool)
            or not math.isfinite(value)
        ):
            raise RigError(f"{source}: [segmentation] {name} must be a number, got {value!r}")
        seg_kwargs[name] = float(value)
    seg = SegmentationParams(**seg_kwargs)
    _check_segmentation(seg, source)
    hint = data.get("rim_radius_px")
    _check_rim_hint(hint, source)
    encoding = data.get("encoding", "linear")
    _check_encoding(encoding, source)
    return Rig(
        wheel_radius_mm=radius,
        confidence_rect=rect,
        travel=travel,
        segmentation=seg,
        rim_radius_px=None if hint is None else float(hint),
        encoding=encoding,
    )


RIG_KEYS = (
    "wheel_radius_mm",
    "confidence_rect",
    "travel",
    "rim_radius_px",
    "encoding",
    "segmentation",
)


def _check_keys(data: dict[str, Any], known: tuple[str, ...], source: str, table: str) -> None:
    """Raise RigError for the first unknown key, suggesting the closest known one."""
    for key in data:
        if key not in known:
            close = difflib.get_close_matches(key, known, n=1, cutoff=0.5)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise RigError(
                f"{source}: unknown {table}key {key!r}; {hint}known keys: {', '.join(known)}"
            )


def _check_segmentation(seg: SegmentationParams, source: str) -> None:
    d = seg.as_dict()
    for kind in ("hue", "sat"):
        lo, hi = d[f"p_d_{kind}"], d[f"p_a_{kind}"]
        if not 0 <= lo < 1 < hi:
            raise RigError(f"{source}: [segmentation] needs 0 <= p_d_{kind} < 1 < p_a_{kind}")
    if d["temperature_hue_deg"] <= 0 or d["temperature_sat"] <= 0:
        raise RigError(f"{source}: [segmentation] temperatures must be > 0")
    if d["veto_fraction"] < 0:
        raise RigError(f"{source}: [segmentation] veto_fraction must be >= 0")


def read_rig_toml(path: str | Path) -> dict[str, Any]:
    """A rig file's TOML as a dict (a UTF-8 byte-order mark is allowed).

    Raises RigError (naming the file) if it cannot be read or is not TOML.
    """
    p = Path(path)
    try:
        return tomllib.loads(p.read_text(encoding="utf-8-sig"))
    except OSError as e:
        raise RigError(f"{p}: cannot read the rig file ({e.strerror or e})") from e
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise RigError(f"{p}: not valid TOML ({e})") from e


def load_rig(path: str | Path) -> Rig:
    """Read a ``rig.toml``. Raises RigError (missing file, bad TOML, bad field) with the fix."""
    p = Path(path)
    if not p.is_file():
        raise RigError(f"rig file {str(p)!r} does not exist; write one (see README) or pass flags")
    return rig_from_dict(read_rig_toml(p), source=str(p))


def rig_to_toml(rig: Rig, comment: str | None = None) -> str:
    """The TOML text of a complete rig file (round-trips through :func:`load_rig`)."""
    x, y, w, h = rig.confidence_rect
    lines = []
    if comment:
        lines += [f"# {line}" for line in comment.splitlines()]
    lines += [
        f"wheel_radius_mm = {float(rig.wheel_radius_mm)!r}",
        f"confidence_rect = [{x}, {y}, {w}, {h}]",
        f'travel = "{rig.travel}"',
        *(
            [f"rim_radius_px = {float(rig.rim_radius_px)!r}"]
            if rig.rim_radius_px is not None
            else []
        ),
        *([f'encoding = "{rig.encoding}"'] if rig.encoding != "linear" else []),
        "",
        "[segmentation]",
    ]
    lines += [f"{k} = {v!r}" for k, v in rig.segmentation.as_dict().items()]
    return "\n".join(lines) + "\n"


def save_rig(rig: Rig, path: str | Path, comment: str | None = None) -> None:
    Path(path).write_text(rig_to_toml(rig, comment), encoding="utf-8")
