"""The command line's start: the soft method's compiled halves load while Python imports sinkjax.

A warm ``sinkjax estimate`` spends about 1.6 s importing (jax about 1 s of it, then equinox,
optimistix, OpenCV and sinkjax itself on one core) and then about 1.4 s deserialising the soft
method's compiled halves (:mod:`sinkjax.app.executables`), which holds no Python lock. So when
this process is that command (:func:`begin`, called first thing by ``sinkjax/__init__.py``:
``sinkjax estimate`` with the soft method, in this process, with its cache on), the executables
that earlier runs called first for the image size of its first PATH (read from the image's
header; for a video, the last run's first size) are deserialised on two threads of their own
from the moment jax is imported, beside the rest of the import. Their names are kept per image
size in :data:`HINT` beside them, in the order a run first called them (:func:`note`).
:class:`~sinkjax.app.executables.ExecutableCache` then takes them (:func:`take`) instead of
reading them again. The names are the compiled files' own keys
(:func:`~sinkjax.app.executables.module_key`): an executable is used only where the run asks
for exactly it, so a wrong guess costs those threads' time and nothing else.
``experiments/campaign.py`` measures the start-up.
"""

from __future__ import annotations

import dataclasses
import functools
import io
import os
import sys
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

HINT = "first.txt"  # in the executables folder: per image size, the compiled files called first
HINT_SIZE = 3  # per image size: prepare, finish and rechoose
HINT_SIZES = 8  # image sizes in the hint, the last run's first
# The command line's options that take no value (tests/test_early.py checks them against it).
NO_VALUE = ("--help", "-h", "--resume", "--smooth", "--no-compile-cache")
# The two halves side by side, beside the import: on 2 cores 3.4 s for 8 frames against 3.6 s
# one after the other (the import is slower, but no half is waited for).
THREADS = 2

# key -> its deserialised parts (Parts), loading or loaded ahead; taken once.
_ahead: dict[str, Future[Any]] = {}
# This process's first compiled files per image size (width, height), in the order asked for.
_asked: dict[tuple[int, int], list[str]] = {}
_size: list[tuple[int, int]] = []  # the image size last asked for (a key without one: that)
_lock = threading.Lock()


def command_args(orig_argv: Sequence[str], argv: Sequence[str]) -> list[str] | None:
    """The arguments after ``sinkjax`` when this process is the command line (the ``sinkjax``
    script, or ``python -m sinkjax.app.cli``), else None."""
    i = 1
    while i < len(orig_argv):
        arg = orig_argv[i]
        if arg == "-m":
            module = orig_argv[i + 1] if i + 1 < len(orig_argv) else ""
            return list(orig_argv[i + 2 :]) if module == "sinkjax.app.cli" else None
        if arg == "-c" or not arg.startswith("-"):
            break  # a command string, or the script: its name decides below
        i += 2 if arg in ("-X", "-W") else 1  # the interpreter's options with a value
    if argv and Path(argv[0]).name == "sinkjax":
        return list(argv[1:])
    return None


def loads_soft(args: Sequence[str]) -> bool:
    """Whether ``sinkjax ARGS`` measures with the soft method in this process, with the compile
    cache on: ``estimate`` without ``--method classic``, a learned ``--segmenter`` (compiled
    through jit, not kept), ``--workers``/``--scheduler`` (the workers load) or
    ``--no-compile-cache``. Abbreviated options are read as argparse reads them; when in
    doubt, no."""
    if not args or args[0] != "estimate":
        return False
    stoppers = ("--segmenter", "--workers", "--scheduler", "--no-compile-cache")
    for i, arg in enumerate(args[1:], start=1):
        name, eq, value = arg.partition("=")
        if len(name) < 3 or not name.startswith("--"):
            continue
        if any(flag.startswith(name) for flag in stoppers):
            return False
        if "--method".startswith(name):
            value = value if eq else (args[i + 1] if i + 1 < len(args) else "")
            if value != "soft":
                return False
    return True


