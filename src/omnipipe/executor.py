"""One executor for every stage's parallel work: inline, local processes, or a Dask cluster.

Every stage that has frame-parallel (or run-parallel) work gets it done through a
:class:`concurrent.futures.Executor` opened by :func:`open_executor`:

- ``workers=1``: :class:`InlineExecutor`, the work runs in the calling process at
  ``submit`` (no pool, no pickling): the serial reference.
- ``workers=N`` (default: the cores this process may use): a
  :class:`~concurrent.futures.ProcessPoolExecutor` of N local processes (forked on
  Linux, so the workers start in milliseconds and share the parent's imports).
- ``scheduler="tcp://HOST:PORT"``: the ``concurrent.futures`` executor of a Dask
  distributed ``Client`` connected to that scheduler (``pip install 'omnipipe[dask]'``).
  The workers must have omnipipe installed and read the dataset at the same path as
  the client (a shared file system); outputs are written by the client.

Results are always gathered in submission order (:func:`ordered_map`), and every task
is a pure function of its arguments, so the outputs do not depend on the executor.
"""

from __future__ import annotations

import os
import sys
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from omnipipe.errors import ConfigError, OmnipipeError

T = TypeVar("T")
R = TypeVar("R")


class SchedulerError(OmnipipeError):
    """The Dask scheduler named by ``--scheduler`` cannot be reached."""


