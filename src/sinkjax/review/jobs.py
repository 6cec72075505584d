"""Long work started from the page (measure, calibrate), one at a time, in a background thread.

The page polls :meth:`Jobs.status` for the progress bar. Calibration uses the flat public API
(``sinkjax.read_labels``, ``sinkjax.calibrate``, ``sinkjax.save_rig``) on the labels saved from
the page, writes ``calibrated.toml`` next to LABELS.csv (the recording's own ``rig.toml`` is never
overwritten), then re-measures the calibrated recording with the new rig.
"""

from __future__ import annotations

import dataclasses
import threading
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .session import ReviewSession

CALIBRATED_FILENAME = "calibrated.toml"
# Share of the progress bar that calibration takes; re-measuring fills the rest.
_CALIBRATE_SHARE = 0.8


class JobBusy(RuntimeError):
    """Another job is still running; the page should wait for it."""


class Jobs:
    """The one background job of a review session and its progress (0 to 1)."""

    def __init__(self, session: ReviewSession) -> None:
        self.session = session
        self._lock = threading.Lock()
        self._state: dict[str, Any] = {"kind": None, "state": "idle", "progress": 0.0}
        self._thread: threading.Thread | None = None

    def status(self) -> dict[str, Any]:
        with self._lock:
            return dict(self._state)

    def _update(self, progress: float, message: str) -> None:
        with self._lock:
            self._state.update(progress=min(max(progress, 0.0), 1.0), message=message)

    def _start(self, kind: str, work: Callable[[], dict[str, Any] | None]) -> None:
        with self._lock:
            if self._state["state"] == "running":
                raise JobBusy(f"a {self._state['kind']} job is still running; wait for it")
            self._state = {"kind": kind, "state": "running", "progress": 0.0, "message": ""}

        def run() -> None:
            try:
                result = work()
            except Exception as e:  # reported to the page: the server must stay up
                traceback.print_exc()
                with self._lock:
                    self._state.update(state="failed", message=f"{type(e).__name__}: {e}")
                return
            with self._lock:
                self._state.update(state="done", progress=1.0, result=result)

        self._thread = threading.Thread(target=run, name=f"sinkjax-review-{kind}", daemon=True)
        self._thread.start()

    def join(self, timeout: float | None = None) -> None:
        """Wait for the current job (tests, and the command line on exit)."""
        if self._thread is not None:
            self._thread.join(timeout)

    # ---------------------------------------------------------------------------- measure

    def measure(self, indices: list[int] | None = None) -> None:
        """Start measuring frames (all by default) with ``session.method``."""

        def work() -> None:
            self._update(0.0, f"measuring with the {self.session.method} method (compiling)")
            self.session.measure(
                indices, progress=lambda d, n: self._update(d / n, f"measured {d}/{n} frames")
            )

        self._start("measure", work)

    # ---------------------------------------------------------------------------- calibrate

    def calibrate(self, steps: int = 50) -> None:
        """Start calibrating the labelled recording's rig on LABELS.csv, then re-measure it."""
        if steps < 1:
            raise ValueError(f"steps must be at least 1, got {steps}")
        recording = self._labelled_recording()
        self._start("calibrate", lambda: self._calibrate(recording, steps))

    def _labelled_recording(self) -> int:
        store = self.session.labels
        keys = set(store.rows())
        if not keys:
            raise ValueError(f"no labels in {store.path} yet; label and save a few frames first")
        found = {f.recording for f in self.session.frames if store.relative(f.path) in keys}
        if len(found) != 1:
            raise ValueError(
                f"the labels in {store.path} cover {len(found) or 'none'} of the recordings "
                "shown; calibrate one camera set-up (one recording) at a time"
            )
        return found.pop()

    def _calibrate(self, recording: int, steps: int) -> dict[str, Any]:
        import sinkjax

        session, store = self.session, self.session.labels
        rig = session.recordings[recording].rig
        self._update(0.0, f"reading {store.path.name}")
        frames = sinkjax.read_labels(store.path, rig)

        # Calibration's own share of the bar: the grid, Adam's steps, the polish.
        share = {"grid": (0.0, 0.4), "step": (0.4, 0.9), "polish": (0.9, 1.0)}

        def show(stage: str, done: int, total: int, message: str) -> None:
            lo, hi = share[stage]
            self._update(
                _CALIBRATE_SHARE * (lo + (hi - lo) * min(done / max(total, 1), 1.0)), message
            )

        def step(i: int, loss: float) -> None:
            show("step", i, steps, f"calibrating: step {i}/{steps}, loss {loss:.4g}")

        def stage(name: str, done: int, total: int) -> None:
            what = "frames measured on a grid of thresholds" if name == "grid" else "polishing"
            show(name, done, total, f"calibrating: {what}, {done}/{total}")

        self._update(0.0, f"calibrating on {len(frames.names)} frames (compiling)")
        result = sinkjax.calibrate(frames, rig, steps=steps, callback=step, on_stage=stage)
        out = Path(store.path).parent / CALIBRATED_FILENAME
        sinkjax.save_rig(
            result.rig,
            out,
            comment=f"calibrated in `sinkjax review` on {store.path.name}: {len(frames.names)} "
            f"frames, loss {result.loss_before:.4g} -> {result.loss_after:.4g}",
        )
        session.recordings[recording].rig = result.rig
        mine = [f.index for f in session.frames if f.recording == recording]

        def measured(d: int, n: int) -> None:
            share = _CALIBRATE_SHARE + (1 - _CALIBRATE_SHARE) * d / n
            self._update(share, f"re-measuring with the calibrated rig: {d}/{n} frames")

        self._update(_CALIBRATE_SHARE, "re-measuring with the calibrated rig (compiling)")
        session.measure(mine, progress=measured)
        return {
            "rig_path": str(out),
            "loss_before": result.loss_before,
            "loss_after": result.loss_after,
            "before": dataclasses.asdict(result.before),
            "after": dataclasses.asdict(result.after),
            "summary": result.summary(),
        }
