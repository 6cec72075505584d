"""Learned segmenters (sinkjax.learn): gradients through the fit against finite differences,
save/load round trip and clear errors for bad files, training lowers the loss, the estimator and
the command line use a saved model. Rendered frames (sinkjax.synth) are the reference."""

from __future__ import annotations

import csv
import functools
import json
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax import learn as L
from sinkjax.app.cli import main
from sinkjax.rig import SegmentationParams, save_rig
from sinkjax.soft.adaptive import default_segmenter
from sinkjax.soft.batch import estimate_batch
from sinkjax.soft.estimator import measure_from_mask
from sinkjax.soft.segmenter import Segmenter
from sinkjax.status import Status

W, H = 240, 180


@functools.cache
def recording(preset: str = "full", seed: int = 11, n: int = 3) -> L.LabelledRecording:
    return L.synthetic_recording(n, seed=seed, preset=preset, width=W, height=H)


@pytest.fixture(scope="session")
def started(computed_once) -> Callable[[str], L.LearnedSegmenter]:
    """``started(kind)``: a model that imitated the exact masks: its fit measures every frame.
    Imitated once per session, by whichever worker needs it first (saved and loaded exactly)."""

    @functools.cache
    def model(kind: str) -> L.LearnedSegmenter:
        def imitate(path: Path) -> None:
            batches = L.frame_batches([recording()])
            seg, ce = L.imitate(L.build(kind, key=1), batches, steps=120, learning_rate=2e-2)
            assert ce < 0.15
            L.save_segmenter(path, seg)

        return L.load_segmenter(computed_once(f"learn_started_{kind}.seg", imitate))

    return model


def _directional(seg: L.LearnedSegmenter, batch: L.FrameBatch, d, eps: float) -> float:
    params, static = eqx.partition(seg, eqx.is_array)

    def loss(t: float) -> float:
        moved = jax.tree_util.tree_map(lambda p, v: p.astype(jnp.float64) + t * v, params, d)
        return float(L.loss_and_grad(eqx.combine(moved, static), batch, 0.1, 2.0)[0])

    return (loss(eps) - loss(-eps)) / (2 * eps)


def _residual(kind: str) -> L.LearnedSegmenter:
    """A residual model whose correction is small but not zero (so that every layer has a
    gradient): its head's weights drawn at 1 % of their usual scale."""
    seg = L.build(kind, key=2, residual=1)
    head = seg.weights[-1] if kind == "mlp" else seg.head[0]
    small = 0.01 * jax.random.normal(jax.random.PRNGKey(5), head.shape, head.dtype)
    return eqx.tree_at(lambda s: s.weights[-1] if kind == "mlp" else s.head[0], seg, small)


@pytest.mark.slow
# The residual wrapper (base log-odds, its extra input, the scaled correction) is the same code
# for both networks, and both networks are checked on their own: one residual case suffices
# (in `make test`; the two plain networks' cases, over a minute each, in `make test-heavy`).
@pytest.mark.parametrize(
    "kind",
    [
        pytest.param("mlp", marks=pytest.mark.heavy),
        pytest.param("cnn", marks=pytest.mark.heavy),
        "mlp-residual",
    ],
)
def test_frame_loss_gradient_matches_finite_differences(kind: str, started) -> None:
    seg = _residual(kind.split("-")[0]) if kind.endswith("residual") else started(kind)
    batch = L.frame_batches([recording()])[0]
    as64 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float64) if eqx.is_array(x) else x, seg)
    value, grad, seen = L.loss_and_grad(as64, batch, 0.1, 2.0)
    assert np.all(np.asarray(seen[:, 3]) == Status.OK.code)  # every frame measures
    assert float(value) > 0
    params = eqx.filter(as64, eqx.is_array)
    # The implicit gradient is exact at the optimum; the solve stops within its tolerance
    # (1e-4), which leaves an absolute error of about 1e-4 of the gradient's size in every
    # direction (measured: 2e-3 on directional derivatives of 2-13 and on one of 0.1 alike).
    # A random direction nearly orthogonal to the gradient has no relative accuracy to give, so
    # each direction is held to 0.5 % of its own derivative or 0.1 % of the gradient's norm.
    g_norm = float(jnp.sqrt(sum(jnp.sum(g * g) for g in jax.tree_util.tree_leaves(grad))))
    rng = np.random.default_rng(0)
    for _ in range(3):
        d = jax.tree_util.tree_map(lambda p: jnp.asarray(rng.normal(size=p.shape)), params)
        ad = sum(
            float(jnp.sum(g * v))
            for g, v in zip(
                jax.tree_util.tree_leaves(grad), jax.tree_util.tree_leaves(d), strict=True
            )
        )
        fd = _directional(as64, batch, d, 1e-6)
        np.testing.assert_allclose(ad, fd, rtol=5e-3, atol=1e-3 * g_norm + 1e-8)


