"""The exported soft method kept on disk (sinkjax.app.executables): a corrupt, truncated or
foreign file costs a fresh export, never a failed run or a changed number."""

from __future__ import annotations

import logging
import threading

import jax
import numpy as np
import pytest

from sinkjax import synth as S
from sinkjax.app.executables import ExecutableCache, cache_key
from sinkjax.soft import batch as E


def _frame() -> tuple[np.ndarray, object]:
    scene = S.recording_scenes(np.random.default_rng(3), 1, width=200, height=150)[0]
    return S.render(scene, seed=0)[0], S.rig_for(scene)


def _numbers(results) -> list[tuple]:
    return [(r.status, r.sinkage_mm, r.theta1_deg, r.theta2_deg, r.radius_px) for r in results]


@pytest.mark.heavy
@pytest.mark.slow
def test_corrupt_file_recompiles_with_identical_numbers(tmp_path, caplog) -> None:
    image, rig = _frame()
    try:
        reference = _numbers(E.estimate_batch([image], rig, ["f"]))  # plain jit, no cache
        E.set_compiled_provider(ExecutableCache(tmp_path))
        fresh = _numbers(E.estimate_batch([image], rig, ["f"]))
        # prepare, finish (with the frame's own rim), rechoose (with the recording's)
        paths = sorted(tmp_path.glob("*.bin"))
        assert len(paths) == 3
        datas = [p.read_bytes() for p in paths]
        # Each file spoilt its own way (truncated, its tail overwritten, not an export at all),
        # all in one run: each must be found unusable and traced again, with the same numbers.
        cuts = (
            lambda d: d[: len(d) // 2],
            lambda d: d[:-40] + b"x" * 40,
            lambda d: b"not a file",
        )
        for path, data, cut in zip(paths, datas, cuts, strict=True):
            path.write_bytes(cut(data))
        E.set_compiled_provider(ExecutableCache(tmp_path))  # a new process, in effect
        with caplog.at_level(logging.INFO, logger="sinkjax"):
            caplog.clear()
            again = _numbers(E.estimate_batch([image], rig, ["f"]))
        unusable = sorted(
            {m.split(" unusable")[0].split()[-1] for m in caplog.messages if "unusable" in m}
        )
        assert unusable == [str(p) for p in paths]
        assert again == fresh
        # Rewritten by the last run: the next loads it silently. Finish and rechoose load on
        # the warm-up thread (soft.warm) while prepare runs; their calls compile nothing more.
        E.set_compiled_provider(ExecutableCache(tmp_path))
        compiles: list[str] = []

        def listen(event: str, start: float, end: float, **kw: object) -> None:
            if event.endswith("backend_compile_duration") and kw.get("fun_name") == "jit(call)":
                compiles.append(threading.current_thread().name.split("_")[0])

        jax.monitoring.register_event_time_span_listener(listen)
        try:
            with caplog.at_level(logging.INFO, logger="sinkjax"):
                caplog.clear()
                loaded = _numbers(E.estimate_batch([image], rig, ["f"]))
        finally:
            jax.monitoring.unregister_event_time_span_listener(listen)
        assert not [m for m in caplog.messages if "exported function" in m]
        # What has a compiled file (written where the session's JAX cache compiled it afresh,
        # see the next test) compiles nothing; the rest compiles once, finish and rechoose on
        # the warm-up thread.
        kept = {p.stem for p in tmp_path.glob("*.exe")}
        assert len(compiles) + len(kept) == 3
        assert compiles.count("MainThread") <= 1
    finally:
        E.set_compiled_provider(None)
    assert fresh == reference
    assert loaded == reference


def test_key_depends_on_shapes_dtypes_and_structure() -> None:
    a = (np.zeros((4, 5, 3), np.uint8), (np.float64(1.0), None))
    assert cache_key("f", a) == cache_key(
        "f", (np.ones((4, 5, 3), np.uint8), (np.float64(2), None))
    )
    assert cache_key("f", a) != cache_key("g", a)
    assert cache_key("f", a) != cache_key("f", (np.zeros((4, 6, 3), np.uint8), a[1]))
    assert cache_key("f", a) != cache_key("f", (np.zeros((4, 5, 3), np.float32), a[1]))
    assert cache_key("f", a) != cache_key("f", (a[0], (np.float64(1.0), np.float64(1.0))))


# Run in a fresh process (JAX decides once per process whether its persistent cache is on): the
# soft method on two frames with the command line's caches in argv[1] ("off": none), printing
# the numbers, whether each executable came from disk, and the fresh compiles of it.
_RUN = """
import json, sys
import jax, numpy as np
from sinkjax import synth as S
from sinkjax.app import executables as X
from sinkjax.app.compile_cache import enable_compile_cache
from sinkjax.soft import batch as E

if sys.argv[1] != "off":
    enable_compile_cache(sys.argv[1])
loaded = []
plain = X.ExecutableCache._load_compiled
def spy(self, key):
    out = plain(self, key)
    loaded.append(out is not None)
    return out
X.ExecutableCache._load_compiled = spy
scene = S.recording_scenes(np.random.default_rng(3), 1, width=200, height=150)[0]
images = [S.render(scene, seed=s)[0] for s in (0, 1)]
rows = E.estimate_batch(images, S.rig_for(scene), ["a", "b"])
numbers = [[r.status, r.sinkage_mm, r.theta1_deg, r.theta2_deg, r.radius_px] for r in rows]
print(json.dumps({"numbers": numbers, "loaded": sorted(loaded)}))
"""


def _run(cache: object) -> dict:
    import json
    import subprocess
    import sys

    proc = subprocess.run(
        [sys.executable, "-c", _RUN, str(cache)], capture_output=True, text=True, check=True
    )
    return json.loads(proc.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


@pytest.mark.heavy
@pytest.mark.slow
def test_compiled_files_load_with_identical_numbers_and_only_fresh_compiles_are_kept(
    tmp_path,
) -> None:
    reference = _run("off")["numbers"]
    cache = tmp_path / "cache"
    cold = _run(cache)
    # prepare, finish and rechoose, each compiled afresh: kept (also rechoose, which compiles
    # in under JAX's threshold, so that JAX's cache does not have it).
    exes = sorted((cache / "executables").glob("*.exe"), key=lambda p: p.stat().st_size)
    assert len(exes) == 3
    warm = _run(cache)
    assert warm["loaded"].count(True) == 3
    # A corrupt file is removed and compiled again (finish, the largest: from JAX's cache), with
    # the same numbers.
    exes[-1].write_bytes(exes[-1].read_bytes()[:1000])
    spoilt = _run(cache)
    assert spoilt["loaded"].count(True) == 2
    assert not exes[-1].exists()
    # ... and an executable JAX loaded from its own cache is not kept (it would not serialise
    # whole): the file stays missing, the numbers stay the same.
    again = _run(cache)
    assert again["loaded"].count(True) == 2
    assert not exes[-1].exists()
    # What JAX's cache does not have is compiled afresh and kept again.
    for entry in cache.glob("*-cache"):  # JAX's own files
        entry.unlink()
    rewritten = _run(cache)
    assert rewritten["loaded"].count(True) == 2 and exes[-1].exists()
    assert _run(cache)["loaded"].count(True) == 3
    assert cold["numbers"] == reference
    assert warm["numbers"] == reference
    assert spoilt["numbers"] == reference
    assert again["numbers"] == reference
    assert rewritten["numbers"] == reference


def _exported(source: str, filename: str) -> object:
    scope: dict = {}
    exec(compile(source, filename, "exec"), {"jnp": jax.numpy}, scope)
    return jax.export.export(jax.jit(scope["f"]))(np.ones((3, 4), np.float32))


def test_module_key_ignores_source_locations_not_the_computation() -> None:
    from sinkjax.app.executables import module_key

    body = "def f(x):\n    y = jnp.sin(x) * 2.0\n    return jnp.cumsum(y, axis=0).sum()\n"
    a = _exported(body, "/a/sinkjax/soft/one.py")
    # The same computation from another file, three lines further down.
    b = _exported("\n\n\n" + body, "/b/elsewhere/two.py")
    assert "one.py" in a.mlir_module() and "two.py" in b.mlir_module()  # type: ignore[attr-defined]
    assert module_key(a) == module_key(b)
    assert module_key(a) != module_key(_exported(body.replace("2.0", "3.0"), "/a/one.py"))
    assert module_key(a) != module_key(_exported(body.replace("axis=0", "axis=1"), "/a/one.py"))


def test_a_compile_is_shown_on_the_bar_and_left_out_of_its_rate(tmp_path, monkeypatch) -> None:
    import io
    import re
    import time

    import jax.numpy as jnp
    from tqdm import tqdm

    from sinkjax.app import executables as X
    from sinkjax.app.compile_cache import compile_notices
    from sinkjax.app.run import _CompileNote

    compile_for_real = X._compile_fresh

    def slow_compile(*args: object) -> object:  # a compile of a known length
        time.sleep(0.5)
        return compile_for_real(*args)

    monkeypatch.setattr(X, "_compile_fresh", slow_compile)
    bar = tqdm(total=4, file=io.StringIO(), mininterval=0)
    heard: list[tuple] = []
    frame = np.ones((48, 64, 3), np.float32)  # (H, W, 3): announced as 64x48
    time.sleep(0.3)
    bar.update(1)  # a frame measured in 0.3 s: its time stays in the rate, the compile's not
    printed = bar.start_t
    with (
        compile_notices(_CompileNote(bar)),
        compile_notices(lambda size, started: heard.append((size, started, bar.postfix))),
    ):
        began = time.perf_counter()
        loaded = ExecutableCache(tmp_path)("twice", jax.jit(lambda x: jnp.sum(2.0 * x)), (frame,))
        assert float(loaded(frame)) == 2.0 * frame.size
        took = time.perf_counter() - began
    # The export (tracing, lowering), then the compile, each announced while it runs.
    assert [h[:2] for h in heard] == [((64, 48), True), ((64, 48), False)] * 2
    assert all("preparing the soft method for 64x48 frames" in h[2] for h in heard[::2])
    assert re.fullmatch(r"prepared in [01] s, not counted in the rate", heard[3][2])
    # unpause: the bar's clock restarts where it last printed, leaving out these waits alone.
    assert 0.5 <= bar.start_t - printed < took + 0.1
    bar.close()
