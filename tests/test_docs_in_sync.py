"""docs/ros.md holds the tables made from the code: every node's parameters (the settings dataclasses), the topics
and the record schemas. When this fails, `python -m htlm_msgs_py.docs records|topics` prints the tables to paste, and
`htlm_msgs_py.docs.params_markdown(cls)` a node's parameters."""

from __future__ import annotations

from pathlib import Path

import pytest

from htlm_agent.experiments.recording import RecordSettings
from htlm_agent.ros.settings import AgentSettings, TrainerSettings
from htlm_msgs_py.docs import params_markdown, records_markdown, topics_markdown
from htlm_world.ros.robot_settings import OperationSettings, RobotSettings
from htlm_world.ros.settings import WorldSettings

ROS_MD = Path(__file__).resolve().parents[1] / "docs" / "ros.md"


@pytest.mark.parametrize(
    "cls", [WorldSettings, AgentSettings, TrainerSettings, RobotSettings, OperationSettings, RecordSettings]
)
def test_the_parameter_tables_are_the_settings(cls: type) -> None:
    assert params_markdown(cls) in ROS_MD.read_text(), f"docs/ros.md: the table of {cls.__name__} is out of date"


@pytest.mark.parametrize("table", ["records", "topics"])
def test_the_record_and_topic_tables_are_the_schemas(table: str) -> None:
    text = records_markdown() if table == "records" else topics_markdown()
    for part in text.strip().split("\n\n"):  # docs/ros.md has prose between the tables
        assert part in ROS_MD.read_text(), f"docs/ros.md: the {table} table beginning {part[:60]!r} is out of date"
