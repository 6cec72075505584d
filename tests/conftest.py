"""Test set-up and the fixtures several test files share.

JAX runs in float64 with strict dtype promotion and no implicit rank promotion, as in the JAX
libraries we learn from; jaxtyping checks every annotated shape of the differentiable core
(``sinkjax.soft``, ``sinkjax.geometry``) at run time (``--jaxtyping-packages`` in
pyproject.toml's ``addopts``).

Shared fixtures (each returns a function, so a test says what it needs in its arguments):

- ``draw_wheel``: an analytic, supersampled wheel-and-soil frame with exact truth (no renderer);
  ``line_truth``: the exact z0 and angles for its straight soil lines.
- ``hsi_reference``: the textbook HSI of one pixel (math.acos), the colour stages' reference.
- ``rendered``: synthetic frames from :mod:`sinkjax.synth` with their truth, once per session.
- ``synthetic_recording``: a recording on disk (frames, truth.csv, rig.toml), once per session.
- ``computed_once``: a file computed once per session and shared by the xdist workers.
- ``use_method``: install a stand-in estimator under both method names (classic and soft).
- ``write_video``: a small grey-level video whose frame i has level (step * i) mod 250.
"""

from __future__ import annotations

import os

os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=1")
# Every compile of the tests (the library's, the tests' own, and those of the subprocesses they
# start) uses sinkjax.xla.FAST_COMPILE_OPTIONS through XLA_FLAGS where XLA knows them: nearly
# every test compiles a new program, so compile time is what counts here (the library keeps
# XLA's defaults, which run faster). An unknown flag there aborts the process, so one
# subprocess probes it, once (the xdist workers inherit the answer); test_xla checks the flag
# is the library's option.
FAST_COMPILE_FLAG = "--xla_cpu_use_fusion_emitters=false"
if "SINKJAX_TEST_FAST_COMPILE" not in os.environ:
    import subprocess
    import sys

    _flags = f"{os.environ['XLA_FLAGS']} {FAST_COMPILE_FLAG}"
    _probe = subprocess.run(
        [sys.executable, "-c", "import jax; jax.jit(lambda x: x + 1)(1.0)"],
        env={**os.environ, "XLA_FLAGS": _flags},
        capture_output=True,
        check=False,
    )
    os.environ["SINKJAX_TEST_FAST_COMPILE"] = "1" if _probe.returncode == 0 else "0"
    if _probe.returncode == 0:
        os.environ["XLA_FLAGS"] = _flags
# Under `pytest -n N` (make test) the N workers share the machine's cores: each keeps to one
# thread (XLA's and torch's pools, and those of the subprocesses it starts), or their pools
# oversubscribe the cores and every test slows down several times.
if os.environ.get("PYTEST_XDIST_WORKER") and os.environ.get("SINKJAX_TEST_THREADS", "1") == "1":
    os.environ["XLA_FLAGS"] += " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
    for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(_name, "1")
# The command line keeps compiled code in ~/.cache; tests that want it name a temporary folder.
os.environ.setdefault("SINKJAX_CACHE_DIR", "off")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")

import fcntl  # noqa: E402
import functools  # noqa: E402
import gc  # noqa: E402
import math  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
from collections.abc import Callable, Iterator  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, NamedTuple  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

# ----------------------------------------------------------------------------- drawn wheels

WHEEL_RGB = (200, 40, 35)  # red: hue straddles 0/360
SOIL_RGB = (190, 165, 120)
SKY_RGB = (70, 90, 130)
HOLE_RGB = (25, 22, 24)
DRAWN_W, DRAWN_H = 320, 240
DRAWN_CX, DRAWN_CY, DRAWN_R_PX = 160.3, 100.6, 85.4  # draw_wheel's default rim


