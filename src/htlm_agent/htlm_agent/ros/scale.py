"""`htlm bench scale`: what a team costs on this machine as it grows, over ROS 2 and in process.

For every team (5, 20, 50 and 100 agents by default: the shipped scenarios paper, facility-20, city-50 and
region-100) and every process layout (one process per agent, and the launcher's default, which hosts several agents
per process on a large team: `htlm launch --agents-per-process`), it runs `htlm launch evaluate` with a built-in
policy (greedy by default) for a few episodes at batch 1 with the default deadlines, and measures from the outside:

- `join_s`: seconds from the start of the team's first process to the last agent's log line that it took the run
  (every agent node made, its policy loaded, the world's announcement received); `launcher_s`, from the command to
  that first process (the launcher's own start and checks);
- `first_episode_s`: from the team's start to the world's first logged episode (discovery and one episode);
  `steady_episode_s`: the median seconds of the later episodes, as the world logs them;
- `rss_mb`, `pss_mb`: the largest total, over the run, of the agent processes' resident memory (RSS counts the
  pages the processes share in each of them, PSS shares them out), from /proc/PID/smaps_rollup every SAMPLE_S;
- `cpu_share`: the CPU seconds (utime + stime of /proc/PID/stat) of every process of the team (world, trainer,
  agents; not the launcher) during the steady episodes, over their wall seconds: the cores the team used;
- `agent_steps_per_s`: the agent-steps the agents acted in (absent ones left out) during the steady episodes, over
  their wall seconds; `absent`: the absent agent-steps of the whole run, from the world's episode log.

A layout that would start more than `--scale-max-processes` agent processes (a process per agent above 50 agents,
by default) is skipped, and the output says so; every launch has a deadline, after which it is stopped (its
process group and every process of its run directory) and the row says what did not happen. Then, in process, for
every scenario: the team step (`htlm bench`'s agent-steps/s of simulator, belief filters and rewards at a batch) and
the wall time of `htlm evaluate`'s evaluation of 500 episodes with greedy and with the auction.

Writes scale.json (everything), ros.csv, inprocess.csv and scale.png (join time, memory per agent, CPU share and
agent-steps/s against the team's size, one line per layout) into `--out`, after every run.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import math
import os
import re
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from htlm_agent.ros.launch import AGENT_NODE, AGENTS_NODE, auto_per_process, host_cores
from htlm_world.scenario import Scenario, ScenarioError, load

DEFAULT_TEAMS = {5: "paper", 20: "facility-20", 50: "city-50", 100: "region-100"}
"""The shipped scenario of each default team size."""

LAYOUTS = {"1": "a process per agent", "auto": "the launcher's default"}
"""Named process layouts (any other is N agents per process)."""

SAMPLE_S = 0.5
"""Seconds between two looks at the team's processes."""

STAMP = re.compile(r"\[(?:DEBUG|INFO|WARN|ERROR|FATAL)\] \[(\d+\.\d+)\] \[([^\]]+)\]: (.*)")
"""A line of a node's log: its time (seconds since the epoch), its node and its text."""
JOINED = re.compile(r"run \S+: agent (\S+) \(index \d+\)")
"""An agent's line that it took the run."""
EPISODE = re.compile(r"episodes? (\d+)(?:\.\.(\d+))?: completion ")
"""The world's line of a finished episode (or batch of episodes)."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Options of the scale benchmark (added to `htlm bench`)."""
    p.add_argument(
        "--scale-teams",
        default="5,20,50,100",
        help="scale: the teams, comma-separated: a size of the shipped ones (5 paper, 20 facility-20, 50 city-50, "
        "100 region-100) or a scenario (a shipped name or a file) (default 5,20,50,100)",
    )
    p.add_argument(
        "--scale-layouts",
        default="1,auto",
        help="scale: the process layouts, comma-separated: 1 (a process per agent), auto (the launcher's default) "
        "or N agents per process (default 1,auto)",
    )
    p.add_argument(
        "--scale-max-processes",
        type=int,
        default=50,
        help="scale: skip a layout that starts more agent processes than this (default 50: a process per agent up "
        "to 50 agents)",
    )
    p.add_argument("--scale-episodes", type=int, default=10, help="scale: episodes of each launch (default 10)")
    p.add_argument("--scale-policy", choices=["greedy", "auction"], default="greedy", help="scale: the agents' policy")
    p.add_argument(
        "--scale-timeout",
        type=float,
        default=0.0,
        help="scale: seconds before a launch is stopped (default 0: the world's join timeout, every step's deadlines "
        "waited out and a quarter more, and 180 s)",
    )
    p.add_argument(
        "--scale-batch", type=int, default=64, help="scale: the batch B of the in-process team step (default 64)"
    )
    p.add_argument(
        "--scale-eval-episodes",
        type=int,
        default=500,
        help="scale: episodes of the in-process evaluations with greedy and the auction (default 500; 0: none)",
    )


