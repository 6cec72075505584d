"""Exact ground truth of a :class:`~.scene.Scene` (docs/conventions.md §1): the paper's
quantities from the TRUE surface and rim circle, with the conventions' definitions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..geometry import travel_sign
from .scene import F64, Scene, surface_y_px

_BOUNDARY_STEP_PX = 0.05  # conventions: boundary sampled uniformly in x, step <= 0.05 px


@dataclass
class Truth:
    """Exact ground truth of one frame (docs/conventions.md §1).

    Angles in degrees; k, b, A and B in the wheel frame."""

    sinkage_mm: float
    theta1_deg: float
    theta2_deg: float
    sinkage_px: float
    center_x_px: float
    center_y_px: float
    radius_px: float
    k: float
    b_px: float
    a_px: tuple[float, float]
    b_end_px: tuple[float, float]
    contact: bool
    terrain: str


def _inside_excess(scene: Scene, x: F64) -> F64:
    """|P - O|^2 - r^2 for the surface point above x: negative where it lies inside the rim."""
    dy = surface_y_px(scene, x) - scene.centre_y_px
    dx = x - scene.centre_x_px
    return dx * dx + dy * dy - scene.radius_px**2


def _bisect(scene: Scene, lo: float, hi: float) -> float:
    """Root of _inside_excess between lo and hi (signs differ), to far below 1e-6 px."""
    f_lo = _inside_excess(scene, np.array(lo))
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        f_mid = _inside_excess(scene, np.array(mid))
        if (f_mid < 0) == (f_lo < 0):
            lo, f_lo = mid, f_mid
        else:
            hi = mid
        if hi - lo < 1e-10:
            break
    return 0.5 * (lo + hi)


def _coarse_inside(scene: Scene, step_px: float = 0.1) -> tuple[F64, NDArray[np.bool_]]:
    r = scene.radius_px
    n = math.ceil(2 * r / step_px) + 1
    xs = np.linspace(scene.centre_x_px - r, scene.centre_x_px + r, n)
    return xs, _inside_excess(scene, xs) < 0


def n_rim_crossings(scene: Scene) -> int:
    """How often the surface crosses the rim circle (2 for a normal contact, 0 for none)."""
    _, inside = _coarse_inside(scene)
    return int(np.count_nonzero(inside[1:] != inside[:-1]))


def boundary_points(scene: Scene) -> tuple[F64, F64]:
    """The true boundary: surface points inside the rim, uniform in x (step <= 0.05 px), image px.

    Its first and last points are the exact rim intersections. Empty arrays without contact.
    """
    xs, inside = _coarse_inside(scene)
    if not inside.any():
        return np.zeros(0), np.zeros(0)
    idx = np.flatnonzero(inside)
    x_lo = _bisect(scene, xs[idx[0] - 1], xs[idx[0]])
    x_hi = _bisect(scene, xs[idx[-1]], xs[idx[-1] + 1])
    n = max(3, math.ceil((x_hi - x_lo) / _BOUNDARY_STEP_PX) + 1)
    x = np.linspace(x_lo, x_hi, n)
    # Several pieces only happen for pathological custom surfaces; keep the inside ones then.
    keep = _inside_excess(scene, x) <= 1e-6 * scene.radius_px
    keep[[0, -1]] = True
    return x[keep], surface_y_px(scene, x[keep])


def true_geometry(scene: Scene) -> Truth:
    """Eqs. 1-3 on the TRUE surface (docs/conventions.md §1): OLS of the dense boundary, exact
    A and B."""
    cx, cy, r = scene.centre_x_px, scene.centre_y_px, scene.radius_px
    x, y = boundary_points(scene)
    if x.size == 0:
        return Truth(
            0.0, 0.0, 0.0, 0.0, cx, cy, r, 0.0, 0.0, (0.0, 0.0), (0.0, 0.0), False, scene.terrain
        )
    s = travel_sign(scene.travel)
    u, v = s * (x - cx), y - cy
    # Centred OLS: algebraically Eq. 1's k and b (same form as geometry.equivalent_line).
    um, vm = u.mean(), v.mean()
    du = u - um
    k = float(np.sum(du * (v - vm)) / np.sum(du * du))
    b = float(vm - k * um)
    z0 = r - abs(b) / math.sqrt(k * k + 1.0)
    ia, ib = (-1, 0) if s > 0 else (0, -1)  # entry end A has the largest u
    a = (float(u[ia]), float(v[ia]))
    be = (float(u[ib]), float(v[ib]))
    # docs/conventions.md §1's atan2 form: continuous, negative past the bottom of the rim.
    t1 = math.atan2(a[0], a[1])
    t2 = math.atan2(-be[0], be[1])
    return Truth(
        sinkage_mm=z0 * scene.wheel_radius_mm / r,
        theta1_deg=math.degrees(t1),
        theta2_deg=math.degrees(t2),
        sinkage_px=z0,
        center_x_px=cx,
        center_y_px=cy,
        radius_px=r,
        k=k,
        b_px=b,
        a_px=a,
        b_end_px=be,
        contact=True,
        terrain=scene.terrain,
    )
