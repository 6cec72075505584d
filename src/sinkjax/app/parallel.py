"""Runs on a Dask cluster: recordings, and chunks of long ones, measured by worker processes.

``sinkjax estimate --workers N`` starts a local cluster of N worker processes; ``--scheduler
ADDRESS`` uses a running ``dask.distributed`` cluster (a lab server, or SLURM through
dask-jobqueue). The run is cut into tasks -- a recording, or a chunk of a long video or folder
-- that workers measure and return as rows. :mod:`sinkjax.app.run` writes them: in input order,
each task's rows as soon as it and every task before it are done, so the results CSV is the
serial run's, byte for byte. A task whose worker dies is run again by Dask on another worker,
so no row is lost; workers read the inputs from the same paths as the run (a shared
filesystem) and stop the run with a clear error when they cannot.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import socket
import threading
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2

from ..result import FrameResult
from ..rig import Rig
from .frames import ALL_FRAMES, FrameSelection, count_frames
from .pipeline import BatchMethod
from .sources import Inputs, Recording, Source

if TYPE_CHECKING:
    from ..soft.segmenter import Segmenter

log = logging.getLogger("sinkjax")

# A long recording is cut into chunks of about this many frames (a multiple of the batch size,
# so that batches are the serial run's): enough work per task to hide its overhead.
CHUNK_FRAMES = 64
# JAX settings that change the numbers: a worker takes the run's, so its rows are the same.
_JAX_OPTIONS = ("jax_enable_x64", "jax_numpy_dtype_promotion")


class ParallelUnavailable(RuntimeError):
    """dask.distributed is not installed; the message names the extra to install."""


class WorkerCannotRead(RuntimeError):
    """A worker cannot see an input file: the inputs must be on a filesystem the workers share."""


@dataclass(frozen=True)
class ParallelOptions:
    """Where to run: ``workers`` local processes, or the cluster at ``scheduler``."""

    workers: int | None = None
    scheduler: str | None = None
    chunk_frames: int = CHUNK_FRAMES

    def __post_init__(self) -> None:
        if (self.workers is None) == (self.scheduler is None):
            raise ValueError("give either --workers N or --scheduler ADDRESS")
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"--workers must be at least 1, got {self.workers}")
        if self.chunk_frames < 1:
            raise ValueError(f"chunk_frames must be at least 1, got {self.chunk_frames}")


@dataclass(frozen=True)
class Task:
    """Frames of one recording for one worker: ``sources`` (absolute paths) with ``select``."""

    recording: int  # index into the run's recordings
    sources: tuple[Source, ...]
    rig: Rig
    select: FrameSelection
    first_image_index: int
    skip: frozenset[str]
    method: str | BatchMethod
    batch_size: int
    overlay_dir: str | None
    jax_options: dict[str, Any] = field(default_factory=dict)
    cache_dir: str | None = None
    size_hint: tuple[int, int] | None = None  # (width, height) of its first frame, if known
    rim: str = "recording"
    # The whole recording (absolute paths), its selection and its first image index: a chunk
    # finds the recording's rim from the recording's first frames, as the serial run does.
    recording_sources: tuple[Source, ...] = ()
    recording_select: FrameSelection = ALL_FRAMES
    recording_first_image_index: int = 0
    segmenter: Segmenter | None = None  # the soft method's (None: the default)


@dataclass
class TaskResult:
    """A task's rows (without overlay geometry) and whether each frame had pixels; the warnings
    it logged, and its compile time."""

    rows: list[tuple[FrameResult, bool]]
    warnings: list[str]
    compile_seconds: float


def import_distributed() -> Any:
    """``dask.distributed``, or ParallelUnavailable naming the extra that installs it."""
    try:
        import dask.distributed as distributed
    except ImportError as e:
        raise ParallelUnavailable(
            f"--workers and --scheduler need dask.distributed ({e}); install it with "
            "pip install 'sinkjax[parallel]'"
        ) from e
    return distributed


def _video_chunks(source: Source, select: FrameSelection, size: int) -> list[FrameSelection]:
    # The container's frame count may be approximate: the last chunk runs to the selection's end.
    n = count_frames([source], select=select)
    k = max(1, math.ceil(n / size))
    step = size * select.stride
    chunks = [
        FrameSelection(select.start + i * step, select.start + (i + 1) * step, select.stride)
        for i in range(k - 1)
    ]
    last = select.start + (k - 1) * step
    return [*chunks, FrameSelection(last, select.stop, select.stride)]


def plan_tasks(
    inputs: Inputs,
    *,
    method: str | BatchMethod,
    batch_size: int,
    select: FrameSelection = ALL_FRAMES,
    skip: Collection[str] = frozenset(),
    chunk_frames: int = CHUNK_FRAMES,
    overlay_dir: str | Path | None = None,
    rim: str = "recording",
    segmenter: Segmenter | None = None,
) -> list[Task]:
    """The run cut into tasks in input order: each video its own task or chunks of it, the
    image files of a recording in chunks of ``chunk_frames`` (rounded up to the batch size)."""
    import jax

    size = math.ceil(chunk_frames / batch_size) * batch_size
    options = {name: getattr(jax.config, name) for name in _JAX_OPTIONS}
    cache = _cache_dir_in_use()
    tasks: list[Task] = []
    sizes: dict[int, tuple[int, int] | None] = {}
    image_index = 0
    first_index: dict[int, int] = {}

    def add(rec_i: int, rec: Recording, sources: list[Source], sel: FrameSelection) -> None:
        if rec_i not in sizes:
            sizes[rec_i] = _frame_size(sources[0])
        names = {s.name for s in sources}
        mine = frozenset(n for n in skip if n in names or n.rpartition("#")[0] in names)
        absolute = tuple(dataclasses.replace(s, path=s.path.absolute()) for s in sources)
        whole = tuple(dataclasses.replace(s, path=s.path.absolute()) for s in rec.sources)
        assert rec.rig is not None
        tasks.append(
            Task(rec_i, absolute, rec.rig, sel, image_index, mine, method, batch_size,
                 None if overlay_dir is None else str(Path(overlay_dir).absolute()),
                 options, cache, sizes[rec_i], rim, whole, select, first_index[rec_i], segmenter)
        )  # fmt: skip

    for rec_i, rec in enumerate(inputs.recordings):
        if rec.rig is None:
            raise ValueError(f"recording {rec.name!r} has no rig; use assign_rigs first")
        first_index[rec_i] = image_index
        images: list[Source] = []
        for source in [*rec.sources, None]:
            if source is not None and source.kind == "image":
                images.append(source)
                if len(images) < size:
                    continue
            if images:
                add(rec_i, rec, images, select)
                image_index += len(images)
                images = []
            if source is not None and source.kind == "video":
                for chunk in _video_chunks(source, select, size):
                    add(rec_i, rec, [source], chunk)
    return tasks


def _cache_dir_in_use() -> str | None:
    import jax

    return getattr(jax.config, "jax_compilation_cache_dir", None)


def _frame_size(source: Source) -> tuple[int, int] | None:
    """(width, height) of a source's first frame, or None if it cannot be told cheaply."""
    if source.kind == "video":
        capture = cv2.VideoCapture(str(source.path))
        try:
            size = (capture.get(cv2.CAP_PROP_FRAME_WIDTH), capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        finally:
            capture.release()
        return (int(size[0]), int(size[1])) if min(size) > 0 else None
    image = cv2.imread(str(source.path), cv2.IMREAD_UNCHANGED)
    return None if image is None else (image.shape[1], image.shape[0])


class _Collect(logging.Handler):
    """The sinkjax warnings of this thread's task, to be re-logged by the run in order."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.thread = threading.get_ident()
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread == self.thread:
            self.messages.append(record.getMessage())


def run_task(task: Task) -> TaskResult:
    """Measure one task's frames on this worker (the serial run's code, frame for frame)."""
    import jax

    from .compile_cache import CompileClock, enable_compile_cache
    from .frames import iter_frames
    from .overlay import OverlayWriter
    from .pipeline import first_frames_reader, iter_estimates

    for source in task.sources:
        if not source.path.exists():
            raise WorkerCannotRead(
                f"worker on {socket.gethostname()} cannot see {source.path} (for {source.name}):"
                " the workers read the inputs from the same paths as the run, so put them on a "
                "filesystem every worker mounts at the same place"
            )
    for name, value in task.jax_options.items():
        if getattr(jax.config, name) != value:
            jax.config.update(name, value)
    if task.cache_dir and _cache_dir_in_use() != task.cache_dir:
        enable_compile_cache(task.cache_dir)
    collect = _Collect()
    logger = logging.getLogger("sinkjax")
    logger.addHandler(collect)
    overlays = OverlayWriter(task.overlay_dir) if task.overlay_dir is not None else None
    rows: list[tuple[FrameResult, bool]] = []
    try:
        frames = iter_frames(
            task.sources,
            select=task.select,
            skip=task.skip,
            first_image_index=task.first_image_index,
        )
        with CompileClock() as clock:
            first = first_frames_reader(
                task.recording_sources or task.sources,
                task.rig,
                task.recording_select,
                task.recording_first_image_index,
            )
            pairs = iter_estimates(
                frames,
                task.rig,
                method=task.method,
                batch_size=task.batch_size,
                rim=task.rim,
                first_frames=first,
                segmenter=task.segmenter,
            )
            for frame, result in pairs:
                if overlays is not None and frame.image is not None:
                    stem = frame.stem or Path(frame.name).stem
                    try:
                        overlays.write(frame.image, result, stem, task.rig)
                    except (OSError, cv2.error) as e:
                        log.warning("%s: overlay not written (%s)", frame.name, e)
                rows.append((dataclasses.replace(result, overlay=None), frame.image is not None))
    finally:
        logger.removeHandler(collect)
    return TaskResult(rows, collect.messages, clock.seconds)


class ParallelRun:
    """The cluster of one run: submit every task, then hand back their results in input order.

    Use as a context manager (the local cluster is shut down on leaving). ``compile_seconds``
    sums the workers' compile times of the tasks returned so far.
    """

    def __init__(self, options: ParallelOptions) -> None:
        self.options = options
        self.compile_seconds = 0.0
        self._client: Any = None
        self._cluster: Any = None

    def __enter__(self) -> ParallelRun:
        distributed = import_distributed()
        if self.options.scheduler is not None:
            self._client = distributed.Client(self.options.scheduler, timeout="30s")
        else:
            self._cluster = distributed.LocalCluster(
                n_workers=self.options.workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=":0",
            )
            self._client = distributed.Client(self._cluster)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._client is not None:
            self._client.close()
        if self._cluster is not None:
            self._cluster.close()

    def results(self, tasks: list[Task]) -> Iterator[tuple[Task, TaskResult]]:
        """Each task with its result, in the order given, as soon as it and those before it are
        done (later ones wait on the cluster). Raises WorkerCannotRead as the workers do."""
        # The first task of each image size goes first: the workers then compile different
        # sizes at the same time, and the later tasks load them from the shared compile cache.
        # Each image size prefers one worker (round robin over the sizes), which then keeps
        # its compiled function: a worker loads a few sizes, not all. Only a preference, so a
        # task of a dead or busy worker still runs elsewhere.
        workers = sorted(self._client.scheduler_info().get("workers", {}))
        home: dict[tuple[int, int] | None, list[str] | None] = {}
        futures = []
        for t in tasks:
            first = t.size_hint is not None and t.size_hint not in home
            if t.size_hint not in home:
                home[t.size_hint] = (
                    [workers[len(home) % len(workers)]]
                    if workers and t.size_hint is not None
                    else None
                )
            prefer: dict[str, Any] = (
                {} if home[t.size_hint] is None
                else {"workers": home[t.size_hint], "allow_other_workers": True}
            )  # fmt: skip
            futures.append(
                self._client.submit(run_task, t, pure=False, priority=int(first), **prefer)
            )
        try:
            for i, task in enumerate(tasks):
                result: TaskResult = futures[i].result()
                futures[i] = None  # the cluster may forget it
                self.compile_seconds += result.compile_seconds
                for message in result.warnings:
                    log.warning("%s", message)
                yield task, result
        finally:
            self._client.cancel([f for f in futures if f is not None])
