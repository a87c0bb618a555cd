"""Bad input of a real deployment: 500 malformed records on every topic a node of the team subscribes to, while
the team runs. No node crashes, no state changes (the run still equals the in-process runtime, the trainer's store
holds exactly the team's transitions), every rejection is counted in /diagnostics by every subscriber, and the
episodes in progress finish.

Two runs: an evaluation (the 13 topics of the lockstep protocol, the scenario and the trainer's inputs), and a
training run with its learning switched off (the trainer stores but does not train, agents act greedily with the
learner's initial Q-networks, ε = 0, so the run is deterministic) for the topics only training uses: the 5 weights
topics, the transitions and their acknowledgements."""

from __future__ import annotations

import json
import random
import signal
from collections import defaultdict
from collections.abc import Callable
from typing import Any

import pytest

from htlm_agent.learning.transition_store import read_store
from htlm_msgs_py import schema as S
from htlm_msgs_py.signing import Signer
from htlm_world import seeds
from support.ros import RosTeam, assert_same_as_in_process, read_json

from .ros_tools import SUBSCRIBERS, subscribed_topics

pytestmark = [pytest.mark.ros, pytest.mark.timeout(180)]

COUNT = 500
FIRST, LONG, SEED = 100, 1000, 6
AGENTS = [f"agent{i}" for i in range(1, 6)]

TRAINING_TOPICS = "weights,transitions,transition_ack"
FAST_DIAGNOSTICS: dict[str, Any] = {
    f"{who}_params": {"diagnostics_period": 0.2} for who in ("world", "agent", "trainer")
}  # the fuzzer paces itself on the subscribers' counters


def _expected_rejections(mode: str, only: str) -> dict[str, int]:
    """How many of the fuzzer's records for each topic fail validation with the paper scenario's limits (the rest
    are well-formed records of episodes outside the run, which the protocol drops)."""
    from wire_fuzz import malformed

    lim = S.limits(5, 4, 6, 5, 30, 1)  # the fuzzed team runs batches of 1
    ours = Signer(None)
    ours.run = "r1"  # the fuzzer writes the team's run where the records name r1
    rng = random.Random(SEED)
    out = {}
    for t, (schema, _) in subscribed_topics(mode).items():
        texts = list(malformed(schema, rng, COUNT, (FIRST, FIRST + LONG), lim))  # same draws as the fuzzer
        if only and not any(t.endswith(k) for k in only.split(",")):
            continue
        n = 0
        for text in texts:
            try:
                S.decode(text, schema, lim, ours)
            except S.WireError:
                n += 1
        out[t] = n
    return out


def _fuzz(team: RosTeam, mode: str, only: str = "", pause: float = 0.01) -> tuple[dict[str, Any], int]:
    """Fuzz the running team, then end its run after the episode in progress and one more (as an operator would,
    `ros2 param set /htlm_world episodes N`). Returns the fuzzer's report and the number of episodes run."""
    team.wait_for(lambda: len(team.world_episodes()) >= 1, 90, "the first episode (every node up and spinning)")
    out = team.tmp / f"fuzz-{mode}.json"
    args = ["fuzz", "--out", str(out), "--mode", mode, "--count", str(COUNT), "--first", str(FIRST)]
    args += ["--episodes", str(LONG), "--pause", str(pause), "--seed", str(SEED)]
    if only:
        args += ["--topics", only]
    fuzzer = team.helper(*args)
    assert fuzzer.wait(timeout=150) == 0
    sent = read_json(out)
    done = len(team.world_episodes())
    print(f"fuzzing {len(sent['sent'])} topics took {sent['seconds']} s, up to episode {FIRST + done}")
    assert sent["unmatched"] == [], sent  # every subscriber matched before the first record: none missed
    assert sent["unacked"] == [], sent  # every subscriber acknowledged every record: none lost on the way
    assert all(n >= COUNT for n in sent["sent"].values()), sent
    setp = team.helper(
        "setparam", "--out", str(team.tmp / "setparam.json"), "--name", "episodes", "--value", str(done + 2)
    )
    assert setp.wait(timeout=30) == 0
    assert read_json(team.tmp / "setparam.json")["successful"]
    assert team.wait("world", 120) == 0
    codes = team.wait_all(60)
    assert codes == dict.fromkeys(codes, 0), codes  # nobody crashed
    episodes = len(team.world_episodes())
    assert episodes > done, "the episode in progress when the fuzzing ended finished"
    return sent, episodes


