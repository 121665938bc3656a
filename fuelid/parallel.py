"""Independent computations run side by side in worker processes: `side_by_side(calls)` is
`[call() for call in calls]`, and inside `jobs(n)` with n > 1 it runs the first call in this process and the others
in up to n − 1 worker processes.

A call must be a pure function of its arguments: it returns what it would return here, and whatever it changes in its
arguments stays in the worker. One that does not pickle (a closure, not a module-level function or a functools.partial
of one) runs here. The results come back in the calls' order; the first call (in that order) that raised raises here.

The workers are spawned, never forked (a fork of a process running threads — BLAS's, a progress bar's — can
deadlock, and not every platform forks), when the `jobs` context opens, so that they load fuelid while this process
reads its data. They never outlive it: the context stops them when it closes (its work done, an error, Ctrl-C, which
they ignore themselves, or SIGTERM, which it turns into an exit); the kernel kills them when this process dies
(Linux's PR_SET_PDEATHSIG), and elsewhere each checks every second that its parent is alive. A worker that dies, or a
call that has not come back within `time_limit` of the first call's time here, is no reason to fail: the call runs
again here (the same result) and the context uses no worker any more.

Without a `jobs` context, in a daemonic process (a Dask worker may not start processes), where processes cannot be
started (no semaphores in a locked-down container) or with n = 1 every call runs here, one after the other: the
library's default, so that a fleet job's memory stays its own.
"""
from __future__ import annotations

import contextlib
import contextvars
import ctypes
import importlib
import multiprocessing
import os
import pickle
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import Any, TypeVar

T = TypeVar("T")

MIN_TIME_LIMIT_S = 60.0  # [s] a worker's call may take this long beyond TIME_FACTOR × the first call's time here
TIME_FACTOR = 20.0  # the calls of one side_by_side are of one kind (fold refits, candidate builds): similar in cost


def time_limit(first_s: float) -> float:
    """[s] How long the other calls of a side_by_side may take, the first having taken first_s [s] here: a call
    this much slower than its sibling is stuck (a worker lost to the system, a deadlock), not busy."""
    return MIN_TIME_LIMIT_S + TIME_FACTOR * first_s


def available_cpus() -> int:
    """The CPUs this process may run on (its affinity where the platform tells it, else the machine's)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on every platform
        return os.cpu_count() or 1


@dataclass
class _Workers:
    """The worker processes of one `jobs` context; usable turns False once one died or a call timed out."""

    pool: ProcessPoolExecutor
    count: int
    usable: bool = True
    processes: list = field(default_factory=list)


_WORKERS: contextvars.ContextVar[_Workers | None] = contextvars.ContextVar("fuelid_workers", default=None)
_BUSY = contextvars.ContextVar("fuelid_side_by_side", default=False)  # within a call side_by_side runs here


@contextlib.contextmanager
def jobs(n: int, preload: Sequence[str] = ()):
    """A context in which `side_by_side` runs up to n calls at once (module docstring); preload: modules the workers
    import as they start (those of the calls to come)."""
    if n < 1:
        raise ValueError(f"jobs must be at least 1, got {n}")
    if n == 1 or multiprocessing.current_process().daemon:
        yield
        return
    pool = _started_pool(n - 1, preload)
    if pool is None:
        yield
        return
    workers = _Workers(pool, n - 1)
    workers.processes = list(pool._processes.values())  # no public handle on them before Python 3.14
    token = _WORKERS.set(workers)
    # SIGTERM (a service stopped, timeout(1)) unwinds as an exit, so that the workers are stopped here too
    terminating = threading.current_thread() is threading.main_thread() \
        and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    if terminating:
        signal.signal(signal.SIGTERM, _terminated)
    try:
        yield
    except BaseException:
        _kill(workers)
        raise
    finally:
        if terminating:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
        _WORKERS.reset(token)
        pool.shutdown(wait=workers.usable, cancel_futures=True)


def _started_pool(count: int, preload: Sequence[str]) -> ProcessPoolExecutor | None:
    """A pool of `count` spawned workers, started now (the pool starts one per call waiting); None where processes
    cannot be started here (no semaphores in a locked-down container)."""
    try:
        pool = ProcessPoolExecutor(count, mp_context=multiprocessing.get_context("spawn"), initializer=_started,
                                   initargs=(os.getpid(), tuple(preload)))
    except (OSError, ImportError, NotImplementedError):
        return None
    try:
        for _ in range(count):
            pool.submit(_ready)
    except (OSError, BrokenProcessPool):
        pool.shutdown(wait=False, cancel_futures=True)
        return None
    return pool


def _terminated(signum, frame):
    """SIGTERM within `jobs`: exit with the status a process killed by it has (128 + 15)."""
    raise SystemExit(128 + signum)


def _kill(workers: _Workers) -> None:
    """Stop the workers now, whatever they run; the context's calls run here from then on."""
    workers.usable = False
    workers.pool.shutdown(wait=False, cancel_futures=True)
    for p in workers.processes:
        with contextlib.suppress(OSError, ValueError):
            p.kill()
    for p in workers.processes:
        with contextlib.suppress(OSError, ValueError, AssertionError):
            p.join(5.0)