def test_save_load_round_trip(tmp_path: Path) -> None:
    image = jnp.asarray(recording().frames.images[0], jnp.float64) / 255.0
    rect = recording().rig.confidence_rect
    for kind, residual in (("mlp", 0), ("cnn", 0), ("mlp", 1), ("cnn", 1)):
        width = {"hidden": 8} if kind == "mlp" else {"channels": 6}
        seg = L.build(kind, key=3, residual=residual, **width)
        if residual:  # a correction that is not zero, so that the comparison below can fail
            seg = _residual(kind)
        path = L.save_segmenter(tmp_path / f"{kind}{residual}.seg", seg, report={"steps": 7})
        back = L.load_segmenter(path)
        assert type(back) is type(seg) and back.hyper == seg.hyper
        for a, b in zip(
            jax.tree_util.tree_leaves(seg), jax.tree_util.tree_leaves(back), strict=True
        ):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        np.testing.assert_array_equal(np.asarray(seg(image, rect)), np.asarray(back(image, rect)))
        header = json.loads(path.read_bytes().split(b"\n", 1)[0])
        assert header["kind"] == kind and header["report"] == {"steps": 7}


@pytest.mark.heavy
def test_a_new_residual_model_measures_what_the_default_method_measures() -> None:
    """Its correction starts at zero: the mask is the default segmenter's (to the 1e-6 of its
    clipped log-odds) and ``estimate_batch`` gives the default method's rows (to 5e-3 mm or
    degree: rounding through the fit), rim and low-light blur included, on a hard recording
    where the default method is far from perfect."""
    rec = L.synthetic_recording(4, seed=7120, preset="hard_mix", width=W, height=H)
    image = jnp.asarray(rec.frames.images[0], jnp.float64) / 255.0
    rect = rec.rig.confidence_rect
    default = default_segmenter(rec.rig.segmentation)
    assert rec.rig.segmentation.as_dict() == SegmentationParams().as_dict()
    names = list(rec.frames.names)
    plain = estimate_batch(list(rec.frames.images), rec.rig, names)
    for kind in ("mlp", "cnn"):
        seg = L.build(kind, key=4, residual=1)
        np.testing.assert_allclose(
            np.asarray(seg(image, rect)), np.asarray(default(image, rect)), atol=1.1e-6
        )
        rows = estimate_batch(list(rec.frames.images), rec.rig, names, segmenter=seg)
        assert [r.status for r in rows] == [r.status for r in plain]
        for a, b in zip(rows, plain, strict=True):
            for field in ("sinkage_mm", "theta1_deg", "theta2_deg", "sinkage_std_mm"):
                x, y = getattr(a, field), getattr(b, field)
                assert (x is None) == (y is None)
                if x is not None:
                    np.testing.assert_allclose(x, y, atol=5e-3)


def test_bad_segmenter_files_give_clear_errors(tmp_path: Path) -> None:
    good = L.save_segmenter(tmp_path / "good.seg", L.build("mlp", key=0))
    data = good.read_bytes()
    head, payload = data.split(b"\n", 1)
    header = json.loads(head)

    def write(name: str, content: bytes) -> Path:
        (tmp_path / name).write_bytes(content)
        return tmp_path / name

    cases = {
        "missing": (tmp_path / "nope.seg", "does not exist"),
        "text": (write("a.seg", b"hello world"), "no header line"),
        "png": (write("b.seg", b"\x89PNG\r\n\x1a\n" + payload), "not a JSON header"),
        "foreign": (write("c.seg", b'{"format": "x"}\n' + payload), "does not say format"),
        "version": (
            write("d.seg", json.dumps(header | {"version": 99}).encode() + b"\n" + payload),
            "version 99",
        ),
        "kind": (
            write("e.seg", json.dumps(header | {"kind": "gan"}).encode() + b"\n" + payload),
            "unknown segmenter kind 'gan'",
        ),
        "hyper": (
            write(
                "f.seg", json.dumps(header | {"hyper": {"hidden": 32}}).encode() + b"\n" + payload
            ),
            "truncated or corrupt",
        ),
        "truncated": (write("g.seg", data[: len(data) - 40]), "truncated or corrupt"),
        "long": (write("h.seg", data + b"\0" * 16), "the file is corrupt"),
    }
    for name, (path, words) in cases.items():
        with pytest.raises(L.SegmenterFileError, match=words):
            L.load_segmenter(path)
        assert name


