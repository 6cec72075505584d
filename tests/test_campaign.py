"""Campaigns: the compile cache's folder and clock, the per-recording summary, parallel runs."""

from __future__ import annotations

import time
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest

from sinkjax.app.compile_cache import CompileClock, cache_dir


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