# --- reading the processes and the logs -----------------------------------------------------------------------------


def stat_fields(text: str) -> list[str]:
    """The fields of a /proc/PID/stat line from the third (the state) on: the command between the parentheses may
    hold spaces and parentheses of its own."""
    return text[text.rindex(")") + 2 :].split()


def cpu_seconds(stat: str, ticks: int) -> float:
    """CPU seconds (user + system) a process used, from its /proc/PID/stat line and the clock ticks per second."""
    f = stat_fields(stat)
    return (int(f[11]) + int(f[12])) / ticks  # utime, stime: fields 14 and 15


def start_ticks(stat: str) -> int:
    """When a process started, in clock ticks since the machine booted (field 22 of /proc/PID/stat)."""
    return int(stat_fields(stat)[19])


def memory_kb(smaps_rollup: str) -> tuple[int, int]:
    """(RSS, PSS) in kB from /proc/PID/smaps_rollup."""
    got = dict(re.findall(r"^(Rss|Pss):\s+(\d+) kB", smaps_rollup, re.M))
    return int(got.get("Rss", 0)), int(got.get("Pss", 0))


def join_times(logs: Iterable[str]) -> dict[str, float]:
    """When each agent took the run (its first such line), from the text of the agent processes' logs (a composed
    process's log holds the lines of all its agents)."""
    out: dict[str, float] = {}
    for text in logs:
        for line in text.splitlines():
            m = STAMP.match(line)
            j = JOINED.match(m.group(3)) if m else None
            if m and j:
                out.setdefault(j.group(1), float(m.group(1)))
    return out


def episode_ends(world_log: str) -> dict[int, float]:
    """When the world logged each finished episode (an episode of a batch: when its batch finished)."""
    out: dict[int, float] = {}
    for line in world_log.splitlines():
        m = STAMP.match(line)
        e = EPISODE.match(m.group(3)) if m else None
        if m and e:
            first = int(e.group(1))
            for k in range(first, int(e.group(2) or first) + 1):
                out[k] = float(m.group(1))
    return out


@dataclass(frozen=True)
class Episode:
    """One episode of the world's episode log (world.jsonl)."""

    index: int
    steps: int
    absent: int
    """Agent-steps the world counted absent."""
    seconds: float


def world_episodes(world_jsonl: str, horizon: int) -> list[Episode]:
    """The complete lines of the world's episode log; the episodes of a batch share their absences and seconds
    (counted once, at the batch's first episode)."""
    out, seen = [], set()
    for line in world_jsonl[: world_jsonl.rfind("\n") + 1].splitlines():
        rec = json.loads(line)
        m = rec["metrics"]
        key = (m["seconds"], tuple(m["absent"]))
        absent = 0 if key in seen else sum(m["absent"])
        seen.add(key)
        steps = len(rec.get("actions") or []) or horizon
        out.append(Episode(int(m["episode"]), steps, absent, float(m["seconds"])))
    return out


