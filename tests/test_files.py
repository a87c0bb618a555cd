"""Run-directory files written while other processes read them (htlm_msgs_py.files.write_atomic): a reader sees a
whole file, old or new, never a part. Without it a trainer once read its run's learner.json empty while another
`htlm launch --only` of the team rewrote it (tests/ros/test_netns.py, beside two CPU hogs)."""

from __future__ import annotations

import multiprocessing
from pathlib import Path

from htlm_msgs_py.files import write_atomic

TEXTS = ["x" * 200_000 + "\n", "y" * 300_000 + "\n"]


def _writer(path: str, which: int, times: int) -> None:
    for _ in range(times):
        write_atomic(Path(path), TEXTS[which])


def test_readers_see_whole_files_while_two_processes_rewrite_them(tmp_path: Path) -> None:
    path = tmp_path / "parameters" / "learner.json"
    write_atomic(path, TEXTS[0])
    writers = [multiprocessing.Process(target=_writer, args=(str(path), k, 300)) for k in (0, 1)]
    for w in writers:
        w.start()
    reads = 0
    seen = set()
    while any(w.is_alive() for w in writers) or reads < 50:
        text = path.read_text()
        assert text in TEXTS, f"a torn read of {len(text)} characters"
        seen.add(text[0])
        reads += 1
    for w in writers:
        w.join()
        assert w.exitcode == 0
    assert seen == {"x", "y"}, seen  # both writers' files were read while they rewrote it
    assert sorted(p.name for p in path.parent.iterdir()) == ["learner.json"]  # no temporary file left behind


def test_a_durable_write_replaces_the_file(tmp_path: Path) -> None:
    path = write_atomic(tmp_path / "progress.json", "old", durable=True)
    write_atomic(path, "new", durable=True)
    assert path.read_text() == "new"
