"""Campaigns: the compile cache's folder and clock, the per-recording summary, parallel runs."""

from __future__ import annotations

import csv
import os
import sys
import time
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax.app.compile_cache import CompileClock, cache_dir
from sinkjax.app.parallel import ParallelOptions, WorkerCannotRead, plan_tasks
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
    """ok with sinkage = mean grey / 10 (and a sigma), no_contact for grey 30, no_wheel for 40;
    segmented by hue+saturation for grey 30, else by intensity+texture."""
    out = []
    for image, name in zip(images, names, strict=True):
        grey = float(image.mean())
        features = "hue+saturation" if grey == 30 else "intensity+texture"
        if grey == 30:
            out.append(
                FrameResult(
                    image=name, status="no_contact", sinkage_mm=0.0, segmenter_features=features
                )
            )
        elif grey == 40:
            out.append(
                FrameResult(
                    image=name, status="no_wheel", message="none", segmenter_features=features
                )
            )
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
                    segmenter_features=features,
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


def test_summary_says_which_features_segmented_each_recording(tmp_path, capsys) -> None:
    from sinkjax.app.cli import main

    a, b, c = (tmp_path / n for n in ("a", "b", "empty"))
    for d in (a, b, c):
        d.mkdir()
    for i, grey in enumerate([10, 20, 60, 30, 40]):  # the fake: 30 hue+saturation, else i+t
        _png(a / f"f{i}.png", grey)
    (a / "f5.png").write_bytes(b"broken")  # never segmented
    _png(b / "g0.png", 50)
    (c / "x.png").write_bytes(b"")
    rig = Rig(wheel_radius_mm=100.0, confidence_rect=(2, 2, 4, 4))
    inputs = with_rig(expand_paths([a, b, c]), rig)
    names = [r.name for r in inputs.recordings]
    out = tmp_path / "results.csv"
    run = estimate_to_csv(inputs, out, method=_fake_batch, summary_csv=tmp_path / "s.csv")
    assert run.segmenter_lines() == [
        "segmenter:",
        f"  {names[0]}: intensity+texture (4), hue+saturation (1)",  # most frames first
        f"  {names[1]}: intensity+texture (1 frame)",
        f"  {names[2]}: no frame segmented",
    ]
    with open(tmp_path / "s.csv", newline="") as f:
        cells = [r["segmenter"] for r in csv.DictReader(f)]
    assert cells == ["intensity+texture (4), hue+saturation (1)", "intensity+texture (1 frame)", ""]
    assert list(SUMMARY_COLUMNS[:3]) == ["recording", "rig", "segmenter"]
    assert COLUMNS[-1] == "message" and "segmenter_features" not in COLUMNS  # the CSV contract

    # --resume: only this run's frames are counted (the results CSV does not hold the features).
    lines = out.read_text().splitlines(keepends=True)
    out.write_text("".join(lines[:3]))  # header, f0, f1 kept
    again = estimate_to_csv(inputs, out, method=_fake_batch, resume=True)
    assert again.segmenter_lines()[:2] == [
        "segmenter (frames measured in this run):",
        f"  {names[0]}: intensity+texture (2), hue+saturation (1)",  # f2, f4; f3
    ]
    # One recording: one line, printed by the command line before the run's line.
    assert main(["estimate", str(b), "--out", str(tmp_path / "b.csv"), "--method", "classic",
                 "--wheel-radius-mm", "100", "--confidence-rect", "2,2,4,4"]) == 0  # fmt: skip
    printed = capsys.readouterr().out.splitlines()
    assert printed[-2:] == ["segmenter: hue+saturation (1 frame)", printed[-1]]
    assert printed[-1].startswith("1 frames: ")


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


# --- parallel runs on Dask -----------------------------------------------------------------------

try:
    import dask.distributed as distributed
except ImportError:  # `make test` installs it; elsewhere these tests say how
    distributed = None
needs_dask = pytest.mark.skipif(distributed is None, reason="pip install 'sinkjax[parallel]'")


class DieOnce:
    """The fake method, except that the first worker to meet ``victim`` dies (os._exit): the
    task must be run again elsewhere and no row lost. ``marker`` records that it happened."""

    def __init__(self, marker: Path, victim: str) -> None:
        self.marker = marker
        self.victim = victim

    def __call__(self, images, rig, names):
        if any(n.endswith(self.victim) for n in names) and not self.marker.exists():
            self.marker.write_text("died")
            os._exit(1)
        return _fake_batch(images, rig, names)


def _video(path: Path, greys: list[int]) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 5, (48, 40))
    for g in greys:
        writer.write(np.full((40, 48, 3), g, np.uint8))
    writer.release()


@pytest.fixture(scope="module")
def cluster():
    """A local Dask cluster of two worker processes, started by the test (``--scheduler``)."""
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
    ) as c:
        yield c


