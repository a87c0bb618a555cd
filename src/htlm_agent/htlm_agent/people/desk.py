"""A person in the team, without ROS or the web: what the person's page shows of the agent they play, and what the
person reports, checked as any record is and turned into what the agent does (docs/usage.md, A person in the team).

An agent that a person plays runs as any deployed agent (its session keeps the step clock, acts, hears its
teammates and broadcasts); the person takes the robot's place: instead of a robot's perception, the person reports
the level they see at their task, which becomes the agent's observation of that step (the node publishes it as an
`htlm/observation` record on the agent's observation topic, signed when the team has a key, so it reaches the agent
and the world's log as a robot's would). `PersonDesk` sits between the session and the page: `view` is what the
page shows, `report` checks one thing the person did and returns its `Outcome`. Reports:

- `{"kind": "level", "episode": e, "step": t, "level": n}`: the level seen at the task of step t (0..L-1), after the
  step's work: from the step's instant until the agent's observation wait after it is over. Refused with its reason
  when n is out of range or not an integer, when step t is not the step in progress (a step long past, or one whose
  instant has not come), when the step already has a report, when the person is not on a task or is marked not
  available.
- `{"kind": "away"}` and `{"kind": "back"}`: the person is not available (the agent is out of the team, the model's
  dropout: from the step not yet applied on, it idles at the site of its previous assignment, and its broadcasts say
  so to its teammates) and back (the model's return: from the step not yet applied on, it acts on its policy's
  choice again).
- `{"kind": "instead", "task": "kind@site"}`: the person takes that task instead of the assignment: the agent acts
  on it at the step in progress when its instant has not passed, else at the next step.

A refused report changes nothing; every report, taken or refused, is logged with its reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from htlm_agent.session.core import AgentSession
from htlm_agent.session.effects import SessionEffects

KINDS = ("level", "away", "back", "instead")
"""What a person can report."""

CHANGES_KEPT = 12
"""Most lines of "what changed since the last step" the page shows."""


@dataclass
class Outcome:
    """What one report of the person did."""

    ok: bool
    """Taken (True) or refused."""
    message: str
    """What the page says: what was taken, or why it was refused (naming the bad value)."""
    effects: SessionEffects = field(default_factory=SessionEffects)
    """What the node carries out (a new action record of the step, a goal pose, the refusal counted)."""
    observation: dict[str, Any] | None = None
    """The fields of the `htlm/observation` record to publish on the agent's observation topic (a level report)."""
    log: dict[str, Any] = field(default_factory=dict)
    """The report and its verdict, a line of the person's report log (RUN/<agent>.person.jsonl)."""