@dataclass
class Samples:
    """What the looks at a team's processes saw: the team's CPU seconds so far (a process that is gone counts with
    its last look) and the agent processes' memory, over time."""

    times: list[float] = field(default_factory=list)
    cpu: list[float] = field(default_factory=list)
    rss_kb: list[int] = field(default_factory=list)
    pss_kb: list[int] = field(default_factory=list)
    agent_processes: list[int] = field(default_factory=list)
    last_cpu: dict[int, float] = field(default_factory=dict)
    started: dict[int, float] = field(default_factory=dict)
    """Every team process seen: its start, seconds since the epoch."""

    def add(self, t: float, cpu: dict[int, float], memory: dict[int, tuple[int, int]]) -> None:
        """One look at time `t`: the CPU seconds of the team's live processes and the memory of its agent ones."""
        self.last_cpu.update(cpu)
        self.times.append(t)
        self.cpu.append(sum(self.last_cpu.values()))
        self.rss_kb.append(sum(r for r, _ in memory.values()))
        self.pss_kb.append(sum(p for _, p in memory.values()))
        self.agent_processes.append(len(memory))

    def cpu_at(self, t: float) -> float | None:
        """The team's CPU seconds at time `t`, interpolated between the looks around it (None outside them)."""
        if not self.times or t < self.times[0] or t > self.times[-1]:
            return None
        for i in range(1, len(self.times)):
            if self.times[i] >= t:
                t0, t1 = self.times[i - 1], self.times[i]
                w = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
                return self.cpu[i - 1] + w * (self.cpu[i] - self.cpu[i - 1])
        return self.cpu[-1]

    def cpu_share(self, a: float, b: float) -> float | None:
        """Cores the team used between times a and b (CPU seconds over wall seconds), None where not seen."""
        ca, cb = self.cpu_at(a), self.cpu_at(b)
        if ca is None or cb is None or b <= a:
            return None
        return (cb - ca) / (b - a)

    def peak(self) -> tuple[int, int, int]:
        """(RSS kB, PSS kB, agent processes) of the look with the most resident memory."""
        if not self.rss_kb:
            return 0, 0, 0
        i = max(range(len(self.rss_kb)), key=self.rss_kb.__getitem__)
        return self.rss_kb[i], self.pss_kb[i], self.agent_processes[i]


def team_pids(run_dir: Path, skip: int) -> dict[int, bool]:
    """The live processes of the run directory `run_dir` (it is on every team process's command line: its
    parameters files), but `skip` (the launcher): pid -> whether it is an agent process."""
    marker = str(run_dir)
    out = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == skip:
            continue
        try:
            words = [w.decode(errors="replace") for w in (d / "cmdline").read_bytes().split(b"\0")]
        except OSError:
            continue
        if any(marker in w for w in words):
            out[int(d.name)] = AGENT_NODE in words or AGENTS_NODE in words
    return out


def look(run_dir: Path, skip: int, samples: Samples, ticks: int) -> None:
    """One look at the team's processes into `samples`."""
    boot = time.time() - float(Path("/proc/uptime").read_text().split()[0])
    cpu: dict[int, float] = {}
    memory: dict[int, tuple[int, int]] = {}
    for pid, agent in team_pids(run_dir, skip).items():
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
            if stat_fields(stat)[0] == "Z":
                continue
            cpu[pid] = cpu_seconds(stat, ticks)
            samples.started.setdefault(pid, boot + start_ticks(stat) / ticks)
            if agent:
                memory[pid] = memory_kb(Path(f"/proc/{pid}/smaps_rollup").read_text())
        except (OSError, ValueError, IndexError):
            continue  # gone meanwhile
    samples.add(time.time(), cpu, memory)


# --- one launch -----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Layout:
    """A process layout of a team."""

    name: str
    """As given: 1, auto or N."""
    per: int
    """Most agents per process (resolved: auto is the launcher's rule on this machine)."""
    processes: int
    """Agent processes it starts."""

    @property
    def label(self) -> str:
        return LAYOUTS.get(self.name, f"{self.name} agents per process")


def layout(name: str, agents: int, cores: int) -> Layout:
    """The layout `name` (1, auto or N) of a team of `agents` on `cores` cores."""
    if name == "auto":
        per = auto_per_process(agents, cores)
    elif name.isdigit() and int(name) >= 1:
        per = int(name)
    else:
        raise ValueError(f"--scale-layouts: {name!r} is not 1, auto or a number of agents per process")
    per = min(per, agents)
    return Layout(name, per, math.ceil(agents / per))


def default_timeout(sc: Scenario, episodes: int) -> float:
    """Seconds a launch may take: the world's join timeout, every step of every episode waiting out its deadlines
    (the world's defaults: an absent agent costs a step at most these) and a quarter more for the world's own work,
    and 180 s for the start and the end."""
    from htlm_world.ros.settings import WorldSettings

    w = WorldSettings()
    step = w.act_deadline + w.update_deadline
    return w.join_timeout + 1.25 * episodes * (w.begin_deadline + sc.horizon * step) + 180.0


