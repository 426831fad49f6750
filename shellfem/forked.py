"""One function run beside this process, in a forked child on one core: two long independent
solves on a two-core machine (e.g. a refinement from two starting states) side by side.

Why a fork and not a pool: the work's inputs (meshes, models, factorisations) are already in
this process's memory and need not be pickled; only the result travels back. Why one thread
each: the solves' numba kernels and MKL PARDISO use both cores, but only about 1.6 of them on
average (the rest of a Newton iteration is serial); two of them side by side on one thread each
took 185 s where one after the other on two threads took 232 s (a 50k-unknown sheet, 210 Newton
iterations each). A simulation's result does not depend on the thread count (MKL's conditional
numerical reproducibility, fixed numba chunks: the same bits on one thread as on two); OpenBLAS
reductions do depend on it, so code run this way holds OpenBLAS to one thread
(shellfem.linalg.one_openblas_thread), and a caller keeps a fixed thread schedule all the same.

    job = start(fn, *args)        # the child runs fn(*args) on one thread; this process too
    ...                           # this process's own work; job.done() polls
    value = job.result()          # the child's return value, or its SelfshapeError raised here

The child stays on one thread to its end: raising its thread count after the fork hung it inside
MKL PARDISO (Intel OpenMP's pool is the parent's; a forked child must not grow it). This process
stays on one thread while any job it started is live, and takes all its cores back when the
last one ends (its result is in, or it was cancelled): the thread schedule lives here, not in
the callers.
"""
from __future__ import annotations

import os
import traceback

from shellfem.errors import SelfshapeError

_LIMITS = None         # threadpoolctl limits in force in this process (to restore)
_LIVE = 0              # jobs started by this process and not yet ended (result in, or cancelled)
_IN_CHILD = False      # this process is a forked child: it stays on one thread


def available() -> bool:
    """A fork is possible (POSIX, not in a daemonic worker process, which may have no children)
    and this machine has two or more cores for this process."""
    import multiprocessing as mp

    if not hasattr(os, "fork") or mp.current_process().daemon:
        return False
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    return cores >= 2


def wanted(parallel: bool | None = None) -> bool:
    """``parallel`` as asked; None: :func:`available`."""
    return available() if parallel is None else bool(parallel)


def set_threads(n: int | None) -> None:
    """Limit numba and BLAS/MKL (PARDISO) in this process to ``n`` threads; None: undo the limit.
    A forked child stays on one thread whatever is asked (see the module doc)."""
    global _LIMITS
    if _IN_CHILD:
        n = 1
    try:
        import numba
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS if n is None else max(1, min(n, numba.config.NUMBA_NUM_THREADS)))
    except (ImportError, ValueError):
        pass
    from threadpoolctl import threadpool_limits
    if _LIMITS is not None:
        _LIMITS.restore_original_limits()
        _LIMITS = None
    if n is not None:
        _LIMITS = threadpool_limits(n)


class Job:
    """A child process running one function (see :func:`start`)."""

    def __init__(self, process, conn, label):
        self.process, self.conn, self.label = process, conn, label
        self._value = None
        self._have = False
        self._ended = False

    def _end(self):
        """This job no longer runs: the parent takes its cores back when no other job does."""
        global _LIVE
        if not self._ended:
            self._ended = True
            _LIVE -= 1
            if _LIVE == 0 and not _IN_CHILD:
                set_threads(None)

    def done(self) -> bool:
        """The child has finished (its result is waiting)."""
        return self._have or self.conn.poll()

    def result(self):
        """Wait for the child and return fn's value;
        the child's SelfshapeError is raised here as it was; any other exception there is a
        RuntimeError carrying its traceback; a child that died (killed, out of memory) is a
        SelfshapeError naming its exit code."""
        if not self._have:
            try:
                self._value = self.conn.recv()
            except EOFError:
                self.process.join()
                self._value = ("died", self.process.exitcode)
            self._have = True
            self.conn.close()
            self.process.join()
            self._end()
        kind, payload = self._value
        if kind == "ok":
            return payload
        if kind == "selfshape":
            raise SelfshapeError(payload)
        if kind == "died":
            raise SelfshapeError(f"{self.label}: the worker process died (exit code {payload}; out of memory?)")
        raise RuntimeError(f"{self.label}: the worker process raised\n{payload}")

    def cancel(self) -> None:
        """Stop the child (nothing is returned)."""
        if self.process.is_alive():
            self.process.kill()
        self.process.join()
        self.conn.close()
        if not self._have:
            self._have, self._value = True, ("selfshape", f"{self.label}: cancelled")
        self._end()


def _child(conn, fn, args):
    global _IN_CHILD, _LIVE
    _IN_CHILD, _LIVE = True, 0
    set_threads(1)
    try:
        msg = ("ok", fn(*args))
    except SelfshapeError as e:
        msg = ("selfshape", str(e))
    except BaseException:                   # noqa: BLE001 - reported to the parent, which raises it
        msg = ("error", traceback.format_exc())
    try:
        conn.send(msg)
    except Exception:                       # noqa: BLE001 - an unpicklable value: say so
        conn.send(("error", traceback.format_exc()))
    conn.close()


def start(fn, *args, label: str = "worker") -> Job:
    """Run ``fn(*args)`` in a forked child on one thread, and limit this process to one thread
    until every job it started has ended (:meth:`Job.result` returned or raised, or
    :meth:`Job.cancel`). ``fn`` may be any callable (a closure too: nothing is pickled but its
    return value, which must pickle)."""
    global _LIVE
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_run_and_exit, args=(send, fn, args), daemon=True)
    proc.start()
    send.close()
    _LIVE += 1
    set_threads(1)
    return Job(proc, recv, label)


def _run_and_exit(conn, fn, args):
    # os._exit: the parent's atexit handlers and open resources are not the child's to run
    try:
        _child(conn, fn, args)
    finally:
        os._exit(0)