@needs_dask
def test_scheduler_chunks_resume_and_a_killed_worker(tmp_path, cluster) -> None:
    import cloudpickle

    # The fakes live in this test module, which the workers cannot import: send them by value.
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    a = tmp_path / "a"
    a.mkdir()
    for i, grey in enumerate([10, 20, 60, 30, 40, 70, 80]):
        _png(a / f"f{i}.png", grey)
    (a / "f7.png").write_bytes(b"broken")
    _video(tmp_path / "v.mp4", [90, 100, 110, 120, 130])
    rig = Rig(wheel_radius_mm=100.0, confidence_rect=(2, 2, 4, 4))
    inputs = with_rig(expand_paths([a, tmp_path / "v.mp4"]), rig)
    serial = tmp_path / "serial.csv"
    estimate_to_csv(inputs, serial, method=_fake_batch, batch_size=2)
    want = serial.read_bytes()
    assert want.count(b"\n") == 1 + 8 + 5

    options = ParallelOptions(scheduler=cluster.scheduler_address, chunk_frames=2)
    tasks = plan_tasks(inputs, method=_fake_batch, batch_size=2, chunk_frames=2)
    assert len(tasks) == 4 + 3  # 8 images in chunks of 2; 5 video frames in chunks of 2
    marker = tmp_path / "died"
    out = tmp_path / "parallel.csv"
    run = estimate_to_csv(
        inputs, out, method=DieOnce(marker, "a/f2.png"), batch_size=2, parallel=options
    )
    assert marker.exists(), "no worker died: the test did not test anything"
    assert out.read_bytes() == want
    assert run.n_frames == 13 and run.n_read == 12

    # --resume: the first rows and half a row remain; the rest is measured on the cluster.
    lines = want.splitlines(keepends=True)
    out.write_bytes(b"".join(lines[:5]) + lines[5][:7])
    estimate_to_csv(inputs, out, method=_fake_batch, batch_size=2, parallel=options, resume=True)
    assert out.read_bytes() == want


@needs_dask
def test_workers_cli_gives_the_serial_csv_with_a_real_method(
    tmp_path, monkeypatch, draw_wheel
) -> None:
    from sinkjax.app.cli import main

    monkeypatch.chdir(tmp_path)
    # Two recordings, two image sizes, drawn wheels at several soil levels (classic: real numbers).
    for name, (w, h), rect in (
        ("r1", (160, 120), "70,30,16,12"),
        ("r2", (176, 128), "76,34,16,12"),
    ):
        Path(name).mkdir()
        for i, level in enumerate((75.0, 82.0, 90.0)):
            image = draw_wheel(cx=80.0, cy=60.0, r=30.0, soil=lambda x, y=level: y + 0.1 * (x - 80),
                               width=w, height=h, ss=2)  # fmt: skip
            assert cv2.imwrite(f"{name}/f{i}.png", image[..., ::-1])
        Path(name, "rig.toml").write_text(
            f'wheel_radius_mm = 140.0\nconfidence_rect = [{rect}]\ntravel = "right"\n'
        )
    args = ["estimate", "r1", "r2", "--method", "classic", "--summary"]
    assert main([*args, "s_serial.csv", "--out", "serial.csv"]) == 0
    assert main([*args, "s_par.csv", "--out", "par.csv", "--workers", "2"]) == 0
    assert Path("par.csv").read_bytes() == Path("serial.csv").read_bytes()
    assert Path("s_par.csv").read_bytes() == Path("s_serial.csv").read_bytes()
    assert Path("serial.csv").read_text().count(",ok,") >= 4


@needs_dask
def test_workers_that_cannot_see_the_inputs_say_so(tmp_path, cluster) -> None:
    d = tmp_path / "gone"
    d.mkdir()
    _png(d / "f.png", 10)
    inputs = with_rig(expand_paths([d]), Rig(wheel_radius_mm=1.0, confidence_rect=(2, 2, 4, 4)))
    (d / "f.png").unlink()  # listed by the run, then gone before a worker reads it
    options = ParallelOptions(scheduler=cluster.scheduler_address)
    with pytest.raises(WorkerCannotRead, match=r"cannot see .*f\.png.*same place"):
        estimate_to_csv(inputs, tmp_path / "r.csv", method="classic", parallel=options)


def test_without_dask_the_message_names_the_extra(tmp_path, monkeypatch, capsys) -> None:
    from sinkjax.app.cli import main

    monkeypatch.setitem(sys.modules, "dask.distributed", None)  # import fails as if missing
    _png(tmp_path / "f.png", 10)
    code = main(["estimate", str(tmp_path / "f.png"), "--workers", "2", "--wheel-radius-mm", "1",
                 "--confidence-rect", "2,2,4,4", "--out", str(tmp_path / "r.csv")])  # fmt: skip
    assert code == 2
    assert "pip install 'sinkjax[parallel]'" in capsys.readouterr().err
    assert not (tmp_path / "r.csv").exists()