def begin() -> None:
    """When this process is ``sinkjax estimate`` measuring with the soft method (see
    :func:`loads_soft`), import jax and start loading the compiled files the cache's hint
    names for its first PATH's image size on threads of their own. Anything amiss (no hint, a
    file missing or unreadable): the run loads that function as it would have."""
    args = command_args(getattr(sys, "orig_argv", sys.argv), sys.argv)
    if args is None or not loads_soft(args):
        return
    from .compile_cache import cache_dir

    try:
        directory = cache_dir()
    except RuntimeError:  # no home directory: the command says so itself
        return
    if directory is None:
        return
    folder = directory / "executables"
    hints = read_hints(folder)
    if not hints:
        return
    size = first_size(args[1:])
    if size is None:  # not known from a header (a video): the last run's first size
        keys = next(iter(hints.values()), [])
    else:
        keys = hints.get(size, [])
    if not keys:
        return
    # jax here, not on the thread: the two threads never import one module at once.
    from jax.experimental import serialize_executable  # noqa: F401

    from .executables import compiled_file

    start(keys, lambda key: read_parts(compiled_file(folder, key), key))
    get_ready_ahead()  # the platform's set-up, which a loaded executable needs to run


def start(keys: Sequence[str], load: Callable[[str], Any]) -> None:
    """Load each key with ``load`` (its parts, or None) on :data:`THREADS` threads of their own,
    started in the order given; :func:`take` hands them out."""
    pool = ThreadPoolExecutor(THREADS, thread_name_prefix="sinkjax-early")
    with _lock:
        for key in keys:
            if key not in _ahead:
                _ahead[key] = pool.submit(load, key)
    pool.shutdown(wait=False)  # the thread ends when the queue is done


@dataclasses.dataclass(frozen=True)
class Parts:
    """A compiled file deserialised up to its pytrees (which name sinkjax's classes, so they
    are read once sinkjax is imported): what ``serialize_executable.deserialize_and_load``
    makes of the executable, and the pickled ``(in_tree, out_tree)``."""

    executable: Any  # the loaded executable
    args_info: list[Any]  # flat
    no_kwargs: bool
    trees: bytes

    def compiled(self) -> Any:
        """The ``jax.stages.Compiled``, as ``deserialize_and_load`` assembles it."""
        import jax

        from .executables import _Unpickler

        in_tree, out_tree = _Unpickler(io.BytesIO(self.trees)).load()
        args_info = in_tree.unflatten(self.args_info)
        return jax.stages.Compiled(
            self.executable, [], args_info, out_tree, no_kwargs=self.no_kwargs
        )


def read_parts(path: Path, key: str) -> Parts | None:
    """``path`` (a compiled file of the current layout, for ``key``) deserialised into
    :class:`Parts`, or None if it is not there; a ValueError if it is of another layout, corrupt
    or for another key (other errors propagate too)."""
    import jax
    from jax.experimental import serialize_executable

    from .executables import COMPILED_MAGIC, _Unpickler, read_checked

    if not path.exists():
        return None
    stream = io.BytesIO(read_checked(path, COMPILED_MAGIC))
    stored, blob = _Unpickler(stream).load()
    if stored != key:
        raise ValueError("written for other arguments")
    device = jax.devices()[0]
    unpickler = serialize_executable._JaxPjrtUnpickler(io.BytesIO(blob), device.client, [device])
    unloaded, args_info, no_kwargs = unpickler.load()
    return Parts(unloaded.load(), args_info, no_kwargs, stream.read())


def take(key: str) -> Parts | None:
    """The parts loaded ahead for ``key`` (waiting while they load), or None: none asked for, a
    load that failed, or one not started yet (cancelled: the caller loads it itself, beside
    the thread rather than after it)."""
    with _lock:
        future = _ahead.pop(key, None)
    if future is None or future.cancel():
        return None
    try:
        return future.result()
    except Exception:  # the caller loads it, and says what is wrong with the file
        return None


