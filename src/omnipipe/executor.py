"""One executor for every stage's parallel work: inline, local processes, or a Dask cluster.

Every stage that has frame-parallel (or run-parallel) work gets it done through a
:class:`concurrent.futures.Executor` opened by :func:`open_executor`:

- ``workers=1``: :class:`InlineExecutor`, the work runs in the calling process at
  ``submit`` (no pool, no pickling): the serial reference.
- ``workers=N`` (default: the cores this process may use; at most 4 x the cores, and
  never more than the tasks): a :class:`~concurrent.futures.ProcessPoolExecutor` of N
  local processes (forked on Linux, so the workers start in milliseconds and share the
  parent's imports). The workers die with the process that opened the pool (also after
  a SIGKILL) and are killed at once when the block that uses them raises.
- ``scheduler="tcp://HOST:PORT"``: the ``concurrent.futures`` executor of a Dask
  distributed ``Client`` connected to that scheduler (``pip install 'omnipipe[dask]'``).
  A malformed address, or one where no scheduler answers, is refused in one line
  within about :data:`CONNECT_TIMEOUT_S` seconds.
  The workers must have omnipipe installed and read the dataset at the same path as
  the client (a shared file system); outputs are written by the client.

Results are always gathered in submission order (:func:`ordered_map`), and every task
is a pure function of its arguments, so the outputs do not depend on the executor.
"""

from __future__ import annotations

import os
import pickle
import re
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar

from omnipipe.errors import ConfigError, DatasetError, OmnipipeError, one_line

T = TypeVar("T")
R = TypeVar("R")
T_co = TypeVar("T_co", covariant=True)


class Pending(Protocol[T_co]):
    """A result that may still be being computed: what ``submit`` returns (a
    :class:`concurrent.futures.Future` of a local pool or of :class:`InlineExecutor`,
    a Dask future) or a handle that holds one (``done()``: it finished, was cancelled or
    failed; ``result()``: the result, waited for, or the task's exception raised)."""

    def done(self) -> bool: ...

    def result(self) -> T_co: ...


class SchedulerError(OmnipipeError):
    """The Dask scheduler named by ``--scheduler`` cannot be reached."""


_WORKER_CACHE: dict[str, tuple[bytes, Any]] = {}


def worker_cached(name: str, key: Any, build: Callable[[], T]) -> T:
    """This process's ``build()`` for ``key``, built once per process and key.

    For what a worker builds from a task's settings and reuses across its chunks (polar
    sampling maps, perspective maps, masks): one entry per ``name``, holding the last
    ``key`` seen (compared by its pickle, so any picklable settings, e.g. frozen
    dataclasses, serve); a new key drops the old value before building the new one.
    """
    token = pickle.dumps(key)
    hit = _WORKER_CACHE.get(name)
    if hit is not None and hit[0] == token:
        return hit[1]
    _WORKER_CACHE.pop(name, None)  # freed before the new one is built
    value = build()
    _WORKER_CACHE[name] = (token, value)
    return value


