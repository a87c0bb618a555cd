"""What `htlm reproduce` trains: the configurations of the paper's Results section (teams, idle incentive,
reassignment penalty, HT mode, the first calibration), shared by the runs and the report."""

from __future__ import annotations

from dataclasses import dataclass

from htlm_world.scenario import REASSIGN_COSTS, Scenario, builtin, load, read_events

TEAM_NAMES = ("heterogeneous", "semi-heterogeneous", "homogeneous")


@dataclass(frozen=True)
class Config:
    """One trained configuration of the reproduction."""

    team: str
    idle: bool
    reassign: str
    mode: str = "htlm"
    base: str = "paper"
    """The shipped scenario the configuration starts from (`first-calibration`: the model's first numbers)."""
    events: str = ""
    """A stress set of the scenario whose events happen in training (resilience training); empty: none."""

    @property
    def name(self) -> str:
        """Directory-safe name, e.g. heterogeneous_ii-on_rp-medium."""
        prefix = "" if self.base == "paper" else f"{self.base}_"
        suffix = f"_ev-{self.events}" if self.events else ""
        if self.mode == "ht":
            return f"{prefix}{self.team}_ht{suffix}"
        return f"{prefix}{self.team}_ii-{'on' if self.idle else 'off'}_rp-{self.reassign}{suffix}"

    @property
    def label(self) -> str:
        """Human label for plots."""
        suffix = ("" if self.base == "paper" else f" ({self.base})") + (
            f", trained with {self.events}" if self.events else ""
        )
        if self.mode == "ht":
            return "HT Dec-POMDP" + suffix
        return f"{'R_II' if self.idle else 'no R_II'}, {self.reassign} T_RP" + suffix

    def scenario(self) -> Scenario:
        """The scenario of this configuration (docs/model.md defaults otherwise)."""
        sc = builtin(self.team, 1.0 if self.idle else 0.0, self.reassign, mode="ht" if self.mode == "ht" else "htlm")
        if self.base != "paper":
            base = load(self.base)
            sc = base.replace(agents=sc.agents, team=sc.team, mode=sc.mode).with_reward(
                idle_incentive=sc.reward.idle_incentive, reassign_cost=sc.reward.reassign_cost
            )
        return sc.with_events(read_events(self.events, sc)) if self.events else sc


HET = "heterogeneous"
IDLE_CONFIGS = [Config(HET, idle, rp) for rp in REASSIGN_COSTS for idle in (False, True)]
TEAM_CONFIGS = [Config(t, True, "medium") for t in TEAM_NAMES]
HT_CONFIG = Config(HET, False, "none", mode="ht")
FIRST_CONFIGS = [Config(HET, idle, "medium", base="first-calibration") for idle in (False, True)]
"""The model's first calibration, kept to show its failure mode beside the defaults."""
TRAINING_EVENTS = "random-events"
"""The paper scenario's stress set the resilience-trained configurations train with (not one they are tested under)."""
RESILIENCE_CONFIGS = [
    Config(HET, True, "medium", events=TRAINING_EVENTS),
    *(Config(HET, idle, "medium", base="paper-standby") for idle in (False, True)),
    Config(HET, True, "medium", base="paper-standby", events=TRAINING_EVENTS),
]
"""Beyond the paper (the unexpected): a team trained with random events, the two teams of the model that admits
surprises (hazard and standby, `paper-standby`), and a team of that model trained with random events."""
STRESS_TEAMS = [Config(HET, True, "medium"), Config(HET, False, "medium"), HT_CONFIG, *RESILIENCE_CONFIGS]
"""The teams put under the stress sets in the report's resilience section."""


def all_configs() -> list[Config]:
    """Every configuration to train, without duplicates, in training order."""
    out: list[Config] = []
    for c in [*IDLE_CONFIGS, *TEAM_CONFIGS, HT_CONFIG, *FIRST_CONFIGS, *RESILIENCE_CONFIGS]:
        if c not in out:
            out.append(c)
    return out
