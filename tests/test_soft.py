"""The soft estimator: accuracy on rendered truth, jit/vmap consistency, gradients, degeneracies,
and which features its segmenter chose, per frame and in the run summary."""

from __future__ import annotations

import colorsys
import csv

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax import synth
from sinkjax.app.run import estimate_to_csv
from sinkjax.geometry import equivalent_line, from_wheel_frame
from sinkjax.result import FEATURES_HUE_SAT
from sinkjax.rig import Rig, SegmentationParams, save_rig
from sinkjax.soft.batch import estimate_batch
from sinkjax.soft.ends import boundary_ends, end_kernel
from sinkjax.soft.estimator import measure
from sinkjax.soft.fit import fit, weighted_points
from sinkjax.soft.model import Evidence, measurements
from sinkjax.soft.uncertainty import UncertaintyModel, covariance, measurement_std
from sinkjax.status import Status

W, H = 320, 240


_jit_measure = jax.jit(
    measure, static_argnames=("rect", "travel", "wheel_radius_mm", "uncertainty")
)


@pytest.mark.parametrize("preset", ["clean", "full"])
def test_accuracy_on_rendered_truth(preset: str, rendered) -> None:
    images, truths, rig = rendered(preset)
    rows = estimate_batch(images, rig, [str(i) for i in range(len(images))])
    for row, t in zip(rows, truths, strict=True):
        if not t.contact:
            assert row.status == "no_contact"
            continue
        if t.sinkage_px < 1.5:
            # Below ~1.5 px the boundary cannot be told from the rim: it reads as no contact,
            # an error of less than 1.5 px.
            assert row.status in ("ok", "no_contact")
            assert abs((row.sinkage_mm or 0.0) - t.sinkage_mm) < 1.5 * t.sinkage_mm / t.sinkage_px
            continue
        assert row.status == "ok", row.message
        assert abs(row.sinkage_mm - t.sinkage_mm) < max(1.0, 0.05 * t.sinkage_mm)
        # Within the frame's own reported uncertainty (3 sigma) or 1.5 deg.
        assert abs(row.theta1_deg - t.theta1_deg) < max(1.5, 3 * row.theta1_std_deg)
        assert abs(row.theta2_deg - t.theta2_deg) < max(1.5, 3 * row.theta2_std_deg)
        assert abs(row.radius_px - t.radius_px) < 0.5
        assert row.sinkage_std_mm > 0 and row.theta1_std_deg > 0


@pytest.mark.parametrize("travel", ["right", "left"])
def test_overlay_ends_are_the_rendered_contact_points(travel: str) -> None:
    """A and B of a row's overlay (image px, drawn by the review page and the plots) are the
    renderer's contact points, for either direction of travel."""
    rng = np.random.default_rng(5)
    scenes = synth.recording_scenes(rng, 3, preset="clean", width=W, height=H, travel=travel)
    out = [synth.render(scene, seed=50 + i) for i, scene in enumerate(scenes)]
    rig = synth.rig_for(scenes[0])
    assert rig.travel == travel
    rows = estimate_batch([o[0] for o in out], rig, ["0", "1", "2"])
    measured = 0
    for row, (_, t) in zip(rows, out, strict=True):
        if row.status != "ok" or t.sinkage_px < 3:
            continue
        measured += 1
        assert row.overlay is not None
        for got, (u, v) in ((row.overlay.a_px, t.a_px), (row.overlay.b_px, t.b_end_px)):
            want = from_wheel_frame(u, v, t.center_x_px, t.center_y_px, travel)
            assert got is not None
            assert abs(got[0] - float(want[0])) < 3.0 and abs(got[1] - float(want[1])) < 3.0
    assert measured >= 2


