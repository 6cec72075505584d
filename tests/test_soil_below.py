"""Wheel below a boundary point counted inside the rim only (soft.outline.wheel_below_in_disc).

A bare-metal wheel on grey sand: the default segmenter takes lit patches of the sand for the
wheel's face. Counted down the whole column, that "wheel" below the soil line made every point
of the line look like the top edge of a lightening hole, and the frame read as no contact.
Where the first count finds no boundary on a mask made from intensity, the soft method counts
again inside the rim.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax import synth as S
from sinkjax.result import FEATURES_HUE_SAT, FEATURES_INTENSITY
from sinkjax.soft.adaptive import default_segmenter
from sinkjax.soft.estimator import measure_from_mask, prepare
from sinkjax.soft.fit import build_evidence
from sinkjax.soft.outline import extract_outline, wheel_below_in_disc
from sinkjax.soft.rim import RecordingRim
from sinkjax.soft.segmentation import smooth
from sinkjax.soft.settings import SoftSettings
from sinkjax.status import Status

CX, CY, R = 160.0, 100.0, 100.0
SINKAGE_PX = 10.0
SETTINGS = SoftSettings()


@functools.cache
def _frame() -> tuple[np.ndarray, S.Truth]:
    scene = S.Scene(
        width=320,
        height=240,
        centre_x_px=CX,
        centre_y_px=CY,
        radius_px=R,
        n_lugs=0,
        hub_radius_px=14.0,
        soil_level_px=CY + R - SINKAGE_PX,
        pebbles=20,
        noise_std=2.0,
        blur_sigma_px=0.5,
    )
    return S.render(scene, seed=5)


@functools.cache
def _mask_with_soil_as_wheel() -> tuple[jnp.ndarray, jnp.ndarray]:
    """The frame's default mask, plus a band of soil taken for wheel just below the rim, under
    the whole chord (clear of the ring at 1.2 r that the checks read)."""
    image, _ = _frame()
    rig = S.rig_for(S.Scene(width=320, height=240, centre_x_px=CX, centre_y_px=CY, radius_px=R))
    img = jnp.asarray(image, jnp.float64) / 255.0
    rim = RecordingRim.fixed(CX, CY, R, 0.05)
    segment = default_segmenter(rig.segmentation).with_rim
    mask = np.array(jax.jit(lambda i: segment(i, rig.confidence_rect, rim.disc()))(img))
    u = np.arange(320) - CX
    mask[int(CY + R) + 3 : int(CY + R) + 11, np.abs(u) <= 45] = 1.0
    return img, jnp.asarray(mask)


def test_counted_inside_the_disc_is_a_column_sum() -> None:
    # Reference: for each outline point, the solid mask (as extract_outline counts it) summed
    # row by row in NumPy from 3 px below the point to the disc's lowest row in its column.
    _, mask = _mask_with_soil_as_wheel()
    outline = jax.jit(lambda m: extract_outline(m, SETTINGS))(mask)
    got = wheel_below_in_disc(outline, mask, *(jnp.asarray(v) for v in (CX, CY, R)))
    solid = 1.0 / (1.0 + np.exp(-(np.asarray(smooth(mask)) - 0.5) / 0.1))
    valid = np.flatnonzero(np.asarray(outline.valid))
    assert valid.size > 100
    for i in valid:
        col = int(np.clip(np.round(float(outline.x_px[i])), 0, 319))
        row = int(np.clip(np.round(float(outline.y_px[i])), 0, 239))
        bottom = int(np.floor(CY + np.sqrt(max(R**2 - (col - CX) ** 2, 0.0))))
        ref = solid[row + 3 : bottom + 1, col].sum()
        assert float(got.wheel_below_px[i]) == pytest.approx(ref, abs=1e-6)
    # The band below the rim is counted down the whole column, not inside the disc.
    x, y = np.asarray(outline.x_px)[valid], np.asarray(outline.y_px)[valid]
    on_line = valid[(np.abs(y - (CY + R - SINKAGE_PX)) < 1.5) & (np.abs(x - CX) < 40.0)]
    assert on_line.size > 20
    assert np.all(np.asarray(outline.wheel_below_px)[on_line] > 5.0)
    assert np.all(np.asarray(got.wheel_below_px)[on_line] < 0.5)


def test_soil_taken_for_wheel_below_the_rim_keeps_the_contact() -> None:
    # The frame's own rim (no recording rim): the recording rim's mask repairs (soft.shadow_cut
    # cuts a mask that spills below the rim) would remove the band before the outline is read.
    img, mask = _mask_with_soil_as_wheel()
    _, truth = _frame()

    # Counted down the whole column, the soil line has no weight left: no contact.
    @jax.jit
    def line_weight(i: jnp.ndarray, m: jnp.ndarray) -> jnp.ndarray:
        prep = prepare(i, m)
        c = prep.choice
        return jnp.sum(build_evidence(prep.outline, c.circle, 1.0, SETTINGS, c.prior_weight).w_line)

    assert float(line_weight(img, mask)) < float(SETTINGS.min_boundary_points)
    run = jax.jit(lambda i, m, f: measure_from_mask(i, m, wheel_radius_mm=R, features=f))
    # A mask made from intensity (a wheel without colour): counted inside the rim, the soil
    # line is found; wheel_radius_mm = r, so millimetres are pixels.
    est = run(img, mask, FEATURES_INTENSITY)
    assert Status.from_code(int(est.status)) == Status.OK
    assert float(est.sinkage_mm) == pytest.approx(truth.sinkage_px, abs=0.3)
    # A hue mask keeps the first count (the comment in soft.estimator.finish says why).
    assert float(run(img, mask, FEATURES_HUE_SAT).sinkage_mm) == 0.0
