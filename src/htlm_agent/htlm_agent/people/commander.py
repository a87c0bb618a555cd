"""The commander's view of a whole operation, without ROS or the web (docs/usage.md, A person in the team): what the
commander's page shows, read-only, from the team's records: the sites on the map with their tasks' levels (as the
agents believe them, and the true ones where an outside source reports them), every agent's assignment, the people's
reports and whether each is available, and how far the mission is.

`CommanderDesk` is fed decoded-on-arrival record texts, as `htlm watch`'s `WatchState` is (it keeps one for the
run, the beliefs, the ground truth, the metrics and the nodes' /diagnostics, and checks every record the same way,
signature included), plus the agents' action records (their assignments) and the observation records of the
agents people play (their reports). `view` is the page's state.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

from htlm_agent.experiments.watch_view import WatchState
from htlm_msgs_py import schema as S
from htlm_msgs_py.signing import Signer

REPORTS_KEPT = 20
"""Most of the people's reports the page lists (the newest)."""


class CommanderDesk:
    """The commander's page state from the team's records."""

    def __init__(self, people: tuple[str, ...], signer: Signer | None = None) -> None:
        """The view of a team whose agents `people` are played by people; `signer` checks the records."""
        self.people = people
        self.state = WatchState(0, signer)
        self.assignments: dict[int, tuple[int, int, int]] = {}
        """agent -> (episode, step, action) of its newest action record."""
        self.reports: list[dict[str, Any]] = []

    def _decode(self, topic: str, text: Any, schema: S.Schema) -> dict[str, Any] | None:
        if self.state.scenario is None:
            self.state.rejected[f"{topic}/no_scenario"] += 1
            return None
        return self.state._decode(topic, text, schema)

    def on_action(self, text: Any) -> None:
        """An agent's action record: its assignment of a step (the first episode of its batch)."""
        rec = self._decode("action", text, S.ACTION)
        if rec is None:
            return
        key = (rec["episode"], rec["step"], int(rec["actions"][0]))
        if key[:2] >= self.assignments.get(rec["agent"], (-1, -1, -1))[:2]:
            self.assignments[rec["agent"]] = key

    def on_report(self, agent: str, text: Any) -> None:
        """The observation record of an agent a person plays: the person's report of a level."""
        rec = self._decode(f"{agent}/observation", text, S.OBSERVATION)
        sc = self.state.scenario
        if rec is None or sc is None:
            return
        names = sc.action_names
        task = int(rec["tasks"][0])
        entry = {
            "agent": agent,
            "episode": rec["episode"],
            "step": rec["step"],
            "task": names[task] if 0 <= task < sc.n_tasks else "none",
            "level": int(rec["levels"][0]),
        }
        self.reports = [*self.reports, entry][-REPORTS_KEPT:]

    def view(self, wall: float) -> dict[str, Any]:
        """What the commander's page shows at wall-clock time `wall` (JSON-ready)."""
        st = self.state
        sc = st.scenario
        if sc is None or st.run is None:
            return {"state": "waiting", "message": "waiting for the team's announcement", "now": wall}
        names = list(sc.action_names)
        sites = [s.name for s in sc.sites]
        truth = None
        if st.truth is not None:
            truth = {"episode": st.truth["episode"], "step": st.truth["step"], "levels": st.truth["levels"][0]}
        tasks = []
        for j, (s, k) in enumerate(sc.tasks):
            votes = Counter(b.confident[j] for b in st.beliefs.values() if j < len(b.confident))
            believed = votes.most_common(1)[0][0] if votes else None
            tasks.append(
                {
                    "name": names[j],
                    "site": sites[s],
                    "kind": sc.kinds[k].name,
                    "believed": believed,
                    "true": truth["levels"][j] if truth is not None else None,
                }
            )
        agents = []
        for i, a in enumerate(sc.agents):
            _e, t, action = self.assignments.get(i, (-1, 0, -1))
            status = st.nodes.get(f"htlm: {a.name}")
            available = None
            if a.name in self.people and status is not None:
                available = status.values.get("person_available") != "false"
            agents.append(
                {
                    "name": a.name,
                    "person": a.name in self.people,
                    "available": available,
                    "step": t,
                    "action": names[action] if 0 <= action < len(names) else "none",
                    "site": sites[sc.action_sites[action]] if 0 <= action < len(names) else "",
                    "status": status.message if status is not None else "not heard",
                }
            )
        steps = [t for _e, t, _a in self.assignments.values()]
        levels = [x["true"] if x["true"] is not None else x["believed"] for x in tasks]
        done = [lv == 0 for lv in levels if lv is not None]
        metrics = st.stats.known
        return {
            "state": "stopped" if st.run.get("state") == "stopped" else "running",
            "now": wall,
            "run": st.run["run"],
            "team": sc.name,
            "episode": max((e for e, _t, _a in self.assignments.values()), default=0),
            "step": max(steps, default=0),
            "horizon": sc.horizon,
            "levels": sc.levels,
            "sites": [{"name": s.name, "x": s.position[0], "y": s.position[1]} for s in sc.sites],
            "tasks": tasks,
            "truth": truth,
            "agents": agents,
            "reports": list(reversed(self.reports)),
            "progress": {
                "tasks_done": sum(done),
                "tasks": sc.n_tasks,
                "episodes_done": len(st.stats.metrics),
                "completion": [m["completion"] for m in metrics][-10:],
            },
        }
