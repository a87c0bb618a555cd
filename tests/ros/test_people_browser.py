"""A person in a real team, as people use it: `htlm launch deploy --person nurse` starts README's hospital over ROS 2
(simulated robots for the other agents, the robots' stand-in operation, a team key), and a real headless browser
plays the nurse through her page: it reports the true level of her task at each step, which becomes her agent's
signed observation and moves its belief; a bad report is refused on the page with its reason; "I am not available"
idles her agent and her teammates see it; "I am back" brings it back; a wrong token sees nothing
(docs/usage.md, A person in the team). With HTLM_SCREENSHOTS=DIR it saves the page's screenshot there."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import pytest
import yaml

from htlm_world.scenario import load
from support.browser import browser, free_port, wait_until

pytestmark = [pytest.mark.ros, pytest.mark.timeout(240)]

HOSPITAL = Path(__file__).resolve().parents[1] / "data" / "hospital.yaml"
PERIOD = 3.0
HORIZON = 12


def _severity(rec_file: Path) -> dict[int, list[int]]:
    """The stand-in operation's true levels of episode 0 by step, as recorded so far."""
    if not rec_file.exists():
        return {}
    try:
        got = json.loads(rec_file.read_text())
    except ValueError:
        return {}
    out = {}
    for topic, _t, text in got:
        rec = json.loads(text)
        if topic == "/htlm/severity" and rec["episode"] == 0:
            out[rec["step"]] = rec["levels"][0]
    return out