def kill_run(launcher: subprocess.Popen[bytes], run_dir: Path) -> None:
    """Stop a launch: its process group (SIGTERM, then SIGKILL), then whatever of its run directory is left (the
    team's processes run in sessions of their own)."""
    for sig, wait in ((signal.SIGTERM, 15.0), (signal.SIGKILL, 5.0)):
        if launcher.poll() is not None:
            break
        try:
            os.killpg(launcher.pid, sig)
        except ProcessLookupError:
            break
        with contextlib.suppress(subprocess.TimeoutExpired):
            launcher.wait(timeout=wait)
    for _ in range(3):
        left = team_pids(run_dir, launcher.pid)
        if not left:
            return
        for pid in left:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        time.sleep(0.5)


def launch_command(
    scenario: str, policy: str, episodes: int, per: int, domain: int, run_dir: Path, timeout: float
) -> list[str]:
    """The `htlm launch evaluate` of one run (batch 1, the default deadlines)."""
    return [
        sys.executable, "-m", "htlm_agent.cli", "launch", "evaluate", "--scenario", scenario, "--policy", policy,
        "--episodes", str(episodes), "--batch", "1", "--agents-per-process", str(per), "--domain-id", str(domain),
        "--run-dir", str(run_dir), "--timeout", f"{timeout:g}", "--json", "--quiet",
    ]  # fmt: skip


def measure(
    scenario: str,
    sc: Scenario,
    lay: Layout,
    policy: str,
    episodes: int,
    domain: int,
    where: Path,
    timeout: float,
) -> dict[str, Any]:
    """Run one launch and measure it (the module's docstring says what); never longer than `timeout` and a minute."""
    where.mkdir(parents=True, exist_ok=True)
    run_dir = (where / "run").resolve()  # on every team process's command line, as the launcher passes it on
    ticks = os.sysconf("SC_CLK_TCK")
    cmd = launch_command(scenario, policy, episodes, 0 if lay.name == "auto" else lay.per, domain, run_dir, timeout)
    samples = Samples()
    t_cmd = time.time()
    load_before = os.getloadavg()[0]
    killed = False
    with open(where / "launcher.out", "wb") as out, open(where / "launcher.err", "wb") as err:
        p = subprocess.Popen(cmd, stdout=out, stderr=err, stdin=subprocess.DEVNULL, start_new_session=True)
    try:
        end = time.monotonic() + timeout + 60.0
        while p.poll() is None:
            look(run_dir, p.pid, samples, ticks)
            if time.monotonic() > end:
                killed = True
                break
            time.sleep(SAMPLE_S)
    finally:
        kill_run(p, run_dir)
    code = p.wait()
    return result(sc, lay, policy, episodes, run_dir, where, samples, t_cmd, code, killed, timeout) | {
        "load_before": round(load_before, 2),
        "load_after": round(os.getloadavg()[0], 2),
    }


def _read(path: Path) -> str:
    return path.read_text(errors="replace") if path.exists() else ""


