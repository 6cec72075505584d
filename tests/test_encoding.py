"""The rig's ``encoding``: sRGB-encoded frames are measured with their edges in linear light."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax import synth as S
from sinkjax.app.sources import RigOverrides
from sinkjax.rig import Rig, RigError, load_rig, rig_from_dict, rig_to_toml
from sinkjax.soft.batch import estimate_batch
from sinkjax.soft.colour import linear_light, srgb_to_linear
from sinkjax.synth.raster import srgb_encode
from sinkjax.synth.recording import frame_seed

# IEC 61966-2-1 worked values: sRGB 0.5 is 21.4 % of full light, 50 % light is sRGB 0.7354.
SRGB_HALF_TO_LINEAR = 0.21404114048223255
LINEAR_HALF_TO_SRGB = 0.7353569830524495


def test_srgb_decoding_matches_the_standard_and_inverts_the_renderers_encoding() -> None:
    assert float(srgb_to_linear(jnp.asarray(0.5))) == pytest.approx(SRGB_HALF_TO_LINEAR, rel=1e-6)
    assert float(srgb_encode(np.float32(0.5))) == pytest.approx(LINEAR_HALF_TO_SRGB, rel=1e-6)
    # Below the knee the curve is the straight line v / 12.92; the two pieces meet there.
    assert float(srgb_to_linear(jnp.asarray(0.02))) == pytest.approx(0.02 / 12.92, rel=1e-6)
    knee = 0.04045
    below = float(srgb_to_linear(jnp.asarray(knee - 1e-6)))
    above = float(srgb_to_linear(jnp.asarray(knee + 1e-6)))
    assert above - below == pytest.approx(0.0, abs=1e-6)
    x = np.linspace(0.0, 1.0, 1001, dtype=np.float32)
    np.testing.assert_allclose(
        np.asarray(srgb_to_linear(jnp.asarray(srgb_encode(x)))), x, atol=2e-6
    )


def test_srgb_decoding_has_finite_gradients_that_match_finite_differences() -> None:
    grad = jax.grad(lambda v: jnp.sum(srgb_to_linear(v)))
    points = jnp.asarray([0.0, 0.01, 0.04045, 0.2, 0.5, 0.9, 1.0])
    g = np.asarray(grad(points))
    assert np.all(np.isfinite(g))
    h = 1e-3
    for v in (0.01, 0.2, 0.5, 0.9):
        fd = (
            float(srgb_to_linear(jnp.asarray(v + h))) - float(srgb_to_linear(jnp.asarray(v - h)))
        ) / (2 * h)
        got = float(grad(jnp.asarray([v]))[0])
        assert got == pytest.approx(fd, rel=1e-3)


def test_linear_light_is_one_compiled_function_for_both_encodings() -> None:
    image = jnp.asarray(np.random.default_rng(0).uniform(0, 1, (6, 5, 3)), jnp.float32)
    fn = jax.jit(linear_light)
    plain = fn(image, jnp.asarray(0.0, jnp.float32))
    decoded = fn(image, jnp.asarray(1.0, jnp.float32))
    assert fn._cache_size() == 1
    np.testing.assert_array_equal(np.asarray(plain), np.asarray(image))
    np.testing.assert_allclose(np.asarray(decoded), np.asarray(srgb_to_linear(image)), rtol=1e-6)
    # Under vmap over frames too (the flag is the rig's: not batched).
    both = jax.vmap(linear_light, in_axes=(0, None))(jnp.stack([image, image]), True)
    np.testing.assert_allclose(np.asarray(both[1]), np.asarray(decoded), rtol=1e-6)


def test_the_rig_file_reads_writes_and_checks_its_encoding(tmp_path) -> None:
    base = {"wheel_radius_mm": 140.0, "confidence_rect": [10, 10, 20, 10]}
    assert rig_from_dict(base).encoding == "linear"
    rig = rig_from_dict({**base, "encoding": "srgb"})
    assert rig.encoding == "srgb"
    path = tmp_path / "rig.toml"
    path.write_text(rig_to_toml(rig))
    assert load_rig(path).encoding == "srgb"
    # The default is not written: a linear rig's file is what it was before the key existed.
    assert "encoding" not in rig_to_toml(dataclasses.replace(rig, encoding="linear"))
    with pytest.raises(RigError, match='encoding must be "linear" or "srgb"'):
        rig_from_dict({**base, "encoding": "gamma"})
    with pytest.raises(RigError, match="did you mean 'encoding'"):
        rig_from_dict({**base, "encodng": "srgb"})
    with pytest.raises(RigError):
        Rig(wheel_radius_mm=140.0, confidence_rect=(1, 1, 2, 2), encoding="SRGB")
    # --encoding overrides every recording's rig, like the other single-field flags.
    flags = RigOverrides(encoding="srgb").as_dict()
    assert flags == {"encoding": "srgb"}
    assert rig_from_dict({**base, **flags}).encoding == "srgb"


def test_the_renderer_stores_srgb_frames_with_the_curve_and_says_so_in_the_rig() -> None:
    rng = np.random.default_rng(5)
    scene = dataclasses.replace(
        S.recording_scenes(rng, 1, preset="clean")[0], noise_std=0.0, jpeg_quality=0
    )
    linear, t_lin = S.render(scene, seed=3)
    coded, t_srgb = S.render(dataclasses.replace(scene, encoding="srgb"), seed=3)
    want = 255.0 * srgb_encode(linear.astype(np.float32) / 255.0)
    # The curve is applied before rounding to 8 bits: within the rounding of both images.
    assert np.max(np.abs(coded.astype(np.float32) - want)) <= 6.0
    assert np.median(np.abs(coded.astype(np.float32) - want)) <= 0.5
    assert t_lin == t_srgb  # the geometry, and so the truth, is the same
    assert S.rig_for(dataclasses.replace(scene, encoding="srgb")).encoding == "srgb"
    assert S.rig_for(scene).encoding == "linear"


@pytest.mark.slow
def test_srgb_frames_measure_closer_to_the_truth_with_the_rigs_encoding_set() -> None:
    # Full-mix scenes (blur 0.7 px, noise, JPEG) stored with the sRGB curve, as a camera does: a
    # blurred edge's dark half is lifted by the curve, so edges located on the stored values sit
    # off the truth (0.20 mm median here); decoded to linear light they mix linearly again (0.05).
    rng = np.random.default_rng(11)
    scenes = [
        dataclasses.replace(s, encoding="srgb") for s in S.recording_scenes(rng, 8, preset="full")
    ]
    assert scenes[0].blur_sigma_px > 0.5  # the effect needs a blurred edge
    rendered = [S.render(s, seed=frame_seed(11, i)) for i, s in enumerate(scenes)]
    images = [im for im, _ in rendered]
    truth = np.asarray([t.sinkage_mm for _, t in rendered])
    errors = {}
    for encoding in ("linear", "srgb"):
        rig = dataclasses.replace(S.rig_for(scenes[0]), encoding=encoding)
        rows = estimate_batch(images, rig, [str(i) for i in range(len(images))])
        assert all(str(r.status) == "ok" for r in rows)
        est = np.asarray([r.sinkage_mm for r in rows], float)
        errors[encoding] = np.abs(est - truth)
    assert np.median(errors["srgb"]) < 0.5 * np.median(errors["linear"])


def test_a_calibrated_rig_keeps_the_encoding_and_the_rim_hint() -> None:
    from sinkjax.calibration.loss import to_raw
    from sinkjax.calibration.optimise import _with

    rig = Rig(
        wheel_radius_mm=140.0, confidence_rect=(1, 1, 4, 4), rim_radius_px=80.0, encoding="srgb"
    )
    raw = to_raw(rig.segmentation)
    out = _with(rig, raw.at[0].add(0.1))
    assert (out.encoding, out.rim_radius_px, out.travel) == ("srgb", 80.0, rig.travel)
    assert out.segmentation.as_dict() != rig.segmentation.as_dict()
    assert _with(rig, raw).segmentation.as_dict() == pytest.approx(rig.segmentation.as_dict())
