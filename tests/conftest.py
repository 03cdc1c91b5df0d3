import os
import sys
from pathlib import Path

import torch

# Tests run on two cores, in as many pytest-xdist workers as `make test` starts: keep torch from oversubscribing.
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
torch.set_num_threads(max(1, min(2, (os.cpu_count() or 1) // _WORKERS)))
sys.path.insert(0, str(Path(__file__).parent))

# A test that hangs must fail and say where, not stall CI until its time limit: after TEST_TIME_LIMIT_S every
# thread's stack is printed and the worker process ends (pytest-xdist reports the test as crashed and goes on).
# The slowest test takes about two minutes on two cores.
TEST_TIME_LIMIT_S = float(os.environ.get("SPLATREPLACE_TEST_TIME_LIMIT_S", "900"))

import faulthandler  # noqa: E402
import threading  # noqa: E402

import pytest  # noqa: E402


def _give_up(item) -> None:
    capture = item.config.pluginmanager.getplugin("capturemanager")
    if capture is not None:
        capture.suspend_global_capture(in_=False)  # the stacks go to the real stderr, not to the test's capture
    print(f"\n{item.nodeid} ran past {TEST_TIME_LIMIT_S:.0f} s; every thread's stack:", file=sys.stderr, flush=True)
    faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
    sys.stderr.flush()
    os._exit(1)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    # the whole protocol: a module fixture's setup (a trained scene) counts with the test that needs it first
    watchdog = threading.Timer(TEST_TIME_LIMIT_S, _give_up, args=(item,))
    watchdog.daemon = True
    watchdog.start()
    try:
        yield
    finally:
        watchdog.cancel()