@pytest.mark.heavy
@pytest.mark.slow
def test_training_a_few_steps_lowers_the_loss(started) -> None:
    batches = L.frame_batches([recording()])
    # A good model with its mask grown (logits + 2): it spreads into the soil, all three frames
    # fail (loss about 18; logits + 1.5 leaves them measuring, loss 5.4). A shrunk mask no longer
    # makes a bad start: the rim edge's dips inside the rim that its soil line left were taken
    # for soil until the boundary had to be one curve (soft.fit.boundary_side); with logits
    # - 1.75 to - 6 every frame now measures.
    good = started("mlp")
    seg = eqx.tree_at(lambda s: s.biases[-1], good, good.biases[-1] + 2.0)
    res = L.train(seg, batches, steps=12, learning_rate=1e-3, eval_every=3, patience=4)
    assert res.train_after.loss < 0.5 * res.train_before.loss
    assert res.train_after.failed < res.train_before.failed
    assert res.best_step > 0
    # The returned model is the best one scored, and its score is what `score` says.
    assert L.score(res.segmenter, batches).loss == pytest.approx(res.train_after.loss)


@pytest.mark.heavy
@pytest.mark.slow
def test_estimate_batch_and_cli_use_a_saved_segmenter(tmp_path: Path, capsys, started) -> None:
    rec = recording()
    seg = started("mlp")
    assert isinstance(seg, Segmenter)
    names = list(rec.frames.names)
    # Each frame's own rim: comparable with measure_from_mask on the frame alone.
    rows = estimate_batch(list(rec.frames.images), rec.rig, names, segmenter=seg, rim="frame")
    image = jnp.asarray(rec.frames.images[0], jnp.float64) / 255.0
    # Jitted: run op by op, the whole method would take half a minute to dispatch.
    direct = jax.jit(measure_from_mask, static_argnames=("travel", "wheel_radius_mm"))(
        image,
        seg(image, rec.rig.confidence_rect),
        travel=rec.rig.travel,
        wheel_radius_mm=rec.rig.wheel_radius_mm,
    )
    assert rows[0].status == Status.OK
    assert rows[0].sinkage_mm == pytest.approx(float(direct.sinkage_mm), rel=1e-9)
    truth = rec.frames.targets[:, 0]
    # The recording's rim (the default) measures as well.
    rows = estimate_batch(list(rec.frames.images), rec.rig, names, segmenter=seg)
    assert np.median(np.abs([r.sinkage_mm for r in rows] - truth) / truth) < 0.10
    assert {r.segmenter_features for r in rows} == {"learned"}  # no hue/intensity choice

    # sinkjax train on a recording on disk, then sinkjax estimate --segmenter with its output.
    from PIL import Image

    folder = tmp_path / "rec"
    folder.mkdir()
    save_rig(rec.rig, folder / "rig.toml")
    with (folder / "LABELS.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["image", "sinkage_mm", "theta1_deg", "theta2_deg"])
        for i, t in enumerate(rec.frames.targets):
            Image.fromarray(rec.frames.images[i]).save(folder / f"f{i}.png")
            w.writerow([f"f{i}.png", *(f"{v:.4f}" for v in t)])
    model = tmp_path / "model.seg"
    args = ["train", str(folder / "LABELS.csv"), "--out", str(model), "--steps", "2"]
    assert main([*args, "--held-out", "0", "--eval-every", "1"]) == 0
    assert L.load_segmenter(model).kind == "mlp" and L.load_segmenter(model).residual
    out = tmp_path / "results.csv"
    capsys.readouterr()
    assert main(["estimate", str(folder), "--segmenter", str(model), "--out", str(out)]) == 0
    assert len(out.read_text().splitlines()) == 1 + len(truth)
    # A residual model (train's default) names the default segmenter's choice beneath it.
    line = f"segmenter: learned+hue+saturation ({len(truth)} frames)"
    assert line in capsys.readouterr().out.splitlines()
    (tmp_path / "bad.seg").write_bytes(b"junk")
    assert main(["estimate", str(folder), "--segmenter", str(tmp_path / "bad.seg")]) == 2
