"""A node process whose rclpy teardown hangs still ends (htlm_msgs_py.ros.run_node): its work done, a destroy_node
that never returns is cut after TEARDOWN_SECONDS, every thread's stack goes to the log and the exit code is 1 (not a
process spinning forever; seen once in about 100 team runs on this machine, inside rclpy and Fast DDS, and once in
the interpreter's exit, in the cyclic garbage collector). The watchdog stays armed through that exit, and no cyclic
collection runs once the work is done."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.timeout(60)]

HEAD = textwrap.dedent(
    """
    import atexit, gc, sys, time, types
    import htlm_msgs_py.ros as R
    from rclpy.node import Node

    R.TEARDOWN_SECONDS = 1.0

    def hang(where):
        print(f"hanging in {where}", flush=True)
        while True:
            time.sleep(0.1)

    class Node_(Node):
        settings = types.SimpleNamespace(executor="single")
        stop_signal = None
    """
)

SCRIPT = HEAD + textwrap.dedent(
    """
    class Stuck(Node_):
        def destroy_node(self):
            hang("destroy_node")

    sys.exit(R.run_node("stuck", lambda: Stuck("htlm_stuck_teardown"), lambda node, ex: 0, lambda node: None, []))
    """
)

AT_EXIT = HEAD + textwrap.dedent(
    """
    code = R.run_node("stuck", lambda: Node_("htlm_stuck_exit"), lambda node, ex: 0, lambda node: None, [])
    print(f"returned {code}, collector enabled {gc.isenabled()}, frozen {gc.get_freeze_count()}", flush=True)
    atexit.register(hang, "the interpreter's exit")
    sys.exit(code)
    """
)


def test_a_teardown_that_hangs_ends_the_process_with_the_stacks_and_code_1() -> None:
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=45)
    took = time.monotonic() - t0
    assert "hanging in destroy_node" in p.stdout, (p.stdout, p.stderr)
    assert p.returncode == 1, (p.returncode, p.stderr[-2000:])
    assert "Timeout" in p.stderr and "destroy_node" in p.stderr, p.stderr[-2000:]  # faulthandler's stack dump
    print(f"the stuck teardown ended the process with code 1 after {took:.1f} s")


def test_a_hang_in_the_interpreters_exit_after_run_node_returned_ends_the_process_too() -> None:
    p = subprocess.run([sys.executable, "-c", AT_EXIT], capture_output=True, text=True, timeout=45)
    assert "returned 0, collector enabled False" in p.stdout, (p.stdout, p.stderr)
    frozen = int(p.stdout.split("frozen ")[1].split()[0])
    assert frozen > 1000, p.stdout  # everything alive when the work was done: rclpy, numpy, the node
    assert "hanging in the interpreter's exit" in p.stdout, (p.stdout, p.stderr)
    assert p.returncode == 1, (p.returncode, p.stderr[-2000:])
    assert "Timeout" in p.stderr and "hang" in p.stderr, p.stderr[-2000:]
