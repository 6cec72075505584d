"""Campaigns: the compile cache's folder and clock, the per-recording summary, parallel runs."""

from __future__ import annotations

import csv
import time
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax.app.compile_cache import CompileClock, cache_dir
from sinkjax.app.plots import plot_recordings, recording_of
from sinkjax.app.results import COLUMNS
from sinkjax.app.run import estimate_to_csv
from sinkjax.app.sources import expand_paths, with_rig
from sinkjax.app.summary import SUMMARY_COLUMNS, source_of
from sinkjax.result import FrameResult
from sinkjax.rig import Rig


def test_cache_dir_default_override_and_off(monkeypatch, tmp_path) -> None:
    monkeypatch.delenv("SINKJAX_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "sinkjax" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert cache_dir() == Path.home() / ".cache" / "sinkjax" / "jax"
    assert cache_dir(enabled=False) is None
    monkeypatch.setenv("SINKJAX_CACHE_DIR", str(tmp_path / "c"))
    assert cache_dir() == tmp_path / "c"
    for off in ("off", "OFF", ""):
        monkeypatch.setenv("SINKJAX_CACHE_DIR", off)
        assert cache_dir() is None


def test_compile_clock_counts_compiles_not_runs() -> None:
    # A function no other test compiles (the constant makes it new), timed around its compile.
    @jax.jit
    def f(x):
        return jnp.cumsum(jnp.sin(x) * 1.2345678) @ jnp.cos(x)

    x = jnp.linspace(0.0, 1.0, 37)
    with CompileClock() as clock:
        start = time.perf_counter()
        f(x).block_until_ready()
        first = time.perf_counter() - start
    compiled = clock.seconds
    assert 0.0 < compiled <= first
    with CompileClock() as again:
        for _ in range(20):
            f(x).block_until_ready()
    assert again.seconds == 0.0
    assert clock.seconds == pytest.approx(compiled)  # closed: later compiles do not count


# --- the campaign summary ----------------------------------------------------------------------


def _fake_batch(images, rig, names):
    """ok with sinkage = mean grey / 10 (and a sigma), no_contact for grey 30, no_wheel for 40."""
    out = []
    for image, name in zip(images, names, strict=True):
        grey = float(image.mean())
        if grey == 30:
            out.append(FrameResult(image=name, status="no_contact", sinkage_mm=0.0))
        elif grey == 40:
            out.append(FrameResult(image=name, status="no_wheel", message="none"))
        else:
            out.append(
                FrameResult(
                    image=name,
                    status="ok",
                    sinkage_mm=grey / 10,
                    sinkage_std_mm=grey / 100,
                    theta1_deg=grey,
                    theta1_std_deg=1.0,
                    theta2_deg=-grey,
                    theta2_std_deg=2.0,
                )
            )
    return out


def _png(path: Path, grey: int) -> None:
    assert cv2.imwrite(str(path), np.full((40, 48, 3), grey, np.uint8))


def test_summary_counts_medians_and_ranges(tmp_path) -> None:
    a, b, c = (tmp_path / n for n in ("a", "b", "empty"))
    for d in (a, b, c):
        d.mkdir()
    for i, grey in enumerate([10, 20, 60, 30, 40]):
        _png(a / f"f{i}.png", grey)
    (a / "f5.png").write_bytes(b"broken")
    _png(b / "g0.png", 50)
    (c / "x.png").write_bytes(b"")
    rig = Rig(wheel_radius_mm=100.0, confidence_rect=(2, 2, 4, 4))
    inputs = with_rig(expand_paths([a, b, c]), rig)
    out = tmp_path / "results.csv"
    run = estimate_to_csv(inputs, out, method=_fake_batch, summary_csv=tmp_path / "s.csv")
    assert run.summary_csv == tmp_path / "s.csv"
    with open(tmp_path / "s.csv", newline="") as f:
        reader = csv.DictReader(f)
        assert tuple(reader.fieldnames or ()) == SUMMARY_COLUMNS
        got = {r["recording"]: r for r in reader}
    assert list(got) == [r.name for r in inputs.recordings]
    ra = got[inputs.recordings[0].name]
    assert (ra["frames"], ra["ok"], ra["no_contact"], ra["failed"]) == ("6", "3", "1", "2")
    assert (ra["no_wheel"], ra["unreadable"], ra["error"]) == ("1", "1", "0")
    # Measured sinkage: 1, 2, 6 (ok) and 0 (no_contact): median 1.5, range 0..6.
    assert float(ra["sinkage_median_mm"]) == 1.5
    assert (float(ra["sinkage_min_mm"]), float(ra["sinkage_max_mm"])) == (0.0, 6.0)
    assert (float(ra["theta2_min_deg"]), float(ra["theta2_max_deg"])) == (-60.0, 0.0)
    assert float(ra["sinkage_std_median_mm"]) == 0.2  # over the ok rows: 0.1, 0.2, 0.6
    assert float(ra["theta2_std_median_deg"]) == 2.0
    rb, rc = got[inputs.recordings[1].name], got[inputs.recordings[2].name]
    assert (rb["frames"], rb["ok"], float(rb["theta1_median_deg"])) == ("1", "1", 50.0)
    assert (rc["frames"], rc["ok"], rc["unreadable"], rc["sinkage_median_mm"]) == (
        "1",
        "0",
        "1",
        "",
    )


def test_source_of_rows_and_per_recording_plot(tmp_path) -> None:
    assert source_of("runs/a.mp4#000012") == "runs/a.mp4"
    assert source_of("runs/a#b.png") == "runs/a#b.png"
    assert recording_of("runs/a.mp4#000012") == ("runs/a.mp4", 12.0)
    assert recording_of("runs/x/f1.png") == ("runs/x", None)
    rows = [
        ["v.mp4#000000", "ok", "1.0", "", "2", "", "3", "", "", "", "", ""],
        ["v.mp4#000005", "fit_failed", "", "", "", "", "", "", "", "", "", "m"],
        ["d/f.png", "no_contact", "0.0", "", "0", "", "0", "", "", "", "", ""],
    ]
    with open(tmp_path / "r.csv", "w", newline="") as f:
        csv.writer(f).writerows([COLUMNS, *rows])
    png = plot_recordings(tmp_path / "r.csv", tmp_path / "p.png")
    assert cv2.imread(str(png)).shape[0] > 400