@pytest.mark.heavy
@pytest.mark.slow
def test_jit_equals_eager_and_vmap_equals_loop(rendered) -> None:
    images, _, rig = rendered("clean", n=2)
    kw = dict(rect=rig.confidence_rect, travel=rig.travel, wheel_radius_mm=rig.wheel_radius_mm)
    ims = jnp.asarray(np.stack(images), jnp.float64) / 255.0
    eager = measure(ims[0], rig.segmentation, **kw)
    jitted = _jit_measure(ims[0], rig.segmentation, **kw)
    np.testing.assert_allclose(eager.params, jitted.params, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(eager.sinkage_mm, jitted.sinkage_mm, rtol=1e-6, atol=1e-8)
    batched = jax.jit(jax.vmap(lambda im: measure(im, rig.segmentation, **kw)))(ims)
    for i in range(2):
        one = _jit_measure(ims[i], rig.segmentation, **kw)
        for field in ("sinkage_mm", "theta1_rad", "theta2_rad", "sinkage_std_mm"):
            np.testing.assert_allclose(
                getattr(batched, field)[i], getattr(one, field), rtol=1e-6, atol=1e-9
            )
        # The clean preset's wheel has colour: the H/S test, under vmap as alone.
        assert int(batched.features[i]) == int(one.features) == FEATURES_HUE_SAT


def test_one_compile_serves_every_rig_of_a_size(rendered) -> None:
    """A second rig (other rectangle, radius, travel) of the same image size compiles nothing,
    and the traced rig gives the static-argument path's numbers."""
    import sinkjax.soft.batch as E

    images, _, rig = rendered("clean", n=2)
    fn = E._finish_batch if E._use_vmap() else E._finish_one
    before = fn._cache_size()
    # Each frame's own rim: comparable with measure() on the frame alone.
    rows = estimate_batch(images, rig, ["a", "b"], rim="frame")
    compiled = fn._cache_size()
    x, y, w, h = rig.confidence_rect
    other = Rig(
        wheel_radius_mm=2.0 * rig.wheel_radius_mm,
        confidence_rect=(x + 1, y + 2, w - 2, h - 2),
        travel="left" if rig.travel == "right" else "right",
        segmentation=rig.segmentation,
    )
    estimate_batch(images, other, ["a", "b"])
    assert compiled - before <= 1 and compiled >= 1
    assert fn._cache_size() == compiled
    kw = dict(rect=rig.confidence_rect, travel=rig.travel, wheel_radius_mm=rig.wheel_radius_mm)
    n_ok = 0
    for image, row in zip(images, rows, strict=True):
        ref = _jit_measure(jnp.asarray(image, jnp.float64) / 255.0, rig.segmentation, **kw)
        assert row.status == Status.from_code(int(ref.status))
        if row.status != "ok":
            continue
        n_ok += 1
        want = [ref.sinkage_mm, np.degrees(ref.theta1_rad), np.degrees(ref.theta2_rad)]
        got = [row.sinkage_mm, row.theta1_deg, row.theta2_deg]
        np.testing.assert_allclose(got, np.asarray(want, float), rtol=1e-6)
        np.testing.assert_allclose(row.sinkage_std_mm, float(ref.sinkage_std_mm), rtol=1e-6)
    assert n_ok >= 1


@pytest.mark.slow
def test_gradients_match_finite_differences(rendered) -> None:
    images, truths, rig = rendered("full", n=3)
    i = next(j for j, t in enumerate(truths) if t.contact and t.sinkage_mm > 8)
    image = jnp.asarray(images[i], jnp.float64) / 255.0
    kw = dict(rect=rig.confidence_rect, travel=rig.travel, wheel_radius_mm=rig.wheel_radius_mm)

    def outputs(seg: SegmentationParams, im: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
        e = measure(im, seg, **kw)
        out = jnp.stack([e.sinkage_mm, e.theta1_rad, e.theta2_rad])
        return out, out

    # One compiled function gives the Jacobian and (its auxiliary output) the values for the
    # differences: the Jacobian of the jitted estimator from Python, and the estimator for the
    # differences, would compile three programs. The image is an argument: closed over, XLA
    # would constant-fold the work done on it.
    jac_and_values = jax.jit(jax.jacrev(outputs, has_aux=True))
    seg = rig.segmentation
    jac = jac_and_values(seg, image)[0]
    eps = 1e-6
    for name in ("p_d_sat", "p_a_hue", "temperature_sat"):
        plus = type(seg)(**{**seg.as_dict(), name: float(getattr(seg, name)) + eps})
        minus = type(seg)(**{**seg.as_dict(), name: float(getattr(seg, name)) - eps})
        fd = (
            np.asarray(jac_and_values(plus, image)[1]) - np.asarray(jac_and_values(minus, image)[1])
        ) / (2 * eps)
        ad = np.asarray(getattr(jac, name))
        assert np.all(np.isfinite(ad))
        np.testing.assert_allclose(ad, fd, rtol=2e-3, atol=1e-5 * np.max(np.abs(fd)) + 1e-9)


def degenerate_images() -> dict[str, tuple[np.ndarray, Rig]]:
    wheel = np.zeros((120, 160, 3), np.uint8)
    wheel[:] = (215, 160, 25)
    soil = np.zeros_like(wheel)
    soil[:] = (150, 125, 95)
    rig = Rig(wheel_radius_mm=140.0, confidence_rect=(60, 40, 20, 20))
    rng = np.random.default_rng(5)
    noisy_soil = np.clip(soil + rng.normal(0, 6, soil.shape), 0, 255).astype(np.uint8)
    # No contact: a full wheel above the soil.
    yy, xx = np.mgrid[0:120, 0:160]
    nc = noisy_soil.copy()
    disk = (xx - 80) ** 2 + (yy - 50) ** 2 < 40**2
    nc[disk] = (215, 160, 25)
    nc[:, :][yy < 95] = np.where(disk[yy < 95][:, None], nc[yy < 95], (90, 95, 100))
    return {"all_wheel": (wheel, rig), "all_soil": (noisy_soil, rig), "no_contact": (nc, rig)}


def _degenerate_loss(
    seg: SegmentationParams, im: jnp.ndarray, rect, travel, wheel_radius_mm
) -> tuple[jnp.ndarray, jnp.ndarray]:
    e = measure(im, seg, rect=rect, travel=travel, wheel_radius_mm=wheel_radius_mm)
    return e.sinkage_mm + e.theta1_rad + e.theta2_rad + e.sinkage_std_mm, e.status


# One compiled gradient (with the status as its auxiliary output) serves the three cases: the
# gradient of the whole method takes half a minute to compile.
_degenerate_grad = jax.jit(
    jax.grad(_degenerate_loss, argnums=(0, 1), has_aux=True),
    static_argnames=("rect", "travel", "wheel_radius_mm"),
)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["all_wheel", "all_soil", "no_contact"])
def test_degenerate_frames_have_status_and_finite_gradients(case: str) -> None:
    image, rig = degenerate_images()[case]
    img = jnp.asarray(image, jnp.float64) / 255.0
    (g_seg, g_img), code = _degenerate_grad(
        rig.segmentation,
        img,
        rect=rig.confidence_rect,
        travel=rig.travel,
        wheel_radius_mm=rig.wheel_radius_mm,
    )
    status = Status.from_code(int(code))
    assert (
        status
        in {"all_wheel": ("no_wheel",), "all_soil": ("no_wheel",), "no_contact": ("no_contact",)}[
            case
        ]
    )
    assert all(np.all(np.isfinite(np.asarray(v))) for v in jax.tree_util.tree_leaves(g_seg))
    assert np.all(np.isfinite(np.asarray(g_img)))


def _clean_evidence() -> tuple[Evidence, tuple[float, float, float], tuple[float, float]]:
    """Rim points on a circle, boundary points on a curved surface inside it; (cx, cy, r) and
    Eq. 1's least-squares line (k, b) of the boundary points."""
    cx, cy, r = 100.0, 90.0, 60.0
    ang = np.linspace(-np.pi, 0.0, 400)  # upper half of the rim (y up = negative)
    rim_x, rim_y = cx + r * np.cos(ang), cy + r * np.sin(ang)
    bx = np.linspace(cx - 40, cx + 38, 300)
    by = cy + 40 + 0.004 * (bx - cx) ** 2 - 0.05 * (bx - cx)
    x = jnp.asarray(np.concatenate([rim_x, bx]))
    y = jnp.asarray(np.concatenate([rim_y, by]))
    n_rim = len(rim_x)
    w_rim = jnp.asarray(np.r_[np.ones(n_rim), np.zeros(len(bx))])
    w_line = 1.0 - w_rim
    u = bx - cx
    w_a = jnp.asarray(np.r_[np.zeros(n_rim), (u > 30).astype(float)])
    w_b = jnp.asarray(np.r_[np.zeros(n_rim), (u < -32).astype(float)])
    start = jnp.asarray([cx + 1.5, cy - 1.0, r + 2.0, 0.0, 38.0, 0.0, 40.0, 0.0, 40.0, 0.0, 0.0])
    k_ref, b_ref = equivalent_line(jnp.asarray(u), jnp.asarray(by - cy))
    # The ends' curves bend away from the end-most boundary points, and their offset priors are
    # anchored on the boundary's line below them (as build_evidence sets both).
    ends_x = np.asarray([bx[-1], bx[0]])
    ev = Evidence(
        x, y, w_rim, w_line, w_a, w_b, jnp.asarray(1.0), start,
        end_origin_px=jnp.asarray(np.stack([ends_x, [by[-1], by[0]]], 1)),
        end_anchor_px=jnp.asarray(
            np.stack([ends_x, cy + float(k_ref) * (ends_x - cx) + float(b_ref)], 1)
        ),
    )  # fmt: skip
    return ev, (cx, cy, r), (float(k_ref), float(b_ref))


def test_joint_fit_reproduces_eq1_on_clean_points() -> None:
    # The fitted line must be exactly Eq. 1's least-squares line of the boundary points.
    ev, (cx, cy, r), (k_ref, b_ref) = _clean_evidence()
    res = fit(ev)
    assert bool(res.ok)
    p = np.asarray(res.params)
    np.testing.assert_allclose(p[:3], [cx, cy, r], atol=1e-3)  # LM stops at rtol 1e-5
    assert p[3] == pytest.approx(k_ref, abs=1e-5)
    assert p[4] == pytest.approx(b_ref, abs=1e-3)
    # Delta method: the reported raw sigma equals sqrt(g C g) with g by finite differences.
    cov = covariance(res.params, ev)
    std = np.asarray(measurement_std(res.params, cov, None, UncertaintyModel.raw()))
    eps = 1e-6
    g = np.stack(
        [
            (
                np.asarray(measurements(res.params + eps * e))
                - np.asarray(measurements(res.params - eps * e))
            )
            / (2 * eps)
            for e in np.eye(len(p))
        ],
        1,
    )
    np.testing.assert_allclose(
        std, np.sqrt(np.einsum("ij,jk,ik->i", g, np.asarray(cov), g)), rtol=1e-5
    )


def _rut_exit_angle(taper: float) -> tuple[float, float]:
    """(fitted, exact) exit angle (deg) of a surface with a rut's edge inside the exit end's
    window (the paper rig's proportions: r = 140 px, a 1.9 px step of width 8.4 px, 20 px from
    B; a 28 px window, the boundary starting 4 px from the rim), the end windows weighted by
    :func:`end_kernel` with ``taper``."""
    cx, cy, r, depth, drop = 200.0, 190.0, 140.0, 130.4, 1.9
    step_x = cx - np.sqrt(r * r - (depth + drop) ** 2) + 20.0

    def surface(x: np.ndarray) -> np.ndarray:
        return cy + depth + drop * 0.5 * (1.0 - np.tanh((x - step_x) / 8.4))

    def crossing(lo: float, hi: float) -> float:  # bisection of the surface with the rim
        def g(x: float) -> float:
            return float((x - cx) ** 2 + (surface(np.asarray(x)) - cy) ** 2 - r * r)

        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if (g(mid) < 0) == (g(lo) < 0) else (lo, mid)
        return 0.5 * (lo + hi)

    xb, xa = crossing(cx - r, cx), crossing(cx + r, cx)
    exact = np.degrees(np.arctan2(cx - xb, float(surface(np.asarray(xb))) - cy))
    ang = np.linspace(-np.pi, 0.0, 400)
    bx = np.linspace(xb + 4.0, xa - 4.0, 100)
    by = surface(bx)
    u, v = jnp.asarray(bx - cx), jnp.asarray(by - cy)
    kern = [
        np.asarray(
            end_kernel((u - u[i]) ** 2 + (v - v[i]) ** 2, jnp.asarray(28.0), jnp.asarray(taper))
        )
        for i in (-1, 0)
    ]
    n, zeros = len(ang), np.zeros(len(ang))
    k0, b0 = (float(a) for a in equivalent_line(u, v))
    ends_x = np.asarray([bx[-1], bx[0]])
    ev = Evidence(
        jnp.asarray(np.r_[cx + r * np.cos(ang), bx]), jnp.asarray(np.r_[cy + r * np.sin(ang), by]),
        jnp.asarray(np.r_[np.ones(n), np.zeros(len(bx))]),
        jnp.asarray(np.r_[zeros, np.ones(len(bx))]),
        jnp.asarray(np.r_[zeros, kern[0]]), jnp.asarray(np.r_[zeros, kern[1]]),
        jnp.asarray(1.0),
        jnp.asarray([cx + 1.0, cy - 1.0, r + 1.0, k0, b0, 0.0, depth, 0.0, depth, 0.0, 0.0]),
        end_origin_px=jnp.asarray(np.stack([ends_x, [by[-1], by[0]]], 1)),
        end_anchor_px=jnp.asarray(np.stack([ends_x, cy + k0 * (ends_x - cx) + b0], 1)),
    )  # fmt: skip
    res = fit(ev)
    assert bool(res.ok)
    return float(np.degrees(measurements(res.params)[2])), float(exact)


def test_tapered_end_window_follows_the_surface_at_the_rim_past_a_rut_edge() -> None:
    # Bulldozing leaves a rut whose edge can lie inside the exit end's window: the surface is
    # flat where it meets the rim, the window's far side slopes. Weighted alike, the window's
    # points read that slope into the tangent at B; tapered, the points next to the rim lead.
    tapered, exact = _rut_exit_angle(1.0)
    uniform, _ = _rut_exit_angle(0.0)
    assert abs(tapered - exact) < 0.25
    assert abs(tapered - exact) < 0.75 * abs(uniform - exact)


def test_fit_on_the_weighted_points_alone_is_the_fit_on_every_slot() -> None:
    ev, _, _ = _clean_evidence()
    n = ev.x_px.shape[0]
    # Interleave 3 unweighted slots (other edges, padding) after every weighted point.
    rng = np.random.default_rng(0)
    order = np.argsort(np.r_[np.arange(n) * 4.0, rng.uniform(0, 4 * n, 3 * n)], kind="stable")
    weighted = order < n

    def spread(a: jax.Array, fill: np.ndarray) -> jax.Array:
        return jnp.asarray(np.r_[np.asarray(a), fill][order])

    xy_fill = rng.uniform(0, 200, 3 * n)
    zeros = np.zeros(3 * n)
    weights = [spread(w, zeros) for w in (ev.w_rim, ev.w_line, ev.w_a, ev.w_b)]
    padded = eqx.tree_at(
        lambda e: (e.x_px, e.y_px, e.w_rim, e.w_line, e.w_a, e.w_b),
        ev,
        (spread(ev.x_px, xy_fill), spread(ev.y_px, xy_fill[::-1]), *weights),
    )
    small, complete = weighted_points(padded, n + 5)
    assert bool(complete)
    np.testing.assert_array_equal(np.asarray(small.x_px[:n]), np.asarray(padded.x_px)[weighted])
    assert float(jnp.sum(small.w_line)) == pytest.approx(float(jnp.sum(ev.w_line)))
    assert float(jnp.sum(small.w_rim[n:])) == 0.0
    full, fast = fit(padded), fit(padded, capacity=n + 5)
    assert bool(full.ok) and bool(fast.ok)
    np.testing.assert_allclose(np.asarray(fast.params), np.asarray(full.params), atol=1e-6)
    assert fast.residuals.shape == full.residuals.shape
    # More weighted points than the capacity (a speckled mask): the fit on every slot, not a
    # fit of some of them.
    over = fit(padded, capacity=n - 1)
    assert bool(over.ok)
    np.testing.assert_allclose(np.asarray(over.params), np.asarray(full.params), atol=1e-6)


def test_bad_rect_rows(rendered) -> None:
    images, _, _ = rendered("clean", n=1)
    bad = Rig(wheel_radius_mm=140.0, confidence_rect=(W - 5, 10, 20, 20))
    rows = estimate_batch(images, bad, ["a"])
    assert rows[0].status == "bad_rect" and "extends beyond" in rows[0].message


def test_run_summary_says_which_features_each_recording_was_segmented_by(rendered, tmp_path):
    """No setting: a coloured wheel is segmented by hue and saturation, a black one by intensity
    and texture; every frame says so and the run summary counts it per recording, printed and
    in ``--summary``. Reference: the saturation of the wheel's paint in the rendered scene."""
    expected, folders = {}, []
    for preset in ("clean", "black_wheel"):
        images, _, rig = rendered(preset, n=2)
        # The scenes rendered() drew (same generator), without rendering them again.
        rng = np.random.default_rng(11)
        scene = synth.recording_scenes(rng, 2, preset=preset, width=W, height=H)[0]
        saturation = colorsys.rgb_to_hsv(*scene.wheel_rgb)[1]
        assert saturation < 0.05 or saturation > 0.2, saturation  # a clear case either way
        folder = tmp_path / preset
        folder.mkdir()
        for i, image in enumerate(images):
            assert cv2.imwrite(str(folder / f"f{i}.png"), image[..., ::-1])
        save_rig(rig, folder / "rig.toml")
        folders.append(folder)
        expected[preset] = "hue+saturation" if saturation > 0.2 else "intensity+texture"
    assert set(expected.values()) == {"hue+saturation", "intensity+texture"}

    run = estimate_to_csv(folders, tmp_path / "r.csv", summary_csv=tmp_path / "s.csv")
    names = [name for name, _ in run.recordings]
    assert run.n_frames == 4
    assert run.segmenter_lines() == [
        "segmenter:",
        *(f"  {name}: {expected[p]} (2 frames)" for name, p in zip(names, expected, strict=True)),
    ]
    with open(tmp_path / "s.csv", newline="") as f:
        cells = [row["segmenter"] for row in csv.DictReader(f)]
    assert cells == [f"{expected[p]} (2 frames)" for p in expected]


def test_boundary_ends_skip_a_stray_edge_beyond_a_gap() -> None:
    """The ends are the end-most points that start a stretch of boundary (half their window
    filled): a pair of points 9 px beyond the boundary's end (a lug's corner near the rim) is
    not B, and a contiguous boundary's ends are its plain extremes."""
    u = np.r_[np.arange(-40.0, 41.0), -50.9, -50.1]  # the boundary, one point a pixel; a pair
    present = jnp.asarray(np.r_[np.ones(81, bool), True, True])
    order = np.random.default_rng(0).permutation(u.size)  # outline order is arbitrary
    i_a, i_b = boundary_ends(jnp.asarray(u[order]), present[order], jnp.asarray(12.0))
    assert u[order][int(i_a)] == 40.0 and u[order][int(i_b)] == -40.0
    # Without the pair, or with the pair 2 px from the boundary (a stretch): plain extremes.
    near = np.r_[np.arange(-40.0, 41.0), -42.0, -43.0]
    i_a, i_b = boundary_ends(jnp.asarray(near), present, jnp.asarray(12.0))
    assert near[int(i_a)] == 40.0 and near[int(i_b)] == -43.0
    # Not a present point: never an end. A boundary shorter than half a window: the extremes.
    absent = present.at[81].set(False).at[82].set(False)
    short = boundary_ends(jnp.asarray(u), absent.at[:75].set(False), jnp.asarray(40.0))
    assert (u[int(short[0])], u[int(short[1])]) == (40.0, 35.0)
