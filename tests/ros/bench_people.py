"""What a person in the team costs the mission, measured (run by name; docs/usage.md, A person in the team):

    HTLM_CHECKPOINT=runs/hospital/checkpoint .venv/bin/python -m pytest -q -s -p no:cacheprovider \\
        tests/ros/bench_people.py [-k truth|away]

README's hospital deployed through `htlm launch deploy --person nurse` with every agent acting from the checkpoint
(simulated robots for the others, at a step in which a robot reaches any site), and the nurse played by a scripted
person through her page's API: `truth` reports the true level of her task (from /htlm/severity) at every step;
`away` does the same but says "I am not available" at step AWAY_AT of every episode and "I am back" at the first
step of the next. Each prints the world's completion steps and failures beside the in-process team on the same
episodes (`htlm evaluate`, and for `away` `htlm stress` with the model's dropout of the nurse at the same step), and
writes them to OUT (HTLM_PEOPLE_OUT, default a temporary directory)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pytest
import yaml

from htlm_world.robots import arrival_period
from htlm_world.scenario import load
from support.browser import free_port

pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(7200)]

HOSPITAL = Path(__file__).resolve().parents[1] / "data" / "hospital.yaml"
EPISODES = int(os.environ.get("HTLM_PEOPLE_EPISODES", "20"))
SPEED = 60.0
AWAY_AT = 3
HTLM = str(Path(sys.executable).with_name("htlm"))


def _api(base: str, token: str, body: dict[str, Any] | None = None) -> dict[str, Any]:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(
        f"{base}/api/{'state' if body is None else 'report'}", data=data, headers={"Authorization": f"Bearer {token}"}
    )
    try:
        with urllib.request.urlopen(req, timeout=5) as r:
            return dict(json.loads(r.read()))
    except urllib.error.HTTPError as e:
        return dict(json.loads(e.read()))
    except urllib.error.URLError:  # the agent's run is over and its process gone, the launch not yet
        return {"ok": False, "state": "gone"}


def _truth(path: Path) -> dict[tuple[int, int], list[int]]:
    try:
        got = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return {(r["episode"], r["step"]): r["levels"][0] for r in (json.loads(x) for _topic, _t, x in got)}


def _step(driver: Any) -> int:
    """The step a page shows (0 before it shows one)."""
    text = driver.find_element("tag name", "body").get_attribute("data-step") or ""
    return int(text) if text.isdigit() else 0


def _in_process(args: list[str]) -> dict[str, Any]:
    out = subprocess.run([HTLM, *args, "--json"], capture_output=True, text=True, check=True).stdout
    return dict(json.loads(out)) if out.strip().startswith("{") else {"rows": json.loads(out)}


@pytest.mark.parametrize("mode", ["truth", "away"])
def test_a_scripted_person_in_the_hospital(launcher: Any, tmp_path: Path, mode: str) -> None:
    ckpt = os.environ.get("HTLM_CHECKPOINT")
    if not ckpt:
        pytest.skip("HTLM_CHECKPOINT: a checkpoint of `htlm train --scenario tests/data/hospital.yaml`")
    out = Path(os.environ.get("HTLM_PEOPLE_OUT", str(tmp_path)))
    out.mkdir(parents=True, exist_ok=True)
    sc = load(str(HOSPITAL))
    names = list(sc.action_names)
    period = arrival_period(sc, SPEED)
    port = free_port()
    team = launcher(
        "deploy", "--scenario", str(HOSPITAL), "--checkpoint", ckpt, "--robots", "sim", "--person", "nurse",
        "--robot-param", f"speed={SPEED}", "--period", str(period), "--episodes", str(EPISODES),
        "--page-port", str(port), "--agent-param", "broadcast_timeout=0.3",
    )  # fmt: skip
    heard = tmp_path / "severity.json"
    team.helper("record_all", "--out", str(heard), "--qos", "events", "/htlm/severity")
    team.wait_for(lambda: "person's page of nurse" in team.log("nurse"), 120, "the nurse's page")
    token = (team.run / "people" / "nurse.token").read_text().strip()
    base = f"http://127.0.0.1:{port}"
    done: set[tuple[int, int]] = set()
    late, refused, away_steps = 0, 0, 0
    while team.popen.poll() is None:
        v = _api(base, token)
        if v.get("state") != "running":
            time.sleep(0.05)
            continue
        e, t = v["episode"], v["step"]
        if mode == "away" and v["available"] and t == AWAY_AT and (e, -1) not in done:
            done.add((e, -1))
            _api(base, token, {"kind": "away"})
        if mode == "away" and not v["available"] and (t < AWAY_AT or (e, -1) not in done):
            _api(base, token, {"kind": "back"})
        if not v["available"]:
            away_steps += (e, t, "away") not in done
            done.add((e, t, "away"))  # type: ignore[arg-type]
        task = v["assignment"]["task"]
        truth = _truth(heard).get((e, t))
        if v["report_open"] and task is not None and truth is not None and (e, t) not in done:
            done.add((e, t))
            got = _api(base, token, {"kind": "level", "episode": e, "step": t, "level": truth[task]})
            if not got["ok"]:
                refused += 1
                late += "past" in got["message"]
        time.sleep(0.05)
    assert team.popen.returncode == 0, team.said()[-3000:]
    eps = team.jsonl("world")
    assert len(eps) == EPISODES
    nurse = [a.name for a in sc.agents].index("nurse")
    reported = sum(sum(o[nurse] >= 0 for o in ep["observations"]) for ep in eps)
    completion = [ep["metrics"]["completion"] for ep in eps]
    failed = [ep["metrics"]["failed"] for ep in eps]
    common = ["--policy", ckpt, "--episodes", str(EPISODES), "--seed", "0"]
    if mode == "truth":
        ref = _in_process(["evaluate", *common, "--out", str(tmp_path / "eval")])
    else:
        events = tmp_path / "away.yaml"
        events.write_text(yaml.safe_dump([{"event": "dropout", "agent": "nurse", "at": AWAY_AT}]))
        ref = _in_process(["stress", *common, "--events", str(events), "--out", str(tmp_path / "stress")])
    result = {
        "mode": mode,
        "episodes": EPISODES,
        "period": period,
        "completion": completion,
        "completion_mean": sum(completion) / len(completion),
        "failures": sum(failed),
        "nurse_observations": reported,
        "reports_refused": refused,
        "reports_late": late,
        "nurse_steps_away": away_steps,
        "names": names,
        "in_process": ref,
    }
    (out / f"people-{mode}.json").write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k not in ("names", "in_process")}))
    print(json.dumps(ref)[:3000])


def test_the_pages_load_and_update_with_twenty_agents(launcher: Any, tmp_path: Path) -> None:
    """facility-20 (20 agents; greedy, no robots: an external operation nobody reports) with a person playing
    utility1, both pages opened in headless chromium: the time from the request to the first view shown, and how
    many steps each page showed without a reload."""
    from support.browser import browser

    out = Path(os.environ.get("HTLM_PEOPLE_OUT", str(tmp_path)))
    out.mkdir(parents=True, exist_ok=True)
    port = free_port()
    team = launcher(
        "deploy", "--scenario", "facility-20", "--policy", "greedy", "--person", "utility1", "--period", "4",
        "--episodes", "1", "--page-port", str(port),
    )  # fmt: skip
    team.wait_for(lambda: (team.run / "people" / "commander.token").exists(), 60, "the pages' tokens")
    pages = {
        "person": (port, (team.run / "people" / "utility1.token").read_text().strip()),
        "commander": (port + 1, (team.run / "people" / "commander.token").read_text().strip()),
    }
    for name, (p, token) in pages.items():  # the agent's process hosts ten agents: its log is the group's
        base = f"http://127.0.0.1:{p}"
        team.wait_for(lambda base=base, token=token: _api(base, token).get("state") == "running", 240, name)
    result: dict[str, Any] = {}
    drivers = {name: browser(412 if name == "person" else 1100) for name in pages}
    try:
        for name, (p, token) in pages.items():  # the team runs: the first load (a cold browser) is not timed
            drivers[name].get(f"http://127.0.0.1:{p}/?token={token}")
        for name, d in drivers.items():
            team.wait_for(lambda d=d: _step(d), 60, f"the {name} page showing a step")
        for name, (p, token) in pages.items():
            d = drivers[name]
            t0 = time.monotonic()
            d.get(f"http://127.0.0.1:{p}/?token={token}")
            team.wait_for(lambda d=d: _step(d), 10, f"the {name} page shown again")
            result[f"{name}_shown_s"] = round(time.monotonic() - t0, 3)
            result[f"{name}_load_ms"] = d.execute_script(
                "const t = performance.getEntriesByType('navigation')[0]; return t.loadEventEnd - t.startTime;"
            )
            d.execute_script("window.notReloaded = true;")
        first = {n: _step(d) for n, d in drivers.items()}
        team.wait_for(lambda: team.popen.poll() is not None, 300, "the end of the episode")
        for name, d in drivers.items():
            last = _step(d)
            result[f"{name}_steps_shown"] = [first[name], last]
            result[f"{name}_not_reloaded"] = bool(d.execute_script("return window.notReloaded === true;"))
    finally:
        for d in drivers.values():
            d.quit()
    (out / "people-load.json").write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))
    assert result["person_not_reloaded"] and result["commander_not_reloaded"]
