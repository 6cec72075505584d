"""sinkjax.xla: the library's jitted functions compile with XLA's defaults, or, where
SINKJAX_FAST_COMPILE=1 asks, with options that cut compile time, give XLA's default numbers,
and fall back to no options where XLA does not know them."""

from __future__ import annotations

import os
from collections.abc import Iterator

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sinkjax import xla
from sinkjax.soft.hough import hough_rim
from sinkjax.soft.outline import extract_outline, refine_outline
from sinkjax.soft.settings import SoftSettings
from sinkjax.soft.shadow_cut import shadow_cut


@pytest.fixture
def fresh_options() -> Iterator[None]:
    """compiler_options() probed again in the test, and again after it."""
    xla.compiler_options.cache_clear()
    yield
    xla.compiler_options.cache_clear()


def _stages(image: jax.Array, mask: jax.Array) -> tuple[jax.Array, ...]:
    # Gathers, scatters, scans, reduce-windows and a while loop: the kinds of operation the soft
    # method is made of.
    s = SoftSettings().astype(mask.dtype)
    outline = refine_outline(image, extract_outline(mask, s), s)
    c = hough_rim(outline, *mask.shape, s)
    cut, moved = shadow_cut(image, mask, (c.cx_px, c.cy_px, c.r_px))
    return outline.x_px, outline.y_px, outline.weight, c.cx_px, c.cy_px, c.r_px, cut, moved


