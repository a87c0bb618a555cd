"""`htlm show RUN_DIR --episode E`: one episode of a run as a picture (htlm_agent.experiments.episode_plot).

RUN_DIR is what `htlm launch`, `htlm evaluate` or `htlm train` printed (or an episode log, world.jsonl, itself); the
episode comes from the run's evaluation when it has one (RUN/evaluate/ of `htlm launch train`, RUN/eval/ of `htlm
train`), else from RUN/world.jsonl. A recording (RUN/recording of `htlm launch --record`, a ROS 2 bag) is read as
the world's log: the episode is rebuilt from its messages. The PNG's path is printed on stdout, the log it was read
from on stderr.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of `htlm show`."""
    p.add_argument(
        "run_dir",
        metavar="RUN_DIR",
        help="run directory of htlm launch / evaluate / train, a world.jsonl file, or a recording (RUN/recording)",
    )
    p.add_argument("--episode", type=int, default=0, metavar="E", help="episode index (default: 0)")
    p.add_argument(
        "--out", default=None, metavar="FILE.png", help="picture to write (default: episode-E.png beside the log)"
    )
    p.add_argument(
        "--all-steps", action="store_true", help="show every step, not only up to three steps after completion"
    )


def run(args: argparse.Namespace) -> int:
    """Read the episode, draw it, print the picture's path."""
    from htlm_agent.experiments.episode_plot import EpisodeLogError, read_episode, save_episode_figure

    if args.episode < 0:
        print(f"htlm show: --episode {args.episode!r}: must be >= 0", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else None
    if out is not None and out.suffix.lower() != ".png":
        print(f"htlm show: --out {args.out!r}: the picture is a PNG file (name it *.png)", file=sys.stderr)
        return 2
    try:
        ep = read_episode(args.run_dir, args.episode)
    except EpisodeLogError as e:
        print(f"htlm show: {e}", file=sys.stderr)
        return 2
    print(
        f"htlm show: episode {ep.episode} of {ep.source} (line {ep.line}); scenario: {ep.scenario_source}",
        file=sys.stderr,
    )
    path = out if out is not None else ep.source.parent / f"episode-{ep.episode}.png"
    try:
        save_episode_figure(ep, path, all_steps=args.all_steps)
    except OSError as e:
        print(f"htlm show: --out {str(path)!r}: {e}", file=sys.stderr)
        return 2
    print(path)
    return 0
