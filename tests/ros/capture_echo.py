"""Capture what `ros2 topic echo` prints on every record topic of a short training run (the default scenario in
batches of 4), as the Markdown of docs/ros.md's section "What `ros2 topic echo` prints". Run by name:

    .venv/bin/python tests/ros/capture_echo.py > /tmp/echo.md

A listener node subscribes to every String topic of the topic table (agent1's for the per-agent ones) and keeps the
first record of each (of the step topic, the first of each phase; of observations, the first of a step), while the
launcher's processes run; records are shown as `ros2 topic echo` shows them, cut at 128 characters."""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

from htlm_agent.ros.launch import LaunchConfig, start, stop
from htlm_msgs_py import topics
from htlm_world.scenario import builtin

CUT = 128
"""`ros2 topic echo` shows the first 128 characters of a string unless given --full-length."""


def main() -> None:
    domain = 200 + os.getpid() % 30
    run = Path(tempfile.mkdtemp(prefix="htlm-capture-"))
    cfg = LaunchConfig(
        mode="train",
        scenario=builtin(),
        episodes=8,
        batch=4,
        run_dir=run / "capture-run",  # the run id: this name and a random part
        domain_id=domain,
        echo=False,
        learner={"envs": 4},
    )
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    import rclpy
    from rclpy.node import Node

    from htlm_msgs_py.ros import EVENTS, STATE_READER, String

    rclpy.init()
    node = Node("htlm_capture")
    got: dict[str, str] = {}
    names = {
        "/htlm/scenario": STATE_READER,
        "/htlm/step": EVENTS,
        "/htlm/action": EVENTS,
        topics.observation("agent1"): EVENTS,
        "/htlm/broadcast": EVENTS,
        "/htlm/ready": EVENTS,
        "/htlm/transitions": EVENTS,
        "/htlm/transition_ack": EVENTS,
        topics.weights("agent1"): STATE_READER,
        "/htlm/trainer/progress": EVENTS,
        topics.belief("agent1"): STATE_READER,
        "/htlm/ground_truth": EVENTS,
        "/htlm/episode_metrics": EVENTS,
    }

    def keep(topic: str, text: str) -> None:
        key = topic
        if topic == "/htlm/step":
            key = f"{topic} (phase {json.loads(text)['phase']})"
        elif topic == topics.observation("agent1") and '"step":0,' in text:
            return
        got.setdefault(key, text)

    for t, q in names.items():
        node.create_subscription(String, t, lambda m, t=t: keep(t, m.data), q)
    procs = start(cfg)
    try:
        end = time.monotonic() + 240
        while time.monotonic() < end and procs[0].popen.poll() is None:
            rclpy.spin_once(node, timeout_sec=0.05)
        for _ in range(40):
            rclpy.spin_once(node, timeout_sec=0.05)
    finally:
        stop(procs)
        node.destroy_node()
        rclpy.try_shutdown()
    order = [
        n if n != "/htlm/step" else f"{n} (phase {p})"
        for n in names
        for p in (("begin", "step") if n == "/htlm/step" else ("",))
    ]
    for key in order:
        if key not in got:
            print(f"<!-- nothing captured on {key} -->")
            continue
        text = got[key]
        topic, _, what = key.partition(" ")
        cut = f"{len(text)} characters, cut" if len(text) > CUT else ""
        label = ", ".join(x for x in (what.strip("()"), cut) if x)
        shown = text if len(text) <= CUT else text[:CUT] + "..."
        print(f"`ros2 topic echo {topic}`" + (f" ({label})" if label else "") + ":\n")
        print("```yaml\ndata: '" + shown.replace("'", "''") + "'\n---\n```\n")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