def note(folder: Path, key: str, size: tuple[int, int] | None) -> None:
    """Record that this process called compiled file ``key`` in ``folder``, for frames of
    ``size`` (width, height; None: the size last noted). Each size's first :data:`HINT_SIZE`
    keys become the hint the next run loads ahead, this run's sizes first (written when it
    changes; a file that cannot be written is no error)."""
    with _lock:
        if size is None:
            if not _size:
                return
            size = _size[0]
        _size[:] = [size]
        keys = _asked.setdefault(size, [])
        if key in keys or len(keys) >= HINT_SIZE:
            return
        keys.append(key)
        mine = {s: list(k) for s, k in _asked.items()}
    old = read_hints(folder)
    for s, k in mine.items():  # a hint that goes on from this run's keys keeps the rest
        if old.get(s, [])[: len(k)] == k:
            mine[s] = old[s]
    merged = list({**mine, **{s: k for s, k in old.items() if s not in mine}}.items())
    if merged[:HINT_SIZES] == list(old.items()):
        return
    text = "".join(f"{w}x{h} {' '.join(k)}\n" for (w, h), k in merged[:HINT_SIZES])
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp = folder / f"{HINT}.{os.getpid()}.{threading.get_ident()}.tmp"
        tmp.write_text(text, encoding="ascii")
        os.replace(tmp, folder / HINT)
    except OSError:
        pass


def read_hints(folder: Path) -> dict[tuple[int, int], list[str]]:
    """The keys in ``folder``'s hint per image size (width, height), the last run's first size
    first; hex names only; {} where there is none."""
    try:
        text = (folder / HINT).read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError):
        return {}
    hexdigits = set("0123456789abcdef")
    hints: dict[tuple[int, int], list[str]] = {}
    for line in io.StringIO(text):
        size, *keys = line.split() or [""]
        w, x, h = size.partition("x")
        if not (x and w.isdigit() and h.isdigit()):
            continue
        keys = [k for k in keys if len(k) == 64 and set(k) <= hexdigits][:HINT_SIZE]
        if keys:
            hints.setdefault((int(w), int(h)), keys)
    return hints


def first_size(args: Sequence[str]) -> tuple[int, int] | None:
    """(width, height) of the first PATH among ``sinkjax estimate``'s arguments: an image's,
    or a directory's first image's, from its header; None for a video or anything unread."""
    from .image_file import header_size, is_image_path

    i = 0
    while i < len(args):
        arg = args[i]
        if arg.startswith("-") and arg != "-":
            i += 1 if "=" in arg or arg in NO_VALUE else 2
            continue
        path = Path(arg)
        if path.is_dir():
            try:
                names = sorted(os.listdir(path))
            except OSError:
                return None
            images = [n for n in names if not n.startswith(".") and is_image_path(n)]
            return header_size(path / images[0]) if images else None
        return header_size(path) if is_image_path(arg) else None
    return None


# ----------------------------------------------------------------------------- the platform


_READY_LOCK = threading.Lock()
_ready_platforms: set[str] = set()


def backend_ready() -> None:
    """Lower a trivial exported call once per process (two threads asking: the second waits):
    what ``jax.export`` initialises for a platform before its first call (on a CPU, the LAPACK
    kernels a deserialised executable calls, about 0.1 s) is then ready."""
    import jax
    import numpy as np

    with _READY_LOCK:
        if jax.default_backend() in _ready_platforms:
            return
        exported = jax.export.export(jax.jit(_identity))(np.float32(0))
        jax.jit(exported.call).lower(np.float32(0))
        _ready_platforms.add(jax.default_backend())


@functools.cache
def get_ready_ahead() -> None:
    # While this thread deserialises (which holds no Python lock), another gets the platform
    # ready; the first call waits for it (backend_ready's lock).
    threading.Thread(target=backend_ready, name="sinkjax-ready", daemon=True).start()


def _identity(x: Any) -> Any:
    return x


def _forget() -> None:
    # A forked child has none of its parent's threads: what they were loading never arrives,
    # and a lock one of them held would never open.
    global _READY_LOCK
    _ahead.clear()
    _READY_LOCK = threading.Lock()
    get_ready_ahead.cache_clear()


os.register_at_fork(after_in_child=_forget)