def _draw_wheel(
    *,
    cx: float = DRAWN_CX,
    cy: float = DRAWN_CY,
    r: float = DRAWN_R_PX,
    soil: Callable[[np.ndarray], np.ndarray] = lambda x: 165.2 + 0.0 * x,
    n_lugs: int = 0,
    lug_h: float = 0.0,
    lug_w_frac: float = 0.35,
    hole_r: float = 0.0,
    n_holes: int = 0,
    ring: float = 55.0,
    ss: int = 4,
    width: int = DRAWN_W,
    height: int = DRAWN_H,
) -> np.ndarray:
    """(H, W, 3) uint8: a red wheel (rim radius r, optional lugs, a ring of ``n_holes`` dark
    lightening holes of radius ``hole_r`` at distance ``ring`` from O, or one annular cut-out
    ``hole_r`` without ``n_holes``) behind soil y > soil(x), anti-aliased by ``ss`` x ``ss``
    supersampling (exact coverage in the limit)."""
    xs = (np.arange(width * ss) + 0.5) / ss - 0.5
    ys = (np.arange(height * ss) + 0.5) / ss - 0.5
    x, y = np.meshgrid(xs, ys)
    dx, dy = x - cx, y - cy
    rho = np.hypot(dx, dy)
    wheel = rho <= r
    if n_lugs:
        pitch = 2 * np.pi / n_lugs
        a = (np.arctan2(dy, dx) + 0.1 + pitch / 2) % pitch - pitch / 2
        lug = (np.abs(rho * np.sin(a)) <= lug_w_frac * pitch * r / 2) & (np.cos(a) > 0)
        wheel |= (rho <= r + lug_h) & lug
    holes = np.zeros_like(wheel)
    if hole_r and not n_holes:
        wheel &= ~((rho < hole_r) & (rho > 0.5 * hole_r))
    for k in range(n_holes):
        ang = 0.3 + 2 * np.pi * k / n_holes
        holes |= np.hypot(x - cx - ring * np.cos(ang), y - cy - ring * np.sin(ang)) < hole_r
    img = np.empty((*x.shape, 3))
    img[:] = SKY_RGB
    img[wheel] = WHEEL_RGB
    img[wheel & holes] = HOLE_RGB
    img[y > soil(x)] = SOIL_RGB
    img = img.reshape(height, ss, width, ss, 3).mean(axis=(1, 3))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _line_truth(
    cx: float, cy: float, r: float, y0: float, slope: float
) -> tuple[float, float, float]:
    """Exact z0 (px), theta1, theta2 (deg) for soil y = y0 + slope (x - cx), travel right."""
    # Line in the O frame: v = slope u + (y0 - cy); intersections with u^2 + v^2 = r^2.
    k, b = slope, y0 - cy
    d = abs(b) / math.hypot(k, 1.0)
    qa, qb, qc = 1 + k * k, 2 * k * b, b * b - r * r
    disc = math.sqrt(qb * qb - 4 * qa * qc)
    ua, ub = (-qb + disc) / (2 * qa), (-qb - disc) / (2 * qa)
    t1 = math.pi / 2 - math.atan((k * ua + b) / ua)
    t2 = math.pi / 2 + math.atan((k * ub + b) / ub)
    return r - d, math.degrees(t1), math.degrees(t2)


# Every compiled function keeps its machine code in memory maps of its own (three per kernel
# on a CPU), and a test process compiles thousands: a worker of `make test` reached 27 000 maps
# in 8 minutes, and once the kernel's vm.max_map_count (65 530 by default) is reached the next
# compile cannot map its code (LLVM "Cannot allocate memory", or a segmentation fault while the
# compilation cache serialises an executable). After each test file, a process past a third of
# that limit drops JAX's compiled functions (later files load theirs from the session's
# compilation cache above).
_MAP_SHARE = 3


