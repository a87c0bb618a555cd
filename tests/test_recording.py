"""A recording (htlm_agent.experiments.recording) without DDS: messages serialized by rclpy, as the recorder node
receives them, written into a rosbag2 directory in MCAP storage, and read back with the reference MCAP reader, which
decodes every message with the schema the file holds (as Foxglove does)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import yaml
from geometry_msgs.msg import PoseStamped
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import serialize_message
from std_msgs.msg import String

from htlm_agent.experiments.recording import (
    Recording,
    RecordSettings,
    free_path,
    messages,
    recorded_topics,
    validate_record_settings,
)
from htlm_msgs_py import qos, topics


def test_every_topic_of_the_table_is_recorded_once_per_agent() -> None:
    rec = recorded_topics(["a1", "b2"])
    names = [t.name for t in rec]
    assert len(names) == len(set(names))
    per_agent = [t for t in topics.TOPICS if "<agent>" in t.name]
    assert len(rec) == len(topics.TOPICS) + len(per_agent)
    assert {"/htlm/a1/odom", "/htlm/b2/goal_pose", "/htlm/markers", "/htlm/transitions", "/diagnostics"} <= set(names)
    by = {t.name: t for t in rec}
    assert by["/htlm/scenario"].reader == qos.STATE_READER and by["/htlm/a1/weights"].reader == qos.STATE_READER
    assert by["/htlm/step"].reader == qos.EVENTS and by["/htlm/b2/odom"].reader == qos.EVENTS
    assert all(t.reader.reliability == "reliable" for t in rec)


def test_a_recording_opens_in_the_reference_mcap_reader_with_every_message(tmp_path: Path) -> None:
    rec_topics = {t.name: t for t in recorded_topics(["agent1"])}
    bag = tmp_path / "recording"
    recording = Recording(bag)
    for name in ("/htlm/step", "/htlm/agent1/goal_pose", "/htlm/markers"):
        recording.add(rec_topics[name])
    recording.add(rec_topics["/htlm/step"])  # once
    sent = []
    for i in range(5):
        text = json.dumps({"schema": "htlm/step", "step": i})
        recording.write("/htlm/step", serialize_message(String(data=text)), 1_000 + i)
        sent.append(text)
    pose = PoseStamped()
    pose.header.frame_id = "map"
    pose.pose.position.x = 12.5
    recording.write("/htlm/agent1/goal_pose", serialize_message(pose), 2_000)
    recording.close()
    assert sorted(p.name for p in bag.iterdir()) == ["metadata.yaml", "recording.mcap"]

    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert (meta["version"], meta["storage_identifier"], meta["message_count"]) == (9, "mcap", 6)
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    assert counts == {"/htlm/step": 5, "/htlm/agent1/goal_pose": 1, "/htlm/markers": 0}
    goal_qos = next(
        t for t in meta["topics_with_message_count"] if t["topic_metadata"]["name"] == "/htlm/agent1/goal_pose"
    )
    assert goal_qos["topic_metadata"]["offered_qos_profiles"][0]["durability"] == "transient_local"

    with (bag / "recording.mcap").open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        schemas = {s.name: s for s in summary.schemas.values()}
        assert set(schemas) == {
            "std_msgs/msg/String",
            "geometry_msgs/msg/PoseStamped",
            "visualization_msgs/msg/MarkerArray",
        }
        assert all(s.encoding == "ros2msg" for s in schemas.values())
        assert schemas["std_msgs/msg/String"].data.strip() == b"string data"
        assert b"MSG: std_msgs/Header" in schemas["geometry_msgs/msg/PoseStamped"].data  # dependencies included
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        got = [(c.topic, m.log_time, d) for _, c, m, d in reader.iter_decoded_messages()]
    assert [json.loads(d.data)["step"] for t, _, d in got if t == "/htlm/step"] == [0, 1, 2, 3, 4]
    (goal,) = [d for t, _, d in got if t == "/htlm/agent1/goal_pose"]
    assert (goal.header.frame_id, goal.pose.position.x) == ("map", 12.5)
    assert [m.msg.data for m in messages(bag, ["/htlm/step"])] == sent  # and rosbags reads it back the same


def test_a_restarted_recorder_starts_a_new_bag(tmp_path: Path) -> None:
    base = tmp_path / "recording"
    assert free_path(base) == base
    base.mkdir()
    (tmp_path / "recording_1").mkdir()
    assert free_path(base) == tmp_path / "recording_2"


@pytest.mark.parametrize(("field", "bad"), [("path", ""), ("agents", "agent1,2x"), ("stop_grace", 0.0)])
def test_record_settings_name_the_bad_parameter(field: str, bad: object) -> None:
    good = RecordSettings(path="x", agents="agent1,agent2")
    assert validate_record_settings(good) == []
    problems = validate_record_settings(dataclasses.replace(good, **{field: bad}))
    assert problems and problems[0].startswith(f"{field}:")


def test_htlm_show_says_what_a_recording_lacks(tmp_path: Path) -> None:
    from htlm_agent.experiments.episode_plot import EpisodeLogError, read_episode

    bag = tmp_path / "recording"
    recording = Recording(bag)
    recording.add(next(t for t in recorded_topics([]) if t.name == "/htlm/step"))
    recording.write("/htlm/step", serialize_message(String(data="{}")), 1)
    recording.close()
    with pytest.raises(EpisodeLogError, match="no run announcement"):
        read_episode(bag, 0)
