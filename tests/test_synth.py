"""The synthetic renderer: reproducible, and its truth agrees with its own pixels."""

from __future__ import annotations

import colorsys
import csv
import math
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax import synth as synth
from sinkjax.geometry import geometry_from_boundary
from sinkjax.rig import load_rig
from sinkjax.synth.layers import FACE, RIM, hole_centres
from sinkjax.synth.presets import camera_setup, with_terrain
from sinkjax.synth.recording import frame_seed


def _plain(scene: synth.Scene) -> synth.Scene:
    """``scene`` without anything that moves a colour crossing off the analytic edge: no noise,
    blur, JPEG, lugs, shadow, highlights, dust or fine texture (smooth shading gradients stay)."""
    return replace(
        scene,
        noise_std=0.0,
        blur_sigma_px=0.0,
        jpeg_quality=0,
        n_lugs=0,
        lug_height_px=0.0,
        shadow_factor=1.0,
        specular=(),
        lamp_white=0.0,
        dust=0.0,
        soil_texture=0.0,
        pebbles=0,
        face_texture=0.0,
    )


def _scene(kind: str, seed: int, preset: str = "clean", **kw: object) -> synth.Scene:
    rng = np.random.default_rng(seed)
    base = camera_setup(rng, kw.pop("width", 320), kw.pop("height", 240), preset)  # type: ignore[arg-type]
    return with_terrain(rng, replace(base, **kw), kind, contact=True)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- reproducibility


def test_same_seed_same_bytes_different_seed_differs():
    scene = synth.random_scene(np.random.default_rng(3), width=200, height=150, preset="full")
    a, ta = synth.render(scene, seed=7)
    b, tb = synth.render(scene, seed=7)
    c, _ = synth.render(scene, seed=8)
    assert a.dtype == np.uint8 and a.shape == (150, 200, 3)
    assert a.tobytes() == b.tobytes()
    assert ta == tb
    assert a.tobytes() != c.tobytes()
    s1 = synth.random_scene(np.random.default_rng(11), preset="dust")
    s2 = synth.random_scene(np.random.default_rng(11), preset="dust")
    assert s1 == s2


@pytest.mark.parametrize("preset", synth.PRESETS)
def test_presets_render_with_valid_rig(preset):
    scenes = synth.recording_scenes(
        np.random.default_rng(5), 5, preset=preset, width=240, height=180
    )
    assert len({(s.centre_x_px, s.centre_y_px, s.radius_px, s.wheel_rgb) for s in scenes}) == 1
    assert [s.terrain for s in scenes] == list(synth.TERRAINS)
    rig = synth.rig_for(scenes[0])
    x, y, w, h = rig.confidence_rect
    assert w * h >= 0.008 * math.pi * scenes[0].radius_px ** 2
    for s in scenes:
        # The rectangle shows nothing but wheel face, whatever the phase, holes, lugs or soil.
        cov = synth.coverage(s)[y : y + h, x : x + w]
        assert np.all(cov[..., FACE] == 1.0)
        img, truth = synth.render(s, seed=1)
        assert img.shape == (180, 240, 3)
        if truth.contact:
            assert synth.n_rim_crossings(s) == 2


# ----------------------------------------------------------------------------- truth vs pixels


def _crossing(t: np.ndarray) -> float | None:
    """Sub-pixel index where the fraction profile ``t`` first crosses 0.5 (linear interpolation)."""
    idx = np.flatnonzero((t[:-1] < 0.5) & (t[1:] >= 0.5))
    if idx.size != 1:
        return None
    i = idx[0]
    return i + (0.5 - t[i]) / (t[i + 1] - t[i])


