"""Independent tasks on Dask distributed: a local cluster, or the lab's cluster by its address.

Parameter sweeps (validation.sweep) and the curvature-law patches (validation.law_tables) are
many independent simulations. :func:`map_tasks` runs ``fn(item)`` for each item as one Dask
task and returns the results in the items' order:

- ``scheduler=None``: a ``distributed.LocalCluster`` on this machine with ``workers`` worker
  processes (default: one per core the process may use) of one thread each, so that the
  simulations run side by side without competing for cores;
- ``scheduler="tcp://host:8786"``: a running ``dask scheduler`` with workers started on the
  lab's machines (``dask worker tcp://host:8786 --nthreads 1``). Those workers must import
  this package (same version, e.g. PYTHONPATH) and see the paths the tasks write (a shared
  file system);
- ``workers=0`` (without a scheduler): in this process, one item after another, no Dask.

A worker that dies (killed, out of memory, its machine lost) loses nothing: the scheduler
gives its unfinished tasks to another worker (Dask's ``allowed-failures``), and a task
that raised is retried ``retries`` times. Each task runs with one numba and one BLAS thread
(:func:`one_thread`): the cluster's parallelism is its processes.

This sits in the lowest layer (beside shellfem.outfiles) so that every layer above may
distribute its work; Dask itself is imported only when a cluster is asked for.
"""
from __future__ import annotations

import contextlib
import logging
import os

from shellfem.errors import SelfshapeError

#: How long a connection to a scheduler may take before it is an error, s.
CONNECT_TIMEOUT_S = 20


def default_workers() -> int:
    """One worker per core this process may run on (the local cluster's default)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _distributed():
    try:
        import distributed
    except ImportError:
        raise SelfshapeError("a cluster needs Dask: pip install 'dask[distributed]' (or run serially with "
                             "--workers 0)") from None
    return distributed


def check_options(scheduler=None, workers=None) -> None:
    """One-line SelfshapeError for a bad ``scheduler`` address or ``workers`` count, before any work."""
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 0):
        raise SelfshapeError(f"--workers must be an integer >= 0, got {workers!r}")
    if scheduler is not None:
        if not isinstance(scheduler, str) or not scheduler.strip() or any(c.isspace() for c in scheduler):
            raise SelfshapeError(f"--scheduler must be an address such as tcp://host:8786, got {scheduler!r}")
        if workers is not None:
            raise SelfshapeError("--workers is for the local cluster; a --scheduler's workers are started with it")


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None):
    """A ``distributed.Client``: connected to ``scheduler``, or to a new LocalCluster of
    ``workers`` single-threaded processes on 127.0.0.1 (no dashboard); closed (and the local
    cluster shut down) on exit. A scheduler that cannot be reached is a one-line SelfshapeError."""
    check_options(scheduler, workers)
    distributed = _distributed()
    if scheduler:
        try:
            client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError, ValueError) as e:
            raise SelfshapeError(f"--scheduler {scheduler}: cannot connect ({type(e).__name__}: "
                                 f"{' '.join(str(e).split())[:160]})") from None
        try:
            yield client
        finally:
            client.close()
        return
    n = workers or default_workers()
    cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                                       dashboard_address=None, silence_logs=logging.ERROR)
    try:
        client = distributed.Client(cluster)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


def one_thread(fn, item):
    """``fn(item)`` with numba and BLAS limited to one thread (each worker process is one core)."""
    try:
        import numba
        numba.set_num_threads(1)
    except (ImportError, ValueError):
        pass
    from threadpoolctl import threadpool_limits
    with threadpool_limits(1):
        return fn(item)


def map_tasks(fn, items, *, scheduler: str | None = None, workers: int | None = None, retries: int = 2,
              keys=None, on_result=None, on_error=None, client=None) -> list:
    """``[fn(item) for item in items]``, each call a Dask task (see the module doc); results in
    the items' order. ``fn`` must be a module-level function (workers import it by name).

    ``keys``: one Dask key per item (unique; default: generated). ``on_result(i, result)`` is
    called in this process as each task finishes (for progress and incremental writing).
    ``on_error(i, exception)``: a task that failed for good (its retries used, or its workers
    killed ``allowed-failures`` times: ``KilledWorker``) returns what it returns instead of
    raising. ``workers=0`` without a scheduler: serial in this process, no Dask. ``client``: an
    open :func:`dask_client` to use (several maps on one cluster) instead of a new one."""
    items = list(items)
    check_options(scheduler, workers)
    if client is None and not scheduler and workers == 0:
        out = []
        for i, item in enumerate(items):
            try:
                r = fn(item)
            except Exception as e:
                if on_error is None:
                    raise
                r = on_error(i, e)
            out.append(r)
            if on_result is not None:
                on_result(i, r)
        return out
    results = [None] * len(items)
    if not items:
        return results
    distributed = _distributed()
    with (contextlib.nullcontext(client) if client is not None else dask_client(scheduler, workers)) as client:
        futures = []
        for i, item in enumerate(items):
            kw = {"key": keys[i]} if keys is not None else {}
            futures.append(client.submit(one_thread, fn, item, retries=retries, pure=False, **kw))
        index = {f.key: i for i, f in enumerate(futures)}
        pending = distributed.as_completed(futures)
        del futures                 # as_completed holds them; each is dropped once its result is here
        for fut in pending:
            i = index[fut.key]
            try:
                r = fut.result()
            except Exception as e:
                if on_error is None:
                    raise
                r = on_error(i, e)
            results[i] = r
            fut.release()           # the result is here: a worker lost later need not recompute it
            if on_result is not None:
                on_result(i, r)
    return results