def _check_counters(team: RosTeam, mode: str, only: str, sent: dict[str, Any]) -> None:
    team.helpers[0].send_signal(signal.SIGTERM)
    team.helpers[0].wait(timeout=10)
    status = {name.split(": ", 1)[1]: v for name, v in json.loads((team.tmp / "diag.json").read_text()).items()}
    expected = _expected_rejections(mode, only)
    report: dict[str, dict[str, tuple[int, int]]] = defaultdict(dict)
    wrong = []
    for topic in sent["sent"]:
        for node, tag in SUBSCRIBERS[topic]:
            st = status[node]
            rejected = sum(int(v) for k, v in st.items() if k.startswith(f"rejected/{tag}/"))
            dropped = sum(int(v) for k, v in st.items() if k.startswith(f"dropped/{tag}/"))
            report[topic][node] = (rejected, dropped)
            want = expected[topic]
            if tag in ("observation", "weights") and node != "agent2":
                want = COUNT  # the well-formed ones name agent index 1 (agent2): on another agent's topic, rejected
            # every malformed record is counted, exactly: none lost (the fuzzer sends only to matched subscribers,
            # paces itself on their counters and waits for every acknowledgement), none counted twice, and no good
            # record rejected
            if rejected != want:
                wrong.append((topic, node, rejected, want))
    total = sum(r for subs in report.values() for r, _ in subs.values())
    print(
        f"{sum(sent['sent'].values())} records on {len(sent['sent'])} topics; {total} rejections counted; "
        f"per topic (node: rejected, dropped): {dict(report)}"
    )
    assert not wrong, f"(topic, node, rejections counted, malformed records sent): {wrong}"


def test_fuzzing_every_topic_of_an_evaluation(ros_team: Any) -> None:
    team = ros_team(policy="greedy", seed=SEED, episodes=LONG, first_episode=FIRST, **FAST_DIAGNOSTICS)
    team.helper("diag", "--out", str(team.tmp / "diag.json"))
    team.start()
    sent, episodes = _fuzz(team, "evaluate")
    assert len(sent["sent"]) == 13
    # no state changed: the run is exactly the in-process one and no agent missed a step
    assert assert_same_as_in_process(team, SEED, "greedy") == episodes
    assert all(sum(w["metrics"]["absent"]) == 0 for w in team.world_episodes())
    _check_counters(team, "evaluate", "", sent)


def _initial_networks(team: RosTeam) -> Callable[[int], Any]:
    """The in-process rollout of episode e with the learner's initial Q-networks (greedy), as the trainer sent them."""
    from htlm_agent.learning.dqn import Learner
    from htlm_agent.learning.qnet import AgentQ, layer_sizes
    from htlm_agent.learning.settings import Settings
    from htlm_agent.mind.policies import DecentralizedPolicy
    from htlm_agent.runtime.team import Team, rollout

    sc = team.cfg.scenario
    settings = Settings.from_dict(json.loads((team.run_dir / "trainer" / "settings.json").read_text()))
    learner = Learner(sc, settings, SEED)
    nets = []
    for i in range(sc.n_agents):
        net = AgentQ(layer_sizes(sc, settings.hidden))
        net.set_weights(learner.agent_weights(i))
        nets.append(net)

    def run(e: int) -> Any:  # train mode: the training streams of batch e (batch 1), as htlm train draws them
        dp = DecentralizedPolicy(nets, SEED, 0.0)  # type: ignore[arg-type]
        dp.rngs = [seeds.train_explore(SEED, i, e) for i in range(sc.n_agents)]
        t = Team(sc, 1, SEED, episode=e)
        t.sim.rng = seeds.train_world(SEED, e)
        t.sim.channel_rngs = [seeds.train_channel(SEED, i, e) for i in range(sc.n_agents)]
        return rollout(t, dp)

    return run


@pytest.mark.slow  # CI budget: the default run keeps the fuzzing of an evaluation's topics; this one with -m slow
def test_fuzzing_the_training_topics(ros_team: Any) -> None:
    team = ros_team(
        mode="train",
        policy="auto",
        seed=SEED,
        episodes=LONG,
        first_episode=FIRST,
        # the networks never change (no update before 10**9 stored transitions): the run equals the initial networks'
        trainer_params={"settings_json": '{"learning_starts": 1000000000}', "diagnostics_period": 0.2},
        agent_params={"epsilon": 0.0, "diagnostics_period": 0.2},
        world_params={"diagnostics_period": 0.2},
    )
    team.helper("diag", "--out", str(team.tmp / "diag.json"))
    team.start()
    sent, episodes = _fuzz(team, "train", TRAINING_TOPICS)
    assert len(sent["sent"]) == 7
    assert assert_same_as_in_process(team, SEED, _initial_networks(team)) == episodes
    assert all(sum(w["metrics"]["absent"]) == 0 for w in team.world_episodes())
    store = read_store(team.run_dir / "trainer" / "transitions.bin")
    assert len(store) == episodes * 30 * 5, "exactly the team's transitions, none forged"
    assert len({bytes(x) for x in store["session"]}) == 5
    assert sorted(set(store["episode"].tolist())) == list(range(FIRST, FIRST + episodes))
    _check_counters(team, "train", TRAINING_TOPICS, sent)