@dataclass(frozen=True)
class _Outcome:
    """A call's result or the exception it raised."""

    value: Any = None
    error: BaseException | None = None

    def get(self):
        if self.error is not None:
            raise self.error
        return self.value


def _outcome(call: Callable[[], T]) -> _Outcome:
    try:
        return _Outcome(call())
    except Exception as exc:  # noqa: BLE001 — handed back in the calls' order (module docstring)
        return _Outcome(error=exc)


def workers_available() -> bool:
    """Whether `side_by_side` runs calls in worker processes here (inside `jobs` with n > 1, its workers usable, and
    not within a call of another side_by_side)."""
    workers = _WORKERS.get()
    return workers is not None and workers.usable and not _BUSY.get()


def side_by_side(calls: Sequence[Callable[[], T]]) -> list[T]:
    """[call() for call in calls], run side by side inside `jobs` (module docstring): in order, each worker given the
    next call not begun whenever it is free and this process taking the next one itself. A call run here runs any
    side_by_side of its own one call after the other (the workers are busy with its siblings)."""
    calls = list(calls)
    if not workers_available() or len(calls) < 2:
        return [call() for call in calls]
    workers = _WORKERS.get()
    todo = list(range(len(calls)))  # not begun, in order
    away: dict[Future, int] = {}  # begun in a worker
    done: dict[int, _Outcome] = {}
    deadline = None
    busy = _BUSY.set(True)
    try:
        while todo or away:
            if todo:
                k = todo.pop(0)
                _send(workers, calls, todo, away)
                t = time.perf_counter()
                done[k] = _outcome(calls[k])
                deadline = deadline or time.perf_counter() + time_limit(time.perf_counter() - t)
                finished, _ = wait(away, timeout=0.0)
            else:
                finished, _ = wait(away, timeout=max(deadline - time.perf_counter(), 0.0), return_when=FIRST_COMPLETED)
                if not finished:  # stuck: no more workers, their calls here
                    _lost(workers, away, todo)
            for future in finished:
                if future not in away:  # put back by _lost: a worker died
                    continue
                k = away.pop(future)
                try:
                    done[k] = _Outcome(future.result())
                except BrokenProcessPool:  # the worker died: no more workers, the call here
                    _lost(workers, away, todo)
                    todo.insert(0, k)
                except Exception as exc:  # noqa: BLE001 — the call's own error, as it would have raised here
                    done[k] = _Outcome(error=exc)
    finally:
        _BUSY.reset(busy)
    return [done[k].get() for k in range(len(calls))]


def _send(workers: _Workers, calls, todo: list[int], away: dict) -> None:
    """Give each free worker the next call of `todo` that pickles (taken off it; one that does not, a closure, is
    left for this process); when the workers are gone, none."""
    for k in list(todo):
        if not workers.usable or len(away) >= workers.count:
            return
        try:
            payload = pickle.dumps(calls[k])
        except Exception:  # noqa: BLE001 — whatever pickling raises, the call runs here
            continue
        try:
            away[workers.pool.submit(_called, payload)] = k
        except BrokenProcessPool:
            _lost(workers, away, todo)
            return
        todo.remove(k)


def _lost(workers: _Workers, away: dict, todo: list[int]) -> None:
    """The workers died or are stuck: stopped, and the calls they had put back in front of `todo`."""
    _kill(workers)
    todo[:0] = sorted(away.values())
    away.clear()


def _started(parent: int, preload: tuple[str, ...]) -> None:
    """A worker's start: die with the parent (module docstring), load the modules its calls will need."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG = 1
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(1)
    threading.Thread(target=_watch, args=(parent,), daemon=True, name="fuelid-parent-watch").start()
    # Ctrl-C reaches the whole process group: the parent stops the workers, none prints a traceback of its own
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for name in preload:
        importlib.import_module(name)


def _watch(parent: int) -> None:
    """Exit the worker once its parent is gone (it is then another process's child)."""
    while os.getppid() == parent:
        time.sleep(1.0)
    os._exit(1)


def _called(payload: bytes):
    """A worker's call: pickled here by `_send`, so that a call that does not pickle fails there, not in the pool."""
    return pickle.loads(payload)()


def _ready() -> None:
    """The call that starts a worker."""