def result(
    sc: Scenario,
    lay: Layout,
    policy: str,
    episodes: int,
    run_dir: Path,
    where: Path,
    samples: Samples,
    t_cmd: float,
    code: int,
    killed: bool,
    timeout: float,
) -> dict[str, Any]:
    """The row of a finished (or stopped) launch, from its logs and the looks at its processes."""
    n = sc.n_agents
    logs = run_dir / "logs"
    agent_logs = (
        [_read(f) for f in sorted(logs.glob("*.log")) if f.stem not in ("world", "trainer")] if logs.exists() else []
    )
    joined = join_times(agent_logs)
    ends = episode_ends(_read(logs / "world.log"))
    eps = world_episodes(_read(run_dir / "world.jsonl"), sc.horizon)
    start = min(samples.started.values(), default=None)
    rss, pss, procs = samples.peak()
    row: dict[str, Any] = {
        "scenario": sc.name,
        "agents": n,
        "layout": lay.name,
        "layout_label": lay.label,
        "agents_per_process": lay.per,
        "agent_processes": procs or None,
        "policy": policy,
        "episodes_asked": episodes,
        "episodes": len(eps),
        "joined": len(joined),
        "launcher_s": None if start is None else round(start - t_cmd, 2),
        "join_s": None,
        "first_episode_s": None,
        "steady_episode_s": None,
        "rss_mb": round(rss / 1024) if rss else None,
        "pss_mb": round(pss / 1024) if pss else None,
        "pss_mb_per_agent": round(pss / 1024 / n, 2) if pss else None,
        "cpu_share": None,
        "agent_steps_per_s": None,
        "absent": sum(e.absent for e in eps) if eps else None,
        "exit_code": code,
        "status": "ok",
        "reason": "",
        "seconds": round(time.time() - t_cmd, 1),
    }
    if start is not None and len(joined) == n:
        row["join_s"] = round(max(joined.values()) - start, 2)
    if start is not None and 0 in ends:
        row["first_episode_s"] = round(ends[0] - start, 2)
    later = [e for e in eps if e.index > 0 and e.index in ends]
    if later:
        row["steady_episode_s"] = round(statistics.median(e.seconds for e in later), 3)
        a, b = ends.get(0), max(ends[e.index] for e in later)
    elif eps and 0 in ends:  # one episode: its own seconds
        later, a, b = eps[:1], ends[0] - eps[0].seconds, ends[0]
    else:
        a = b = None
    if a is not None and b is not None and b > a:
        share = samples.cpu_share(a, b)
        row["cpu_share"] = None if share is None else round(share, 3)
        acted = sum(n * e.steps - e.absent for e in later)
        row["agent_steps_per_s"] = round(acted / (b - a), 1)
    missing = []
    if len(joined) < n:
        missing.append(f"{len(joined)} of {n} agents took the run")
    if len(eps) < episodes:
        missing.append(f"{len(eps)} of {episodes} episodes logged")
    if killed or code == 124:
        row["status"] = "timeout"
        row["reason"] = f"stopped after the deadline of {timeout:g} s" + (f": {'; '.join(missing)}" if missing else "")
    elif code != 0 or missing:
        row["status"] = "failed"
        said = [x for x in _read(where / "launcher.err").splitlines() if x.strip()]
        row["reason"] = f"the launch exited {code}" + (f": {'; '.join(missing)}" if missing else "")
        if said:
            row["reason"] += f" (it said: {said[-1][:300]})"
    return row


# --- the benchmark --------------------------------------------------------------------------------------------------


def teams(spec: str) -> list[tuple[str, Scenario]]:
    """The teams of `--scale-teams`: (what `htlm launch --scenario` takes, the scenario)."""
    out = []
    for word in (w.strip() for w in spec.split(",") if w.strip()):
        if word.isdigit():
            if int(word) not in DEFAULT_TEAMS:
                raise SystemExit(
                    f"htlm bench scale: --scale-teams: no shipped team of {word} agents "
                    f"(sizes {', '.join(map(str, DEFAULT_TEAMS))}; or name a scenario)"
                )
            word = DEFAULT_TEAMS[int(word)]
        try:
            out.append((word, load(word)))
        except ScenarioError as e:
            raise SystemExit(f"htlm bench scale: {e}") from None
    return out


def inprocess(sc: Scenario, batch: int, seconds: float, episodes: int, say: Callable[[str], None]) -> dict[str, Any]:
    """The team step of `sc` at batch B and the wall time of an evaluation of `episodes` episodes with greedy and
    with the auction, in this process."""
    from htlm_agent.experiments.baselines import make_baseline
    from htlm_agent.experiments.speed import team_rate
    from htlm_agent.runtime.evaluate import evaluate_run

    row: dict[str, Any] = {"scenario": sc.name, "agents": sc.n_agents, "batch": batch}
    row["team_agent_steps_per_s"] = round(team_rate(batch, seconds, sc))
    say(
        f"in process {sc.name} ({sc.n_agents} agents): team step at B={batch} "
        f"{row['team_agent_steps_per_s']:,} agent-steps/s"
    )
    if episodes > 0:
        row["eval_episodes"] = episodes
        for name in ("greedy", "auction"):
            policy, s = make_baseline(name, sc)
            t0 = time.perf_counter()
            m = evaluate_run(policy, s, episodes, seed=0, policy_name=name).metrics
            wall = time.perf_counter() - t0
            row[f"{name}_eval_s"] = round(wall, 2)
            row[f"{name}_completion"] = round(m["completion"]["mean"], 2)
            row[f"{name}_failure_rate"] = round(m["completion"]["failure_rate"], 4)
            say(
                f"in process {sc.name}: {episodes} episodes of {name} in {wall:.2f} s (completion "
                f"{m['completion']['mean']:.2f}, failures {m['completion']['failure_rate']:.1%})"
            )
    return row


