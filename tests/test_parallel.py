"""fuelid.parallel: calls side by side in spawned workers, the same results as one after the other, and workers that
never outlive their parent nor hold up a result."""
import functools
import multiprocessing
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from fuelid import parallel
from fuelid.errors import InputError
from fuelid.parallel import jobs, side_by_side, workers_available


def square(x: int) -> tuple[int, int]:
    return x * x, os.getpid()


def fails_on(x: int, bad: int) -> int:
    if x == bad:
        raise InputError(f"bad {x}")
    return x


def dies_in_worker(parent: int) -> str:
    if os.getpid() != parent:
        os._exit(1)
    return "here"


def sleeps_in_worker(parent: int) -> str:
    if os.getpid() != parent:
        time.sleep(60.0)
        return "worker"
    return "here"


def nested(x: int) -> list[int]:
    return [y for y, _ in side_by_side([functools.partial(square, x + k) for k in range(3)])]


def daemon_sees_workers(queue) -> None:
    with jobs(2):
        queue.put(workers_available())


def test_without_jobs_every_call_runs_here_in_order():
    assert not workers_available()
    assert side_by_side([functools.partial(square, k) for k in range(4)]) == [(k * k, os.getpid()) for k in range(4)]


def test_jobs_runs_calls_in_a_worker_and_returns_them_in_order():
    with jobs(2):
        assert workers_available()
        out = side_by_side([functools.partial(square, k) for k in range(6)])
    assert [v for v, _ in out] == [k * k for k in range(6)]
    assert {pid for _, pid in out} - {os.getpid()}, "no call ran in a worker"
    assert not workers_available()


def test_a_call_that_does_not_pickle_runs_here():
    with jobs(2):
        out = side_by_side([functools.partial(square, 2), lambda: (9, os.getpid()), functools.partial(square, 4)])
    assert out[1] == (9, os.getpid()) and [v for v, _ in out] == [4, 9, 16]


def test_the_first_error_in_call_order_is_raised():
    with jobs(2), pytest.raises(InputError, match="bad 2"):
        side_by_side([functools.partial(fails_on, k, 2) for k in range(5)])


def test_a_call_inside_a_call_runs_its_own_calls_here():
    with jobs(2):
        assert side_by_side([functools.partial(nested, k) for k in (0, 10)]) == [[0, 1, 4], [100, 121, 144]]


@pytest.mark.parametrize("n", [2, 3])
def test_a_worker_that_dies_costs_its_call_a_rerun_here_and_no_error(n):
    with jobs(n):
        out = side_by_side([functools.partial(dies_in_worker, os.getpid()) for _ in range(3)])
        assert not workers_available()  # the rest of the context runs here
        assert side_by_side([functools.partial(square, 3)] * 2) == [(9, os.getpid())] * 2
    assert out == ["here"] * 3


def test_a_stuck_worker_is_killed_and_its_call_run_here(monkeypatch):
    monkeypatch.setattr(parallel, "MIN_TIME_LIMIT_S", 1.0)
    with jobs(2):
        processes = list(parallel._WORKERS.get().processes)
        t = time.perf_counter()
        out = side_by_side([functools.partial(sleeps_in_worker, os.getpid()) for _ in range(2)])
        assert time.perf_counter() - t < 20.0
    assert out == ["here", "here"]
    assert _all_gone([p.pid for p in processes])


def test_an_error_in_the_context_kills_the_workers():
    with pytest.raises(KeyboardInterrupt):
        with jobs(2):
            processes = list(parallel._WORKERS.get().processes)
            raise KeyboardInterrupt
    assert processes and _all_gone([p.pid for p in processes])


def test_ctrl_c_is_the_parents_to_handle_not_the_workers():
    with jobs(2):
        (worker,) = parallel._WORKERS.get().processes
        side_by_side([functools.partial(square, 1)] * 3)  # the worker up
        os.kill(worker.pid, signal.SIGINT)
        out = side_by_side([functools.partial(square, k) for k in range(4)])
        assert workers_available() and worker.pid in {pid for _, pid in out}


def test_a_daemonic_process_runs_everything_here():
    ctx = multiprocessing.get_context("spawn")
    queue = ctx.Queue()
    p = ctx.Process(target=daemon_sees_workers, args=(queue,), daemon=True)
    p.start()
    assert queue.get(timeout=60) is False
    p.join(10)


@pytest.mark.parametrize("sig, status", [(signal.SIGKILL, -signal.SIGKILL), (signal.SIGTERM, 128 + signal.SIGTERM)])
def test_workers_die_with_a_killed_parent(tmp_path, sig, status):
    script = tmp_path / "parent.py"
    script.write_text(textwrap.dedent("""
        import functools, os, sys, time
        from fuelid import parallel
        if __name__ == "__main__":
            with parallel.jobs(2):
                # the worker up and idle: it has run a call (its pid back), waiting for the next
                pids = parallel.side_by_side([functools.partial(os.getpid)] * 3)
                assert set(pids) - {os.getpid()}
                print(*[p.pid for p in parallel._WORKERS.get().processes], flush=True)
                time.sleep(600)
    """))
    # (its resource tracker, left alone, says on stderr that it cleaned up after it)
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                              text=True)
    try:
        workers = [int(pid) for pid in parent.stdout.readline().split()]
        assert workers
        parent.send_signal(sig)
        assert parent.wait(10) == status  # SIGTERM: an exit that stops the workers first
        assert _all_gone(workers), "a worker outlived its killed parent"
    finally:
        parent.kill()


def _all_gone(pids: list[int], within_s: float = 10.0) -> bool:
    """Whether none of the processes pids runs within within_s [s]."""
    deadline = time.monotonic() + within_s
    while any(_alive(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    return not any(_alive(pid) for pid in pids)


def _alive(pid: int) -> bool:
    """Whether process pid runs (a zombie, dead but not yet reaped by init, does not)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_where_no_process_can_be_started_everything_runs_here(monkeypatch):
    def no_semaphores(*args, **kwargs):
        raise ImportError("This platform lacks a functioning sem_open implementation")

    monkeypatch.setattr(parallel, "ProcessPoolExecutor", no_semaphores)
    with jobs(2):
        assert not workers_available()
        assert side_by_side([functools.partial(square, 2)] * 2) == [(4, os.getpid())] * 2


def test_jobs_must_be_at_least_one():
    with pytest.raises(ValueError):
        with jobs(0):
            pass
