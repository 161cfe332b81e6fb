"""Where a campaign's tasks run: a small seam of :mod:`concurrent.futures` shape.

:class:`Engine` is an ``Executor`` (``submit`` returns a ``concurrent.futures.Future``,
``shutdown``) plus :meth:`Engine.missing` (what a worker cannot see). :func:`open_engine`
makes the default — Dask distributed: a ``LocalCluster`` of one single-threaded worker
process per core, every listener on 127.0.0.1, no dashboard unless asked — or connects to
an existing cluster (``--scheduler tcp://HOST:PORT``, ``--scheduler-file F``);
:class:`PoolEngine` runs the same tasks on a plain ``ProcessPoolExecutor`` (the baseline of
the benchmarks, and tests).

A worker that dies is retried once (``distributed.scheduler.allowed-failures`` = 1 on the
local cluster; on an existing cluster its scheduler's setting decides, see the user guide).
"""
from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from typing import Any

from rsra.daq.campaign.dataset import CampaignError

ALLOWED_FAILURES = 1  # a task whose worker died is run once more, then fails


class Engine:
    """An executor and what the campaign asks of it beyond ``submit``."""

    #: the executor the tasks are submitted to
    executor: Executor
    #: number of worker processes (single-threaded each)
    workers: int = 1
    #: what the engine is, for the progress line
    describe: str = ""

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        return self.executor.submit(fn, *args)

    def missing(self, paths: list[str]) -> dict[str, list[str]]:
        """Worker -> the paths it cannot see (empty when every worker sees all)."""
        return {}

    def close(self) -> None:
        self.executor.shutdown(wait=False, cancel_futures=True)


class PoolEngine(Engine):
    """A plain ``ProcessPoolExecutor`` (same machine: the paths are the driver's)."""

    def __init__(self, workers: int):
        self.workers = workers
        self.executor = ProcessPoolExecutor(max_workers=workers, initializer=ignore_sigint)
        self.describe = f"{workers} processes (ProcessPoolExecutor)"


class DaskEngine(Engine):
    """A Dask distributed client: a local cluster it made, or an existing cluster."""

    def __init__(self, client: Any, cluster: Any = None):
        self.client = client
        self.cluster = cluster
        self.executor = client.get_executor(pure=False)
        info = client.scheduler_info()
        self.workers = max(1, sum(w.get("nthreads", 1) for w in info["workers"].values()))
        where = "local cluster" if cluster is not None else f"cluster {client.scheduler.address}"
        self.describe = f"Dask {where}, {self.workers} workers"

    def missing(self, paths: list[str]) -> dict[str, list[str]]:
        if self.cluster is not None:  # our own workers on this machine see what we see
            return {}
        from rsra.daq.campaign.task import check_visible

        out = self.client.run(check_visible, paths)
        return {w: m for w, m in out.items() if m}

    def close(self) -> None:
        try:
            self.executor.shutdown(wait=False)
        finally:
            self.client.close()
            if self.cluster is not None:
                self.cluster.close()


def ignore_sigint() -> None:
    """In a worker process: Ctrl-C is the driver's (it cancels, keeps what finished and
    closes the workers); a worker would only die of it with a traceback."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored while the local cluster starts its worker processes (they inherit it,
    and neither Python nor asyncio then installs a handler of its own)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def _start_method() -> str:
    """How the local cluster's nannies start their worker: fork where the platform has it."""
    import multiprocessing

    return "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"


def cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # (not on Linux)
        return os.cpu_count() or 1


@contextlib.contextmanager
def open_engine(workers: int | None = None, scheduler: str | None = None,
                scheduler_file: str | None = None, dashboard: str | None = None,
                pool: bool = False) -> Iterator[Engine]:
    """The engine of a campaign, closed (cluster, client, workers) on the way out."""
    engine: Engine
    if pool:
        engine = PoolEngine(workers or cores())
    else:
        engine = _dask(workers, scheduler, scheduler_file, dashboard)
    try:
        yield engine
    finally:
        engine.close()


def _dask(workers: int | None, scheduler: str | None, scheduler_file: str | None,
          dashboard: str | None) -> DaskEngine:
    import logging

    import dask
    from distributed import Client, LocalCluster

    for name in ("distributed", "bokeh", "tornado"):
        # the user sees our lines (a lost worker: the recording's reason), not theirs
        logging.getLogger(name).setLevel(logging.CRITICAL)
    if scheduler or scheduler_file:
        what = f"--scheduler {scheduler}" if scheduler else f"--scheduler-file {scheduler_file}"
        try:
            if scheduler_file:
                if not os.path.isfile(scheduler_file):
                    raise CampaignError(f"--scheduler-file {scheduler_file}: no such file; fix: "
                                        "give the file `dask scheduler --scheduler-file` wrote")
                client = Client(scheduler_file=scheduler_file, timeout="10s")
            else:
                client = Client(scheduler, timeout="10s")
        except CampaignError:
            raise
        except (OSError, TimeoutError, ValueError) as e:
            raise CampaignError(f"{what}: cannot connect ({' '.join(str(e).split())[:120]}); "
                                "fix: start `dask scheduler` and `dask worker`s, or leave the "
                                "option out to use this machine's cores") from None
        if not client.scheduler_info()["workers"]:
            client.close()
            raise CampaignError(f"{what}: the cluster has no workers; fix: start `dask "
                                "worker SCHEDULER_ADDRESS` on each machine")
        return DaskEngine(client)
    n = workers or cores()
    # the workers' own log (a scheduler gone at Ctrl-C, a lost worker): the recording's
    # reason and our lines say what matters; read by each worker process as it starts
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "critical")
    # the identification worker of a recomputed replay is a child of the task's process:
    # worker processes are not daemonic; a task whose worker died runs once more
    dask.config.set({"distributed.worker.daemon": False,
                     "distributed.scheduler.allowed-failures": ALLOWED_FAILURES,
                     "distributed.admin.system-monitor.gil.enabled": False,
                     # one task a worker thread, the rest queued at the scheduler: a worker
                     # free takes the next recording (no task waiting behind a long one on a
                     # busy worker while another idles at the end of the campaign)
                     "distributed.scheduler.worker-saturation": 1.0,
                     # the workers forked from this process, as a ProcessPoolExecutor's are:
                     # spawned, each re-imports Python, distributed and numpy/scipy/pyarrow
                     # and takes seconds more to start and to close (measured: docs/performance.md, the campaign against a process pool)
                     "distributed.worker.multiprocessing-method": _start_method(),
                     # the statistical profiler samples every worker thread every 10 ms for
                     # the dashboard's profile: only when there is a dashboard
                     "distributed.worker.profile.enabled": dashboard is not None})
    with _sigint_ignored():
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                               host="127.0.0.1", scheduler_port=0,
                               dashboard_address=dashboard, worker_dashboard_address=None)
    try:
        client = Client(cluster)
    except BaseException:
        cluster.close()
        raise
    return DaskEngine(client, cluster)
