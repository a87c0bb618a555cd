"""docs/ros.md holds the tables made from the code: every node's parameters (the settings dataclasses), the topics
and the record schemas. When this fails, `python -m htlm_msgs_py.docs records|topics` prints the tables to paste, and
`htlm_msgs_py.docs.params_markdown(cls)` a node's parameters."""

from __future__ import annotations

from pathlib import Path

import pytest

from htlm_agent.experiments.recording import RecordSettings
from htlm_agent.ros.settings import AgentSettings, CommanderSettings, TrainerSettings
from htlm_msgs_py.docs import params_markdown, records_markdown, topics_markdown
from htlm_world.ros.robot_settings import OperationSettings, RobotSettings
from htlm_world.ros.settings import WorldSettings

ROS_MD = Path(__file__).resolve().parents[1] / "docs" / "ros.md"


@pytest.mark.parametrize(
    "cls",
    [
        WorldSettings,
        AgentSettings,
        TrainerSettings,
        RobotSettings,
        OperationSettings,
        RecordSettings,
        CommanderSettings,
    ],
)
def test_the_parameter_tables_are_the_settings(cls: type) -> None:
    assert params_markdown(cls) in ROS_MD.read_text(), f"docs/ros.md: the table of {cls.__name__} is out of date"


@pytest.mark.parametrize("table", ["records", "topics"])
def test_the_record_and_topic_tables_are_the_schemas(table: str) -> None:
    text = records_markdown() if table == "records" else topics_markdown()
    for part in text.strip().split("\n\n"):  # docs/ros.md has prose between the tables
        assert part in ROS_MD.read_text(), f"docs/ros.md: the {table} table beginning {part[:60]!r} is out of date"


def test_every_record_version_the_documents_name_is_the_schemas() -> None:
    """Wherever README.md or docs/ name a record's version (a table's `htlm/<name>` vN, an echoed record's
    "schema":"htlm/<name>","v":N), it is the version of the schema in htlm_msgs_py.schema."""
    import re

    from htlm_msgs_py.schema import SCHEMAS

    root = ROS_MD.parents[1]
    wrong = []
    for doc in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        text = doc.read_text()
        for pattern in (r"`(htlm/[a-z_]+)` v(\d+)", r'"schema":"(htlm/[a-z_]+)","v":(\d+)'):
            for m in re.finditer(pattern, text):
                schema = SCHEMAS.get(m.group(1))
                if schema is not None and int(m.group(2)) != schema.version:
                    line = text.count("\n", 0, m.start()) + 1
                    wrong.append(f"{doc.name}:{line}: {m.group(0)} (the schema is v{schema.version})")
    assert not wrong, "\n".join(wrong)