def test_the_nurse_plays_her_agent_through_her_page(launcher: Any, tmp_path: Path) -> None:
    spec = yaml.safe_load(HOSPITAL.read_text())
    scenario_file = tmp_path / "hospital.yaml"
    scenario_file.write_text(yaml.safe_dump({**spec, "horizon": HORIZON}))
    sc = load(str(scenario_file))
    names = list(sc.action_names)
    nurse = [a.name for a in sc.agents].index("nurse")
    key = tmp_path / "team.key"
    key.write_bytes(os.urandom(32).hex().encode())
    port = free_port()
    team = launcher(
        "deploy",
        "--scenario", str(scenario_file),
        "--policy", "greedy",
        "--robots", "sim",
        "--person", "nurse",
        "--period", str(PERIOD),
        "--episodes", "1",
        "--page-port", str(port),
        "--key-file", str(key),
        "--agent-param", "broadcast_timeout=0.5",
    )  # fmt: skip
    heard = tmp_path / "heard.json"
    team.helper("record_all", "--out", str(heard), "--qos", "events", "/htlm/severity", "/htlm/nurse/observation")
    address = team.wait_for(lambda: _address(team.said(), "nurse's page"), 60, "the nurse's page printed by the launch")
    chief = team.wait_for(lambda: _address(team.said(), "commander's page"), 60, "the commander's page address")
    token = address.split("token=")[1]
    assert (team.run / "people" / "nurse.token").read_text().strip() == token
    base = f"http://127.0.0.1:{port}"
    team.wait_for(lambda: "person's page of nurse" in team.log("nurse"), 60, "the nurse's agent serving her page")
    driver = browser()
    try:
        # a wrong token, or none: nothing shown
        for bad in ("/", "/?token=" + "0" * 32, f"/?token={token[:-1]}"):
            driver.get(base + bad)
            body = driver.find_element("tag name", "body").text
            assert "no access" in body and "What to do now" not in body, (bad, body)
        driver.get(address)
        step = lambda: int(driver.find_element("tag name", "body").get_attribute("data-step") or 0)  # noqa: E731
        wait_until(lambda: step() >= 1, 90, "the nurse's page showing step 1", team.said)
        reported: dict[int, int] = {}
        believed: dict[int, int] = {}
        for t in (1, 2, 3):  # the scripted person: the true level of her task, once the step's instant passed
            wait_until(lambda t=t: step() == t, 3 * PERIOD, f"the page at step {t}", team.said)
            action = driver.find_element("id", "task").get_attribute("data-action")
            truth = wait_until(lambda t=t: _severity(heard).get(t), 2 * PERIOD, f"the true levels of step {t}")
            if names.index(action) >= sc.n_tasks:
                continue  # standing by: no level to report
            level = truth[names.index(action)]
            button = wait_until(lambda level=level: _enabled(driver, f"level{level}"), PERIOD, "the report open")
            button.click()
            answer = wait_until(lambda: driver.find_element("id", "answer").text, PERIOD, "the answer to a report")
            assert f"level {level} at {action} taken for episode 0 step {t}" in answer, answer
            reported[t] = level
            # the same step again: refused on the page, with its reason (it has a report, or is over by now)
            driver.execute_script(f"send({{kind: 'level', level: {level}, episode: 0, step: {t}}})")
            wait_until(lambda t=t: _refused_again(driver.find_element("id", "answer").text, t), PERIOD,
                       "the page refusing a second report of the step")  # fmt: skip
            wait_until(lambda t=t: step() > t, 2 * PERIOD, f"the page past step {t}")  # her belief after the step
            believed[t] = int(driver.find_element("css selector", f"tr[data-task='{action}'] .likely").text)
        assert reported, "the nurse had a task to report at none of steps 1 to 3"
        # her report moved her agent's belief: after a step, the likeliest level of the task she reported is hers
        assert any(believed[t] == reported[t] for t in reported), (reported, believed)
        # a level out of range and a step long past: refused on the page, naming the bad value
        driver.execute_script("send({kind: 'level', level: 9})")
        wait_until(lambda: "level 9 is out of range" in driver.find_element("id", "answer").text, PERIOD, "refusal")
        driver.execute_script("send({kind: 'level', level: 1, episode: 0, step: 1})")
        wait_until(lambda: "step 1 is past" in driver.find_element("id", "answer").text, PERIOD, "past refusal")
        if os.environ.get("HTLM_SCREENSHOTS"):
            driver.save_screenshot(str(Path(os.environ["HTLM_SCREENSHOTS"]) / "person-page.png"))
        # not available: her agent idles from the step not yet applied on, and the page says so
        driver.find_element("id", "awaybtn").click()
        wait_until(lambda: driver.find_element("id", "away").is_displayed(), PERIOD, "the page marking her away")
        away_at = step()
        # the commander's page: her reports, her availability, the true levels; read-only, behind its own token
        boss = browser(1100, 1000)
        try:
            boss.get(chief.replace(chief.split("token=")[1], token))  # the nurse's token opens no other page
            assert "no access" in boss.find_element("tag name", "body").text
            boss.get(chief)
            shown_all = lambda: boss.find_element("tag name", "body").get_attribute("data-version")  # noqa: E731
            wait_until(shown_all, 3 * PERIOD, "the commander's page rendering a whole view (data-version set)")
            row = lambda: boss.find_element("css selector", "tr[data-agent=nurse]").text  # noqa: E731
            wait_until(lambda: "not available" in row(), 3 * PERIOD, "the commander's page showing the nurse away")
            shown = boss.find_element("id", "reports").text
            lines = shown.splitlines()
            for t, level in reported.items():
                assert any(x.startswith(f"nurse 0/{t} ") and x.endswith(f" {level}") for x in lines), shown
            wait_until(lambda: boss.find_element("id", "tasks").text.count("\n") >= sc.n_tasks - 1, PERIOD, "tasks")
            assert f"of {sc.n_tasks} tasks done" in boss.find_element("id", "progress").text
            if os.environ.get("HTLM_SCREENSHOTS"):
                boss.save_screenshot(str(Path(os.environ["HTLM_SCREENSHOTS"]) / "commander-page.png"))
        finally:
            boss.quit()
        wait_until(lambda: step() >= away_at + 3, 5 * PERIOD, "three steps while she is away")
        driver.find_element("id", "back").click()
        wait_until(lambda: not driver.find_element("id", "away").is_displayed(), PERIOD, "the page marking her back")
        back_at = step()
    finally:
        driver.quit()
    wait_until(lambda: team.popen.poll() is not None, HORIZON * PERIOD + 60, "the launch to finish", team.said)
    assert team.popen.returncode == 0, team.said()[-3000:]
    (ep,) = team.jsonl("world")
    # her reports are her agent's observations in the world's log, and went out signed
    for t, level in reported.items():
        assert ep["observations"][t - 1][nurse] == level, (t, ep["observations"])
    sent = [json.loads(x) for topic, _t, x in json.loads(heard.read_text()) if topic == "/htlm/nurse/observation"]
    assert [r["step"] for r in sent] == sorted(reported) and all("sig" in r for r in sent), sent
    # away: idle (at the site of her previous assignment) at every step after the one she left in, until the one she
    # came back in (that one idle too once its instant had passed, else her policy's choice again)
    idle = [ep["actions"][t - 1][nurse] >= sc.n_tasks for t in range(away_at + 1, back_at)]
    assert idle and all(idle), (away_at, back_at, [a[nurse] for a in ep["actions"]])
    # her teammates heard it: the tablet's own log has her idle there too (the broadcasts)
    log = [json.loads(x) for x in (team.run / "nurse.person.jsonl").read_text().splitlines()]
    kinds = [(x["report"].get("kind") if isinstance(x["report"], dict) else None, x["ok"]) for x in log]
    assert ("away", True) in kinds and ("back", True) in kinds and ("level", False) in kinds, kinds
    assert sum(ok for k, ok in kinds if k == "level") == len(reported)


def _enabled(driver: Any, button: str) -> Any:
    b = driver.find_element("id", button)
    return b if b.is_enabled() else None


def _refused_again(answer: str, t: int) -> bool:
    return f"step {t} already has your report" in answer or f"step {t} is past" in answer


def _address(said: str, whose: str) -> str | None:
    for line in said.splitlines():
        if whose in line and "token=" in line:
            return line.split(": ", 2)[-1].strip()
    return None