def default_workers() -> int:
    """Cores this process may run on (``os.sched_getaffinity`` where known)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


# ``--workers`` may ask for at most this many processes per core (more only costs memory
# and time: each forked worker holds the parent's imports, ~140 MB).
WORKERS_PER_CORE = 4


def max_workers() -> int:
    """The largest ``--workers`` accepted: :data:`WORKERS_PER_CORE` x the usable cores."""
    return WORKERS_PER_CORE * default_workers()


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


# Dask's communication schemes that omnipipe can reach (host:port addresses).
SCHEDULER_SCHEMES = ("tcp", "tls", "ws", "wss", "ucx")
_HOST = re.compile(r"\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9]([A-Za-z0-9.-]{0,252}[A-Za-z0-9])?")
# Seconds to wait for the scheduler: a reachable one answers in milliseconds, and every
# --scheduler error must come back well within 5 s.
CONNECT_TIMEOUT_S = 2.0


def parse_scheduler_address(scheduler: str) -> tuple[str, str, int]:
    """``(scheme, host, port)`` of a Dask scheduler address ``SCHEME://HOST:PORT``.

    The scheme is one of :data:`SCHEDULER_SCHEMES`; HOST a name, an IPv4 address or a
    bracketed IPv6 address; PORT 1-65535 (required: Dask cannot guess it).

    Raises:
        ConfigError: naming ``--scheduler`` and what is wrong.
    """
    text = str(scheduler).strip()
    example = "expected a Dask scheduler address like tcp://HOST:8786"
    scheme, sep, rest = text.partition("://")
    if not sep or not scheme or not rest:
        raise ConfigError("--scheduler", f"{example}, got {text!r}")
    if scheme.lower() not in SCHEDULER_SCHEMES:
        raise ConfigError(
            "--scheduler",
            f"unknown protocol {scheme + '://'!r} in {text!r} (one of "
            f"{', '.join(s + '://' for s in SCHEDULER_SCHEMES)})",
        )
    host, colon, port_text = rest.rstrip("/").rpartition(":")
    bracketed = host.startswith("[")
    if not colon or not host or (":" in host) != (bracketed and host.endswith("]")):
        raise ConfigError("--scheduler", f"{text!r} has no port ({example})")
    if not _HOST.fullmatch(host):
        raise ConfigError("--scheduler", f"{host!r} is not a host name or IP address in {text!r}")
    if not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
        raise ConfigError("--scheduler", f"port must be 1-65535, got {port_text!r} in {text!r}")
    return scheme.lower(), host.strip("[]"), int(port_text)


def check_scheduler_address(scheduler: str) -> str:
    """``scheduler`` if it is a Dask address ``SCHEME://HOST:PORT``
    (:func:`parse_scheduler_address`), stripped.

    Raises:
        ConfigError: naming ``--scheduler``.
    """
    parse_scheduler_address(scheduler)
    return str(scheduler).strip()


def check_workers(workers: int | None, field: str = "--workers") -> int:
    """``workers`` as a count (None: :func:`default_workers`), 1 to :func:`max_workers`.

    Raises:
        ConfigError: not a whole number in 1 .. :func:`max_workers`.
    """
    if workers is None:
        return default_workers()
    most = max_workers()
    if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= most:
        raise ConfigError(
            field,
            f"must be a whole number from 1 to {most} ({WORKERS_PER_CORE} x "
            f"{default_workers()} cores), got {workers!r}",
        )
    return workers


def _probe(host: str, port: int, address: str, *, greeting: bool) -> None:
    """Refuse at once a scheduler that nothing listens to (a refused TCP connection)
    and, with ``greeting`` (plain ``tcp://``), a listener that is not a Dask scheduler:
    a scheduler sends its handshake as soon as a connection opens, and Dask's own
    client would wait for it without end."""
    import socket

    def refuse(reason: str) -> SchedulerError:
        return SchedulerError(f"cannot reach the Dask scheduler at {address} ({reason})")

    try:
        sock = socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S)
    except TimeoutError:
        raise refuse(f"no answer within {CONNECT_TIMEOUT_S:g} s") from None
    except OSError as exc:
        raise refuse(exc.strerror or str(exc) or type(exc).__name__) from None
    with sock:
        try:
            if greeting and not sock.recv(1):
                raise refuse("it closed the connection: not a Dask scheduler")
        except TimeoutError:
            raise refuse(f"no Dask handshake within {CONNECT_TIMEOUT_S:g} s") from None
        except OSError as exc:
            raise refuse(exc.strerror or str(exc) or type(exc).__name__) from None


@contextmanager
def _quiet_dask() -> Iterator[None]:
    """Dask's own log lines and the ``Client.__del__`` of a client that never connected
    stay silent while connecting: the error is reported in one line by the caller."""
    import gc
    import logging

    logger = logging.getLogger("distributed")
    level, hook = logger.level, sys.unraisablehook
    logger.setLevel(logging.CRITICAL + 1)
    sys.unraisablehook = lambda unraisable: None
    try:
        yield
    finally:
        gc.collect()  # a failed Client's __del__ runs now, while it is silenced
        logger.setLevel(level)
        sys.unraisablehook = hook


def check_scheduler_reachable(scheduler: str) -> str:
    """``scheduler`` (stripped) once Dask is known to be installed and something listens
    at its address: the CLI calls this before any heavy work, so that a wrong
    ``--scheduler`` is refused in one line within about :data:`CONNECT_TIMEOUT_S`.

    Raises:
        ConfigError: a malformed address, or Dask not installed.
        SchedulerError: nothing answers at the address.
    """
    import importlib.util

    scheme, host, port = parse_scheduler_address(scheduler)
    address = check_scheduler_address(scheduler)
    try:  # found, not imported (importing Dask takes a second or more)
        found = importlib.util.find_spec("distributed") is not None
    except (ImportError, ValueError):
        found = False
    if not found:
        raise ConfigError(
            "--scheduler", "needs Dask, which is not installed: pip install 'omnipipe[dask]'"
        )
    if scheme in ("tcp", "tls", "ws", "wss"):
        _probe(host, port, address, greeting=scheme == "tcp")
    return address


def _dask_client(scheduler: str) -> Any:
    """A connected ``distributed.Client`` (one-line errors without Dask or scheduler,
    within about :data:`CONNECT_TIMEOUT_S`)."""
    address = check_scheduler_reachable(scheduler)
    try:
        from distributed import Client
    except ImportError:
        raise ConfigError(
            "--scheduler", "needs Dask, which is not installed: pip install 'omnipipe[dask]'"
        ) from None

    reason = ""
    with _quiet_dask():
        try:
            return Client(address, timeout=f"{CONNECT_TIMEOUT_S:g}s", set_as_default=False)
        except Exception as exc:  # Dask raises OSError, TimeoutError, ValueError, ...
            reason = one_line(str(exc)) or type(exc).__name__
    raise SchedulerError(f"cannot reach the Dask scheduler at {address} ({reason})")


@contextmanager
def open_executor(
    workers: int | None = None, scheduler: str | None = None, tasks: int | None = None
) -> Iterator[Executor]:
    """The executor for ``workers`` local processes or the Dask cluster at ``scheduler``.

    Args:
        workers: local processes, 1 .. :func:`max_workers` (None: every core, 1: inline,
            no pool). Ignored when ``scheduler`` is given (the cluster's workers do the
            work).
        scheduler: a Dask scheduler address ``tcp://HOST:PORT``, or None.
        tasks: the most tasks there will be (frames, runs): no more processes than that
            are started. None: no cap.

    Yields:
        a ``concurrent.futures.Executor``; it is shut down (the Dask client closed) when
        the block ends. When the block raises (an error, Ctrl-C, SIGTERM) the local
        workers are killed at once rather than waited for; they also die with this
        process (:func:`worker_init`).

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
    if tasks is not None:
        n = max(1, min(n, int(tasks)))
    if n == 1:
        yield InlineExecutor()
        return
    import multiprocessing as mp

    from omnipipe.spill import share_with_local_workers

    share_with_local_workers()  # read-only scratch arrays go to the workers by reference
    ctx = mp.get_context("fork") if sys.platform.startswith("linux") else None
    # Ctrl-C reaches the whole process group: the workers ignore it and the parent
    # (which owns the output folder) stops the pool, so one line is printed, not N
    # tracebacks.
    pool = ProcessPoolExecutor(
        max_workers=n, mp_context=ctx, initializer=worker_init, initargs=(os.getpid(),)
    )
    try:
        if ctx is not None:
            _fork_workers_now(pool)
        yield pool
    except BaseException:
        kill_workers(pool)
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _fork_workers_now(pool: ProcessPoolExecutor) -> None:
    """Fork ``pool``'s worker processes now, with OpenCV's thread pool stopped here.

    A forked child inherits every lock as it was at the fork. One of OpenCV's pool
    threads can hold its pool's mutex for a moment after a parallel call returned (going
    back to sleep); a worker forked in that moment waited for ever on the mutex at its
    first parallel OpenCV call (seen once: a benchmark's 53rd run, in ``cv2.remap``). With
    OpenCV's threads at 0 during the fork the parent's pool threads are joined first, and
    the workers inherit the setting: their OpenCV calls run on their own thread (the pool
    already has a process per core) and never touch the inherited pool. The parent's
    setting is restored after the fork. A forked local pool starts all its processes at
    its first task (``concurrent.futures``), so an empty task is sent here.
    """
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(0)
    try:
        pool.submit(_nothing).result()
    finally:
        cv2.setNumThreads(before)


def kill_workers(pool: ProcessPoolExecutor) -> None:
    """End ``pool``'s worker processes now (SIGKILL), not after their current task: a
    run that stops (error, Ctrl-C, SIGTERM) does not wait for the work in progress."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    # Tasks still queued for the dead workers: the queue's feeder thread may be blocked
    # writing one into a full pipe that nothing reads any more, and the pool's manager
    # thread would wait for that thread at shutdown, and the interpreter for the manager
    # at exit (a hang seen once after a whole test run). The feeder is a daemon thread:
    # do not wait for it.
    call_queue = getattr(pool, "_call_queue", None)
    if call_queue is not None:
        call_queue.cancel_join_thread()
    # Killed before the shutdown: the pool's manager thread then sees the dead workers
    # (a broken pool) and ends, instead of waiting for their results at interpreter exit.
    for proc in processes:
        try:
            proc.kill()
        except (OSError, ValueError, AttributeError):
            pass
    for proc in processes:
        try:
            proc.join(timeout=5)
        except (OSError, ValueError, AssertionError):
            pass
    _close_result_writer(pool)
    manager = getattr(pool, "_executor_manager_thread", None)
    pool.shutdown(wait=False, cancel_futures=True)
    if manager is not None:
        manager.join(timeout=5)


def _close_result_writer(pool: ProcessPoolExecutor) -> None:
    """Close this process's end of ``pool``'s result pipe once its workers are dead.

    A worker killed while it was writing a result leaves half a message in the pipe; the
    pool's manager thread then waits in ``recv`` for the rest, and nothing else would
    ever write it (the parent held the pipe's other end, so no end-of-file came): the
    interpreter hung at exit. With every writer closed the read ends at once (EOFError),
    the manager marks the pool broken and ends.
    """
    result_queue = getattr(pool, "_result_queue", None)
    writer = getattr(result_queue, "_writer", None)
    if writer is None:
        return
    try:
        writer.close()
    except OSError:
        pass


# Seconds between a worker's checks that its parent is still alive (the fallback of
# PR_SET_PDEATHSIG).
PARENT_POLL_S = 0.5


def worker_init(parent: int) -> None:
    """Initializer of every local worker process: it dies with ``parent``.

    SIGINT is ignored (the parent handles Ctrl-C and ends the pool); BLAS runs
    single-threaded (the pool's processes share the cores). On Linux the kernel
    sends the worker SIGKILL when the parent dies (``prctl(PR_SET_PDEATHSIG)``, also
    after a SIGKILL or the OOM killer); everywhere a daemon thread checks every
    :data:`PARENT_POLL_S` s that ``parent`` is still this process's parent and kills
    the worker when it is not.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # The pool already has a process per core: BLAS threads inside each worker would only
    # compete with the other workers (small least-squares SVDs waited on busy threads).
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    global _FORKED_WORKER
    _FORKED_WORKER = True
    _die_with_parent()
    if os.getppid() != parent:  # the parent died before the line above took effect
        os.kill(os.getpid(), signal.SIGKILL)
    threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()


def _die_with_parent() -> bool:
    """``prctl(PR_SET_PDEATHSIG, SIGKILL)`` on Linux; False where unavailable."""
    if not sys.platform.startswith("linux"):
        return False
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        return int(libc.prctl(pr_set_pdeathsig, int(signal.SIGKILL), 0, 0, 0)) == 0
    except (OSError, AttributeError):
        return False


def _watch_parent(parent: int) -> None:
    while True:
        time.sleep(PARENT_POLL_S)
        if os.getppid() != parent:
            os.kill(os.getpid(), signal.SIGKILL)


_THREADS: tuple[int, int, ThreadPoolExecutor] | None = None  # (pid, threads, pool)
# True in a local pool's worker (:func:`worker_init`), forked from a parent with threads.
_FORKED_WORKER = False


@contextmanager
def opencv_threads(threads: int) -> Iterator[None]:
    """OpenCV's own thread pool limited to ``threads`` inside the block (restored after).

    For a process that runs OpenCV's calls on threads of its own (:func:`thread_map`):
    OpenCV's internal pool then splits each call's few hundred points or rows again,
    and its synchronisation costs CPU the other threads and processes need (the
    tracker's pyramidal flow on 1600x1200's views: 41-46 CPU-ms a frame with OpenCV's
    two threads, 37 with one). The results do not depend on it.

    A no-op in a local pool's worker (a run of ``omnipipe batch``): forked from a parent
    whose OpenCV pool had threads, ``cv2.setNumThreads`` there can wait for ever on a lock
    one of those threads held at the fork (seen once in a worker's initializer).
    """
    if _FORKED_WORKER:
        yield
        return
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(threads)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def thread_map(fn: Callable[..., R], *iterables: Iterable[Any], threads: int = 1) -> list[R]:
    """``[fn(*args) for args in zip(*iterables)]``, in order, on up to ``threads``
    threads of this process (one pool per process, made on first use).

    For independent calls that release the GIL (OpenCV's SIFT and optical flow per
    perspective view): the process that chains the frames then uses the cores the
    workers leave idle. The results are those of the serial loop; ``threads <= 1``
    is that loop.
    """
    args = list(zip(*iterables, strict=True))
    if threads <= 1 or len(args) <= 1:
        return [fn(*a) for a in args]
    global _THREADS
    if _THREADS is None or _THREADS[0] != os.getpid() or _THREADS[1] != threads:
        # A forked child inherits the parent's pool object without its threads: new one.
        _THREADS = (os.getpid(), threads, ThreadPoolExecutor(threads, thread_name_prefix="omnipipe"))
    return list(_THREADS[2].map(lambda a: fn(*a), args))


def parallelism(executor: Executor) -> int:
    """How many tasks ``executor`` runs at once (1 inline, N processes, the cluster's threads)."""
    if isinstance(executor, InlineExecutor):
        return 1
    if isinstance(executor, ProcessPoolExecutor):
        return int(executor._max_workers)
    return int(getattr(executor, "omnipipe_parallelism", default_workers()))


def shares_files(executor: Executor) -> bool:
    """True when ``executor``'s tasks run in other processes of this machine (a local
    process pool): they can read this run's scratch files by path rather than be sent
    the arrays through a pipe (inline: nothing is sent; a Dask cluster: its workers may
    be elsewhere)."""
    return isinstance(executor, ProcessPoolExecutor)


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
    forget_last_task(executor)


def shared_fields(value: T, executor: Executor) -> T:
    """``value`` (a dataclass) for tasks on ``executor``: on a local pool, its array fields
    copied into the run's scratch, read-only (:func:`omnipipe.spill.shared_on_disk`), so
    that each task carries a reference to them rather than their values (the same values
    in the task); ``value`` itself on other executors."""
    import dataclasses

    import numpy as np

    if not shares_files(executor) or not dataclasses.is_dataclass(value):
        return value
    from omnipipe.spill import shared_on_disk

    arrays = {
        f.name: shared_on_disk(v)
        for f in dataclasses.fields(value)
        if isinstance(v := getattr(value, f.name), np.ndarray)
    }
    return dataclasses.replace(value, **arrays)  # type: ignore[type-var]


def _nothing() -> None:
    """The task :func:`forget_last_task` sends (it does nothing)."""


def forget_last_task(executor: Executor) -> None:
    """Let a local pool's queue drop the last task it sent (no effect on other executors).

    The pool's queue pickles each task in a feeder thread of this process, which keeps
    the last task's pickle (its local variable) until it sends the next: after a stage
    whose tasks carry large arrays (the defect search's wall samples: 16 MB at 10,000
    frames) that pickle stayed resident until the next stage sent something. An empty
    task sent now takes its place.
    """
    if isinstance(executor, ProcessPoolExecutor):
        try:
            executor.submit(_nothing)
        except RuntimeError:  # shut down (or broken) meanwhile: nothing to send
            pass


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
        handoff: the folder of a :class:`~omnipipe.handoff.FrameHandoff` whose frames
            are read from there rather than decoded again (a video's or bag's by
            :meth:`take`, in the calling process), or None.
    """

    rig: Any
    frames: Sequence[int]
    paths: tuple[Path, ...] | None = None
    arrays: tuple[Any, ...] | None = None
    payload: tuple[Any, ...] | None = None
    handoff: str | None = None

    @staticmethod
    def take(
        dataset: Any,
        frames: Sequence[int],
        payload: Sequence[Any] | None = None,
        handoff: str | None = None,
        planar: bool = False,
    ) -> FrameSource:
        """The ``frames`` of an opened :class:`omnipipe.dataset.Dataset` (``payload``:
        one item per frame, carried to the task; ``handoff``: see the attribute;
        ``planar``: a video's or bag's frame handed on planar is carried as its
        :class:`~omnipipe.handoff.PlanarFrame`, as :meth:`read` gives it with ``planar``)."""
        extra = None if payload is None else tuple(payload)
        if dataset.video is None and dataset.source is None:
            paths = tuple(dataset.frame_paths[i] for i in frames)
            return FrameSource(dataset.rig, frames, paths=paths, payload=extra, handoff=handoff)
        arrays = tuple(_read_here(dataset, i, handoff, planar) for i in frames)
        return FrameSource(dataset.rig, frames, arrays=arrays, payload=extra)

    def __len__(self) -> int:
        return len(self.frames)

    def read(self, k: int, planar: bool = False) -> Any:
        """The k-th frame of this source (0-based within it) as an array; with ``planar``
        a frame handed on planar as its :class:`~omnipipe.handoff.PlanarFrame` (for a
        reader that samples it at some pixels only).

        Raises:
            DatasetError: unreadable image or wrong size, naming the file.
        """
        if self.arrays is not None:
            return self.arrays[k]
        if self.handoff is not None:
            from omnipipe.handoff import handed, handed_frame

            i = int(self.frames[k])
            image = handed_frame(self.handoff, i) if planar else handed(self.handoff, i)
            if image is not None:
                return image
        from omnipipe.dataset import read_image

        if self.paths is None:  # take() always sets one of paths / arrays
            raise DatasetError(f"frame {int(self.frames[k])}: neither an image nor its path was handed over")
        return read_image(self.paths[k], self.rig)


def _read_here(dataset: Any, i: int, handoff: str | None, planar: bool = False) -> Any:
    """Frame ``i`` of a video or bag, read in this process: from ``handoff`` where the
    decoding pass left it (no seek and decode; ``planar``: as :meth:`FrameSource.read`),
    else decoded."""
    if handoff is not None:
        from omnipipe.handoff import handed, handed_frame

        image = handed_frame(handoff, i) if planar else handed(handoff, i)
        if image is not None:
            return image
    return dataset.read_frame(i)


def iter_frames(
    executor: Executor,
    fn: Callable[[FrameSource], list[R]],
    dataset: Any,
    frames: Sequence[int] | None = None,
    *,
    most: int = 16,
    payload: Callable[[int], Any] | None = None,
    handoff: str | None = None,
) -> Iterator[tuple[int, R]]:
    """Frame-parallel streaming: ``(frame index, fn's result for it)`` in frame order.

    ``fn(source)`` runs on consecutive chunks of the frames (:class:`FrameSource`, at
    most ``most`` frames a chunk) and returns one result per frame. At most
    2 x :func:`parallelism` chunks are in flight and nothing is kept once yielded, so
    memory stays bounded however long the run (a consumer that keeps only what it
    needs holds only that). ``frames``: a subset of the dataset's indices (default:
    all), e.g. only the moving frames. ``payload(i)``: what the task needs of frame i
    besides its image (:attr:`FrameSource.payload`). ``handoff``: frames read from a
    :class:`~omnipipe.handoff.FrameHandoff`'s folder where there. Chunks are cut lazily, so a
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
        FrameSource.take(dataset, part, None if payload is None else [payload(i) for i in part], handoff)
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
