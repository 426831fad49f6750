"""shellfem.forked: a function run beside this process in a forked child on one thread."""
import os

import numpy as np
import pytest

from shellfem import forked
from shellfem.errors import SelfshapeError

pytestmark = pytest.mark.skipif(not forked.available(), reason="needs fork and two cores")


def _threads():
    import numba
    from threadpoolctl import threadpool_info
    return numba.get_num_threads(), {d["internal_api"]: d["num_threads"] for d in threadpool_info()}


def test_the_child_returns_its_value_and_runs_on_one_thread_while_the_parent_does_too():
    big = np.arange(10.0)                               # the child sees this process's memory (no pickling)
    job = forked.start(lambda k: (float(big.sum()) * k, os.getpid(), _threads()), 2.0)
    n_numba, pools = _threads()
    assert n_numba == 1 and all(v == 1 for v in pools.values())
    value, pid, (child_numba, child_pools) = job.result()
    assert value == 90.0 and pid != os.getpid()
    assert child_numba == 1 and all(v == 1 for v in child_pools.values())
    assert forked._LIMITS is None and forked._LIVE == 0            # the parent's cores are back


def test_the_parent_stays_on_one_thread_until_its_last_job_has_ended():
    import numba
    wide = numba.get_num_threads()
    a, b = forked.start(lambda: 1), forked.start(lambda: forked.set_threads(None) or _threads())
    assert a.result() == 1
    assert _threads()[0] == 1 and forked._LIVE == 1                # b still runs: still one thread
    child_numba, child_pools = b.result()                           # a child asking for more stays on one
    assert child_numba == 1 and all(v == 1 for v in child_pools.values())
    assert numba.get_num_threads() == wide and forked._LIMITS is None and forked._LIVE == 0
    c = forked.start(lambda: 2)
    assert c.result() == 2 and c.result() == 2 and forked._LIVE == 0   # a result read twice ends the job once


def test_errors_in_the_child_are_raised_in_the_parent():
    def user_error():
        raise SelfshapeError("target.obj: a one-line error")
    with pytest.raises(SelfshapeError, match="^target.obj: a one-line error$"):
        forked.start(user_error).result()

    def bug():
        return 1 / 0
    with pytest.raises(RuntimeError, match="ZeroDivisionError"):
        forked.start(bug, label="the bug").result()

    def dies():
        os._exit(3)
    with pytest.raises(SelfshapeError, match="worker process died .exit code 3"):
        forked.start(dies, label="dies").result()
    assert forked._LIVE == 0 and forked._LIMITS is None


def test_a_cancelled_child_is_gone():
    import time
    job = forked.start(time.sleep, 60)
    job.cancel()
    assert not job.process.is_alive() and forked._LIVE == 0 and forked._LIMITS is None
    with pytest.raises(SelfshapeError, match="cancelled"):
        job.result()
