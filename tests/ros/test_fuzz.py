"""Bad input of a real deployment: 1000 malformed records on every topic a node of the team subscribes to (18
topics in train mode), while the team runs. No node crashes, no state changes (the trajectories still equal the
in-process runtime, the store holds exactly the team's transitions), every rejection is counted in /diagnostics,
and the episodes in progress finish.

The team runs in train mode with its learning switched off (the trainer stores but does not train, agents act
greedily, ε = 0), so that the run is deterministic: the agents' Q-networks are the learner's initial ones."""

from __future__ import annotations

import json
import random
import signal
from collections import defaultdict
from typing import Any

import pytest

from htlm_agent.transition_store import read_store
from htlm_msgs_py import schema as S
from htlm_msgs_py import topics

from .conftest import assert_same_as_in_process, read_json
from .ros_tools import subscribed_topics

pytestmark = [pytest.mark.ros, pytest.mark.timeout(150)]

COUNT = 1000
FIRST, LONG, SEED = 100, 1000, 6

# which node subscribes to what, and the counter name (topic tag) it files rejections under
SUBSCRIBERS: dict[str, list[tuple[str, str]]] = {
    topics.SCENARIO: [(f"agent{i}", "scenario") for i in range(1, 6)] + [("trainer", "scenario")],
    topics.STEP: [(f"agent{i}", "step") for i in range(1, 6)],
    topics.ACTION: [("world", "action")],
    topics.READY: [("world", "ready")],
    topics.BROADCAST: [(f"agent{i}", "broadcast") for i in range(1, 6)],
    topics.TRANSITIONS: [("trainer", "transitions")],
    topics.TRANSITION_ACK: [(f"agent{i}", "transition_ack") for i in range(1, 6)],
    topics.EPISODE_METRICS: [("trainer", "episode_metrics")],
    **{topics.observation(f"agent{i}"): [(f"agent{i}", "observation")] for i in range(1, 6)},
    **{topics.weights(f"agent{i}"): [(f"agent{i}", "weights")] for i in range(1, 6)},
}


def _expected_rejections(lim: dict[str, int]) -> dict[str, int]:
    """How many of the fuzzer's records for each topic fail validation (the rest are well-formed records of
    episodes outside the run, which the protocol drops)."""
    from wire_fuzz import malformed

    rng = random.Random(SEED)
    out = {}
    for t, (schema, _) in subscribed_topics("train").items():
        n = 0
        for text in malformed(schema, rng, COUNT, (FIRST, FIRST + LONG), lim):
            try:
                S.decode(text, schema, lim)
            except S.WireError:
                n += 1
        out[t] = n
    return out


def _count(status: dict[str, str], kind: str, tag: str) -> int:
    return sum(int(v) for k, v in status.items() if k.startswith(f"{kind}/{tag}/"))


def _reference(team: Any) -> Any:
    """The in-process rollout of episode e with the agents' initial Q-networks (greedy)."""
    from htlm_agent.learner import Learner, Settings
    from htlm_agent.lockstep import DecentralizedPolicy
    from htlm_agent.qnet import AgentQ, layer_sizes
    from htlm_agent.team import Team, rollout

    sc = team.cfg.scenario
    settings = Settings.from_dict(json.loads((team.run_dir / "trainer" / "settings.json").read_text()))
    learner = Learner(sc, settings, SEED)
    nets = []
    for i in range(sc.n_agents):
        net = AgentQ(layer_sizes(sc, settings.hidden))
        net.set_weights(learner.agent_weights(i))
        nets.append(net)

    def run(e: int) -> Any:
        dp = DecentralizedPolicy(nets, SEED, 0.0)  # type: ignore[arg-type]
        dp.begin(e)
        return rollout(Team(sc, 1, SEED, episode=e), dp)

    return run


def test_fuzzing_every_subscribed_topic(ros_team: Any) -> None:
    team = ros_team(
        mode="train",
        policy="auto",
        seed=SEED,
        episodes=LONG,  # shortened below, once the fuzzing is over
        first_episode=FIRST,
        trainer_params={"train_every": 0},
        agent_params={"epsilon": 0.0},
    )
    diag = team.tmp / "diag.json"
    team.helper("diag", "--out", str(diag))
    team.start()
    team.wait_for(lambda: len(team.world_episodes()) >= 1, 60, "the first episode (every node up and spinning)")
    out = team.tmp / "fuzz.json"
    fuzzer = team.helper(
        "fuzz",
        "--out",
        str(out),
        "--mode",
        "train",
        "--count",
        str(COUNT),
        "--first",
        str(FIRST),
        "--episodes",
        str(LONG),
        "--pause",
        "0.03",
        "--seed",
        str(SEED),
    )
    assert fuzzer.wait(timeout=90) == 0
    sent = read_json(out)
    fuzz_done_at = len(team.world_episodes())
    print(
        f"fuzzing took {sent['seconds']} s, ended during episode {FIRST + fuzz_done_at} of {FIRST}..{FIRST + EPISODES - 1}"
    )
    assert sent["unmatched"] == [], sent
    assert all(n >= COUNT for n in sent["sent"].values()), sent
    # end the run after the episode in progress and one more: an operator's `ros2 param set /htlm_world episodes`
    episodes = fuzz_done_at + 2
    setp = team.helper(
        "setparam", "--out", str(team.tmp / "setparam.json"), "--name", "episodes", "--value", str(episodes)
    )
    assert setp.wait(timeout=30) == 0
    assert read_json(team.tmp / "setparam.json")["successful"]
    assert team.wait("world", 90) == 0
    codes = team.wait_all(30)
    assert codes == dict.fromkeys(codes, 0), codes  # nobody crashed
    # no state changed: the run is exactly the in-process one, no agent missed a step, the store holds exactly the
    # team's transitions (one session per agent, every step of every episode)
    assert assert_same_as_in_process(team, SEED, _reference(team)) == episodes
    assert all(sum(w["metrics"]["absent"]) == 0 for w in team.world_episodes())
    store = read_store(team.run_dir / "trainer" / "transitions.bin")
    assert len(store) == episodes * 30 * 5 and len({bytes(x) for x in store["session"]}) == 5
    assert sorted(set(store["episode"].tolist())) == list(range(FIRST, FIRST + episodes))
    # every malformed record was rejected and counted, by every node that subscribes to its topic
    team.helpers[0].send_signal(signal.SIGTERM)
    team.helpers[0].wait(timeout=10)
    status = {name.split(": ", 1)[1]: v for name, v in json.loads(diag.read_text()).items()}
    lim = S.limits(5, 4, 6, 5, 30)
    expected = _expected_rejections(lim)
    report: dict[str, dict[str, tuple[int, int]]] = defaultdict(dict)
    wrong = []
    for topic, subs in SUBSCRIBERS.items():
        for node, tag in subs:
            st = status[node]
            rejected = _count(st, "rejected", tag)
            dropped = _count(st, "dropped", tag)
            report[topic][node] = (rejected, dropped)
            want = expected[topic]
            if tag in ("observation", "weights") and node != "agent2":
                want = COUNT  # the well-formed ones name agent index 1 (agent2): on another agent's topic, rejected
            if rejected != want:
                wrong.append((topic, node, rejected, want))
    total = sum(r for subs in report.values() for r, _ in subs.values())
    print(
        f"fuzz: {sum(sent['sent'].values())} records on {len(sent['sent'])} topics; "
        f"{total} rejections counted; per topic (node: rejected, dropped): {dict(report)}"
    )
    assert not wrong, f"(topic, node, rejections counted, malformed records sent): {wrong}"