def default_workers() -> int:
    """Cores this process may run on (``os.sched_getaffinity`` where known)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


class InlineExecutor(Executor):
    """Runs each task in the calling process when it is submitted (``workers=1``).

    An exception of the task is stored in its future (raised by ``result()``), like a
    pool's; KeyboardInterrupt and SystemExit propagate at once.
    """

    def submit(self, fn: Callable[..., R], /, *args: Any, **kwargs: Any) -> Future[R]:
        future: Future[R] = Future()
        try:
            result = fn(*args, **kwargs)
        except Exception as exc:  # re-raised by future.result(), as a pool would
            future.set_exception(exc)
        else:
            future.set_result(result)
        return future


def check_scheduler_address(scheduler: str) -> str:
    """``scheduler`` if it looks like a Dask address (``tcp://HOST:PORT``, ``tls://...``).

    Raises:
        ConfigError: naming ``--scheduler``.
    """
    text = str(scheduler).strip()
    scheme, sep, rest = text.partition("://")
    if not sep or not scheme or not rest:
        raise ConfigError(
            "--scheduler", f"expected a Dask scheduler address like tcp://HOST:PORT, got {text!r}"
        )
    return text


def check_workers(workers: int | None, field: str = "--workers") -> int:
    """``workers`` as a count (None: :func:`default_workers`).

    Raises:
        ConfigError: not a whole number >= 1.
    """
    if workers is None:
        return default_workers()
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(field, f"must be a whole number >= 1, got {workers!r}")
    return workers


def _dask_client(scheduler: str) -> Any:
    """A connected ``distributed.Client`` (one-line errors without Dask or scheduler)."""
    address = check_scheduler_address(scheduler)
    try:
        from distributed import Client
    except ImportError:
        raise ConfigError(
            "--scheduler", "needs Dask, which is not installed: pip install 'omnipipe[dask]'"
        ) from None
    try:
        return Client(address, timeout="10s", set_as_default=False)
    except (OSError, TimeoutError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SchedulerError(f"cannot reach the Dask scheduler at {address} ({reason})") from None


@contextmanager
def open_executor(workers: int | None = None, scheduler: str | None = None) -> Iterator[Executor]:
    """The executor for ``workers`` local processes or the Dask cluster at ``scheduler``.

    Args:
        workers: local processes (None: every core, 1: inline, no pool). Ignored when
            ``scheduler`` is given (the cluster's workers do the work).
        scheduler: a Dask scheduler address ``tcp://HOST:PORT``, or None.

    Yields:
        a ``concurrent.futures.Executor``; it is shut down (the Dask client closed) when
        the block ends.

    Raises:
        ConfigError: bad ``workers``/``scheduler``, or ``scheduler`` without Dask installed.
        SchedulerError: the scheduler cannot be reached.
    """
    if scheduler is not None:
        client = _dask_client(scheduler)
        try:
            executor = client.get_executor(pure=False)
            executor.omnipipe_parallelism = max(1, sum(client.nthreads().values()))
            yield executor
        finally:
            client.close()
        return
    n = check_workers(workers)
    if n == 1:
        yield InlineExecutor()
        return
    import multiprocessing as mp

    ctx = mp.get_context("fork") if sys.platform.startswith("linux") else None
    # Ctrl-C reaches the whole process group: the workers ignore it and the parent
    # (which owns the output folder) stops the pool, so one line is printed, not N
    # tracebacks.
    pool = ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=_ignore_sigint)
    try:
        yield pool
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _ignore_sigint() -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def parallelism(executor: Executor) -> int:
    """How many tasks ``executor`` runs at once (1 inline, N processes, the cluster's threads)."""
    if isinstance(executor, InlineExecutor):
        return 1
    if isinstance(executor, ProcessPoolExecutor):
        return int(executor._max_workers)
    return int(getattr(executor, "omnipipe_parallelism", default_workers()))


def describe(executor: Executor) -> dict[str, Any]:
    """``{"kind": "inline"|"processes"|"dask", "workers": N}`` for report.json."""
    if isinstance(executor, InlineExecutor):
        kind = "inline"
    elif isinstance(executor, ProcessPoolExecutor):
        kind = "processes"
    else:
        kind = "dask" if hasattr(executor, "omnipipe_parallelism") else type(executor).__name__
    return {"kind": kind, "workers": parallelism(executor)}


def ordered_map(
    executor: Executor,
    fn: Callable[[T], R],
    items: Iterable[T],
    *,
    max_pending: int | None = None,
) -> Iterator[R]:
    """``fn(item)`` for every item on ``executor``, yielded in submission order.

    At most ``max_pending`` tasks (default: 2 x :func:`parallelism`) are in flight, so
    the results held in memory stay bounded however long ``items`` is. A task's
    exception is raised when its turn comes; the tasks not yet started are cancelled.
    """
    limit = max(1, max_pending if max_pending is not None else 2 * parallelism(executor))
    pending: deque[Future[R]] = deque()
    try:
        for item in items:
            pending.append(executor.submit(fn, item))
            while len(pending) >= limit:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        for future in pending:
            future.cancel()


def chunks(n: int, executor: Executor, *, per_worker: int = 4, most: int = 16) -> list[range]:
    """Split ``range(n)`` into consecutive chunks: about ``per_worker`` per worker, each of
    at most ``most`` items (few pickles per task, work spread evenly)."""
    if n <= 0:
        return []
    size = max(1, min(most, -(-n // (per_worker * parallelism(executor)))))
    return [range(i, min(n, i + size)) for i in range(0, n, size)]


@dataclass(frozen=True)
class FrameSource:
    """Consecutive frames of a dataset that a worker decodes itself (picklable, small).

    Image folders send only file paths (the worker decodes them: each frame decoded
    once, in parallel); videos and bags, which decode sequentially, send the decoded
    arrays (decoded in the calling process).

    Attributes:
        rig: the dataset's rig (size checks, camera model).
        frames: the dataset indices (0-based) of these frames.
        paths: image file of each frame, or None.
        arrays: decoded RGB (H, W, 3) / grey (H, W) frames, or None.
        payload: per frame, what the task needs of it besides the image (e.g. the
            laser ring's pixels to mask), or None.
    """

    rig: Any
    frames: Sequence[int]
    paths: tuple[Path, ...] | None = None
    arrays: tuple[Any, ...] | None = None
    payload: tuple[Any, ...] | None = None

    @staticmethod
    def take(dataset: Any, frames: Sequence[int], payload: Sequence[Any] | None = None) -> FrameSource:
        """The ``frames`` of an opened :class:`omnipipe.dataset.Dataset` (``payload``:
        one item per frame, carried to the task)."""
        extra = None if payload is None else tuple(payload)
        if dataset.video is None and dataset.source is None:
            paths = tuple(dataset.frame_paths[i] for i in frames)
            return FrameSource(dataset.rig, frames, paths=paths, payload=extra)
        arrays = tuple(dataset.read_frame(i) for i in frames)
        return FrameSource(dataset.rig, frames, arrays=arrays, payload=extra)

    def __len__(self) -> int:
        return len(self.frames)

    def read(self, k: int) -> Any:
        """The k-th frame of this source (0-based within it) as an array.

        Raises:
            DatasetError: unreadable image or wrong size, naming the file.
        """
        if self.arrays is not None:
            return self.arrays[k]
        from omnipipe.dataset import read_image

        assert self.paths is not None  # one of paths/arrays is always set by take()
        return read_image(self.paths[k], self.rig)


def iter_frames(
    executor: Executor,
    fn: Callable[[FrameSource], list[R]],
    dataset: Any,
    frames: Sequence[int] | None = None,
    *,
    most: int = 16,
    payload: Callable[[int], Any] | None = None,
) -> Iterator[tuple[int, R]]:
    """Frame-parallel streaming: ``(frame index, fn's result for it)`` in frame order.

    ``fn(source)`` runs on consecutive chunks of the frames (:class:`FrameSource`, at
    most ``most`` frames a chunk) and returns one result per frame. At most
    2 x :func:`parallelism` chunks are in flight and nothing is kept once yielded, so
    memory stays bounded however long the run (a consumer that keeps only what it
    needs holds only that). ``frames``: a subset of the dataset's indices (default:
    all), e.g. only the moving frames. ``payload(i)``: what the task needs of frame i
    besides its image (:attr:`FrameSource.payload`). Chunks are cut lazily, so a
    video's frames are decoded only as their chunk is submitted.

    Raises:
        RuntimeError: ``fn`` returned another number of results than it got frames.
    """
    order = list(range(len(dataset))) if frames is None else [int(i) for i in frames]
    if not order:
        return
    size = min(len(chunks(len(order), executor, most=most)[0]), max(1, most))
    parts = [order[i : i + size] for i in range(0, len(order), size)]
    sources = (
        FrameSource.take(dataset, part, None if payload is None else [payload(i) for i in part])
        for part in parts
    )
    for part, result in zip(parts, ordered_map(executor, fn, sources), strict=True):
        if len(result) != len(part):
            raise RuntimeError(f"{fn!r} returned {len(result)} results for {len(part)} frames")
        yield from zip(part, result, strict=True)


def map_frames(
    executor: Executor,
    fn: Callable[[FrameSource], list[R]],
    dataset: Any,
    progress: Callable[[int], None] | None = None,
    frames: Sequence[int] | None = None,
) -> list[R]:
    """Frame-parallel helper for any stage: ``fn(source)`` on consecutive chunks of the
    frames of ``dataset`` (:class:`FrameSource`), one result per frame, in frame order.

    ``fn`` must be a picklable callable (a module-level function or an instance of a
    module-level class) that decodes its frames with ``source.read(k)`` and returns one
    result per frame; ``progress(done)`` is called after each frame with the number of
    frames done. ``frames``: a subset of the dataset's indices (default: all), e.g. only
    the moving frames. The list form of :func:`iter_frames`. E.g. SIFT features per
    frame: ``map_frames(executor, features_of_chunk, dataset, frames=moving)``.
    """
    out: list[R] = []
    for _, result in iter_frames(executor, fn, dataset, frames):
        out.append(result)
        if progress is not None:
            progress(len(out))
    return out