def _map_counts() -> tuple[int, int] | None:
    """(memory maps of this process, the kernel's limit), or None where /proc cannot say."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            used = sum(1 for _ in maps)
        with open("/proc/sys/vm/max_map_count") as limit:
            return used, int(limit.read())
    except (OSError, ValueError):
        return None


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code() -> Iterator[None]:
    yield
    counts = _map_counts()
    if counts is not None and counts[0] * _MAP_SHARE > counts[1]:
        jax.clear_caches()
        gc.collect()


@pytest.fixture(scope="session")
def draw_wheel() -> Callable[..., np.ndarray]:
    """The analytic wheel painter (keyword arguments: see ``_draw_wheel``)."""
    return _draw_wheel


@pytest.fixture(scope="session")
def line_truth() -> Callable[..., tuple[float, float, float]]:
    """``line_truth(cx, cy, r, y0, slope) -> (z0 px, theta1 deg, theta2 deg)``, travel right."""
    return _line_truth


# ----------------------------------------------------------------------------- colour


def _hsi_reference(r: float, g: float, b: float) -> tuple[float, float, float]:
    """Gonzalez & Woods' HSI of one pixel with math.acos (the paper's definition); hue in
    [0, 360) degrees, grey and black have hue 0, black has saturation 0."""
    num = 0.5 * ((r - g) + (r - b))
    den = math.sqrt((r - g) ** 2 + (r - b) * (g - b))
    if den == 0.0:
        h = 0.0
    else:
        theta = math.degrees(math.acos(max(-1.0, min(1.0, num / den))))
        h = theta if b <= g else 360.0 - theta
    total = r + g + b
    s = 0.0 if total == 0 else 1.0 - 3.0 * min(r, g, b) / total
    return h % 360.0, s, total / 3.0


@pytest.fixture(scope="session")
def hsi_reference() -> Callable[[float, float, float], tuple[float, float, float]]:
    return _hsi_reference


# ----------------------------------------------------------------------------- synthetic data


class Rendered(NamedTuple):
    """Rendered frames (uint8 (H, W, 3) each), their :class:`sinkjax.synth.Truth` and the rig."""

    images: list[np.ndarray]
    truths: list[Any]
    rig: Any


@pytest.fixture(scope="session")
def rendered() -> Callable[..., Rendered]:
    """``rendered(preset, n=4, seed=11, width=320, height=240)``: ``n`` frames of one recording
    of ``synth.recording_scenes`` (frame i rendered with seed ``10 * seed + i``), cached for the
    session. Rendering a 320x240 frame takes about a second."""
    from sinkjax import synth

    @functools.cache
    def render(
        preset: str, n: int = 4, seed: int = 11, width: int = 320, height: int = 240
    ) -> Rendered:
        rng = np.random.default_rng(seed)
        scenes = synth.recording_scenes(rng, n, preset=preset, width=width, height=height)
        out = [synth.render(sc, seed=seed * 10 + i) for i, sc in enumerate(scenes)]
        return Rendered([o[0] for o in out], [o[1] for o in out], synth.rig_for(scenes[0]))

    return render


@pytest.fixture(scope="session")
def synthetic_recording(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., Path]:
    """``synthetic_recording(preset="clean", n_frames=3, seed=1, width=160, height=120)``: the
    folder ``synth.write_recording`` writes (frame PNGs, truth.csv, rig.toml), written once per
    session and argument set. Shared: copy it (``copy_to=``) before writing into it."""
    from sinkjax.synth import write_recording

    @functools.cache
    def written(preset: str, n_frames: int, seed: int, width: int, height: int) -> Path:
        return write_recording(
            tmp_path_factory.mktemp(f"rec_{preset}"),
            n_frames=n_frames,
            seed=seed,
            preset=preset,
            width=width,
            height=height,
            progress=False,
        )

    def recording(
        preset: str = "clean",
        n_frames: int = 3,
        seed: int = 1,
        width: int = 160,
        height: int = 120,
        copy_to: Path | None = None,
    ) -> Path:
        src = written(preset, n_frames, seed, width, height)
        if copy_to is None:
            return src
        shutil.copytree(src, copy_to)
        return copy_to

    return recording


# Within this test session, the processes (the xdist workers) share one JAX compilation cache:
# many tests compile the same functions at the same sizes, and a worker loads what the other
# compiled instead of compiling it again. It lives in a folder made by the controlling process
# and is removed at the end; the library's own caches (SINKJAX_CACHE_DIR) stay off. Measured
# (pytest on this 2-core machine, make test): 16:41 on a fresh clone before it, 14:19 in a
# checkout and 17:37 on a fresh clone with it; with --dist worksteal and the slow files first
# (pytest_collection_modifyitems below), 15:27 in a checkout. About 28 CPU-minutes of tests on
# two cores: the spread from run to run is a minute or more.
_XLA_CACHE_ENV = "SINKJAX_TEST_XLA_CACHE"
_OWN_XLA_CACHE = pytest.StashKey[str]()


def pytest_configure(config: pytest.Config) -> None:
    if not hasattr(config, "workerinput") and _XLA_CACHE_ENV not in os.environ:
        os.environ[_XLA_CACHE_ENV] = tempfile.mkdtemp(prefix="sinkjax-test-xla-")
        config.stash[_OWN_XLA_CACHE] = os.environ[_XLA_CACHE_ENV]
    jax.config.update("jax_compilation_cache_dir", os.environ[_XLA_CACHE_ENV])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


def pytest_unconfigure(config: pytest.Config) -> None:
    own = config.stash.get(_OWN_XLA_CACHE, None)
    if own is not None:
        shutil.rmtree(own, ignore_errors=True)
        os.environ.pop(_XLA_CACHE_ENV, None)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The test files with a test marked ``slow`` or ``heavy`` first, each file's tests together
    and in order (so a module-scoped fixture is made once): with ``--dist worksteal`` (make
    test) the workers start on the long tests and share out the short ones at the end, rather
    than one worker finishing a long test while the other has nothing left to do."""
    slow = {
        item.path
        for item in items
        if item.get_closest_marker("slow") is not None or item.get_closest_marker("heavy")
    }
    items.sort(key=lambda item: item.path not in slow)


