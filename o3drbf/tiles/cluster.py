"""Where tile tasks run: in this process, on a local Dask cluster, or on any scheduler.

One rule for every tiled step: ``client`` is

- ``None``: a ``LocalCluster`` (processes, ``workers`` workers of one thread)
  when there is more than one task, else this process;
- ``"synchronous"``: this process, one task after the other (the reference);
- a scheduler address (``"tcp://host:8786"``): a client connected to it;
- a ``distributed.Client``: used as given (never closed here).

Results do not depend on the choice: every task is a pure function of its
inputs and runs with one BLAS thread.
"""

from __future__ import annotations

import contextlib
import logging
import time
import uuid

from o3drbf.progress import progress_bar
from o3drbf.validation import check_number

__all__ = ["tile_client", "run_tasks", "measured_call", "worker_summary", "peak_rss", "SYNCHRONOUS"]

log = logging.getLogger("o3drbf")

SYNCHRONOUS = "synchronous"


@contextlib.contextmanager
def tile_client(client=None, tasks: int = 2, workers: int = 2, memory_limit=None):
    """Yield a ``distributed.Client``, or None for in-process execution.

    Parameters
    ----------
    client : None, "synchronous", str or distributed.Client
        See the module notes.
    tasks : int
        How many tasks will run (``client=None`` with one task runs in-process).
    workers : int
        Workers of a LocalCluster started here (>= 1).
    memory_limit : int or str, optional
        Per-worker memory limit of a LocalCluster started here; default 80 %
        of the available memory divided among the workers.
    """
    if client is not None and not isinstance(client, str):
        yield client
        return
    if client == SYNCHRONOUS or (client is None and tasks <= 1):
        yield None
        return
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise RuntimeError("tiled reconstruction on Dask needs dask.distributed: pip install 'o3drbf[tiles]' (or pass client='synchronous')") from None
    if client is None:
        workers = check_number("workers", workers, low=1, high=1024, integer=True)
        if memory_limit is None:
            from o3drbf.solvers.base import available_memory

            memory_limit = int(0.8 * available_memory() / workers)
        # the workers' own Dask log lines (memory pauses, restarts) print straight to stderr: only errors, all with -v
        quiet = logging.WARNING if log.isEnabledFor(logging.INFO) else logging.ERROR
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, memory_limit=memory_limit, dashboard_address=":0",
                               silence_logs=quiet)
        c = Client(cluster)
        log.info("Dask LocalCluster: %d workers x 1 thread, %s per worker; dashboard %s", workers, _size(memory_limit), c.dashboard_link)
        try:
            yield c
        finally:
            c.close()
            cluster.close()
        return
    c = Client(client)
    log.info("Dask scheduler %s; dashboard %s", client, c.dashboard_link)
    try:
        yield c
    finally:
        c.close()


def peak_rss() -> int:
    """Peak resident memory of this process, bytes: VmHWM of its own memory map on Linux
    (``ru_maxrss`` there also counts a parent's memory at fork, kept across exec), else ``ru_maxrss``."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    import resource

    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def measured_call(func, i: int, **kwargs):
    """``func(i, **kwargs)`` and a record of where and how it ran (a task wrapper).

    Returns
    -------
    result
        What ``func`` returned.
    record : dict
        ``task``, ``worker`` (the Dask worker's address, else ``"pid N"``),
        ``seconds``, ``cpu`` (CPU seconds of the worker process, user + system, during the task), ``peak_rss`` (the worker process's peak resident memory so
        far, bytes, :func:`peak_rss`) and ``rss`` (resident memory after the task), measured in
        the process that ran the task.
    """
    import os

    import psutil

    t0, c0 = time.perf_counter(), time.process_time()
    out = func(i, **kwargs)
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    try:
        from distributed import get_worker

        worker = get_worker().address
    except (ImportError, ValueError):
        worker = f"pid {os.getpid()}"
    rec = {"task": int(i), "worker": worker, "seconds": seconds, "cpu": cpu,
           "peak_rss": peak_rss(),
           "rss": int(psutil.Process().memory_info().rss)}
    return out, rec


def worker_summary(records: list) -> dict:
    """Per worker: ``tasks``, ``seconds`` (summed task time) and ``peak_rss`` (bytes, the largest seen), from :func:`measured_call` records."""
    out: dict = {}
    for r in records:
        w = out.setdefault(r["worker"], {"tasks": 0, "seconds": 0.0, "peak_rss": 0})
        w["tasks"] += 1
        w["seconds"] += float(r["seconds"])
        w["peak_rss"] = max(w["peak_rss"], int(r["peak_rss"]), int(r["rss"]))
    return dict(sorted(out.items()))


def run_tasks(client, func, count: int, shared: dict, progress: bool = False, desc: str = "tiles",
              per_task: list | None = None, records: list | None = None) -> list:
    """``[func(i, **shared, **per_task[i]) for i in range(count)]``, on ``client`` or in-process.

    ``shared`` (arrays every task needs) is scattered once to every worker;
    ``per_task[i]`` (e.g. tile i's own points, or the path of its file) goes
    to task i only.  One future per task; results come back in task order
    whatever order they finish in.  Every task runs through
    :func:`measured_call`: its record is appended to ``records`` when given.
    Logs each task's completion and shows one bar tick per task.
    """
    bar = progress_bar(progress, total=count, desc=desc, unit="tile")
    t0 = time.perf_counter()
    results = [None] * count
    own = [{} for _ in range(count)] if per_task is None else per_task
    if len(own) != count:
        raise ValueError(f"run_tasks: {len(own)} per-task argument sets for {count} tasks (a bug)")
    done = [None] * count
    try:
        if client is None:
            for i in range(count):
                results[i], done[i] = measured_call(func, i, **shared, **own[i])
                _done(bar, desc, i, count, t0)
        else:
            from distributed import as_completed

            # hash=False: a fresh key per call (a re-scattered equal object could hit a key being released).
            # Each value in a list: scattering a dict itself (the lattice, the settings) makes one future per
            # item keyed by the item's *name* ("origin", "seed", ...), the same names in every pass, so one
            # pass releasing its keys loses the next pass's data ("lost dependencies").
            remote = {k: client.scatter([v], broadcast=True, hash=False)[0] for k, v in shared.items()}
            futures = []
            run = uuid.uuid4().hex  # not id(): a later call's dict can reuse a freed one's id, and so its keys
            for i in range(count):
                mine = {k: (v if isinstance(v, (str, int, float, type(None))) else client.scatter([v], hash=False)[0])
                        for k, v in own[i].items()}
                futures.append(client.submit(measured_call, func, i, pure=False, key=f"{desc}-{i}-{run}", **remote, **mine))
            index = {f.key: i for i, f in enumerate(futures)}
            for fut in as_completed(futures):
                i = index[fut.key]
                results[i], done[i] = fut.result()
                _done(bar, desc, i, count, t0)
        if records is not None:
            records.extend(done)
        return results
    finally:
        if bar is not None:
            bar.close()


def _done(bar, desc, i, count, t0):
    log.debug("%s: task %d of %d done at %.1f s", desc, i + 1, count, time.perf_counter() - t0)
    if bar is not None:
        bar.update(1)


def _size(limit) -> str:
    return f"{limit / 2**30:.1f} GiB" if isinstance(limit, (int, float)) else str(limit)
