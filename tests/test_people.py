"""A person in the team without ROS or a browser: the desk between an agent's session and the person's page
(htlm_agent.people.desk), and the page's API with its token (htlm_agent.people.web), served by uvicorn on a free
port of this machine (docs/usage.md, A person in the team)."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from typing import Any

import pytest

from htlm_agent.people.desk import PersonDesk
from htlm_agent.people.web import Bridge, PageServer, make_app, new_token, page
from htlm_agent.ros.settings import AgentSettings
from htlm_agent.session.core import AgentSession
from htlm_msgs_py import schema as S
from htlm_msgs_py.schema import limits
from htlm_world.protocol import LockstepSettings, world_protocol
from htlm_world.scenario import builtin

SC = builtin()
PERIOD = 10.0
EPOCH = 1000.0
LIM = limits(SC.n_agents, SC.n_tasks, SC.n_actions, SC.levels, SC.horizon, 1)
ME = 2
"""The agent the person plays."""


def _session() -> tuple[AgentSession, list[dict[str, Any]]]:
    """The person's agent on its own clock (wall clock = `now`), the epoch 1 s ahead; and the action records it
    sends, appended to as the test feeds it."""
    settings = LockstepSettings(
        run_id="p1", mode="deploy", episodes=2, operation="external", clock="free", period=PERIOD
    )
    rec = {**world_protocol(SC, settings).scenario_record("running"), "epoch": EPOCH}
    s = AgentSession(AgentSettings(agent=SC.agents[ME].name, policy="greedy", observation_wait=5.0).session())
    sent: list[dict[str, Any]] = []
    _take(s.on_scenario(S.decode(S.encode(S.SCENARIO, rec), S.SCENARIO), EPOCH - 1.0), sent)
    return s, sent


def _take(eff: Any, sent: list[dict[str, Any]]) -> None:
    assert eff.fatal is None, eff.fatal
    for kind, text in eff.publish:
        if kind == "action":
            sent.append(S.decode(text, S.ACTION, LIM))


def _at(s: AgentSession, wall: float, sent: list[dict[str, Any]]) -> None:
    _take(s.tick(wall), sent)


def test_a_level_report_is_the_agents_observation_and_bad_reports_change_nothing() -> None:
    s, sent = _session()
    desk = PersonDesk(s)
    v = desk.view(EPOCH - 0.5)
    assert v["state"] == "running" and (v["episode"], v["step"]) == (0, 1)
    assert not v["report_open"] and v["deadline"] == EPOCH + 5.0
    early = desk.report({"kind": "level", "episode": 0, "step": 1, "level": 1}, EPOCH - 0.5, EPOCH - 0.5)
    assert not early.ok and "step 1 has not begun: reports open at its instant" in early.message
    assert [x["name"] for x in v["sites"]] == list(SC.site_names)
    task = v["assignment"]["task"]
    assert task is not None and 0 <= task < SC.n_tasks, v["assignment"]
    _at(s, EPOCH + 0.1, sent)  # the instant of step 1 passed: the step waits for the person's level
    assert desk.view(EPOCH + 0.1)["report_open"]
    assert s.mind is not None and s.mind.pending is not None and s.mind.pending.observed_at is None
    before = s.mind.marg.copy()
    refused = [
        ({"kind": "level", "episode": 0, "step": 1, "level": 7}, "level 7 is out of range"),
        ({"kind": "level", "episode": 0, "step": 1, "level": True}, "level True is out of range"),
        ({"kind": "level", "episode": 0, "step": 1, "level": "2"}, "level '2' is out of range"),
        ({"kind": "level", "episode": 0, "step": 4, "level": 1}, "episode 0 step 4 has not begun"),
        ({"kind": "level", "episode": 0, "step": 0, "level": 1}, "episode 0 step 0 is past"),
        ({"kind": "instead", "task": "triage@nowhere"}, "task 'triage@nowhere' does not exist"),
        ({"kind": "jump"}, "kind 'jump' is not a report"),
        ({"kind": "back"}, "you are already available"),
        (["level", 2], "a report is a JSON object, not list"),
    ]
    for body, why in refused:
        got = desk.report(body, EPOCH + 0.2, EPOCH + 0.2)
        assert not got.ok and why in got.message, (body, got.message)
        assert got.observation is None and not got.effects.publish
        assert got.effects.rejects and got.effects.rejects[0][0] == "person"
    assert desk.refused == len(refused) + 1 and s.mind.pending.observed_at is None
    assert (s.mind.marg == before).all()
    seen = max(SC.initial_levels[task] - 1, 0)  # a level the task can have after one step
    got = desk.report({"kind": "level", "episode": 0, "step": 1, "level": seen}, EPOCH + 0.3, EPOCH + 0.3)
    assert got.ok, got.message
    obs = got.observation
    assert obs == {"agent": ME, "episode": 0, "step": 1, "tasks": [task], "levels": [seen], "acted": [ME]}
    again = desk.report({"kind": "level", "episode": 0, "step": 1, "level": 1}, EPOCH + 0.3, EPOCH + 0.3)
    assert not again.ok and f"already has your report (level {seen})" in again.message
    # the node publishes it as any observation record (signed with a key); the agent takes it as its observation
    rec = S.decode(S.encode(S.OBSERVATION, {"run": "p1", **obs}), S.OBSERVATION, LIM)
    _take(s.on_observation(rec, EPOCH + 0.4), sent)
    assert s.mind.pending is None or s.mind.pending.t == 2 or s.mind.pending.observed_at is not None
    _at(s, EPOCH + 5.5, sent)  # no teammate heard: the step closes with the person's level in the belief
    twin, _ = _session()  # the same agent with no report: its belief only predicts the step
    _at(twin, EPOCH + 0.1, [])
    _at(twin, EPOCH + 5.5, [])
    _at(twin, EPOCH + 7.0, [])  # its observation overdue at +5 s, then the teammates waited for 1 s
    assert twin.mind is not None and s.mind.t == twin.mind.t == 1
    assert s.mind.marg[0, task, seen] > twin.mind.marg[0, task, seen], "the report moved the belief to its level"
    late = desk.report({"kind": "level", "episode": 0, "step": 1, "level": 0}, EPOCH + 6.0, EPOCH + 6.0)
    assert not late.ok and "is past" in late.message


def test_not_available_idles_the_agent_until_the_person_is_back_and_instead_is_acted_on() -> None:
    s, sent = _session()
    desk = PersonDesk(s)
    assert s.mind is not None and s.mind.pending is not None
    chosen = int(s.mind.pending.action[0])
    away = desk.report({"kind": "away"}, EPOCH - 0.5, EPOCH - 0.5)
    assert away.ok
    # before its instant, the step's action is sent again: idle at the site of the previous assignment
    acts = [S.decode(t, S.ACTION, LIM) for k, t in away.effects.publish if k == "action"]
    idle = int(s.mind.idle_action()[0])
    assert [(a["step"], a["actions"]) for a in acts] == [(1, [idle])] and idle >= SC.n_tasks != chosen
    _take(away.effects, sent)
    refused = desk.report({"kind": "level", "episode": 0, "step": 1, "level": 2}, EPOCH - 0.4, EPOCH - 0.4)
    assert not refused.ok and "not available" in refused.message
    assert not desk.view(EPOCH)["report_open"]
    for k in range(1, 4):  # steps go by with no level: the agent stays idle
        for dt in (0.1, 6.0, 9.0):  # the instant; the observation overdue and the teammates waited for; before the next
            _at(s, EPOCH + (k - 1) * PERIOD + dt, sent)
    last = {a["step"]: a["actions"][0] for a in sent if a["episode"] == 0}  # the action each step went with
    assert [last[t] >= SC.n_tasks for t in (1, 2, 3)] == [True, True, True]
    back = desk.report({"kind": "back"}, EPOCH + 29.5, EPOCH + 29.5)
    assert back.ok and "from step 4" in back.message
    # before step 4's instant: its action is sent again, the policy's own choice (the model's return)
    acts = [S.decode(t, S.ACTION, LIM) for k, t in back.effects.publish if k == "action"]
    assert s.mind.chosen is not None and [(a["step"], a["actions"]) for a in acts] == [(4, [int(s.mind.chosen[0])])]
    _take(back.effects, sent)
    for dt in (30.1, 36.0, 39.0):
        _at(s, EPOCH + dt, sent)
    assert sent[-1]["actions"][0] < SC.n_tasks, "back: the policy chooses a task again"
    # a task taken instead, before the instant of the step it is for: that step's action is sent again
    names = list(SC.action_names)
    other = next(n for j, n in enumerate(names[: SC.n_tasks]) if j != sent[-1]["actions"][0])
    took = desk.report({"kind": "instead", "task": other}, EPOCH + 39.5, EPOCH + 39.5)
    assert took.ok, took.message
    acts = [S.decode(t, S.ACTION, LIM) for k, t in took.effects.publish if k == "action"]
    assert acts and acts[-1]["actions"] == [names.index(other)]
    assert desk.view(EPOCH + 39.6)["assignment"]["action"] == other


def _get(url: str, token: str | None) -> tuple[int, str]:
    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"} if token else {})
    try:
        with urllib.request.urlopen(req, timeout=5) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode()


def _post(url: str, token: str, body: bytes) -> tuple[int, dict[str, Any]]:
    req = urllib.request.Request(url, data=body, headers={"Authorization": f"Bearer {token}"}, method="POST")
    try:
        with urllib.request.urlopen(req, timeout=5) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


@pytest.fixture
def served() -> Any:
    bridge = Bridge()
    token = new_token()
    server = PageServer(make_app(bridge, token, page("person.html")), "127.0.0.1", 0)
    server.start()
    yield bridge, token, f"http://127.0.0.1:{server.port}"
    server.stop()


def test_the_page_and_its_api_answer_only_their_own_token(served: Any) -> None:
    bridge, token, base = served
    bridge.show({"agent": "nurse", "state": "running", "step": 3})
    for t in (None, new_token(), token[:-1]):
        code, text = _get(f"{base}/api/state", t)
        assert code == 401 and "nurse" not in text
        code, text = _get(f"{base}/?token={t}" if t else f"{base}/", None)
        assert code == 401 and "<html" not in text and "no access" in text
        code, ans = _post(f"{base}/api/report", t or "", b'{"kind": "away"}')
        assert code == 401 and not ans["ok"]
    assert bridge.take() == [], "nothing reached the agent without the token"
    code, text = _get(f"{base}/?token={token}", None)
    assert code == 200 and "<html" in text
    code, text = _get(f"{base}/api/state", token)
    assert code == 200 and json.loads(text)["step"] == 3
    code, ans = _post(f"{base}/api/report", token, b"{not json")
    assert code == 400 and "a report is JSON" in ans["message"]


def test_htlm_launch_with_a_person_checks_her_name_and_starts_her_page_instead_of_her_robot(tmp_path: Any) -> None:
    from htlm_agent.cli.launch import LaunchError, config
    from htlm_agent.ros.launch import page_addresses, process_specs

    for argv, why in (
        (["deploy", "--policy", "greedy", "--person", "nobody"], "--person nobody: not an agent of the team"),
        (["evaluate", "--policy", "greedy", "--person", "agent1"], "people play agents of a deployed team"),
        (["deploy", "--policy", "greedy", "--person", "agent1,agent1"], "an agent is named twice"),
    ):
        with pytest.raises(LaunchError, match=why):
            config(argv)
    cfg = config(
        ["deploy", "--policy", "greedy", "--robots", "sim", "--person", "agent3", "--run-dir", str(tmp_path / "r")]
    )
    assert cfg.period == 120.0 and cfg.operation == "external"  # a step a person can keep
    specs = {name: params for name, _module, params in process_specs(cfg)}
    assert "robot_agent3" not in specs and "robot_agent1" in specs
    assert specs["operation"]["people"] == "agent3"
    me = specs["agent3"]
    assert me["person"] and me["observation_wait"] == 60.0 and "pose_topic" not in me
    assert (me["page_address"], me["page_port"]) == ("127.0.0.1", 8600)
    assert specs["commander"]["page_port"] == 8601 and specs["commander"]["people"] == "agent3"
    pages = page_addresses(cfg)
    token_file = tmp_path / "r" / "people" / "agent3.token"
    assert pages["agent3"] == f"http://127.0.0.1:8600/?token={token_file.read_text().strip()}"
    assert token_file.stat().st_mode & 0o077 == 0, "the token is readable by its owner only"
    assert page_addresses(cfg) == pages, "a run directory keeps its tokens"