ROS_FIELDS = [
    "scenario", "agents", "layout", "agents_per_process", "agent_processes", "policy", "episodes", "joined",
    "launcher_s", "join_s", "first_episode_s", "steady_episode_s", "rss_mb", "pss_mb", "pss_mb_per_agent",
    "cpu_share", "agent_steps_per_s", "absent", "exit_code", "status", "reason", "seconds", "load_before",
    "load_after",
]  # fmt: skip
INPROCESS_FIELDS = [
    "scenario", "agents", "batch", "team_agent_steps_per_s", "eval_episodes", "greedy_eval_s", "greedy_completion",
    "greedy_failure_rate", "auction_eval_s", "auction_completion", "auction_failure_rate",
]  # fmt: skip


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    """Join time, memory per agent, CPU share and agent-steps/s against the team's size, one line per layout; the
    runs that were skipped or did not finish are named below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [
        ("join_s", "time to join (s)"),
        ("pss_mb_per_agent", "memory per agent (PSS, MB)"),
        ("cpu_share", "CPU share (cores)"),
        ("agent_steps_per_s", "agent-steps/s (steady episodes)"),
    ]
    sizes = sorted({r["agents"] for r in rows})
    layouts = list(dict.fromkeys(r["layout"] for r in rows))
    fig, axes = plt.subplots(2, 2, figsize=(10, 7))
    for ax, (key, title) in zip(axes.flat, panels, strict=True):
        for k, name in enumerate(layouts):
            pts = sorted((r["agents"], r[key]) for r in rows if r["layout"] == name and r.get(key) is not None)
            if pts:
                label = next(r["layout_label"] for r in rows if r["layout"] == name)
                ax.plot(
                    [x for x, _ in pts],
                    [y for _, y in pts],
                    marker="os^vD"[k % 5],
                    linestyle=["-", "--", ":", "-."][k % 4],
                    markersize=7 - k,
                    label=label,
                )
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("agents", fontsize=8)
        ax.set_xticks(sizes)
        top = max((y for line in ax.lines for y in line.get_ydata()), default=1.0)
        ax.set_ylim(0, 1.15 * float(top) or 1.0)
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=7)
    notes = [
        f"{r['scenario']}, {r['layout_label']}: {r['status']} ({r['reason']})" for r in rows if r["status"] != "ok"
    ]
    fig.suptitle("htlm launch evaluate over ROS 2 on this machine, by team size and process layout", fontsize=10)
    if notes:
        fig.text(0.01, 0.005, "\n".join(notes)[:1500], fontsize=6.5, va="bottom")
    fig.tight_layout(rect=(0, 0.03 * len(notes), 1, 1))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write(out: Path, res: dict[str, Any]) -> None:
    """scale.json, ros.csv, inprocess.csv and scale.png of the results so far."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "scale.json").write_text(json.dumps(res, indent=1) + "\n")
    for name, fields, rows in (("ros", ROS_FIELDS, res["ros"]), ("inprocess", INPROCESS_FIELDS, res["inprocess"])):
        with (out / f"{name}.csv").open("w", newline="") as f:
            w = csv.DictWriter(f, fields, extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)
    if res["ros"]:
        plot(res["ros"], out / "scale.png")


