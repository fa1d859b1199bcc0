"""Running a graph of pipeline tasks: in this process, on local worker processes, or on Dask.

A task graph is an ordered dict ``key -> Task(fn, args, deps)``, every task after the tasks it
depends on. ``fn(*args, *[pass-on part of each dep's result])`` returns a pair ``(keep, pass_on)``:
``keep`` comes back to the caller, ``pass_on`` only goes to the tasks that depend on it (so the
caller never holds what only a worker needs). The result does not depend on the runner or the
number of workers: tasks are pure functions of their arguments.

Runners (:func:`make_runner`):

* ``jobs=1``: in this process, in graph order.
* ``jobs=N``: N local worker processes (``concurrent.futures`` with the ``forkserver`` start
  method, so workers never inherit this process's threads or memory), each with one BLAS thread
  (:func:`one_blas_thread`).
* ``dask="tcp://host:8786"``: an existing Dask distributed scheduler (every worker needs polycc
  installed, same version); ``dask="local:N"``: a local Dask cluster of N single-threaded worker
  processes, started for the run and closed after it. Needs ``pip install 'polycc[dask]'``.

``Runner.local_cores`` is how many local processes the stages outside the graph (the budget's
candidates) may fork: N for ``jobs=N`` and ``local:N``, every core for a remote scheduler.
A local cluster's workers run without Dask's statistical profiler and without the nanny's
``MALLOC_TRIM_THRESHOLD_`` (setting it turns off glibc's adaptive mmap threshold, so every large numpy
array was mapped and faulted in afresh: the 1.5M-splat room at 2.5 cm spent 49 s in the kernel
instead of 15, and its occupancy took 20.6 s on 2 workers instead of 6.9).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from polycc.errors import PolyccError

Progress = Callable[[int, int], None]


@dataclass
class Task:
    """``fn(*args, *passed-on results of deps)``; ``args`` may be a callable that returns the
    tuple, called when the task starts (so a graph need not hold every task's data at once)."""

    fn: Callable
    args: Any = ()
    deps: tuple = ()
    weight: float = 1.0  # relative cost, for progress only


@dataclass
class RunStats:
    """Wall and summed task seconds of a run, per task-name prefix (``key[0]`` of tuple keys)."""

    wall_s: float = 0.0
    task_s: dict = field(default_factory=dict)
    workers: int = 1
    where: str = "this process"


def available_cores() -> int:
    """Cores this process may run on (the default for ``--jobs``)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


ROW_CHUNK = 32_768  # rows per chunk of :func:`in_row_chunks` (a 3DGS .ply record is 248 B: 8 MB a chunk)


def in_row_chunks(n: int, fn: Callable[[int, int], None], chunk: int | None = None, threads: int | None = None) -> None:
    """Call ``fn(start, stop)`` for consecutive row ranges of ``n`` rows, ``chunk`` rows each (default
    :data:`ROW_CHUNK`), on ``threads`` threads of this process (default: one per core). For numpy work on
    millions of rows: numpy releases the GIL in its loops, and a chunk's rows stay in the cache between the
    steps of ``fn``. ``fn`` writes its rows into arrays made before; when it works row by row the result is the
    same bit for bit as one call on every row. The first exception raised is raised here, after every chunk
    has finished.

    Measured on the 6M-splat room's 1.49 GB .ply: its 16 used columns to float64 in 0.29 s on 2 threads,
    against 1.5 s column by column (each column a strided pass over every record)."""
    from concurrent.futures import ThreadPoolExecutor

    chunk = max(1, int(ROW_CHUNK if chunk is None else chunk))
    starts = range(0, n, chunk)
    threads = min(available_cores() if threads is None else max(1, int(threads)), len(starts))
    if threads <= 1:
        for s in starts:
            fn(s, min(n, s + chunk))
        return
    with ThreadPoolExecutor(threads, thread_name_prefix="polycc-rows") as ex:
        futs = [ex.submit(fn, s, min(n, s + chunk)) for s in starts]
    for f in futs:
        f.result()


def one_blas_thread():
    """Context manager: BLAS and OpenMP thread pools of this process at one thread (threadpoolctl), restored
    on exit. For a process that computes beside other worker processes: N workers on N cores each with a
    BLAS pool of N threads run N^2 threads that spin against each other (OpenBLAS busy-waits). Measured on
    the 6M-splat room's cover: the two selection-score tasks, side by side on 2 worker processes, took 2.8 s
    each with 2-thread BLAS pools and 1.4-2.0 s with one thread (1.2 s alone in one process). Dask's local
    cluster sets the same limit through its workers' environment."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1)


def init_worker() -> None:
    """Initialiser of every local worker process: one BLAS thread for the life of the process."""
    one_blas_thread()


def _timed(fn, *args):
    t = time.perf_counter()
    keep, pass_on = fn(*args)
    return keep, pass_on, time.perf_counter() - t


class Runner:
    """Serial runner: every task in this process, in graph order."""

    workers = 1
    where = "this process"
    local_cores = 1  # local processes the stages outside the graph may fork (the budget); None: every core

    def __init__(self):
        self.stats = RunStats(workers=self.workers, where=self.where)

    def _account(self, key, seconds: float) -> None:
        name = key[0] if isinstance(key, tuple) else str(key)
        self.stats.task_s[name] = self.stats.task_s.get(name, 0.0) + seconds

    def run(self, graph: dict, progress: Progress | None = None) -> dict:
        t0 = time.perf_counter()
        passed: dict = {}
        out: dict = {}
        users = _users(graph)
        if progress:
            progress(0, len(graph))
        for k, (key, task) in enumerate(graph.items()):
            keep, pass_on, dt = _timed(task.fn, *_args(task), *[passed[d] for d in task.deps])
            self._account(key, dt)
            out[key] = keep
            if users[key]:
                passed[key] = pass_on
            for d in task.deps:
                users[d] -= 1
                if not users[d]:
                    passed.pop(d, None)
            if progress:
                progress(k + 1, len(graph))
        self.stats.wall_s += time.perf_counter() - t0
        return out

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _args(task: Task) -> tuple:
    return tuple(task.args()) if callable(task.args) else tuple(task.args)


def _users(graph: dict) -> dict:
    users = {key: 0 for key in graph}
    for task in graph.values():
        for d in task.deps:
            users[d] += 1
    return users


class PoolRunner(Runner):
    """N local worker processes; a task starts as soon as its dependencies are done."""

    def __init__(self, jobs: int):
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        self.workers = self.local_cores = int(jobs)
        self.where = f"{jobs} local processes"
        super().__init__()
        method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        ctx = mp.get_context(method)
        if method == "forkserver":
            ctx.set_forkserver_preload(["polycc.parallel", "numpy", "scipy.spatial"])
        self.pool = ProcessPoolExecutor(self.workers, mp_context=ctx, initializer=init_worker)

    def run(self, graph: dict, progress: Progress | None = None) -> dict:
        from concurrent.futures import FIRST_COMPLETED, wait

        t0 = time.perf_counter()
        users = _users(graph)
        waiting = {key: set(task.deps) for key, task in graph.items()}
        passed: dict = {}
        out: dict = {}
        running: dict = {}
        done_n = 0
        if progress:
            progress(0, len(graph))

        def launch():
            for key in [k for k, deps in waiting.items() if not deps]:
                task = graph[key]
                del waiting[key]
                fut = self.pool.submit(_timed, task.fn, *_args(task), *[passed[d] for d in task.deps])
                running[fut] = key
                for d in task.deps:
                    users[d] -= 1
                    if not users[d]:
                        passed.pop(d, None)

        launch()
        while running:
            finished, _ = wait(list(running), return_when=FIRST_COMPLETED)
            for fut in finished:
                key = running.pop(fut)
                try:
                    keep, pass_on, dt = fut.result()
                except Exception:
                    for f in running:
                        f.cancel()
                    raise
                self._account(key, dt)
                out[key] = keep
                if users[key]:
                    passed[key] = pass_on
                for k2, deps in waiting.items():
                    deps.discard(key)
                done_n += 1
                if progress:
                    progress(done_n, len(graph))
            launch()
        self.stats.wall_s += time.perf_counter() - t0
        return {key: out[key] for key in graph}

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


class DaskRunner(Runner):
    """The same graph on Dask distributed: an existing scheduler or a local cluster."""

    def __init__(self, address: str):
        try:
            from dask.distributed import Client, LocalCluster
        except ImportError:
            raise PolyccError("--dask needs Dask distributed: pip install 'polycc[dask]' (or dask[distributed])") \
                from None
        self.cluster = None
        if address.startswith("local:"):
            try:
                n = int(address.split(":", 1)[1])
            except ValueError:
                n = 0
            if n < 1:
                raise PolyccError(f"--dask {address}: expected local:N with N >= 1 worker processes, e.g. local:2")
            import dask

            # no MALLOC_TRIM_THRESHOLD_ in the workers' environment (module docstring: measured), and no
            # statistical profiler (it samples each running task's stack 100 times a second under the GIL;
            # not measured on its own). A cluster of your own: `dask worker --no-nanny` sets no environment
            with dask.config.set({"distributed.worker.profile.enabled": False,
                                  "distributed.nanny.pre-spawn-environ": {
                                      "OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1}}):
                self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                            dashboard_address=None)
            self.client = Client(self.cluster)
            self.workers = self.local_cores = n
            self.where = f"local Dask cluster, {n} workers"
        else:
            try:
                self.client = Client(address, timeout="20s")
            except (OSError, TimeoutError) as exc:
                raise PolyccError(f"--dask {address}: cannot reach the Dask scheduler ({exc}); start one with "
                                  "`dask scheduler` and workers with `dask worker ADDRESS`, or use --dask local:N")\
                    from None
            self.workers = max(1, len(self.client.scheduler_info().get("workers", {})))
            self.local_cores = None  # the budget runs on this machine, on every core
            self.where = f"Dask scheduler {address}, {self.workers} workers"
        super().__init__()

    def run(self, graph: dict, progress: Progress | None = None) -> dict:
        import operator

        import numpy as np
        from dask.distributed import as_completed

        t0 = time.perf_counter()
        c = self.client
        passed: dict = {}
        keep: dict = {}
        tag = f"{os.getpid()}-{time.time_ns()}"

        def ship(a: Any):
            # large arrays go to the workers once, not inside the task graph
            return c.scatter(a) if isinstance(a, np.ndarray) and a.nbytes > (1 << 20) else a

        users = _users(graph)
        if progress:
            progress(0, len(graph))
        for n, (key, task) in enumerate(graph.items()):
            name = f"polycc-{tag}-{n}"
            fut = c.submit(_timed, task.fn, *[ship(a) for a in _args(task)], *[passed[d] for d in task.deps],
                           key=name, pure=False)
            keep[c.submit(operator.itemgetter(0, 2), fut, key=name + "-keep", pure=False)] = key
            if users[key]:
                passed[key] = c.submit(operator.itemgetter(1), fut, key=name + "-pass", pure=False)
            del fut
        passed.clear()  # the scheduler keeps what the submitted tasks still need, and frees the rest
        out: dict = {}
        for k, fut in enumerate(as_completed(list(keep))):
            kept, dt = fut.result()
            key = keep[fut]
            self._account(key, dt)
            out[key] = kept
            if progress:
                progress(k + 1, len(graph))
        self.stats.wall_s += time.perf_counter() - t0
        return {key: out[key] for key in graph}

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def make_runner(jobs: int | None = None, dask: str | None = None) -> Runner:
    """A runner for ``--jobs`` / ``--dask`` (see the module docstring); jobs None = every core."""
    if dask:
        return DaskRunner(dask)
    jobs = available_cores() if jobs is None else int(jobs)
    if jobs < 1:
        raise PolyccError(f"--jobs {jobs}: must be at least 1")
    return Runner() if jobs == 1 else PoolRunner(jobs)
