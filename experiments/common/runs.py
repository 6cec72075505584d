"""How an experiment runs: quick or full, output and cache folders, seed, logging, summaries.

:class:`Setup` and :func:`parse_args` are the command line every experiment script shares;
:func:`timed` runs one experiment and stores its summary (JSON) for the results index.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parents[1]
RESULTS = HERE / "results"
QUICK_RESULTS = RESULTS / "quick"
CACHE = HERE / "_cache" / "paper_experiments"


@dataclasses.dataclass(frozen=True)
class Setup:
    """How an experiment runs: quick (320x240, few frames) or full (640x480)."""

    quick: bool
    out_dir: Path
    cache_dir: Path
    seed: int = 2024

    @property
    def width(self) -> int:
        return 320 if self.quick else 640

    @property
    def height(self) -> int:
        return 240 if self.quick else 480

    @property
    def mode(self) -> str:
        return "quick" if self.quick else "full"

    def n(self, full: int, quick: int) -> int:
        """A count for this mode."""
        return quick if self.quick else full

    def rng(self, *key: int) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence([self.seed, *key]))


def parse_args(
    description: str, argv: Sequence[str] | None = None, *, run_help: str | None = None
) -> tuple[Setup, argparse.Namespace]:
    """The command line every experiment script shares (``run_help``: also a ``--run`` flag)."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--quick", action="store_true", help="320x240 and few frames (a smoke run)")
    p.add_argument(
        "--out-dir",
        type=Path,
        default=None,
        help=f"where the .md and .png go (default {RESULTS.relative_to(HERE.parent)}, or "
        f"{QUICK_RESULTS.relative_to(HERE.parent)} with --quick)",
    )
    p.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="where per-frame records (CSV) and summaries (JSON) go (default "
        f"{CACHE.relative_to(HERE.parent)}[/quick])",
    )
    p.add_argument("--seed", type=int, default=2024, help="base seed (2024)")
    if run_help:
        p.add_argument("--run", action="store_true", help=run_help)
    a = p.parse_args(argv)
    return make_setup(a.quick, a.out_dir, a.cache_dir, a.seed), a


def make_setup(
    quick: bool, out_dir: Path | None = None, cache_dir: Path | None = None, seed: int = 2024
) -> Setup:
    out = out_dir or (QUICK_RESULTS if quick else RESULTS)
    cache = cache_dir or (CACHE / "quick" if quick else CACHE)
    out.mkdir(parents=True, exist_ok=True)
    cache.mkdir(parents=True, exist_ok=True)
    return Setup(quick=quick, out_dir=out, cache_dir=cache, seed=seed)


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def machine() -> str:
    load = "/".join(f"{x:.1f}" for x in os.getloadavg())
    return (
        f"{platform.machine()}, {os.cpu_count()} CPU cores visible, load average {load} "
        f"(1/5/15 min) at the end"
    )


def save_summary(setup: Setup, name: str, summary: dict[str, Any]) -> None:
    """Headline numbers for the results index (``<cache>/<name>_summary.json``)."""
    path = setup.cache_dir / f"{name}_summary.json"
    path.write_text(json.dumps(summary, indent=1, default=float) + "\n", encoding="utf-8")


def load_summary(cache_dir: Path, name: str) -> dict[str, Any] | None:
    path = cache_dir / f"{name}_summary.json"
    if not path.is_file():
        return None
    data: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    return data


def write_json(path: Path, data: Any) -> None:
    """``data`` as JSON, a NaN (a statistic over no frames) as null, for any JSON reader."""

    def clean(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [clean(x) for x in v]
        return None if isinstance(v, float) and v != v else v

    path.write_text(json.dumps(clean(data), indent=1) + "\n", encoding="utf-8")


def save_run(setup: Setup, name: str, info: dict[str, Any]) -> None:
    """What a run did besides its per-frame records (time, frames rendered, calibration losses):
    ``<cache>/<name>_run.json``, read back by the experiment's report."""
    path = setup.cache_dir / f"{name}_run.json"
    path.write_text(json.dumps(info, indent=1, default=float) + "\n", encoding="utf-8")


def load_run(setup: Setup, name: str) -> dict[str, Any]:
    """The ``save_run`` record of ``name``. Raises FileNotFoundError when it was not run."""
    data: dict[str, Any] = json.loads(
        (setup.cache_dir / f"{name}_run.json").read_text(encoding="utf-8")
    )
    return data


def timed(fn: Callable[[Setup], dict[str, Any]], setup: Setup, name: str) -> dict[str, Any]:
    """Run one experiment, log its wall time, store its summary (with ``seconds``)."""
    t0 = time.perf_counter()
    log(f"{name}: start ({setup.mode})")
    summary = fn(setup)
    summary["seconds"] = time.perf_counter() - t0
    summary["mode"] = setup.mode
    save_summary(setup, name, summary)
    log(f"{name}: done in {summary['seconds']:.0f} s")
    return summary