@pytest.fixture(scope="session")
def computed_once(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Callable[[str, Callable[[Path], None]], Path]:
    """``computed_once(name, write) -> path``: the file ``name`` in a folder this session's
    workers share (``pytest -n N``; else the session's own), written by ``write(path)`` in
    whichever worker asks first while the others wait on a file lock, then read by all. For an
    expensive, deterministic start (a model trained for a few hundred steps) that tests on
    either worker need: every worker runs single-threaded, so it would compute the same bits."""
    root = tmp_path_factory.getbasetemp()
    if hasattr(request.config, "workerinput"):  # an xdist worker: the session's folder
        root = root.parent
    folder = root / "computed_once"
    folder.mkdir(exist_ok=True)

    def get(name: str, write: Callable[[Path], None]) -> Path:
        path = folder / name
        with open(folder / f"{name}.lock", "w") as lock:
            fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
            if not path.exists():
                part = folder / f"{name}.part"
                write(part)
                os.replace(part, path)
        return path

    return get


# ----------------------------------------------------------------------------- the pipeline


@pytest.fixture
def use_method(monkeypatch: pytest.MonkeyPatch) -> Callable[[Callable[..., Any]], None]:
    """``use_method(fn)`` makes ``fn(images, rig, names) -> rows`` both the classic and the soft
    method of the pipeline and CLI, for this test only."""
    from sinkjax.app import pipeline

    def use(fn: Callable[..., Any]) -> None:
        monkeypatch.setitem(pipeline._LOADERS, "classic", lambda rim, first: fn)
        monkeypatch.setitem(pipeline._LOADERS, "soft", lambda rim, first: fn)

    return use


def _write_video(
    path: Path, n: int, size: tuple[int, int] = (32, 24), fps: float = 5, step: int = 40
) -> Path:
    """``n`` flat grey frames of ``size`` (w, h), frame i at level (step * i) mod 250; MJPG for
    .avi, mp4v otherwise."""
    fourcc = "MJPG" if path.suffix == ".avi" else "mp4v"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, size)
    assert writer.isOpened()
    for i in range(n):
        writer.write(np.full((size[1], size[0], 3), (step * i) % 250, np.uint8))
    writer.release()
    return path


@pytest.fixture(scope="session")
def write_video() -> Callable[..., Path]:
    return _write_video
