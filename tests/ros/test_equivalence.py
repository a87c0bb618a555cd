"""With the same seed and policies, an evaluation over ROS (7 processes, real DDS) gives exactly the trajectories of
the in-process runtime, episode by episode: with batch 1, team.rollout on Team(scenario, 1, seed, episode=e); with a
batch of B episodes at once (world parameter `batch`), Team(scenario, B, seed, episode=b) and
DecentralizedPolicy.begin(b) for batch b (episodes b*B..b*B+B-1)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from htlm_agent.mind.policies import DecentralizedPolicy
from htlm_agent.runtime.team import Team, rollout
from support.ros import assert_same_as_in_process

pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]


@pytest.mark.parametrize(
    ("policy", "seed", "first"),
    [("greedy", 11, 0), pytest.param("random", 5, 40, marks=pytest.mark.slow)],  # random at B=1: -m slow
)
def test_ros_evaluation_equals_in_process(ros_team: Any, policy: str, seed: int, first: int) -> None:
    team = ros_team(policy=policy, seed=seed, episodes=3, first_episode=first)
    team.start()
    assert team.wait("world", 60) == 0
    codes = team.wait_all(30)
    assert codes == dict.fromkeys(codes, 0), codes
    assert assert_same_as_in_process(team, seed, policy) == 3
    assert all(sum(w["metrics"]["absent"]) == 0 for w in team.world_episodes())


@pytest.mark.parametrize(
    ("policy", "seed", "first"),
    # CI budget: both with -m slow; the default run keeps batch 16 in the checkpoint evaluation below
    [pytest.param("greedy", 11, 0, marks=pytest.mark.slow), pytest.param("random", 5, 16, marks=pytest.mark.slow)],
)
def test_ros_evaluation_of_a_batch_of_16_equals_team_of_that_batch(
    ros_team: Any, policy: str, seed: int, first: int
) -> None:
    """16 episodes at once: every agent process keeps 16 beliefs and acts for all of them with one call; the run
    equals Team(scenario, 16, seed, b) + DecentralizedPolicy.begin(b) of batch b = first / 16 bit for bit."""
    team = ros_team(policy=policy, seed=seed, episodes=16, first_episode=first, batch=16)
    team.start()
    assert team.wait("world", 60) == 0
    codes = team.wait_all(30)
    assert codes == dict.fromkeys(codes, 0), codes
    assert assert_same_as_in_process(team, seed, policy) == 16
    eps = team.world_episodes()
    assert sorted(w["metrics"]["episode"] for w in eps) == list(range(first, first + 16))
    assert all(sum(w["metrics"]["absent"]) == 0 for w in eps)


@pytest.mark.parametrize(
    ("batch", "episodes", "first"), [pytest.param(1, 2, 7, marks=pytest.mark.slow), (16, 16, 32)]
)  # at B=1: -m slow
def test_ros_evaluation_of_a_checkpoint_equals_in_process(
    ros_team: Any, tmp_path: Path, batch: int, episodes: int, first: int
) -> None:
    """Agents load their own Q-networks (AgentQ) from a checkpoint of the learner, as `htlm evaluate` does."""
    from htlm_agent.learning.settings import Settings

    team = ros_team(policy="checkpoint", seed=3, episodes=episodes, first_episode=first, batch=batch)
    assert _checkpoint_run_equals_in_process(team, tmp_path, Settings(memory=1000, envs=1), 3, batch) == episodes


def _checkpoint_run_equals_in_process(team: Any, tmp_path: Path, settings: Any, seed: int, batch: int) -> int:
    """Run `team` (not started, policy checkpoint, master seed `seed`) with fresh networks of a learner of `settings`
    and check its episodes against Team(scenario, batch, seed, b) acting with the same networks; their number."""
    from htlm_agent.learning.dqn import Learner

    learner = Learner(team.cfg.scenario, settings, seed=42)
    with np.errstate(all="ignore"):
        ckpt = learner.save(tmp_path / "ckpt")
    return _run_equals_in_process(team, ckpt, seed, batch)


def _run_equals_in_process(team: Any, ckpt: Path, seed: int, batch: int, team_wide: bool = False) -> int:
    """Run `team` (not started, policy checkpoint, master seed `seed`) on the checkpoint `ckpt` and check its episodes
    against Team(scenario, batch, seed, b) with every agent's policy from the same checkpoint (`team_wide`: with the
    team policy `htlm evaluate` acts with, one call for every agent); their number."""
    from htlm_agent.learning.checkpoint import load_checkpoint
    from htlm_agent.learning.learners import agent_policy, team_policy

    sc = team.cfg.scenario
    team.cfg.checkpoint = str(ckpt)
    team.start()
    assert team.wait("world", 90) == 0
    assert team.wait_all(30) == dict.fromkeys(team.procs, 0)
    ck = load_checkpoint(ckpt)
    nets = [agent_policy(ck, i) for i in range(sc.n_agents)]

    def reference(b: int) -> Any:
        if team_wide:
            return rollout(Team(sc, batch, seed, episode=b), team_policy(ck))
        dp = DecentralizedPolicy(nets, seed, 0.0)
        dp.begin(b)
        return rollout(Team(sc, batch, seed, episode=b), dp)

    n: int = assert_same_as_in_process(team, seed, reference)
    return n


@pytest.mark.slow  # CI budget: the default run keeps the lockstep's equivalence; -m slow
def test_free_running_clock_equals_in_process(ros_team: Any) -> None:
    """The world steps every 100 ms instead of as soon as everyone answered; agents that keep up give the same run
    (at 50 ms an agent on the loaded 2-core CI machine missed a step of the first episode once)."""
    team = ros_team(policy="greedy", seed=1, episodes=2, world_params={"clock": "free", "period": 0.1})
    team.start()
    assert team.wait("world", 60) == 0
    assert team.wait_all(30) == dict.fromkeys(team.procs, 0)
    assert assert_same_as_in_process(team, 1, "greedy") == 2
    seconds = [w["metrics"]["seconds"] for w in team.world_episodes()]
    assert seconds[-1] >= 30 * 0.1 * 0.9, seconds  # paced by the clock, not by the agents


def test_ros_evaluation_under_events_equals_in_process(ros_team: Any, tmp_path: Path) -> None:
    """A surge (by chance, per episode), a dropout and a return (docs/model.md, Events) over ROS: the world decides
    them from the same stream as the in-process Team, the dropped-out agent's process keeps running while the world
    idles it, and the 4 episodes of the batch equal Team(scenario, 4, seed, b) bit for bit; the world's log lists
    the events of each episode."""
    import yaml

    from htlm_world.scenario import EventSpec, builtin

    events = (
        EventSpec("surge", site="site2", task="fire", level=4, at=4, probability=0.5),
        EventSpec("dropout", agent="agent2", at=3),
        EventSpec("return", agent="agent2", at=8, probability=0.3),
    )
    sc = builtin().with_events(events)
    (path := tmp_path / "events.yaml").write_text(yaml.safe_dump(sc.to_dict()))  # the world reads a scenario file
    team = ros_team(policy="greedy", seed=2, episodes=4, batch=4, scenario=sc, scenario_file=str(path))
    team.start()
    assert team.wait("world", 60) == 0
    assert team.wait_all(30) == dict.fromkeys(team.procs, 0)
    assert assert_same_as_in_process(team, 2, "greedy") == 4
    logged = {w["metrics"]["episode"]: w for w in team.world_episodes()}
    labels = [[label for _, label in logged[e]["events"]] for e in range(4)]
    assert all("dropout agent2" in x for x in labels), labels
    surges = {t for e in range(4) for t, label in logged[e]["events"] if label == "surge fire@site2 to 4"}
    assert len(surges) > 1, f"the chance surge came at the same step in every episode: {surges}"
    assert all(sum(w["metrics"]["absent"]) == 0 for w in logged.values()), "a dropout is not an absence"


def test_no_launched_process_maps_fast_dds_shared_memory(ros_team: Any) -> None:
    """The cause of a process that stops hearing the world after a teammate was SIGKILLed: a Fast DDS shared-memory
    port whose lock the dead process held. The launch keeps every process on UDP (htlm_msgs_py/fastdds_loopback.xml;
    Jazzy's LOCALHOST discovery range would add shared memory), so none may map a Fast DDS segment."""
    team = ros_team(policy="greedy", seed=3, episodes=4)
    team.start()
    team.wait_for(lambda: len(team.world_episodes()) >= 1, 60, "the first episode")
    mapped = {}
    for name, p in team.procs.items():
        maps = Path(f"/proc/{p.popen.pid}/maps").read_text()
        mapped[name] = sorted({line.split()[-1] for line in maps.splitlines() if "/dev/shm/fastrtps" in line})
    assert mapped == {name: [] for name in team.procs}, mapped
    assert team.wait("world", 60) == 0
    assert team.wait_all(30) == dict.fromkeys(team.procs, 0)


@pytest.mark.slow  # CI budget: the default run keeps the checkpoint evaluations; this one with -m slow
def test_token_networks_with_a_roster_over_ros_equal_in_process(ros_team: Any, tmp_path: Path) -> None:
    """The token learner's networks (one shared network, a copy in every agent process) on a scenario with the roster,
    the teammates' places and a dropout: every agent sees from the broadcasts who went silent and where the others
    were, as the in-process Team does from who sat out and the joint assignment, and the 4 episodes equal
    Team(scenario, 4, seed, b) bit for bit."""
    import yaml

    from htlm_agent.learning.settings import Settings
    from htlm_world.scenario import EventSpec, builtin

    sc = builtin().replace(roster=True, teammates=True).with_events((EventSpec("dropout", agent="agent2", at=3),))
    (path := tmp_path / "roster.yaml").write_text(yaml.safe_dump(sc.to_dict()))
    team = ros_team(policy="checkpoint", seed=6, episodes=4, batch=4, scenario=sc, scenario_file=str(path))
    settings = Settings(learner="tokens", hidden=(16, 16), memory=1000, envs=1)
    assert _checkpoint_run_equals_in_process(team, tmp_path, settings, 6, 4) == 4


@pytest.mark.slow  # CI budget: the default run keeps the checkpoint evaluations; -m slow
def test_the_lookahead_learner_over_ros_equals_in_process(ros_team: Any, tmp_path: Path) -> None:
    """The lookahead learner's checkpoint (a copy of its value network in every agent process) with the roster and a
    dropout: every agent draws its states from a hash of its own knowledge state, so its process draws what the
    team policy of `htlm evaluate` draws for it in one call for the whole team, and the 4 episodes equal
    Team(scenario, 4, seed, b) acting with that policy bit for bit."""
    import yaml

    from htlm_agent.learning.run import train
    from htlm_agent.learning.settings import Settings
    from htlm_world.scenario import EventSpec, builtin

    sc = builtin().replace(roster=True).with_events((EventSpec("dropout", agent="agent2", at=3),))
    (path := tmp_path / "roster.yaml").write_text(yaml.safe_dump(sc.to_dict()))
    team = ros_team(policy="checkpoint", seed=8, episodes=4, batch=4, scenario=sc, scenario_file=str(path))
    settings = Settings.for_learner(learner="lookahead", episodes=500, value_updates=50, batch_size=256)
    train(sc, settings, tmp_path / "run", progress=False, tensorboard=False, evaluate_at_end=False)
    assert _run_equals_in_process(team, tmp_path / "run" / "checkpoint", 8, 4, team_wide=True) == 4


def test_the_fair_market_over_ros_equals_in_process(ros_team: Any, tmp_path: Path) -> None:
    """The auction with the roster (docs/model.md, Baselines: the fair market): every agent process leaves out the
    teammate whose broadcasts stopped, as in process, bit for bit."""
    import yaml

    from htlm_world.scenario import EventSpec, builtin

    sc = builtin().replace(roster=True).with_events((EventSpec("dropout", agent="agent2", at=3),))
    (path := tmp_path / "roster.yaml").write_text(yaml.safe_dump(sc.to_dict()))
    team = ros_team(policy="auction", seed=4, episodes=4, batch=4, scenario=sc, scenario_file=str(path))
    team.start()
    assert team.wait("world", 60) == 0
    assert team.wait_all(30) == dict.fromkeys(team.procs, 0)
    assert assert_same_as_in_process(team, 4, "auction") == 4
    assert all(w["metrics"]["completion"] < 30 for w in team.world_episodes()), "the market left agent2's work undone"


def test_drives_over_ros_equal_in_process(ros_team: Any, tmp_path: Path) -> None:
    """An operation with travel (docs/model.md, Travel) over ROS: the world applies the drives, every agent process
    follows its teammates' drives from their broadcast assignments, and the finish-time auction's 4 episodes equal
    Team(scenario, 4, seed, b) bit for bit, with agents on their way in every episode."""
    import yaml

    from htlm_world.metrics import drives
    from htlm_world.scenario import from_dict

    team_spec = [{"name": f"agent{i + 1}", "fire": f, "rescue": r} for i, (f, r) in enumerate(HETEROGENEOUS)]
    team_spec[0]["speed"] = 50.0
    sc = from_dict({"step_seconds": 2.0, "speed": 10.0, "agents": team_spec}, "<travel>")
    (path := tmp_path / "travel.yaml").write_text(yaml.safe_dump(sc.to_dict()))
    team = ros_team(policy="auction", seed=5, episodes=4, batch=4, scenario=sc, scenario_file=str(path))
    team.start()
    assert team.wait("world", 60) == 0
    assert team.wait_all(30) == dict.fromkeys(team.procs, 0)
    assert assert_same_as_in_process(team, 5, "auction") == 4
    actions = np.array([w["actions"] for w in team.world_episodes()]).transpose(1, 0, 2)  # (h, B, N)
    _, on_way = drives(sc, actions)
    assert (on_way.sum(axis=1) > 0).all(), "no agent drove in some episode"


HETEROGENEOUS = ((3, 1), (3, 2), (2, 0), (0, 1), (1, 1))
"""The paper's heterogeneous team (fire, rescue), docs/model.md."""