def _int(value: Any) -> int | None:
    """`value` as an integer when it is one (a bool or a float with a fraction is not)."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        return int(value)
    return None


class PersonDesk:
    """The page's side of an agent a person plays: `view` and `report`, fed with the agent's session."""

    def __init__(self, session: AgentSession) -> None:
        """The desk of `session`'s agent (its run comes with the session's)."""
        self.session = session
        self.available = True
        self.reported: dict[tuple[int, int], int] = {}
        """(episode, step) -> the level the person reported."""
        self.instead: str | None = None
        """The task the person took instead for the next step (shown until the agent acts on it)."""
        self.refused = 0
        self.taken = 0
        self.changes: list[str] = []
        self._seen: tuple[int, int] | None = None
        self._last: dict[str, Any] | None = None

    # ----- the state the page shows -------------------------------------------------------------------------------
    def view(self, wall: float) -> dict[str, Any]:
        """What the person's page shows at wall-clock time `wall` (JSON-ready)."""
        se = self.session
        run, m = se.joined, se.mind
        out: dict[str, Any] = {"agent": se.name, "now": wall, "available": self.available}
        if run is None or m is None or m.episode is None:
            out["state"] = "waiting"
            out["message"] = "waiting for the team to start"
            return out
        sc, model = run.scenario, run.model
        names = list(sc.action_names)
        out["state"] = "stopped" if se.stopping else "running"
        out["run"] = run.run
        out["period"] = run.period
        out["levels"] = sc.levels
        out["sites"] = [{"name": s.name, "x": s.position[0], "y": s.position[1]} for s in sc.sites]
        p = m.pending
        step = p.t if p is not None else m.t
        action = int(p.action[0]) if p is not None else int(m.prev[0])
        out["episode"], out["step"] = m.episode, step
        out["horizon"] = sc.horizon
        open_step = self._open_step()
        out["report_open"] = open_step is not None and self.available and self._applied()
        clock = se.deploy.clock if se.deploy is not None else None
        if clock is not None and p is not None:
            out["instant"] = clock.at(m.episode, step)
            out["deadline"] = out["instant"] + se.observation_wait()
        out["assignment"] = self._action(model, names, action)
        out["instead"] = self.instead
        marg = m.marg[0]  # (p, L)
        mine = {k for k, kind in enumerate(sc.kinds) if sc.agents[run.index].capability(kind.uses) > 0}
        tasks = []
        for j, (s, k) in enumerate(sc.tasks):
            probs = [round(float(x), 3) for x in marg[j]]
            tasks.append(
                {
                    "index": j,
                    "name": names[j],
                    "site": sc.sites[s].name,
                    "kind": sc.kinds[k].name,
                    "belief": probs,
                    "likely": int(np.argmax(marg[j])),
                    "expected": round(float(np.dot(np.arange(sc.levels), marg[j])), 2),
                    "mine": k in mine,
                    "assigned": j == action,
                }
            )
        out["tasks"] = tasks
        known = m.known[0]
        out["team"] = [
            {"name": a.name, **self._action(model, names, int(known[i])), "heard": bool(m.heard[0, i])}
            for i, a in enumerate(sc.agents)
            if i != run.index
        ]
        self._note_changes(out)
        out["changes"] = list(self.changes)
        out["reports"] = {f"{e}/{t}": lv for (e, t), lv in sorted(self.reported.items())[-5:]}
        return out

    @staticmethod
    def _action(model: Any, names: list[str], action: int) -> dict[str, Any]:
        if action < 0:
            return {"action": "none", "site": "", "task": None}
        site = int(model.action_site[action])
        task = action if action < model.scenario.n_tasks else None
        return {"action": names[action], "site": model.scenario.sites[site].name, "task": task}

    def _note_changes(self, view: dict[str, Any]) -> None:
        """What changed since the last step: beliefs' likely levels and teammates' destinations (kept per step)."""
        key = (view["episode"], view["step"])
        if key == self._seen:
            return
        last, self._seen = self._last, key
        self._last = view
        if last is None or last["episode"] != view["episode"]:
            self.changes = [f"episode {view['episode']} began"] if last is not None else []
            return
        lines = []
        for old, new in zip(last["tasks"], view["tasks"], strict=True):
            if old["likely"] != new["likely"]:
                lines.append(f"{new['name']}: likely level {old['likely']} -> {new['likely']}")
        for old, new in zip(last["team"], view["team"], strict=True):
            if old["action"] != new["action"]:
                lines.append(f"{new['name']}: now at {new['action']} (was {old['action']})")
        if last["assignment"]["action"] != view["assignment"]["action"]:
            lines.append(f"you: {view['assignment']['action']} (was {last['assignment']['action']})")
        self.changes = lines[:CHANGES_KEPT] or ["nothing changed"]

    def _open_step(self) -> tuple[int, int] | None:
        """(episode, step) whose observation the agent still takes (None: none now)."""
        m = self.session.mind
        if m is None or m.episode is None or m.pending is None or m.pending.observed_at is not None:
            return None
        return m.episode, m.pending.t

    def _applied(self) -> bool:
        """Whether the instant of the step in progress has passed (its action can no longer change)."""
        se, m = self.session, self.session.mind
        if se.deploy is None or m is None or m.episode is None or m.pending is None:
            return True
        return se.deploy.applied >= se.deploy.clock.index(m.episode, m.pending.t)

    # ----- what the person reports --------------------------------------------------------------------------------
    def report(self, body: Any, now: float, wall: float) -> Outcome:
        """Check one report of the person (a decoded JSON body) at monotonic time `now`, wall-clock time `wall`,
        and turn it into its outcome."""
        out = self._report(body, now)
        out.log = {"wall": wall, "report": body, "ok": out.ok, "message": out.message}
        if out.ok:
            self.taken += 1
        else:
            self.refused += 1
            kind = body.get("kind") if isinstance(body, dict) and isinstance(body.get("kind"), str) else "report"
            out.effects.rejects.append(("person", kind if kind in KINDS else "kind", out.message))
        return out

    def _report(self, body: Any, now: float) -> Outcome:
        se = self.session
        if not isinstance(body, dict):
            return Outcome(False, f"a report is a JSON object, not {type(body).__name__}")
        kind = body.get("kind")
        if kind not in KINDS:
            return Outcome(False, f"kind {kind!r} is not a report (kinds: {', '.join(KINDS)})")
        run, m = se.joined, se.mind
        if run is None or m is None or m.episode is None or se.stopping:
            return Outcome(False, "the team is not running: nothing can be reported now")
        if kind == "away":
            return self._away(now)
        if kind == "back":
            return self._back()
        if kind == "instead":
            return self._instead(body.get("task"), now)
        return self._level(body, now)

    def _level(self, body: dict[str, Any], now: float) -> Outcome:
        se = self.session
        run, m = se.joined, se.mind
        assert run is not None and m is not None and m.episode is not None
        levels = run.scenario.levels
        level = _int(body.get("level"))
        if level is None or not 0 <= level < levels:
            return Outcome(
                False, f"level {body.get('level')!r} is out of range: levels run from 0 (done) to {levels - 1}"
            )
        e, t = _int(body.get("episode")), _int(body.get("step"))
        if e is None or t is None:
            return Outcome(False, f"episode {body.get('episode')!r}, step {body.get('step')!r}: must be integers")
        if not self.available:
            return Outcome(False, "you are marked not available: say 'I am back' before you report")
        here = self._open_step()
        cur = (m.episode, m.current)
        if here is None or (e, t) < here:
            return Outcome(False, f"episode {e} step {t} is past: the team is at episode {cur[0]} step {cur[1]}")
        if (e, t) > here or not self._applied():
            return Outcome(
                False, f"episode {e} step {t} has not begun: reports open at its instant, once its work is done"
            )
        if (e, t) in self.reported:
            return Outcome(False, f"episode {e} step {t} already has your report (level {self.reported[(e, t)]})")
        assert m.pending is not None
        action = int(m.pending.action[0])
        if not 0 <= action < run.scenario.n_tasks:
            name = run.scenario.action_names[action] if action >= 0 else "none"
            return Outcome(False, f"you are not on a task at step {t} ({name}): there is no level to report")
        self.reported[(e, t)] = level
        while len(self.reported) > 64:
            del self.reported[min(self.reported)]
        obs = {
            "agent": run.index,
            "episode": e,
            "step": t,
            "tasks": [action],
            "levels": [level],
            "acted": [run.index],
        }
        name = run.scenario.action_names[action]
        return Outcome(True, f"level {level} at {name} taken for episode {e} step {t}", observation=obs)

    def _away(self, now: float) -> Outcome:
        se, m = self.session, self.session.mind
        assert m is not None
        if not self.available:
            return Outcome(False, "you are already marked not available")
        self.available = False
        m.out = True
        m.instead = None
        self.instead = None
        out = Outcome(True, "marked not available: your agent idles and the team goes on without you")
        if not self._applied():
            se.carry("person", m.reassign(int(m.idle_action()[0])), out.effects)
        return out

    def _back(self) -> Outcome:
        se, m = self.session, self.session.mind
        assert m is not None
        if self.available:
            return Outcome(False, "you are already available")
        self.available = True
        m.out = False
        if self._applied() or m.pending is None or m.chosen is None:
            return Outcome(True, "welcome back: your agent takes a task again from the next step")
        out = Outcome(True, f"welcome back: your agent takes a task again from step {m.pending.t}")
        se.carry("person", m.reassign(m.chosen), out.effects)  # the policy's choice of the step not yet applied
        return out

    def _instead(self, task: Any, now: float) -> Outcome:
        se = self.session
        run, m = se.joined, se.mind
        assert run is not None and m is not None
        names = list(run.scenario.action_names)
        tasks = names[: run.scenario.n_tasks]
        if not isinstance(task, str) or task not in tasks:
            return Outcome(False, f"task {task!r} does not exist (tasks: {', '.join(tasks)})")
        if not self.available:
            return Outcome(False, "you are marked not available: say 'I am back' before you take a task")
        j = tasks.index(task)
        if not self._applied():
            out = Outcome(True, f"you take {task} instead, from step {m.current}")
            se.carry("person", m.reassign(j), out.effects)
            return out
        m.instead = j
        self.instead = task
        return Outcome(True, f"you take {task} instead, from step {m.current + 1}")