def test_options_give_the_numbers_of_xla_defaults(
    draw_wheel, fresh_options: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(xla.ENV_SWITCH, "1")
    image = jnp.asarray(draw_wheel(width=160, height=120, cx=80.3, cy=50.6, r=42.7), jnp.float64)
    image = image / 255.0
    mask = jax.nn.sigmoid((image[..., 0] - image[..., 1] - 0.3) * 20.0)
    if os.environ.get("SINKJAX_TEST_FAST_COMPILE") == "0":
        pytest.skip("this XLA does not know the option (conftest's probe): nothing to compare")
    assert xla.compiler_options() == xla.FAST_COMPILE_OPTIONS
    fast = xla.jit(_stages)(image, mask)
    # The tests' XLA_FLAGS carry the option too: the reference asks for XLA's default.
    default = {k: not v for k, v in xla.FAST_COMPILE_OPTIONS.items()}
    ref = jax.jit(_stages, compiler_options=default)(image, mask)
    assert float(jnp.sum(fast[2])) > 50  # an outline to compare
    for a, b in zip(fast, ref, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)


def test_an_option_xla_does_not_know_means_none(
    fresh_options: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(xla.ENV_SWITCH, "1")
    monkeypatch.setattr(xla, "FAST_COMPILE_OPTIONS", {"xla_no_such_option_here": True})
    assert xla.compiler_options() == {}
    assert float(xla.jit(lambda x: 2.0 * x)(jnp.asarray(3.0))) == 6.0


def test_the_options_are_off_unless_the_switch_asks(
    fresh_options: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(xla.ENV_SWITCH, raising=False)
    assert xla.compiler_options() == {}
    monkeypatch.setenv(xla.ENV_SWITCH, "0")
    xla.compiler_options.cache_clear()
    assert xla.compiler_options() == {}
    monkeypatch.setenv(xla.ENV_SWITCH, "1")
    xla.compiler_options.cache_clear()
    known = os.environ.get("SINKJAX_TEST_FAST_COMPILE") != "0"  # conftest's probe
    assert xla.compiler_options() == (xla.FAST_COMPILE_OPTIONS if known else {})


def test_jit_is_a_jitted_function_in_each_form() -> None:
    def f(x: jax.Array, n: int) -> jax.Array:
        return x * n

    plain = xla.jit(f, static_argnames="n")
    assert plain.__name__ == "f" and plain.__wrapped__ is f
    assert float(plain(jnp.asarray(2.0), n=3)) == 6.0
    assert "multiply" in plain.lower(jnp.asarray(2.0), n=3).as_text()
    plain(jnp.asarray(5.0), n=3)
    assert plain._cache_size() == 1  # one compile for one shape and static value
    plain(jnp.asarray(5.0), n=4)
    assert plain._cache_size() == 2

    @xla.jit
    def g(x: jax.Array) -> jax.Array:
        return x + 1

    @xla.jit(static_argnames="k")
    def h(x: jax.Array, k: int) -> jax.Array:
        return x - k

    @xla.filter_jit
    def e(x: jax.Array, k: int) -> jax.Array:  # filter_jit: the int is static
        return x * k

    assert float(g(jnp.asarray(1.0))) == 2.0
    assert float(h(jnp.asarray(1.0), k=3)) == -2.0
    assert float(e(jnp.asarray(2.0), 5)) == 10.0


def test_the_tests_flag_is_the_librarys_option() -> None:
    from conftest import FAST_COMPILE_FLAG

    name, value = FAST_COMPILE_FLAG.removeprefix("--").split("=")
    assert xla.FAST_COMPILE_OPTIONS == {name: value == "true"}
    if os.environ.get("SINKJAX_TEST_FAST_COMPILE") == "1":
        assert FAST_COMPILE_FLAG in os.environ["XLA_FLAGS"]


def _newton_sqrt(a: jax.Array) -> tuple[jax.Array, jax.Array]:
    """sqrt(a) by Newton's method to 1e-12, and the iterations it took: a loop whose length
    depends on the frame, like the fit's Levenberg-Marquardt loop."""

    def step(c: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
        x, k = c
        return 0.5 * (x + a / x), k + 1

    return jax.lax.while_loop(lambda c: jnp.abs(c[0] ** 2 - a) > 1e-12 * a, step, (a, 0))


@pytest.mark.parametrize("lockstep", [False, True])
def test_map_frames_gives_each_frames_own_result(
    monkeypatch: pytest.MonkeyPatch, lockstep: bool
) -> None:
    # One frame after another (a CPU) or vmapped (an accelerator): each frame's value, its
    # derivative and the iterations its loop took; against NumPy's sqrt, d sqrt(a)/da =
    # 1 / (2 sqrt(a)) and the loop run on that frame alone.
    assert xla.frames_in_lockstep() == (jax.default_backend() != "cpu")
    monkeypatch.setattr(xla, "frames_in_lockstep", lambda: lockstep)
    frames = jnp.asarray([2.0, 9.0, 1e6])

    def one(a: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        root, k = _newton_sqrt(a)
        return root, k, jax.jacfwd(lambda b: _newton_sqrt(b)[0])(a)

    roots, iterations, grads = jax.jit(lambda f: xla.map_frames(one, f))(frames)
    np.testing.assert_allclose(roots, np.sqrt([2.0, 9.0, 1e6]), rtol=1e-12)
    np.testing.assert_allclose(grads, 0.5 / np.sqrt([2.0, 9.0, 1e6]), rtol=1e-9)
    alone = [int(_newton_sqrt(a)[1]) for a in frames]
    assert [int(k) for k in iterations] == alone and len(set(alone)) == 3


def test_side_by_side_keeps_the_order_and_runs_the_first_row_alone(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import threading
    import time

    monkeypatch.setenv("SINKJAX_FRAME_THREADS", "2")
    seen: list[tuple[int, str]] = []

    def slow(i: int, j: int) -> int:
        seen.append((i, threading.current_thread().name))
        time.sleep(0.02 * (5 - i))  # later rows finish first
        return 10 * i + j

    assert xla.side_by_side(slow, range(5), range(5, 10)) == [5, 16, 27, 38, 49]
    assert seen[0] == (0, threading.current_thread().name)  # the first row, in the caller
    assert {name for _, name in seen[1:]} <= {f"{xla._POOL_NAME}_{k}" for k in range(2)}
    # Called from a pool thread (a point's frames within points side by side): no deadlock.
    nested = xla.side_by_side(lambda i: xla.side_by_side(lambda k: i * k, range(3)), range(3))
    assert nested == [[0, 0, 0], [0, 1, 2], [0, 2, 4]]
    monkeypatch.setenv("SINKJAX_FRAME_THREADS", "1")
    seen.clear()
    assert xla.side_by_side(slow, range(3), range(3)) == [0, 11, 22]
    assert {name for _, name in seen} == {threading.current_thread().name}
    monkeypatch.setenv("SINKJAX_FRAME_THREADS", "two")
    with pytest.raises(ValueError, match="SINKJAX_FRAME_THREADS must be a whole number"):
        xla.side_by_side(slow, range(2), range(2))


def test_side_by_side_of_a_compiled_function_runs_every_row_on_the_pool(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import threading
    import time

    monkeypatch.setenv("SINKJAX_FRAME_THREADS", "2")
    seen: list[str] = []
    started = threading.Barrier(2, timeout=5)  # both rows must be running at once

    def together(i: int) -> int:
        seen.append(threading.current_thread().name)
        started.wait()
        time.sleep(0.01 * (2 - i))
        return 3 * i

    assert xla.side_by_side(together, range(2), compiled=True) == [0, 3]
    assert set(seen) <= {f"{xla._POOL_NAME}_{k}" for k in range(2)} and len(seen) == 2
    # Without ``compiled`` the first row runs alone in the caller: two rows never meet.
    started.reset()
    with pytest.raises(threading.BrokenBarrierError):
        xla.side_by_side(lambda i: started.wait(timeout=0.2), range(2))
