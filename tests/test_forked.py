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
    forked.set_threads(None)
    assert value == 90.0 and pid != os.getpid()
    assert child_numba == 1 and all(v == 1 for v in child_pools.values())
    assert forked._LIMITS is None


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
    forked.set_threads(None)


def test_a_cancelled_child_is_gone():
    import time
    job = forked.start(time.sleep, 60)
    job.cancel()
    forked.set_threads(None)
    assert not job.process.is_alive()
    with pytest.raises(SelfshapeError, match="cancelled"):
        job.result()
