"""The parts of an agent's session, each on its own without ROS or a session around it: the outbox of transitions
and the action resend (htlm_agent.session.outbox), the trainer's weights and their lag gate (weights), the policy
source (policy), the robot's arrival (arrival), the teammates' clock offsets (offsets), the deployed team's step
clock driver (deploy_clock), the run joined (run), the records the mind's effects become (carry) and the records
written (records)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from htlm_agent.learning.qnet import AgentQ, layer_sizes
from htlm_agent.learning.settings import Settings
from htlm_agent.mind.agent import AgentMind, Effects
from htlm_agent.mind.deploy import DeployObservations, Observed
from htlm_agent.ros.settings import AgentSettings
from htlm_agent.session.arrival import ArrivalTracker
from htlm_agent.session.carry import EffectCarrier
from htlm_agent.session.deploy_clock import DeployClock
from htlm_agent.session.effects import SessionEffects
from htlm_agent.session.offsets import CLOCK_SAMPLES, ClockOffsets
from htlm_agent.session.outbox import ActionResend, Outbox
from htlm_agent.session.policy import PolicySource
from htlm_agent.session.records import RecordWriter
from htlm_agent.session.run import JoinedRun, NotInTeamError
from htlm_agent.session.weights import WEIGHTS_KEPT, WeightsClient
from htlm_msgs_py import schema as S
from htlm_msgs_py.payload import seal
from htlm_msgs_py.schema import limits
from htlm_msgs_py.signing import Signer
from htlm_world.clock import FUTURE_STEPS, StepClock
from htlm_world.episode import global_step
from htlm_world.protocol import LockstepSettings, world_protocol
from htlm_world.scenario import ScenarioRecordError, builtin

SC = builtin()
H = SC.horizon
NAMES = [a.name for a in SC.agents]


def _record(**kw: Any) -> dict[str, Any]:
    """A decoded scenario record of a run."""
    settings = LockstepSettings(**{"run_id": "r1", "episodes": 2, **kw})
    return {**world_protocol(SC, settings).scenario_record("running"), "seq": 0, "nonce": "00000000000000aa"}


# ----- the outbox and the action resend ---------------------------------------------------------------------------


def test_the_outbox_resends_in_batches_forgets_at_the_ack_and_drops_its_oldest_when_full() -> None:
    box = Outbox(limit=3, resend_period=1.0, resend_batch=2)
    for i, at in enumerate([0.0, 0.1, 0.2, 0.3]):
        out = SessionEffects()
        box.put(box.next_seq(), f"t{i}", at, out)
        assert out.publish == [("transition", f"t{i}")]
        assert out.counters["outbox_dropped"] == (1 if i == 3 else 0)
    assert list(box.waiting) == [1, 2, 3] and box.seq == 4 and len(box) == 3
    out = SessionEffects()
    box.resend(1.15, out)  # sent at 0.1 and 0.2 (due), 0.3 (not yet): at most 2 per pass anyway
    assert out.publish == [("transition", "t1")] and out.counters["resent"] == 1
    out = SessionEffects()
    box.resend(5.0, out)
    assert [t for _, t in out.publish] == ["t1", "t2"] and [k.sent for k in box.waiting.values()] == [5.0, 5.0, 0.3]
    out = SessionEffects()
    box.ack("0" * 16, 9, out)
    assert out.drops == [("transition_ack", "session")] and len(box) == 3
    box.ack(box.session, 2, SessionEffects())
    assert list(box.waiting) == [3] and box.acked == 2
    assert box.values() == {"transitions_sent": "4", "transitions_acked": "2", "outbox": "1"}


def test_the_action_is_resent_only_for_the_step_it_was_sent_for() -> None:
    r = ActionResend(period=0.5)
    out = SessionEffects()
    r.due(0, 1, 10.0, out)
    assert out.publish == []  # nothing sent yet
    r.sent(0, 1, "a1", 1.0)
    r.due(0, 1, 1.4, out)
    assert out.publish == []
    r.due(0, 2, 1.6, out)  # another step: not ours to resend
    assert out.publish == []
    r.due(0, 1, 1.5, out)
    assert out.publish == [("action", "a1")] and out.counters["actions_resent"] == 1
    r.due(0, 1, 1.9, out)
    assert len(out.publish) == 1  # the period counts from the resend


# ----- the trainer's weights --------------------------------------------------------------------------------------


LEARNER = Settings.from_dict({"hidden": [8]}, "test")


def _weights(version: int, trained: int, every: int = 1, agent: int = 0) -> dict[str, Any]:
    data = AgentQ(layer_sizes(SC, LEARNER.hidden), seed=version).get_weights()
    rec = {"agent": agent, "version": version, "episode": 0, "trained": trained, "every": every}
    return {**rec, **seal(data), "settings": LEARNER.to_dict()}


def test_the_weights_client_caches_the_newest_versions_and_gates_by_the_lag() -> None:
    w = WeightsClient("agent1", timeout=2.0)
    g0 = global_step(0, 1, 1, H)
    w.join(SC, 0, 1, g0, trainer_lag=1, training=True)
    assert w.gate(0, 1) is None and w.epsilon(0, 1) is None  # nothing yet
    out = SessionEffects()
    first = w.take(_weights(0, g0), out)
    assert first is not None and out == SessionEffects() and w.version == 0
    assert w.gate(0, 1) is first and w.gate(0, 2) is first  # T = max(g0, g - 1)
    assert w.gate(0, 3) is None  # the version of g0 + 1 is on its way
    assert w.take(_weights(0, g0 + 1), out) is None and out.drops == [("weights", "past")]
    assert w.take(_weights(1, g0, agent=2), out) is None and out.rejects[-1][:2] == ("weights", "agent")
    for v in range(1, WEIGHTS_KEPT + 3):
        w.take(_weights(v, g0 + v), SessionEffects())
    assert len(w.versions) == WEIGHTS_KEPT and min(w.versions) == g0 + 3
    assert w.epsilon(0, 2) is not None  # the learner's schedule came with the weights
    w.hold(10.0)
    assert not w.overdue(12.0) and w.overdue(12.1)


def test_the_weights_client_acts_with_the_baseline_in_the_warm_start() -> None:
    w = WeightsClient("agent1", timeout=2.0)
    w.join(SC, 0, 1, global_step(0, 1, 1, H), trainer_lag=0, training=True)
    w.learner = Settings.from_dict({"learner": "tokens", "imitate": "greedy", "imitate_episodes": 4}, "test")
    expert = w.gate(0, 1)
    assert expert is not None and expert is w.gate(3, 1)  # made once
    assert w.gate(4, 1) is None  # past the warm start: the trainer's version of that step, not there yet
    w.training = False
    assert w.gate(0, 1) is None  # no warm start outside training


def test_the_policy_source_picks_by_mode_and_takes_the_trainers_weights() -> None:
    train = JoinedRun.from_record(_record(mode="train", trainer_lag=0), NAMES[0])
    src = PolicySource(NAMES[0], "auto", "", -1.0, 2.0)
    out = SessionEffects()
    assert src.choose(train, out) is None and out.subscribe_weights and src.kind == "trainer" and src.gated(train)
    assert src.policy is None
    net = src.take(_weights(0, train.first_step), SessionEffects())
    assert net is not None and src.policy is net
    evaluate = JoinedRun.from_record(_record(mode="evaluate"), NAMES[0])
    assert src.choose(evaluate, SessionEffects()) == (
        "mode evaluate: no policy: set checkpoint:=DIR, or policy:= one of greedy, auction, qmdp, lookahead, random"
    )
    greedy = PolicySource(NAMES[0], "greedy", "", 0.3, 2.0)
    assert greedy.choose(evaluate, SessionEffects()) is None and greedy.policy is not None
    assert greedy.epsilon(0, 1) == 0.3 and not greedy.gated(evaluate)
    assert greedy.take(_weights(0, 0), SessionEffects()) is None  # not a trainer's policy: the weights are cached only
    broken = PolicySource(NAMES[0], "checkpoint", "/nonexistent", -1.0, 2.0)
    why = broken.choose(evaluate, SessionEffects())
    assert why is not None and why.startswith("policy checkpoint: ")


# ----- the robot's arrival ----------------------------------------------------------------------------------------


def test_the_arrival_tracker_sends_a_goal_per_site_and_logs_changes_once() -> None:
    a = ArrivalTracker(radius=2.0)
    assert a.arrival() == ("unknown", -1.0)
    a.scenario = SC
    out = SessionEffects()
    a.assign(1, out)
    a.assign(1, out)
    assert out.goals == [tuple(float(v) for v in SC.site_positions[1])]
    x, y = out.goals[0]
    a.on_pose(x + 3.0, y, out)
    a.on_pose(x + 2.5, y, out)
    a.on_pose(x + 1.0, y, out)
    a.on_pose(x, y, out)
    site = SC.site_names[1]
    assert out.log == [("info", f"robot on its way to site {site} (3 m)"), ("info", f"robot at site {site}")]
    assert a.arrival() == ("yes", 0.0)


def test_the_arrival_values_are_the_diagnostics_strings() -> None:
    a = ArrivalTracker(radius=2.0)
    assert a.values() == {"arrived": "unknown", "distance_to_site": "-1"}
    a.scenario, a.site, a.position = SC, 1, (float(SC.site_positions[1][0]) + 3.0, float(SC.site_positions[1][1]))
    assert a.values() == {"arrived": "no", "distance_to_site": "3"}


# ----- the mind's effects as records ------------------------------------------------------------------------------


def test_the_carrier_publishes_the_action_sends_a_goal_and_counts_a_drop() -> None:
    run = JoinedRun.from_record(_record(), NAMES[0])
    mind = AgentMind(SC, 0, 0, *_Host._policy(), batch=1, mode="evaluate")
    outbox = Outbox(8, 1.0, 8)
    resend, arrival = ActionResend(0.5), ArrivalTracker(2.0)
    arrival.scenario = SC
    signer = Signer(None)
    signer.run = run.run
    records = RecordWriter(signer, outbox.session, run.index)
    carrier = EffectCarrier(
        AgentSettings(agent=NAMES[0]).session(), records, outbox, resend, arrival, lambda _k: 0, 0.0
    )
    out = SessionEffects()
    carrier.carry("step", Effects(drop="past"), mind, run, 1.0, False, out)
    assert out.drops == [("step", "past")] and not out.publish and not out.goals
    eff = mind.begin(0)
    assert eff.action is not None
    carrier.carry("step", eff, mind, run, 1.0, False, out)
    assert [kind for kind, _ in out.publish] == ["action"] and resend.last is not None
    site = int(run.model.action_site[int(eff.action[1][0])])
    assert out.goals == [tuple(float(v) for v in SC.site_positions[site])] and arrival.site == site
    assert carrier.episodes_done == 0 and len(outbox) == 0


# ----- clock offsets ----------------------------------------------------------------------------------------------


def test_clock_offsets_take_the_least_of_the_recent_samples_and_warn_beyond_the_tolerance() -> None:
    c = ClockOffsets()
    assert c.offsets() == {} and c.values(NAMES, 1.0) == {} and c.warning(NAMES, 1.0) is None
    for x in [0.5, 0.31, 0.4]:
        c.sample(2, x)
    c.sample(1, -0.01)
    assert c.offsets() == {1: -0.01, 2: 0.31}
    assert c.warning(NAMES, 1.0) == (
        f"teammates' clocks off ours by more than 0.25 s (a quarter of the period): {NAMES[2]} -0.310 s"
    )
    assert c.warning(NAMES, 2.0) is None
    assert c.values(NAMES, None) == {
        f"clock_offset/{NAMES[1]}": "+0.010",
        f"clock_offset/{NAMES[2]}": "-0.310",
        "clock_offset_max": "0.310",
    }
    assert c.values(NAMES, 1.0)["clock_tolerance"] == "0.25"
    for _ in range(CLOCK_SAMPLES):
        c.sample(2, 0.9)
    assert c.offsets()[2] == 0.9  # only the last CLOCK_SAMPLES count


# ----- the deployed team's step clock -----------------------------------------------------------------------------


class _Host:
    """A session stand-in around one real mind: what the driver asks of it, recorded."""

    def __init__(self) -> None:
        self.stopping = False
        self.mind = AgentMind(SC, 0, 0, *self._policy(), batch=1, mode="deploy")
        self.carried: list[tuple[str, Effects]] = []
        self.observed: list[Observed] = []
        self.stops: list[str] = []

    @staticmethod
    def _policy() -> tuple[Any, Any]:
        from htlm_agent.session.builtin import builtin_policy
        from htlm_world.model import Model

        return builtin_policy(SC, "greedy", 0)[0], Model.build(SC)

    def the_mind(self) -> AgentMind:
        return self.mind

    def carry(self, topic: str, eff: Effects, out: SessionEffects) -> None:
        self.carried.append((topic, eff))

    def observe_deployed(self, ready: list[Observed], now: float, out: SessionEffects) -> None:
        for ob in ready:  # observed, and closed at once (no teammate to hear)
            self.observed.append(ob)
            self.carry("observation", self.mind.observe(ob.episode, ob.step, ob.levels, [0], now, True), out)
            self.carry("tick", self.mind.tick(now, -1.0), out)

    def epsilon(self, episode: int, size: int) -> Any:
        return 0.0

    def stop_run(self, now: float, out: SessionEffects, why: str = "stopped by the world") -> None:
        self.stopping = True
        self.stops.append(why)


def test_the_deploy_clock_acts_before_each_instant_and_stops_when_the_run_is_over() -> None:
    clock = StepClock(100.0, 1.0, H, 0, 1)
    host = _Host()
    obs = DeployObservations(1)
    d = DeployClock(clock, obs, 0.0, host)
    assert d.future(0, FUTURE_STEPS + 2, 100.0) and not d.future(0, FUTURE_STEPS + 1, 100.0)
    out = SessionEffects()
    d.run(99.0, 99.0, out)  # before the epoch: join at step 1, act for it now
    assert d.joined_at == (0, 1) and d.applied == -1 and out.log == []
    assert [t for t, e in host.carried if e.action is not None] == ["clock"] and host.mind.episode == 0
    for k in range(H):
        obs.on_robot(0, k + 1, [-1])  # the robot's observation comes first: the step is observed at its instant
        d.run(100.0 + k, 100.0 + k, out)
        assert d.applied == k and host.observed[-1].step == k + 1
    assert host.stops == ["over on our own clock"] and host.mind.finished


def test_the_deploy_clock_joins_mid_run_at_the_next_instant_and_finishes_the_step_in_progress_at_a_stop() -> None:
    clock = StepClock(100.0, 1.0, H, 0, 2)
    host = _Host()
    obs = DeployObservations(1)
    d = DeployClock(clock, obs, 0.0, host)
    out = SessionEffects()
    d.run(104.5, 104.5, out)  # the instant of step 5 has passed
    assert d.joined_at == (0, 6) and out.log == [("info", "joined the team's clock at episode 0 step 6")]
    assert host.mind.pending is not None and host.mind.pending.t == 6
    assert d.stop_at(105.1) == (0, 6) and d.stop_after == 5  # within the tolerance: step 6 is finished first
    obs.on_robot(0, 6, [-1])
    d.run(105.1, 105.1, out)
    assert host.stops == ["stopped by the world"] and host.observed[-1].step == 6


# ----- the run joined and the records written ---------------------------------------------------------------------


def test_the_joined_run_reads_the_announcement() -> None:
    run = JoinedRun.from_record(_record(first_episode=4, episodes=2, operation="external", clock="free"), NAMES[1])
    assert (run.run, run.index, run.first_episode, run.deployed, run.names) == ("r1", 1, 4, True, NAMES)
    assert [run.in_run(e) for e in (3, 4, 5, 6)] == [False, True, True, False]
    assert run.first_step == global_step(4, 1, 1, H) and run.lim is not None
    with pytest.raises(NotInTeamError, match="agent 'agent9' is not in the scenario's team"):
        JoinedRun.from_record(_record(), "agent9")
    with pytest.raises(ScenarioRecordError):
        JoinedRun.from_record({**_record(), "layout": "0" * 64}, NAMES[0])


def test_the_record_writer_encodes_what_a_receiver_decodes() -> None:
    signer = Signer(None)
    signer.run = "r1"
    w = RecordWriter(signer, "ab" * 8, index=2)
    a, lv = np.array([3]), np.array([1])
    assert S.decode(w.broadcast(0, 1, a, lv, -5.0), S.BROADCAST)["sent"] == 0.0
    assert S.decode(w.action(0, 2, a, [1]), S.ACTION) == {
        "run": "r1",
        "agent": 2,
        "episode": 0,
        "step": 2,
        "actions": [3],
        "before": [1],
    }
    assert S.decode(w.ready(0, H), S.READY) == {"run": "r1", "agent": 2, "episode": 0, "step": H}
    lim = limits(SC.n_agents, SC.n_tasks, SC.n_actions, SC.levels, SC.horizon, 1)
    belief = S.decode(w.belief(0, 1, [0.5] * lim["marginals"], [0] * SC.n_tasks, "no", 3.5), S.BELIEF, lim)
    assert (belief["arrived"], belief["distance"]) == ("no", 3.5)
    assert dataclasses.is_dataclass(JoinedRun)