def _edge_deviations_px(
    img: np.ndarray, scene: synth.Scene, *, method: str = "crossing", strict: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """|edge found in the pixels - analytic edge| for the rim (upper half) and the soil line.

    Edges are found from pixels alone, along image columns (rim top, soil line) and rows (rim
    sides): each pixel's colour is expressed as the fraction t of the way from the colour a few
    px before the edge to the colour a few px after it (4 px; on the rim, within the rim ring).
    ``method="crossing"``: where t crosses 0.5, linearly interpolated between pixel centres (off
    by up to ~0.1 px even for a perfect box-filtered edge, as that profile is only piecewise
    linear). ``method="area"``: the edge is the window end minus sum(t), exact for an
    area-sampled straight edge. Only the window position comes from the truth. ``strict``
    asserts every probe finds one crossing (noise-free frames); otherwise ambiguous probes are
    skipped. Returns (rim deviations, soil deviations), px.
    """
    im = img.astype(np.float64)
    cx, cy, r = scene.centre_x_px, scene.centre_y_px, scene.radius_px
    # Reference colours must come from the rim ring itself, not the face beyond it.
    rim_w = max(2, min(4, int(scene.rim_width_px) - 2))
    rim_dev: list[float] = []
    soil_dev: list[float] = []

    def check(out: list[float], line: np.ndarray, edge: float, where: str, half_w: int = 4) -> None:
        e = math.floor(edge)
        if e - half_w < 0 or e + half_w + 1 >= line.shape[0]:
            return
        lo, hi = line[e - half_w], line[e + half_w + 1]
        axis = hi - lo
        t = (line[e - half_w + 1 : e + half_w + 1] - lo) @ axis / (axis @ axis)
        got = _crossing(t)
        assert got is not None or not strict, f"no unique crossing in {where}"
        if got is None:
            return
        if method == "area":
            found = e + half_w + 0.5 - float(np.sum(t))
        else:
            found = e - half_w + 1 + got
        out.append(abs(found - edge))

    # Rim, upper half: columns near the top, rows near the sides (edge crossed steeply).
    for j in range(math.ceil(cx - 0.7 * r), math.floor(cx + 0.7 * r) + 1):
        check(rim_dev, im[:, j], cy - math.sqrt(r * r - (j - cx) ** 2), f"column {j}", rim_w)
    for i in range(math.ceil(cy - 0.7 * r), math.floor(cy - 0.05 * r)):
        half = math.sqrt(r * r - (i - cy) ** 2)
        check(rim_dev, im[i], cx + half, f"row {i}", rim_w)
        check(rim_dev, im[i, ::-1], (scene.width - 1) - (cx - half), f"row {i}", rim_w)
    # Soil line: every column where the surface is at least 6 px from any other edge.
    surf = synth.surface_y_px(scene, np.arange(scene.width, dtype=np.float64))
    for j in range(scene.width):
        y = surf[j]
        d = math.hypot(j - cx, y - cy)
        others = [d - r, d - (r - scene.rim_width_px), d - scene.hub_radius_px]
        others += [
            math.hypot(j - hx, y - hy) - scene.hole_radius_px for hx, hy in hole_centres(scene)
        ]
        if min(abs(o) for o in others) < 6 or y > scene.height - 6:
            continue
        check(soil_dev, im[:, j], y, f"soil column {j}")
    return np.array(rim_dev), np.array(soil_dev)


@pytest.mark.parametrize(("kind", "seed"), [(k, s) for s, k in enumerate(synth.TERRAINS)])
def test_truth_matches_rendered_edges(kind, seed):
    scene = _plain(_scene(kind, seed, width=320, height=240))
    img, truth = synth.render(scene, seed=0)
    assert truth.contact
    rim, soil = _edge_deviations_px(img, scene)
    print(
        f"{kind} crossing: max |dev| rim {rim.max():.3f} px ({rim.size}), soil {soil.max():.3f} px"
    )
    assert rim.size > 100 and soil.size > 50
    assert rim.max() < 0.5
    assert soil.max() < 0.5
    # Area-based edges are exact for area-sampled edges: what is left is the coverage quantisation
    # (8x8 samples per edge pixel) and colour drift inside the window, so flatten the lighting.
    flat_lit = replace(
        scene, shading=0.0, wall_gradient=0.0, wall_texture=0.0, soil_rgb2=scene.soil_rgb
    )
    img, _ = synth.render(flat_lit, seed=0)
    rim, soil = _edge_deviations_px(img, flat_lit, method="area")
    print(
        f"{kind} area: |dev| rim median {np.median(rim):.3f} max {rim.max():.3f} px, "
        f"soil median {np.median(soil):.3f} max {soil.max():.3f} px"
    )
    assert np.median(rim) < 0.05 and rim.max() < 0.1
    assert np.median(soil) < 0.05 and soil.max() < 0.1


def test_truth_matches_rendered_edges_textured_clean_preset():
    # The clean preset as shipped (texture, pebbles, mild noise and blur): edges stay on the truth
    # on the whole; single probes can be pulled by a pebble touching the surface.
    scene = _scene("rough", 42, width=320, height=240)
    img, _ = synth.render(scene, seed=0)
    rim, soil = _edge_deviations_px(img, scene, strict=False)
    print(
        f"clean: rim median {np.median(rim):.3f} max {rim.max():.3f}; soil median "
        f"{np.median(soil):.3f} p90 {np.quantile(soil, 0.9):.3f} max {soil.max():.3f} px"
    )
    assert rim.size > 200 and soil.size > 50
    assert np.median(rim) < 0.15 and rim.max() < 0.5
    assert np.median(soil) < 0.25 and np.quantile(soil, 0.9) < 0.5


def test_coverage_is_the_area_of_the_rim_disc():
    scene = replace(
        _plain(synth.Scene(width=200, height=200, centre_x_px=99.3, centre_y_px=90.6)),
        radius_px=60.3,
        soil_level_px=400.0,
        hub_radius_px=0.0,
        rim_width_px=8.0,
    )
    cov = synth.coverage(scene)
    inside = cov[..., FACE] + cov[..., RIM]
    assert inside.sum() == pytest.approx(math.pi * 60.3**2, rel=2e-4)
    assert cov[..., RIM].sum() == pytest.approx(math.pi * (60.3**2 - 52.3**2), rel=1e-3)


# ----------------------------------------------------------------------------- truth sanity


def test_flat_truth_is_the_textbook_identity():
    for z0 in (0.7, 5.0, 23.4, 61.0):
        scene = synth.Scene(radius_px=150.0, centre_y_px=200.0, soil_level_px=350.0 - z0)
        t = synth.true_geometry(scene)
        assert t.contact
        assert t.sinkage_px == pytest.approx(z0, abs=1e-9)
        expect = math.degrees(math.acos(1 - z0 / 150.0))
        assert t.theta1_deg == pytest.approx(expect, abs=1e-6)
        assert t.theta2_deg == pytest.approx(expect, abs=1e-6)
        assert t.sinkage_mm == pytest.approx(z0 * 140.0 / 150.0, abs=1e-9)
        assert t.k == pytest.approx(0.0, abs=1e-12)


def test_truth_ends_on_rim_and_matches_geometry_module():
    # One jitted Eqs. 1-3 from the JAX module, fed zero-weight-padded boundaries (one compile).
    n_pad = 4096
    geometry = jax.jit(
        lambda x, y, w, cx, cy, r, a, b: geometry_from_boundary(
            x, y, cx, cy, r, weight=w, a_px=a, b_end_px=b
        )
    )
    for seed, kind in enumerate(synth.TERRAINS):
        scene = _scene(kind, seed + 3, preset="full")
        t = synth.true_geometry(scene)
        x, y = synth.boundary_points(scene)
        assert np.all(np.diff(x) <= 0.05 + 1e-12) and x.size <= n_pad
        for u, v in (t.a_px, t.b_end_px):
            assert math.hypot(u, v) == pytest.approx(scene.radius_px, abs=1e-6)
            xi = np.array(scene.centre_x_px + u)  # travel right: wheel frame u = x - cx
            v_surface = synth.surface_y_px(scene, xi) - scene.centre_y_px
            assert v_surface == pytest.approx(v, abs=1e-6)
        w = np.zeros(n_pad)
        w[: x.size] = 1.0
        xp, yp = np.full(n_pad, x[0]), np.full(n_pad, y[0])
        xp[: x.size], yp[: x.size] = x, y
        c = jnp.asarray([scene.centre_x_px, scene.centre_y_px, scene.radius_px])
        g = geometry(xp, yp, w, c[0], c[1], c[2], jnp.asarray(t.a_px), jnp.asarray(t.b_end_px))
        assert float(g.sinkage_px) == pytest.approx(t.sinkage_px, abs=1e-8)
        assert float(g.k) == pytest.approx(t.k, abs=1e-10)
        assert math.degrees(float(g.theta1_rad)) == pytest.approx(t.theta1_deg, abs=1e-8)
        assert math.degrees(float(g.theta2_rad)) == pytest.approx(t.theta2_deg, abs=1e-8)


def test_truth_angles_atan2_form():
    # A ahead of O and B behind it: the paper's Eqs. 2-3 as printed.
    t = synth.true_geometry(_scene("bulldozed", 4, preset="full"))
    (ua, va), (ub, vb) = t.a_px, t.b_end_px
    assert ua > 0 > ub
    assert t.theta1_deg == pytest.approx(90 - math.degrees(math.atan(va / ua)), abs=1e-9)
    assert t.theta2_deg == pytest.approx(90 + math.degrees(math.atan(vb / ub)), abs=1e-9)
    # A 45-degree slope rising to the entry side that touches only the entry half of the rim:
    # B lies ahead of O, so theta2 = atan2(-x_B, y_B) < 0 (docs/conventions.md §1).
    r, cy = 100.0, 120.0
    scene = synth.Scene(
        width=320, height=240, centre_x_px=160.0, centre_y_px=cy, radius_px=r,
        soil_level_px=cy + 1.2 * r, tilt=-1.0,
    )  # fmt: skip
    t = synth.true_geometry(scene)
    (ua, va), (ub, vb) = t.a_px, t.b_end_px
    assert t.contact and ua > ub > 0
    assert t.theta2_deg == pytest.approx(math.degrees(math.atan2(-ub, vb)), abs=1e-9)
    assert t.theta2_deg < -5 and t.theta1_deg > 0


def test_travel_left_swaps_angles_and_mirror_keeps_truth():
    scene = _scene("bulldozed", 8, preset="full")
    right = synth.true_geometry(scene)
    left = synth.true_geometry(replace(scene, travel="left"))
    assert left.sinkage_mm == pytest.approx(right.sinkage_mm, abs=1e-9)
    assert left.theta1_deg == pytest.approx(right.theta2_deg, abs=1e-9)
    assert left.theta2_deg == pytest.approx(right.theta1_deg, abs=1e-9)
    assert right.theta1_deg > right.theta2_deg + 1  # the pile is ahead, on the entry side
    m = synth.true_geometry(synth.mirrored(scene))
    for name in ("sinkage_mm", "theta1_deg", "theta2_deg", "k", "b_px"):
        assert getattr(m, name) == pytest.approx(getattr(right, name), abs=1e-8)
    # The mirrored scene has the mirrored layout (up to the sample pattern, which is not
    # mirror-symmetric: a few samples per edge pixel).
    cov_a = synth.coverage(scene)
    cov_b = synth.coverage(synth.mirrored(scene))[:, ::-1]
    assert np.abs(cov_a - cov_b).max() <= 0.25
    np.testing.assert_allclose(cov_a.sum((0, 1)), cov_b.sum((0, 1)), rtol=2e-3, atol=2)
    lefts = synth.recording_scenes(
        np.random.default_rng(2), 4, travel="left", width=240, height=180
    )
    rights = synth.recording_scenes(
        np.random.default_rng(2), 4, travel="right", width=240, height=180
    )
    for sl, sr in zip(lefts, rights, strict=True):
        assert sl.travel == "left"
        tl, tr = synth.true_geometry(sl), synth.true_geometry(sr)
        assert tl.sinkage_mm == pytest.approx(tr.sinkage_mm, abs=1e-8)
        assert tl.theta1_deg == pytest.approx(tr.theta1_deg, abs=1e-8)


def test_no_contact_frames_are_zero():
    scene = synth.Scene(radius_px=150.0, centre_y_px=200.0, soil_level_px=352.0)
    t = synth.true_geometry(scene)
    assert not t.contact
    assert (t.sinkage_mm, t.theta1_deg, t.theta2_deg, t.sinkage_px, t.k, t.b_px) == (0,) * 6
    rng = np.random.default_rng(0)
    base = camera_setup(rng, 320, 240, "full")
    for kind in synth.TERRAINS:
        s = with_terrain(rng, base, kind, contact=False)
        assert not synth.true_geometry(s).contact
        assert synth.n_rim_crossings(s) == 0


def test_random_scenes_spread_sinkage_and_wheel_colours():
    rng = np.random.default_rng(123)
    scenes = [synth.random_scene(rng, width=320, height=240) for _ in range(120)]
    truths = [synth.true_geometry(s) for s in scenes]
    z = np.array([t.sinkage_mm for t in truths if t.contact])
    assert 0.8 * len(scenes) < z.size < len(scenes)
    assert 0.04 < np.mean(z < 5) < 0.25
    assert z.max() < 60 and np.mean(z < 50) > 0.9
    hues = [colorsys.rgb_to_hsv(*s.wheel_rgb)[0] * 360 for s in scenes]
    assert any(h < 8 or h > 352 for h in hues)  # red, across the hue wrap
    for s in scenes:
        r = s.radius_px
        assert 0.25 * 240 <= r <= 0.4 * 240
        assert s.centre_y_px - r - s.lug_height_px >= 0
        assert s.centre_y_px + r < 240 - 20  # soil visible below the wheel
        if s.n_lugs:
            assert s.lug_width_px < 0.5 * 2 * math.pi * r / s.n_lugs


# ----------------------------------------------------------------------------- recording


def test_write_recording(tmp_path):
    out = synth.write_recording(
        tmp_path / "rec", n_frames=3, seed=4, preset="full", width=200, height=150, progress=False
    )
    rows = list(csv.reader((out / "truth.csv").open()))
    assert tuple(rows[0]) == synth.TRUTH_COLUMNS
    assert rows[0][:4] == ["image", "sinkage_mm", "theta1_deg", "theta2_deg"]
    assert [r[0] for r in rows[1:]] == ["frame_0000.jpg", "frame_0001.jpg", "frame_0002.jpg"]
    for r in rows[1:]:
        assert (out / r[0]).is_file()
        assert r[5] in ("true", "false")
        float(r[1]), float(r[2]), float(r[3])
    rig = load_rig(out / "rig.toml")
    assert rig.wheel_radius_mm == 140.0 and rig.travel == "right"
    x, y, w, h = rig.confidence_rect
    assert x + w <= 200 and y + h <= 150
    clean = synth.write_recording(
        tmp_path / "clean",
        n_frames=2,
        preset="clean",
        width=200,
        height=150,
        travel="left",
        progress=False,
    )
    assert (clean / "frame_0001.png").is_file()
    assert load_rig(clean / "rig.toml").travel == "left"
    # The written PNG is exactly the rendered frame.
    import cv2

    scenes = synth.recording_scenes(
        np.random.default_rng(0), 2, preset="clean", width=200, height=150, travel="left"
    )
    img, _ = synth.render(scenes[1], frame_seed(0, 1))
    disk = cv2.imread(str(clean / "frame_0001.png"))[..., ::-1]
    assert np.array_equal(img, disk)


def test_hard_presets_are_hard_and_leave_the_others_alone():
    from sinkjax.synth.hard import HARD_PRESETS, harden

    assert synth.PRESETS[:6] == ("clean", "full", "shading", "dust", "cast", "lowlight")
    # A hard set-up is the full set-up drawn first, made worse: same geometry and soil.
    full = camera_setup(np.random.default_rng(9), 320, 240, "full")
    for preset in HARD_PRESETS:
        hard = camera_setup(np.random.default_rng(9), 320, 240, preset)
        assert (hard.radius_px, hard.soil_rgb, hard.n_lugs) == (
            full.radius_px,
            full.soil_rgb,
            full.n_lugs,
        )
        assert len(hard.specular) >= 3 and max(a for *_, a in hard.specular) >= 0.4
    with pytest.raises(ValueError, match="hard_"):
        harden(np.random.default_rng(0), full, "full")

    def hue(rgb):
        return colorsys.rgb_to_hsv(*rgb)[0] * 360

    def gap(a, b):
        d = abs(a - b) % 360
        return min(d, 360 - d)

    # The cast tints the soil towards the wheel's hue: the hue gap shrinks.
    for seed in range(4):
        s = camera_setup(np.random.default_rng(seed), 320, 240, "hard_cast")
        cast = np.asarray(s.cast_rgb)
        before = gap(hue(s.soil_rgb), hue(s.wheel_rgb))
        after = gap(hue(np.asarray(s.soil_rgb) * cast), hue(np.asarray(s.wheel_rgb) * cast))
        assert after < before - 5
    # hard_mix recordings cycle in hollow_ahead: soil only on the entry half, B ahead of O.
    scenes = synth.recording_scenes(
        np.random.default_rng(1), 6, preset="hard_mix", width=240, height=180
    )
    assert [s.terrain for s in scenes] == [*synth.TERRAINS, "hollow_ahead"]
    t = synth.true_geometry(scenes[-1])
    assert t.b_end_px[0] > 0 and t.theta2_deg < 0 < t.theta1_deg
    img, _ = synth.render(scenes[-1], seed=0)
    assert img.shape == (180, 240, 3)
