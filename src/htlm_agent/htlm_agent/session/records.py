"""The records an agent publishes, encoded and signed, without ROS (`RecordWriter`)."""

from __future__ import annotations

from htlm_agent.mind.agent import Transition
from htlm_msgs_py import schema as S
from htlm_msgs_py.schema import encode
from htlm_msgs_py.signing import Signer
from htlm_world.types import IntArray


class RecordWriter:
    """Encodes agent `index`'s records of the wire contract (htlm_msgs_py.schema), each signed with `signer`."""

    def __init__(self, signer: Signer, session: str, index: int = -1) -> None:
        """The writer of agent `index` (set when a run is joined), of the process whose session id is `session`."""
        self.signer = signer
        self.session = session
        self.index = index

    def broadcast(self, episode: int, t: int, actions: IntArray, levels: IntArray, wall: float) -> str:
        """Our broadcast of step t: our actions and the levels we observed (after the channel), sent at `wall`."""
        fields = {
            "agent": self.index,
            "episode": episode,
            "step": t,
            "actions": actions.tolist(),
            "levels": levels.tolist(),
            "sent": round(max(0.0, wall), 6),
        }
        return encode(S.BROADCAST, fields, self.signer)

    def action(self, episode: int, t: int, actions: IntArray, before: list[int]) -> str:
        """Our actions of step t, with what we did `before` (a deployed team: the steps before t)."""
        fields = {"agent": self.index, "episode": episode, "step": t, "actions": actions.tolist(), "before": before}
        return encode(S.ACTION, fields, self.signer)

    def ready(self, episode: int, t: int) -> str:
        """Our ready after the last step t of a batch."""
        return encode(S.READY, {"agent": self.index, "episode": episode, "step": t}, self.signer)

    def transition(self, tr: Transition, seq: int) -> str:
        """Our transition `tr`, number `seq` of this session, for the trainer."""
        fields = {
            "agent": self.index,
            "session": self.session,
            "seq": seq,
            "episode": tr.episode,
            "step": tr.step,
            "k": tr.k,
            "a": tr.a,
            "r": tr.r,
            "k2": tr.k2,
            "mask2": tr.mask2,
            "done": tr.done,
        }
        return encode(S.TRANSITION, fields, self.signer)

    def belief(
        self, episode: int, t: int, marginals: list[float], confident: list[int], arrived: str, distance: float
    ) -> str:
        """Our belief summary after step t of `episode`, with the robot's arrival at its site."""
        fields = {
            "agent": self.index,
            "episode": episode,
            "step": t,
            "marginals": marginals,
            "confident": confident,
            "arrived": arrived,
            "distance": distance,
        }
        return encode(S.BELIEF, fields, self.signer)
