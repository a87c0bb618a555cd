"""A node process whose rclpy teardown hangs still ends, with the exit code of its work
(htlm_msgs_py.ros.lifecycle.run_node): a destroy_node that never returns, with the GIL held as Fast DDS's spinning
participant destruction holds it, is cut after TEARDOWN_SECONDS; every thread's stack goes to the log and the process
exits with the code `run` returned (htlm_msgs_py.ros.exit_timer). The watchdog stays armed through the interpreter's
exit, and no cyclic collection runs once the work is done. Where the exit timer is missing, faulthandler ends the
process with code 1."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time

import pytest

from htlm_msgs_py.ros import exit_timer

pytestmark = [pytest.mark.ros, pytest.mark.timeout(60)]

HEAD = textwrap.dedent(
    """
    import atexit, ctypes, gc, sys, types
    import htlm_msgs_py.ros.lifecycle as R
    from rclpy.node import Node

    R.TEARDOWN_SECONDS = 1.0

    def hang(where):
        print(f"hanging in {where}", flush=True)
        ctypes.PyDLL(None).pause()  # in C with the GIL held, as Fast DDS's spin holds it: no Python thread runs

    class Node_(Node):
        settings = types.SimpleNamespace(executor="single")
        stop_signal = None
    """
)

STUCK = HEAD + textwrap.dedent(
    """
    class Stuck(Node_):
        def destroy_node(self):
            hang("destroy_node")

    sys.exit(R.run_node("stuck", lambda: Stuck("htlm_stuck_teardown"), lambda node, ex: 3, lambda node: None, []))
    """
)

NO_TIMER = "import htlm_msgs_py.ros.exit_timer as T\nT.exit_after = lambda seconds, code: False\n" + STUCK

AT_EXIT = HEAD + textwrap.dedent(
    """
    code = R.run_node("stuck", lambda: Node_("htlm_stuck_exit"), lambda node, ex: 5, lambda node: None, [])
    print(f"returned {code}, collector enabled {gc.isenabled()}, frozen {gc.get_freeze_count()}", flush=True)
    atexit.register(hang, "the interpreter's exit")
    sys.exit(code)
    """
)


def _run(script: str) -> subprocess.CompletedProcess[str]:
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=45)
    print(f"exit code {p.returncode} after {time.monotonic() - t0:.1f} s")
    return p


@pytest.mark.skipif(not exit_timer.supported(), reason="exit_timer needs 64-bit little-endian Linux")
def test_a_teardown_that_hangs_holding_the_gil_ends_the_process_with_the_runs_code_and_the_stacks() -> None:
    p = _run(STUCK)
    assert "hanging in destroy_node" in p.stdout, (p.stdout, p.stderr)
    assert p.returncode == 3, (p.returncode, p.stderr[-2000:])  # what `run` returned, not a failure of its own
    assert "Timeout" in p.stderr and "destroy_node" in p.stderr, p.stderr[-2000:]  # faulthandler's stack dump


def test_without_the_exit_timer_faulthandler_ends_the_hung_teardown_with_code_1() -> None:
    p = _run(NO_TIMER)
    assert "hanging in destroy_node" in p.stdout, (p.stdout, p.stderr)
    assert p.returncode == 1, (p.returncode, p.stderr[-2000:])
    assert "Timeout" in p.stderr and "destroy_node" in p.stderr, p.stderr[-2000:]


@pytest.mark.skipif(not exit_timer.supported(), reason="exit_timer needs 64-bit little-endian Linux")
def test_a_hang_in_the_interpreters_exit_after_run_node_returned_ends_the_process_too() -> None:
    p = _run(AT_EXIT)
    assert "returned 5, collector enabled False" in p.stdout, (p.stdout, p.stderr)
    frozen = int(p.stdout.split("frozen ")[1].split()[0])
    assert frozen > 1000, p.stdout  # everything alive when the work was done: rclpy, numpy, the node
    assert "hanging in the interpreter's exit" in p.stdout, (p.stdout, p.stderr)
    assert p.returncode == 5, (p.returncode, p.stderr[-2000:])
    assert "Timeout" in p.stderr and "hang" in p.stderr, p.stderr[-2000:]