def describe(r: dict[str, Any]) -> str:
    """A run's progress line."""
    head = f"{r['scenario']} ({r['agents']} agents), {r['layout_label']}"
    if r["status"] == "skipped":
        return f"{head}: skipped: {r['reason']}"
    if r.get("same_run_as"):
        head += f" (here the same layout as {LAYOUTS.get(r['same_run_as'], r['same_run_as'])}, measured once)"

    def num(key: str, fmt: str, unit: str) -> str:
        return "-" if r.get(key) is None else f"{r[key]:{fmt}}{unit}"

    text = (
        f"{head} ({r['agent_processes'] or '?'} agent processes): joined in {num('join_s', '.1f', ' s')} "
        f"({r['joined']} of {r['agents']}), first episode at {num('first_episode_s', '.1f', ' s')}, later episodes "
        f"{num('steady_episode_s', '.2f', ' s')}, {num('agent_steps_per_s', ',.0f', ' agent-steps/s')}, CPU "
        f"{num('cpu_share', '.2f', ' cores')}, PSS {num('pss_mb', ',', ' MB')} (RSS {num('rss_mb', ',', ' MB')}), "
        f"absent agent-steps {num('absent', '', '')}"
    )
    return text if r["status"] == "ok" else f"{text}; {r['status'].upper()}: {r['reason']}"


def scale_bench(args: argparse.Namespace) -> dict[str, Any]:
    """Every ROS run (team x layout), then the in-process figures of every scenario; writes the results into
    `args.out` after each and returns them."""
    chosen = teams(str(args.scale_teams))
    names = [w.strip() for w in str(args.scale_layouts).split(",") if w.strip()]
    cores = host_cores()
    try:
        for _, sc in chosen:
            for name in names:
                layout(name, sc.n_agents, cores)
    except ValueError as e:
        raise SystemExit(f"htlm bench scale: {e}") from None
    if args.scale_episodes < 1:
        raise SystemExit("htlm bench scale: --scale-episodes must be at least 1")
    out = Path(args.out) if args.out else Path("runs") / time.strftime("bench-scale-%Y%m%d-%H%M%S")
    domain = int(getattr(args, "domain_id", 99))

    def say(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    res: dict[str, Any] = {
        "machine": {"cpu_count": os.cpu_count(), "cores": cores, "memory_mb": _memory_mb()},
        "settings": {
            "teams": [s for s, _ in chosen],
            "layouts": names,
            "policy": args.scale_policy,
            "episodes": args.scale_episodes,
            "batch": 1,
            "max_processes": args.scale_max_processes,
            "inprocess_batch": args.scale_batch,
            "eval_episodes": args.scale_eval_episodes,
            "domain_id": domain,
        },
        "ros": [],
        "inprocess": [],
    }
    say(f"htlm bench scale: results into {out}")
    for sc_name, sc in chosen:
        timeout = args.scale_timeout or default_timeout(sc, args.scale_episodes)
        done: dict[int, dict[str, Any]] = {}
        for name in names:
            lay = layout(name, sc.n_agents, cores)
            base = {"scenario": sc.name, "agents": sc.n_agents, "layout": lay.name, "layout_label": lay.label,
                    "agents_per_process": lay.per, "policy": args.scale_policy}  # fmt: skip
            if lay.per in done:
                row = {**done[lay.per], **base, "same_run_as": done[lay.per]["layout"]}
            elif lay.processes > args.scale_max_processes:
                row = {**base, "agent_processes": lay.processes, "status": "skipped",
                       "reason": f"{lay.processes} agent processes, more than --scale-max-processes "
                                 f"{args.scale_max_processes}"}  # fmt: skip
            else:
                say(f"{sc.name} ({sc.n_agents} agents), {lay.label}: {lay.processes} agent processes, "
                    f"{args.scale_episodes} episodes, deadline {timeout:.0f} s ...")  # fmt: skip
                tag = f"{sc.name}-per{lay.per}"
                row = measure(sc_name, sc, lay, args.scale_policy, args.scale_episodes, domain, out / "runs" / tag,
                              timeout)  # fmt: skip
                done[lay.per] = row
            res["ros"].append(row)
            say(describe(row))
            write(out, res)
    for _, sc in chosen:
        res["inprocess"].append(inprocess(sc, args.scale_batch, args.seconds, args.scale_eval_episodes, say))
        write(out, res)
    say(f"htlm bench scale: {out / 'scale.json'}, ros.csv, inprocess.csv, scale.png")
    return res


def _memory_mb() -> int | None:
    m = re.search(r"^MemTotal:\s+(\d+) kB", _read(Path("/proc/meminfo")), re.M)
    return round(int(m.group(1)) / 1024) if m else None
