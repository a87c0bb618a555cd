"""Where an agent's robot is against the site of its assignment, without ROS (`ArrivalTracker`): the goal pose to
send when the site changes, whether the robot has arrived, and a log line when that changes."""

from __future__ import annotations

from htlm_agent.session.effects import SessionEffects
from htlm_msgs_py.schema import Arrival
from htlm_world.robots import site_distance
from htlm_world.scenario import Scenario


class ArrivalTracker:
    """The site of the agent's assignment and its robot's position (from its pose topic), compared: the robot has
    arrived within `radius` metres of the site. The site and the position outlive a run (the robot stays where it
    is)."""

    def __init__(self, radius: float) -> None:
        """No site and no position yet."""
        self.radius = radius
        self.scenario: Scenario | None = None
        """The scenario of the run (its sites)."""
        self.site = -1
        """The site of the assignment (-1: none yet)."""
        self.position: tuple[float, float] | None = None
        """The robot's (x, y) in the map frame, from its pose topic."""
        self.logged = Arrival.UNKNOWN
        """The arrival last logged."""

    def assign(self, site: int, out: SessionEffects) -> None:
        """The assignment's site is `site`: a goal pose (x, y) to send when it changed."""
        assert self.scenario is not None
        if site != self.site:
            self.site = site
            x, y = self.scenario.site_positions[site]
            out.goals.append((float(x), float(y)))

    def on_pose(self, x: float, y: float, out: SessionEffects) -> None:
        """The robot's position (finite, map frame): log when it reaches the site or leaves it (a change, never
        per step)."""
        self.position = (x, y)
        arrived, distance = self.arrival()
        if arrived != self.logged and arrived != Arrival.UNKNOWN:
            self.logged = arrived
            assert self.scenario is not None
            site = self.scenario.site_names[self.site]
            away = f"robot on its way to site {site} ({distance:g} m)"
            out.log.append(("info", f"robot at site {site}" if arrived == Arrival.YES else away))

    def arrival(self) -> tuple[Arrival, float]:
        """Whether the robot is at the site of its assignment and its distance (-1: unknown)."""
        if self.position is None or self.scenario is None or self.site < 0:
            return Arrival.UNKNOWN, -1.0
        d = site_distance(self.scenario, self.site, *self.position)
        return (Arrival.YES if d <= self.radius else Arrival.NO), round(d, 3)

    def values(self) -> dict[str, str]:
        """The arrival and the distance for the node's /diagnostics."""
        arrived, distance = self.arrival()
        return {"arrived": arrived.value, "distance_to_site": f"{distance:g}"}
