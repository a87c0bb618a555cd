"""`htlm watch`: a live terminal view of a running team (htlm_agent.ros.watch_node, htlm_agent.experiments.watch_view).

The options are the fields of `WatchSettings` (their docstrings are the help) plus where to find the team: the ROS
domain and discovery range default to the environment's ROS_DOMAIN_ID and ROS_AUTOMATIC_DISCOVERY_RANGE, else to
those `htlm launch` uses (42, localhost), so a plain `htlm watch` finds a team started by `htlm launch` or `make run`.
`--replay RUN` shows a recording (`htlm launch --record`) the same way, without ROS.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import math
import os
import sys

from htlm_agent.experiments.watch_view import WatchSettings
from htlm_msgs_py.params import field_docs, problems

DISCOVERY = {"localhost": "LOCALHOST", "subnet": "SUBNET", "off": "OFF", "system_default": "SYSTEM_DEFAULT"}
"""--discovery choices -> ROS_AUTOMATIC_DISCOVERY_RANGE (as `htlm launch`)."""

DEFAULT_DOMAIN = 42
"""`htlm launch`'s default ROS_DOMAIN_ID."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of `htlm watch`."""
    docs = field_docs(WatchSettings)
    for f in dataclasses.fields(WatchSettings):
        if f.name == "executor":
            continue
        flag = "--" + f.name.replace("_", "-")
        if f.type in (bool, "bool"):
            p.add_argument(flag, action="store_true", help=docs.get(f.name, ""))
        else:
            kind = {"int": int, "float": float}.get(str(f.type), str)
            p.add_argument(flag, type=kind, default=f.default, help=f"{docs.get(f.name, '')} (default {f.default})")
    p.add_argument(
        "--domain-id",
        type=int,
        default=None,
        help=f"ROS_DOMAIN_ID of the team (default: $ROS_DOMAIN_ID, else {DEFAULT_DOMAIN} as htlm launch)",
    )
    p.add_argument(
        "--discovery",
        choices=sorted(DISCOVERY),
        default=None,
        help="ROS_AUTOMATIC_DISCOVERY_RANGE (default: $ROS_AUTOMATIC_DISCOVERY_RANGE, else localhost as htlm launch)",
    )
    p.add_argument("--peers", default="", help="ROS_STATIC_PEERS: 'host1;host2' to find a team on other hosts")
    p.add_argument("--key-file", default="", help="the team key file, when the team signs its records")
    p.add_argument(
        "--replay",
        default="",
        metavar="RUN",
        help="watch a recording instead of a live team: a run directory of `htlm launch --record` or its bag "
        "(RUN/recording); no ROS needed",
    )
    p.add_argument(
        "--speed", type=float, default=1.0, help="--replay: times the recorded pace (0: as fast as it reads; default 1)"
    )


def _fail(text: str) -> int:
    print(f"htlm watch: {text}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    """Watch the team until --duration elapses or Ctrl-C (exit code 0; 2 for bad options)."""
    from htlm_msgs_py.signing import ENV_KEY, ENV_KEY_FILE, SigningError, signer_from_env

    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(WatchSettings) if hasattr(args, f.name)}
    settings = WatchSettings(**values)
    bad = problems(settings)
    if bad:
        return _fail("; ".join("--" + b.split(":", 1)[0].replace("_", "-") + ":" + b.split(":", 1)[1] for b in bad))
    if args.domain_id is not None:
        if not 0 <= args.domain_id <= 232:
            return _fail(f"--domain-id: {args.domain_id} is not in 0..232")
        os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)
    else:
        os.environ.setdefault("ROS_DOMAIN_ID", str(DEFAULT_DOMAIN))
    if args.discovery is not None:
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = DISCOVERY[args.discovery]
    else:
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", DISCOVERY["localhost"])
    if args.peers:
        os.environ["ROS_STATIC_PEERS"] = args.peers
    if args.key_file:
        os.environ[ENV_KEY_FILE] = args.key_file
        os.environ.pop(ENV_KEY, None)
    try:
        signer = signer_from_env()
    except SigningError as e:
        return _fail(str(e))
    if args.replay:
        from pathlib import Path

        from htlm_agent.experiments.recording import find_bag
        from htlm_agent.experiments.watch_view import replay

        if not (math.isfinite(args.speed) and args.speed >= 0.0):
            return _fail(f"--speed: {args.speed!r} must be a number >= 0")
        bag = find_bag(Path(args.replay))
        if bag is None:
            return _fail(
                f"--replay {args.replay}: no recording there (a bag directory with metadata.yaml, or RUN/recording)"
            )
        return replay(bag, settings, signer, sys.stdout, args.speed)
    # by name: the node is glue around untyped rclpy, outside the strictly typed core (pyproject's mypy excludes ros/)
    node = importlib.import_module("htlm_agent.ros.watch_node")
    code: int = node.main(settings, signer, sys.stdout)
    return code
