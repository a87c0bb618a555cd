"""The learner registry (`htlm_agent.learning.learners`): every learner by name behind one interface, the rules of its
settings with their messages, its preset, and what it says about itself instead of callers comparing names."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from htlm_agent.learning.learners import DEFAULT_LEARNER, DEFAULT_Q_LEARNER, LEARNERS, LearnerKind, learner
from htlm_agent.learning.settings import Settings
from htlm_world.scenario import builtin


def test_every_learner_is_one_object_under_its_name() -> None:
    assert list(LEARNERS) == ["paper", "tokens", "lookahead", "expert"]
    for name, kind in LEARNERS.items():
        assert isinstance(kind, LearnerKind) and kind.name == name and learner(name) is kind
    assert DEFAULT_LEARNER in LEARNERS and DEFAULT_Q_LEARNER in LEARNERS
    assert Settings().learner == "paper"  # the paper's learner is what Settings() means (the pinned digests)


def test_an_unknown_learner_names_the_value_and_the_choices() -> None:
    message = "settings.learner: 'dqn' is not one of paper, tokens, lookahead, expert"
    with pytest.raises(ValueError, match=message):
        learner("dqn")
    with pytest.raises(ValueError, match=message):
        Settings(learner="dqn")


def test_a_learners_rules_keep_their_messages() -> None:
    with pytest.raises(
        ValueError, match=re.escape("settings.imitate: 'auction' needs learner 'tokens' or 'expert', not 'paper'")
    ):
        Settings(imitate="auction")
    with pytest.raises(ValueError, match=re.escape("needs learner 'tokens' or 'expert', not 'lookahead'")):
        Settings.for_learner(learner="lookahead", imitate="greedy")
    with pytest.raises(
        ValueError, match=re.escape("settings.trainer_lag: 2: the expert-iteration learner's rounds play each")
    ):
        Settings.for_learner(learner="expert", trainer_lag=2)
    with pytest.raises(
        ValueError, match=re.escape("settings.imitate: 'qmdp': the expert-iteration learner's first round")
    ):
        Settings.for_learner(learner="expert", imitate="qmdp")
    Settings.for_learner(learner="tokens", imitate="qmdp")  # the token learner may imitate QMDP


def test_presets_start_from_the_learners_own_settings() -> None:
    assert Settings.with_preset({"episodes": 10}) == {"episodes": 10}  # no learner named: the changes alone
    assert Settings.with_preset({"learner": "paper", "episodes": 10}) == {"learner": "paper", "episodes": 10}
    tokens = Settings.for_learner(learner="tokens", episodes=1000)
    assert tokens.hidden == (32, 32) and tokens.imitate == "auction" and tokens.imitate_episodes == 500
    assert Settings.for_learner(learner="tokens").imitate_episodes == 2048
    assert Settings.for_learner(learner="lookahead").batch_size == 2048
    expert = Settings.for_learner(learner="expert", rounds=2)
    assert expert.rounds == 2 and expert.trainer_lag == 0 and expert.value_updates == 0  # DAgger: round 0's value
    with pytest.raises(ValueError, match="value_updates"):
        Settings.for_learner(learner="lookahead", value_updates=0)
    with pytest.raises(TypeError):  # a preset is read only
        LEARNERS["tokens"].preset["hidden"] = (8,)  # type: ignore[index]


def test_what_a_learner_says_about_itself() -> None:
    kinds = {name: Settings.for_learner(learner=name) for name in LEARNERS}
    assert {n: s.network for n, s in kinds.items()} == {
        "paper": "mlp",
        "tokens": "tokens",
        "lookahead": "value",
        "expert": "tokens",
    }
    assert [n for n, k in LEARNERS.items() if k.in_process_only] == ["lookahead"]
    assert [n for n, k in LEARNERS.items() if k.rounds] == ["expert"]
    assert [n for n, k in LEARNERS.items() if k.imitates] == ["tokens", "expert"]
    expert = kinds["expert"]
    assert expert.warm_baseline == "auction"
    assert Settings.for_learner(learner="expert", imitate="greedy").warm_baseline == "greedy"
    assert expert.warm_start(expert.round_batches * expert.envs - 1) and not expert.warm_start(
        expert.round_batches * expert.envs
    )
    tokens = kinds["tokens"]
    assert tokens.warm_start(tokens.imitate_episodes - 1) and not tokens.warm_start(tokens.imitate_episodes)
    assert not kinds["paper"].warm_start(0) and kinds["paper"].warm_baseline == "none"


def test_the_lookahead_refuses_to_train_over_ros() -> None:
    settings = Settings.for_learner(learner="lookahead")
    with pytest.raises(ValueError, match=re.escape("settings.learner: 'lookahead' learns in process only")):
        learner("lookahead").over_ros(builtin(), settings, 0, 1, None)


def test_reading_settings_loads_no_learner_code() -> None:
    """Every process reads `Settings` (the launcher, an agent with a built-in policy): the registry it checks them
    with loads no torch until a learner trains or acts."""
    code = (
        "import sys; from htlm_agent.learning.settings import Settings; "
        "Settings(**Settings.for_users({})); Settings.for_learner(learner='lookahead').network; "
        "assert 'torch' not in sys.modules, 'torch loaded'"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr
