"""Which run a node follows, from the world's announcements on /htlm/scenario (docs/ros.md, Run control). Every
announcement carries the run id, the nonce of the world process that sent it (new at every start of the world) and a
sequence number that only grows over the whole run, also across restarts of the world (it is kept in the run
directory). A node joins the first run it hears (or only the run it was told to join) and from then on follows that
run alone: an announcement of another run is rejected while its own run goes on (a stop or a switch from anybody
else cannot touch it), and an announcement of its run that is not newer than the last one it took is a replay and is
rejected too, and so is one more than `SEQ_AHEAD` ahead of it. Only once its run has stopped may a node that stays
up join the next one. With a team key the announcements are signed, so nobody without the key can make a newer one;
without a key any participant of the ROS domain can (docs/ros.md, Run control).
"""

from __future__ import annotations

import re
import secrets
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

from .files import write_atomic

SEQ_AHEAD = 1000
"""How far ahead of the last announcement a node took the next may be: a world announces a few times per run (its
start, its epoch, a changed episode count, a restart, its stop), so a sequence number further ahead is not its
(`future`), and a forged one cannot make every later announcement of the run look like a replay."""


class Verdict(StrEnum):
    """What an announcement means for the node that judges it (`RunControl.take`); the values are the reasons
    its counters and warnings name."""

    JOIN = "join"
    """A run to join (the node's first, or the next after its run stopped)."""
    UPDATE = "update"
    """A newer announcement of the node's run (the same world)."""
    RESTART = "restart"
    """A newer announcement of the node's run from a restarted world (another nonce)."""
    STOP = "stop"
    """The node's run stopped."""
    OTHER_RUN = "other_run"
    """Rejected: another run while the node's goes on."""
    REPLAY = "replay"
    """Rejected: not newer than the last announcement taken."""
    FUTURE = "future"
    """Rejected: more than SEQ_AHEAD ahead of the last announcement taken."""


REFUSED = (Verdict.OTHER_RUN, Verdict.REPLAY, Verdict.FUTURE)
"""The verdicts of `RunControl.take` that reject an announcement."""


def unique_run_id(name: str) -> str:
    """A run id unique to one run: `name` (e.g. the run directory's, cut to the id's letters) and 12 random hex
    digits, so a signed record of an earlier run under the same name is never taken as this run's."""
    base = re.sub(r"[^A-Za-z0-9_.:-]", "_", name)[:51] or "run"
    return f"{base}-{secrets.token_hex(6)}"


def run_id_of(run_dir: Path) -> str:
    """The run id of the run in `run_dir`: the one kept in `run_dir/run_id`, or a new unique one (written there),
    so a launch into the same directory continues its run and a launch into a new one starts another, whatever
    its name."""
    f = run_dir / "run_id"
    try:
        kept = f.read_text().strip()
    except FileNotFoundError:
        kept = ""
    if re.fullmatch(r"[A-Za-z0-9_.:-]{1,64}", kept):
        return kept
    run = unique_run_id(run_dir.name)
    write_atomic(f, run + "\n", durable=True)
    return run


@dataclass
class RunControl:
    """A node's view of the run it follows."""

    wanted: str = ""
    """The run id the node was told to join (empty: the first it hears)."""
    run: str | None = None
    nonce: str | None = None
    seq: int = -1
    stopped: bool = False

    def take(self, rec: dict[str, Any]) -> Verdict:
        """Judge a decoded scenario record; returns what it means for the node (`Verdict`)."""
        run, nonce, seq = rec["run"], rec["nonce"], rec["seq"]
        if self.run is None or (run != self.run and self.stopped and not self.wanted):
            if self.wanted and run != self.wanted:
                return Verdict.OTHER_RUN
            self.run, self.nonce, self.seq, self.stopped = run, nonce, seq, rec["state"] == "stopped"
            return Verdict.JOIN
        if run != self.run:
            return Verdict.OTHER_RUN
        if seq <= self.seq:
            return Verdict.REPLAY
        if seq > self.seq + SEQ_AHEAD:
            return Verdict.FUTURE
        restarted = nonce != self.nonce
        self.nonce, self.seq = nonce, seq
        if rec["state"] == "stopped":
            if self.stopped:
                return Verdict.UPDATE
            self.stopped = True
            return Verdict.STOP
        if self.stopped:  # a restarted world goes on with the run
            self.stopped = False
            return Verdict.RESTART
        return Verdict.RESTART if restarted else Verdict.UPDATE

    def refused(self, rec: dict[str, Any]) -> str:
        """The detail of a rejected announcement `rec`, for the node's counters and its warning."""
        return f"run {rec['run']} announcement {rec['seq']} (we follow {self.run})"
