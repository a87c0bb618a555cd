"""What `htlm reproduce` trains: the configurations of the paper's Results section (teams, idle incentive,
reassignment penalty, HT mode, the first calibration), shared by the runs and the report."""

from __future__ import annotations

from dataclasses import dataclass

from htlm_world.scenario import REASSIGN_COSTS, Scenario, builtin, load

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

    @property
    def name(self) -> str:
        """Directory-safe name, e.g. heterogeneous_ii-on_rp-medium."""
        prefix = "" if self.base == "paper" else f"{self.base}_"
        if self.mode == "ht":
            return f"{prefix}{self.team}_ht"
        return f"{prefix}{self.team}_ii-{'on' if self.idle else 'off'}_rp-{self.reassign}"

    @property
    def label(self) -> str:
        """Human label for plots."""
        suffix = "" if self.base == "paper" else f" ({self.base})"
        if self.mode == "ht":
            return "HT Dec-POMDP" + suffix
        return f"{'R_II' if self.idle else 'no R_II'}, {self.reassign} T_RP" + suffix

    def scenario(self) -> Scenario:
        """The scenario of this configuration (docs/model.md defaults otherwise)."""
        sc = builtin(self.team, 1.0 if self.idle else 0.0, self.reassign, mode="ht" if self.mode == "ht" else "htlm")
        if self.base == "paper":
            return sc
        base = load(self.base)
        return base.replace(agents=sc.agents, team=sc.team, mode=sc.mode).with_reward(
            idle_incentive=sc.reward.idle_incentive, reassign_cost=sc.reward.reassign_cost
        )


HET = "heterogeneous"
IDLE_CONFIGS = [Config(HET, idle, rp) for rp in REASSIGN_COSTS for idle in (False, True)]
TEAM_CONFIGS = [Config(t, True, "medium") for t in TEAM_NAMES]
HT_CONFIG = Config(HET, False, "none", mode="ht")
FIRST_CONFIGS = [Config(HET, idle, "medium", base="first-calibration") for idle in (False, True)]
"""The model's first calibration, kept to show its failure mode beside the defaults."""


def all_configs() -> list[Config]:
    """Every configuration to train, without duplicates, in training order."""
    out: list[Config] = []
    for c in [*IDLE_CONFIGS, *TEAM_CONFIGS, HT_CONFIG, *FIRST_CONFIGS]:
        if c not in out:
            out.append(c)
    return out
