"""Start a team over ROS 2 as separate OS processes: the world, the agents (one process each, or several per process
on a large team: `agents_per_process`), the trainer.

Every process gets its own parameters file and log file under the run directory, the ROS domain and discovery
settings of the launch (by default ROS_DOMAIN_ID=42 and discovery on localhost: UDP on 127.0.0.1 only, see
`ros_env`, so nothing leaves this machine), and dies with the launcher. The launcher supervises them: a process that
dies is started again after a back-off, within a limit, while the others go on (`restarts`, `RESTART_POLICY`); one
that fails where a restart cannot help stops the launch at once. Ctrl-C (SIGINT) or SIGTERM is forwarded to every
process; the launcher waits for them, kills stragglers, and its exit code says how the run ended (see `EXIT_CODES`).

Agents on other hosts: start the same launch on every host with `--only` naming the processes of that host and
`--discovery subnet` (or `--peers` with the other hosts' addresses for unicast discovery), with the same
`--domain-id` and team key. ROS-free: this module only starts processes.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from htlm_agent.learning.learners import LEARNERS
from htlm_agent.learning.settings import Settings
from htlm_msgs_py.files import write_atomic
from htlm_msgs_py.qos import FASTDDS_LOOPBACK_PROFILE, FASTDDS_PROFILE
from htlm_msgs_py.run_control import run_id_of
from htlm_world.robots import ROBOT_READY
from htlm_world.scenario import Scenario

EXIT_CODES = {
    0: "the run finished",
    1: "a process of the team failed",
    2: "bad arguments or settings",
    124: "the launch timed out",
    130: "stopped by SIGINT (Ctrl-C)",
    143: "stopped by SIGTERM",
}
"""Exit codes of `htlm launch`."""

FREE_PERIOD = 0.5
"""Step period, seconds, of the free clock of an external operation without simulated robots (`--period`)."""

PEOPLE_PERIOD = 120.0
"""Step period, seconds, of a team with people in it unless `--period` is given: a step a person can keep."""
PERSON_WAIT = 0.5
"""The share of the step period after its instant that a person has to report the level of their task."""
COMMANDER = "commander"
"""The process of the commander's page (with people in the team), and the name of its token file."""
COMMANDER_NODE = "htlm_agent.ros.commander_node"
PAGE_PORT = 8600
"""Port of the first person's page (`--page-port`)."""

RESPAWN_DELAY = 1.0
"""Default seconds before a process that died starts again (`--respawn-delay`)."""
MAX_RESTARTS = 5
"""Default restarts in a row of one process before the launcher gives up (`--max-restarts`)."""

RECORD_NODE = "htlm_agent.ros.record_node"
"""The recorder's module (`htlm launch --record`)."""

DISCOVERY = {"localhost": "LOCALHOST", "subnet": "SUBNET", "off": "OFF", "system_default": "SYSTEM_DEFAULT"}


@dataclass
class LaunchConfig:
    """One launch: the mode, the team, what to start here, and how to reach the other hosts."""

    mode: str
    """train, evaluate or deploy."""
    scenario: Scenario
    """The operation and team (the world announces it; the trainer and agents take it from the world)."""
    scenario_file: str = ""
    """Scenario YAML file passed to the world (empty: built-in with scenario.team)."""
    episodes: int = 10
    """Episodes the world runs (0: until stopped)."""
    first_episode: int = 0
    """Index of the first episode (a multiple of `batch`)."""
    batch: int = 1
    """B, episodes run at once (the learner's envs in train mode)."""
    seed: int = 0
    """Master seed."""
    run_dir: Path = Path("runs/launch")
    """Directory of this launch: logs/, parameters/, the world's and agents' logs, the trainer's store."""
    policy: str = "auto"
    """Agents' policy (agent_node parameter `policy`)."""
    checkpoint: str = ""
    """Checkpoint directory for the agents (evaluate, deploy)."""
    only: tuple[str, ...] = ()
    """Processes to start on this host (world, trainer, agent names); empty: all."""
    domain_id: int = 42
    """ROS_DOMAIN_ID of every process."""
    discovery: str = "localhost"
    """ROS_AUTOMATIC_DISCOVERY_RANGE: localhost, subnet, off or system_default."""
    peers: str = ""
    """ROS_STATIC_PEERS: semicolon-separated addresses of the other hosts (unicast discovery)."""
    key_file: str = ""
    """Team key file for message signing (HTLM_TEAM_KEY_FILE)."""
    learner: dict[str, Any] = field(default_factory=dict)
    """Learner settings of a training run (`--set`, with the learner `htlm launch` chose), after the preset of the
    learner they name (`Settings.with_preset`)."""
    world_params: dict[str, Any] = field(default_factory=dict)
    """Extra world_node parameters."""
    agent_params: dict[str, Any] = field(default_factory=dict)
    """Extra agent_node parameters (every agent)."""
    trainer_params: dict[str, Any] = field(default_factory=dict)
    """Extra trainer_node parameters."""
    timeout: float = 0.0
    """Seconds before the launch stops the team and exits 124 (0: none)."""
    grace: float = 30.0
    """Seconds the other processes get to finish after the world ended (trainer checkpoint, agents' outbox)."""
    echo: bool = True
    """Print the world's and trainer's episode lines while the team runs."""
    echo_to_stderr: bool = False
    """Print those lines on stderr instead of stdout (`htlm launch --json`: stdout holds only the summary)."""
    operation: str = "simulated"
    """simulated (the world simulates the severities) or external (the robots observe; world parameter operation)."""
    robots: str = ""
    """sim: start a simulated robot per agent and their stand-in operation (implies operation external, the free
    clock, and the agents' arrival from the robots' odometry); empty: none."""
    period: float = FREE_PERIOD
    """Step period of the free clock (external operation), seconds."""
    notes: tuple[str, ...] = ()
    """What the launch says before it starts (the step period it chose, a warning), one line each."""
    robot_params: dict[str, Any] = field(default_factory=dict)
    """Extra robot_node parameters (every simulated robot)."""
    record: bool = False
    """Start the recorder too: every topic of the team into a ROS 2 bag (MCAP storage) under run_dir/recording."""
    respawn_delay: float = RESPAWN_DELAY
    """Seconds before a process that died is started again (doubled at each restart in a row, at most
    RESPAWN_DELAY_MAX; see `restarts`)."""
    max_restarts: int = MAX_RESTARTS
    """Restarts in a row of one process before the launcher gives up on the team (0: none; a process that stayed up
    RESPAWN_STABLE seconds starts counting again)."""
    agents_per_process: int = 0
    """Most agents one process hosts (`htlm_agent.ros.agents_node`); 1: a process per agent; 0: `auto_per_process`
    of the agents this host starts and its cores."""
    cores: int = 0
    """Cores the launch counts for `auto_per_process` (0: those this process may run on)."""
    people: tuple[str, ...] = ()
    """Agents that people play (`--person`): no simulated robot; each serves its person's page."""
    page_address: str = "127.0.0.1"
    """Address the people's pages listen on (`--page-address`)."""
    page_port: int = PAGE_PORT
    """Port of the first person's page; the next people's follow (`--page-port`)."""


@dataclass
class Proc:
    """A started process."""

    name: str
    popen: subprocess.Popen[bytes]
    log: Path


def _yaml_value(v: Any) -> str:
    return json.dumps(v)  # JSON scalars are valid YAML scalars


def write_params(path: Path, params: dict[str, Any]) -> Path:
    """A ROS 2 parameters file applying `params` to any node name."""
    if not params:  # an empty mapping must be written as one: rcl refuses a bare key
        lines = ["/**:", "  ros__parameters: {}"]
    else:
        lines = ["/**:", "  ros__parameters:"] + [f"    {k}: {_yaml_value(v)}" for k, v in params.items()]
    return write_atomic(path, "\n".join(lines) + "\n")  # the team's other launchers may be reading it


def ros_env(cfg: LaunchConfig) -> dict[str, str]:
    """The environment of every process of the launch."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(cfg.domain_id)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = DISCOVERY[cfg.discovery]
    if cfg.discovery == "localhost" and "FASTRTPS_DEFAULT_PROFILES_FILE" not in env:
        # Jazzy's LOCALHOST range makes rmw_fastrtps add Fast DDS's shared-memory transport whatever the settings
        # below say; SUBNET with a profile that binds UDP to 127.0.0.1 only keeps the team on this machine without it
        # (htlm_msgs_py/fastdds_loopback.xml says why shared memory must go)
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SUBNET"
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(FASTDDS_LOOPBACK_PROFILE)
    if cfg.peers:
        env["ROS_STATIC_PEERS"] = cfg.peers
    else:
        env.pop("ROS_STATIC_PEERS", None)
    env.pop("ROS_LOCALHOST_ONLY", None)  # deprecated in Jazzy; the discovery range replaces it
    # UDP only, no Fast DDS shared-memory transport: a process killed (SIGKILL, OOM) while it writes into another's
    # shared-memory port leaves that port's interprocess mutex locked, and every later writer to it blocks for good
    # (a restarted node hangs on start). Over UDP a dead process takes nothing with it. An explicit setting wins. (With
    # the LOCALHOST range rmw_fastrtps adds shared memory anyway: localhost discovery is arranged above.)
    env.setdefault("FASTDDS_BUILTIN_TRANSPORTS", "UDPv4")
    # one thread per process for torch's (OpenMP's) kernels: a team is seven or more processes, and a second thread
    # per process only spins waiting for a core (the trainer's gradient updates took 4x as long on two cores). An
    # explicit setting wins; the trainer then uses the learner's `threads`, as `htlm train` does.
    env.setdefault("OMP_NUM_THREADS", "1")
    # participants announce themselves every 0.25 s, not 3 s: a process joining a running graph (a restarted node, a
    # viewer) matches the others within 0.4 s instead of up to 3 s (htlm_msgs_py/fastdds.xml). An explicit file wins.
    env.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(FASTDDS_PROFILE))
    if cfg.key_file:
        env["HTLM_TEAM_KEY_FILE"] = str(Path(cfg.key_file).resolve())
        env.pop("HTLM_TEAM_KEY", None)
    env["PYTHONUNBUFFERED"] = "1"
    env["RCUTILS_COLORIZED_OUTPUT"] = "0"
    return env


@dataclass(frozen=True)
class ProcessSpec:
    """One process of a team: what `htlm launch` starts and what the ROS 2 launch file (team.launch.py) hands to
    launch_ros, from the one definition `team_processes`."""

    name: str
    """Process name: world, trainer, an agent's name, operation, robot_<agent>, recorder (its log is logs/NAME.log)."""
    module: str
    """Its Python module (`python -m MODULE`), PACKAGE.ros.EXECUTABLE."""
    params: dict[str, Any]
    """Its node parameters (written to parameters/NAME.yaml)."""
    respawn: bool
    """Restart it whenever it exits with an error or is killed (deploy: the team keeps stepping on its own clock
    while it is down); else only when it was killed (`RESTART_POLICY`)."""
    respawn_delay: float = RESPAWN_DELAY
    """Seconds before it starts again (team.launch.py's `respawn_delay`; `htlm launch` doubles it at each restart in
    a row)."""
    max_restarts: int = MAX_RESTARTS
    """Restarts before the launch gives up (team.launch.py's `respawn_max_retries`; `htlm launch` counts restarts in
    a row)."""
    hosted: tuple[ProcessSpec, ...] = ()
    """A composed process (`AGENTS_NODE`, `ROBOTS_NODE`): the agents or robots it hosts, each the process it would be
    alone (its node name and parameters file are those of that process); empty: a process of one node."""

    @property
    def package(self) -> str:
        """The ROS package of its executable."""
        return self.module.split(".", 1)[0]

    @property
    def executable(self) -> str:
        """Its console script, `ros2 run PACKAGE EXECUTABLE`."""
        return self.module.rsplit(".", 1)[1]

    @property
    def node(self) -> str:
        """Its node name (a composed process has none of its own: its agents are named by `arguments`)."""
        return "" if self.hosted else f"htlm_{self.name}"

    def arguments(self, params_dir: Path) -> list[str]:
        """Its words before `--ros-args`: for a composed process every hosted agent's NODE=PARAMETERS_FILE, with
        the files `prepare` writes into `params_dir`."""
        return [f"{h.node}={params_dir / f'{h.name}.yaml'}" for h in self.hosted]

    @property
    def agents(self) -> tuple[str, ...]:
        """The agents of the process: those it hosts, or its own name for an agent's own process."""
        return tuple(h.name for h in self.hosted) if self.hosted else (self.name,)


RESPAWN_DELAY_MAX = 30.0
"""Longest back-off before a restart, seconds."""
RESPAWN_STABLE = 30.0
"""Seconds a restarted process must stay up to count as recovered: its back-off and restart count start again."""

RESTART_POLICY = {
    "deploy": "any process that exits with an error or is killed is started again; one that exits 0 has finished",
    "train": "a process killed by a signal is started again; one that exits with an error stops the launch",
    "evaluate": "a process killed by a signal is started again; one that exits with an error stops the launch",
}
"""What `htlm launch` does when a process dies before the run is over, per mode (exit code 2, a bad parameter or
store, stops every mode's launch: a restart would fail the same way)."""


def team_processes(cfg: LaunchConfig) -> list[ProcessSpec]:
    """Every process this host starts, with its parameters: the one definition `htlm launch` and team.launch.py use.

    The agents this host starts are grouped into composed processes of at most `per_process(cfg)` agents each, in
    the scenario's order (`compose`). ROS-free; it writes the learner settings file (parameters/learner.json) the
    trainer's parameters name."""
    respawn = cfg.mode == "deploy"
    specs = [
        ProcessSpec(name, module, params, respawn, cfg.respawn_delay, cfg.max_restarts)
        for name, module, params in process_specs(cfg)
    ]
    return compose(specs, per_process(cfg))


JOIN_TIMEOUT = 60.0
"""The world's `join_timeout` (seconds it waits for every agent before its first step) for a launch of few processes."""
JOIN_PER_PROCESS = 3.0
"""Seconds of the world's `join_timeout` per process the launch starts on this host, beyond JOIN_TIMEOUT: city-50 with
its 50 simulated robots (54 processes on 2 cores) took 96 s from the world's start until its last agent joined."""


AGENT_NODE = "htlm_agent.ros.agent_node"
"""An agent's own process."""
AGENTS_NODE = "htlm_agent.ros.agents_node"
"""A process hosting several agents (`htlm launch --agents-per-process`)."""
ROBOT_NODE = "htlm_world.ros.robot_node"
"""A simulated robot's own process."""
ROBOTS_NODE = "htlm_world.ros.robots_node"
"""A process hosting several simulated robots (grouped as the agents are)."""

ALONE_UP_TO = 8
"""`auto_per_process`: teams of at most this many agents (on this host) run one process per agent."""


def auto_per_process(agents: int, cores: int) -> int:
    """How many agents one process hosts by default, for the `agents` this host starts on `cores` cores.

    Up to ALONE_UP_TO agents: one each (every agent isolated, as small teams always ran). Beyond, as many processes
    as cores, each hosting its share: a process's agents run on one core (one executor thread, one interpreter), so
    `cores` processes can use every core, and every further process only adds its start-up (the imports, a DDS
    participant that every other one discovers) and its memory (docs/ros.md, A large team on one machine)."""
    if agents <= ALONE_UP_TO:
        return 1
    return math.ceil(agents / max(1, cores))


def host_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def per_process(cfg: LaunchConfig) -> int:
    """Most agents one process of this launch hosts: `cfg.agents_per_process`, or `auto_per_process` of the agents
    this host starts (`--only`) and its cores."""
    if cfg.agents_per_process > 0:
        return cfg.agents_per_process
    here = [a.name for a in cfg.scenario.agents if not cfg.only or a.name in cfg.only]
    return auto_per_process(len(here), cfg.cores or host_cores())


GROUP_NAME_MAX = 60
"""Longest name of a composed process that lists all its agents; a longer one names its first and last."""


def group_name(agents: list[str]) -> str:
    """The process name of a composed process (its log is logs/NAME.log): its agents joined by "+" ("agent1+agent2+
    agent3"), or, when that is longer than GROUP_NAME_MAX, its first and last agent and their count
    ("agent1..agent25_25": the 25 agents from agent1 to agent25 in the scenario's order)."""
    joined = "+".join(agents)
    return joined if len(joined) <= GROUP_NAME_MAX else f"{agents[0]}..{agents[-1]}_{len(agents)}"


def compose(specs: list[ProcessSpec], per: int) -> list[ProcessSpec]:
    """`specs` with their agents' processes (AGENT_NODE) grouped, in order, into composed processes (AGENTS_NODE) of
    at most `per` agents each, in the place of the first agent, and the simulated robots' (ROBOT_NODE) likewise into
    ROBOTS_NODE processes; a group of one stays a process of its own."""
    out = specs
    for single, many in ((AGENT_NODE, AGENTS_NODE), (ROBOT_NODE, ROBOTS_NODE)):
        out = _group(out, per, single, many)
    return out


def _group(specs: list[ProcessSpec], per: int, single: str, many: str) -> list[ProcessSpec]:
    """`compose` for the processes of module `single`, grouped into processes of module `many`."""
    members = [s for s in specs if s.module == single]
    if per <= 1 or len(members) <= 1:
        return specs
    out: list[ProcessSpec] = []
    for s in specs:
        if s.module != single:
            out.append(s)
        elif s is members[0]:
            for i in range(0, len(members), per):
                group = members[i : i + per]
                if len(group) == 1:
                    out.append(group[0])
                    continue
                name = group_name([g.name for g in group])
                out.append(ProcessSpec(name, many, {}, s.respawn, s.respawn_delay, s.max_restarts, tuple(group)))
    return out


def killed(rc: int) -> bool:
    """Whether exit code `rc` (Popen's returncode) is a process killed or stopped by a signal it did not send itself:
    negative (killed), or 128 + SIGINT / SIGTERM (a node stopped by a signal exits so)."""
    return rc < 0 or rc in (128 + signal.SIGINT, 128 + signal.SIGTERM)


def restarts(spec: ProcessSpec, rc: int) -> bool:
    """Whether `htlm launch` starts process `spec` again after it exited with `rc` before the run was over.

    Deploy (`respawn`): after any exit but 0 (finished) and 2 (bad parameters or store: it would fail again). Train
    and evaluate: after a kill only (`killed`): the world continues its run at the first batch it had not logged, an
    agent rejoins at the next begin, the trainer resumes from its checkpoint and store (the agents send again what it
    had not acknowledged), the recorder writes the next recording; a process that exits with an error would fail
    again, or (the trainer) train on from a state the error left, so the launch stops."""
    if rc in (0, 2):
        return False
    return spec.respawn or killed(rc)


def prepare(cfg: LaunchConfig) -> list[tuple[ProcessSpec, Path]]:
    """`team_processes` with the parameters file of each written (parameters/NAME.yaml; a composed process's holds
    the parameters of the process, none, and every hosted agent has its own file, as its own process would), and
    logs/ made."""
    (cfg.run_dir / "logs").mkdir(parents=True, exist_ok=True)
    write_tokens(cfg)
    params = cfg.run_dir / "parameters"
    out = []
    for spec in team_processes(cfg):
        for h in spec.hosted:
            write_params(params / f"{h.name}.yaml", h.params)
        out.append((spec, write_params(params / f"{spec.name}.yaml", spec.params)))
    return out


EXPERT_WEIGHTS_TIMEOUT = 3600.0
"""Seconds an agent of an expert-iteration training run waits for the weights of a step (a round's learning, between
the last step of a round and the first of the next, takes minutes on a large team; the trainer tells the world it is
alive meanwhile)."""


def in_rounds(learner: dict[str, Any]) -> bool:
    """Whether the learner settings `learner` name a learner in rounds (`LearnerKind.rounds`, the expert-iteration
    learner): its play stops after each round while it learns."""
    name = learner.get("learner")
    return isinstance(name, str) and name in LEARNERS and LEARNERS[name].rounds


def process_specs(cfg: LaunchConfig) -> list[tuple[str, str, dict[str, Any]]]:
    """(name, module, parameters) of every process this host starts."""
    run = cfg.run_dir.resolve()
    sc = cfg.scenario
    specs: list[tuple[str, str, dict[str, Any]]] = []
    # the learner of a training run (its budget the run's episodes); evaluate and deploy learn nothing
    learner = Settings.with_preset({"episodes": max(cfg.episodes, 1), **cfg.learner}) if cfg.mode == "train" else {}
    world = {
        "team": sc.team,
        "seed": cfg.seed,
        "mode": cfg.mode,
        "episodes": cfg.episodes,
        "first_episode": cfg.first_episode,
        "batch": cfg.batch,
        "run_dir": str(run),
        "run_id": run_id_of(run),
        **({"operation": "external", "clock": "free", "period": cfg.period} if deployed(cfg) else {}),
        # the agents act with the networks the learner's trainer_lag says, and the world paces its steps by it
        **({"trainer_lag": learner.get("trainer_lag", Settings().trainer_lag)} if cfg.mode == "train" else {}),
        **cfg.world_params,
    }
    if cfg.scenario_file:
        world["scenario"] = str(Path(cfg.scenario_file).resolve())
    specs.append(("world", "htlm_world.ros.world_node", world))
    # every `htlm launch --only ...` of a team sharing the run directory writes it; a trainer may be reading it
    settings_file = write_atomic(run / "parameters" / "learner.json", json.dumps(learner, indent=1) + "\n")
    specs.append(
        (
            "trainer",
            "htlm_agent.ros.trainer_node",
            {"run_dir": str(run / "trainer"), "settings_file": str(settings_file), **cfg.trainer_params},
        )
    )
    for a in sc.agents:
        params: dict[str, Any] = {"agent": a.name, "policy": cfg.policy, "run_dir": str(run)}
        if a.name in cfg.people:  # a person plays it: their page, their reports for the robot's observations
            params.update(
                {
                    "person": True,
                    "page_address": cfg.page_address,
                    "page_port": page_port(cfg, a.name),
                    "page_token_file": str(token_file(run, a.name)),
                    "observation_wait": round(PERSON_WAIT * cfg.period, 3),
                }
            )
        elif cfg.robots == "sim":  # arrival from the simulated robot's odometry
            params.update({"pose_topic": f"/htlm/{a.name}/odom", "pose_type": "odometry"})
        if in_rounds(learner):  # the first step of a round waits for the round's learning
            params["weights_timeout"] = EXPERT_WEIGHTS_TIMEOUT
        params.update(cfg.agent_params)
        if cfg.checkpoint:
            params["checkpoint"] = str(Path(cfg.checkpoint).resolve())
        specs.append((a.name, AGENT_NODE, params))
    if cfg.robots == "sim":
        specs.append(("operation", "htlm_world.ros.operation_node", {"people": ",".join(cfg.people)}))
        for a in sc.agents:
            if a.name in cfg.people:
                continue
            specs.append((f"robot_{a.name}", ROBOT_NODE, {"agent": a.name, **cfg.robot_params}))
    if cfg.people:  # the commander's page of the whole operation
        commander = {
            "people": ",".join(cfg.people),
            "page_address": cfg.page_address,
            "page_port": page_port(cfg, COMMANDER),
            "page_token_file": str(token_file(run, COMMANDER)),
        }
        specs.append((COMMANDER, COMMANDER_NODE, commander))
    if cfg.record:  # the agents are named up front: their topics are recorded from the first message on
        agents = ",".join(a.name for a in sc.agents)
        specs.append(("recorder", RECORD_NODE, {"path": str(run / "recording"), "agents": agents}))
    if cfg.only:
        specs = [s for s in specs if s[0] in cfg.only]
    if "join_timeout" not in cfg.world_params:  # the world waits as long as this host's processes take to start
        procs = len(compose([ProcessSpec(n, m, {}, False) for n, m, _ in specs], per_process(cfg)))
        for name, _, params in specs:
            if name == "world":
                params["join_timeout"] = max(JOIN_TIMEOUT, JOIN_PER_PROCESS * procs)
    return specs


def token_file(run_dir: Path, agent: str) -> Path:
    """Where the token of `agent`'s person's page is kept (RUN/people/<agent>.token)."""
    return run_dir / "people" / f"{agent}.token"


def page_port(cfg: LaunchConfig, name: str) -> int:
    """The port of a page: `page_port` for the first person's, the next people's after it, then the commander's."""
    if not cfg.page_port:
        return 0
    return cfg.page_port + (cfg.people.index(name) if name in cfg.people else len(cfg.people))


def write_tokens(cfg: LaunchConfig) -> dict[str, str]:
    """Each person's page token, made once per run directory (kept, readable by the owner only): agent -> token."""
    from htlm_agent.people.web import new_token, read_token

    out = {}
    for name in (*cfg.people, COMMANDER) if cfg.people else ():
        path = token_file(cfg.run_dir.resolve(), name)
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(new_token() + "\n")
        out[name] = read_token(path)
    return out


def page_addresses(cfg: LaunchConfig) -> dict[str, str]:
    """Each person's page and the commander's, with its token: agent (or commander) -> address to open."""
    host = "127.0.0.1" if cfg.page_address in ("0.0.0.0", "::") else cfg.page_address
    return {name: f"http://{host}:{page_port(cfg, name)}/?token={tok}" for name, tok in write_tokens(cfg).items()}


def deployed(cfg: LaunchConfig) -> bool:
    """Whether the launch deploys the team (operation external: the world simulates nothing)."""
    return cfg.operation == "external" or cfg.robots == "sim"


def _die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG: no orphans if the launcher is killed
    except (OSError, AttributeError):
        pass


def spawn(spec: ProcessSpec, params_file: Path, log: Path, env: dict[str, str], note: str = "") -> Proc:
    """Start one process of the launch, its output appended to `log` (after the line `note`, if given)."""
    name = ["-r", f"__node:={spec.node}"] if spec.node else []  # a composed process names each of its agents
    cmd = [sys.executable, "-m", spec.module, *spec.arguments(params_file.parent), "--ros-args", *name]
    cmd += ["--params-file", str(params_file)]
    with open(log, "ab") as out:
        if note:
            out.write(f"{note}\n".encode())
            out.flush()
        popen = subprocess.Popen(
            cmd,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,  # Ctrl-C reaches the launcher only; it forwards the signal in order
            preexec_fn=_die_with_parent,
        )
    return Proc(spec.name, popen, log)


def start(cfg: LaunchConfig) -> list[Proc]:
    """Start every process of the launch (world first); returns them."""
    return [slot.proc for slot in _start_slots(cfg)]


@dataclass
class _Slot:
    """A process of the launch under supervision: its current incarnation and its restarts."""

    spec: ProcessSpec
    params_file: Path
    proc: Proc
    started: float
    """When the current incarnation started (monotonic)."""
    in_a_row: int = 0
    """Restarts since it last stayed up RESPAWN_STABLE seconds."""
    total: int = 0
    """Restarts in the launch."""
    done: bool = False
    """Its current incarnation exited and was dealt with."""
    due: float | None = None
    """When it starts again (monotonic), or None."""
    last_rc: int = 0
    """Exit code of the incarnation that ended last."""

    @property
    def name(self) -> str:
        return self.spec.name


def _start_order(spec: ProcessSpec) -> int:
    """When a process starts: the recorder, then the simulated robots, then the rest of the team."""
    return 0 if spec.module == RECORD_NODE else 1 if spec.module in (ROBOT_NODE, ROBOTS_NODE) else 2


def _start_slots(cfg: LaunchConfig) -> list[_Slot]:
    logs = cfg.run_dir / "logs"
    env = ros_env(cfg)
    slots: list[_Slot] = []
    # the recorder first, and the team once it is subscribed: a run's first messages are recorded too; then the
    # robots, and the agents and the world once the robots are up, as a deployment starts (docs/ros.md): a team's
    # first steps then do not share the cores with tens of robot processes starting
    robots: list[tuple[Proc, int]] = []
    for spec, pfile in sorted(prepare(cfg), key=lambda sp: _start_order(sp[0])):
        if robots and _start_order(spec) == 2:
            end = time.monotonic() + ROBOTS_START
            for proc, count in robots:  # every robot a process hosts says it is up
                _wait_for_line(proc, ROBOT_READY, max(end - time.monotonic(), 0.0), count)
            robots = []
        proc = spawn(spec, pfile, logs / f"{spec.name}.log", env)
        slots.append(_Slot(spec, pfile, proc, time.monotonic()))
        if spec.name == "recorder":
            _wait_for_line(proc, RECORDER_READY, RECORDER_START)
        elif _start_order(spec) == 1:
            robots.append((proc, max(len(spec.hosted), 1)))
    return slots


def last_error(log: Path, since: int = 0) -> str:
    """The line of a process's log (from byte `since`) that says why it failed: the last line of its last Python
    traceback, else its last ERROR line, else its last line."""
    try:
        with open(log, "rb") as f:
            f.seek(max(since, f.seek(0, os.SEEK_END) - 65536))
            raw = [x.rstrip() for x in f.read().decode(errors="replace").splitlines()]
    except OSError:
        return ""
    lines = [x.strip() for x in raw if x.strip()]
    if not lines:
        return ""
    for i in range(len(raw) - 1, -1, -1):
        if raw[i].startswith("Traceback (most recent call last)"):
            tail = [x for x in raw[i + 1 :] if x and not x[0].isspace()]
            if tail:
                return tail[0][:500]
    errors = [x for x in lines if "[ERROR]" in x]
    return (errors[-1].split("]: ", 1)[-1] if errors else lines[-1])[:500]


RECORDER_READY = "]: recording "
"""The recorder's log line once it has subscribed to every topic (htlm_agent.ros.record_node)."""
RECORDER_START = 30.0
"""Longest `start` waits for the recorder before it starts the team anyway, seconds."""
ROBOTS_START = 120.0
"""Longest `start` waits for the simulated robots to be up (`ROBOT_READY` in each log) before it starts the agents and
the world anyway, seconds."""


def _wait_for_line(proc: Proc, text: str, timeout: float, count: int = 1) -> bool:
    """Wait until the process's log holds `text` `count` times (True), it exited or `timeout` seconds passed
    (False)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end and proc.popen.poll() is None:
        with contextlib.suppress(OSError):
            if proc.log.read_text(errors="replace").count(text) >= count:
                return True
        time.sleep(0.05)
    return False


def stop(procs: list[Proc], sig: int = signal.SIGINT, wait: float = 10.0) -> None:
    """Send `sig` to every live process, wait up to `wait` seconds, then SIGKILL what is left."""
    for p in procs:
        if p.popen.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                p.popen.send_signal(sig)
    end = time.monotonic() + wait
    while time.monotonic() < end and any(p.popen.poll() is None for p in procs):
        time.sleep(0.05)
    stuck = [p for p in procs if p.popen.poll() is None]
    if stuck and sig != signal.SIGKILL:
        for p in stuck:  # a node that ignores the signal: its stack goes to its log (faulthandler on SIGUSR1)
            print(f"htlm launch: {p.name} did not stop; its stacks are in {p.log}", flush=True, file=sys.stderr)
            with contextlib.suppress(ProcessLookupError):
                p.popen.send_signal(signal.SIGUSR1)
        time.sleep(0.3)
    for p in stuck:
        if p.popen.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                p.popen.kill()
            p.popen.wait()


class _Tail:
    """Follow a log file and print its lines that match (on stdout, or on stderr with `to_stderr`)."""

    def __init__(self, path: Path, words: tuple[str, ...], prefix: str, to_stderr: bool = False) -> None:
        self.path, self.words, self.prefix, self.pos = path, words, prefix, 0
        self.to_stderr = to_stderr

    def lines(self) -> list[str]:
        """The whole lines written since the last call."""
        try:
            with open(self.path, "rb") as f:
                f.seek(self.pos)
                data = f.read()
        except OSError:
            return []
        cut = data.rfind(b"\n") + 1
        self.pos += cut
        return data[:cut].decode(errors="replace").splitlines()

    def poll(self) -> None:
        for line in self.lines():
            if any(w in line for w in self.words):
                out = sys.stderr if self.to_stderr else sys.stdout  # looked up now: a test may replace them
                print(f"{self.prefix}{line.split(']: ', 1)[-1]}", flush=True, file=out)


class _ProgressTail(_Tail):
    """Follow the world's log and show its finished episodes as a progress line (rate, ETA, running completion)."""

    PATTERN = re.compile(r"episodes? (\d+)(?:\.\.(\d+))?: completion ([0-9.]+)(?: \(mean\))?(?:, (\d+) failed)?")
    SECONDS = re.compile(r", ([0-9.]+) s$")

    def __init__(self, path: Path, total: int, first: int, rounds: bool = False) -> None:
        """`rounds`: the learner stops the play after each round to learn (the expert-iteration learner): the
        estimate counts the play only, and says so."""
        from htlm_agent.progress import Progress

        super().__init__(path, ("episode",), "")
        self.rounds = rounds
        self.first = first
        self.bar = Progress(total, unit="ep")
        self.done = 0
        self.comp_sum = 0.0
        self.failed = 0
        self.batches = 0
        self.told = False

    def _tell(self, n: int, line: str) -> None:
        """Once, after the second batch (the first one also waits for every process to join and for the trainer's
        first updates): how long the rest of the run will take, from that batch's time."""
        from htlm_agent.progress import format_duration

        self.batches += 1
        if self.batches < 2:
            return
        self.told = True
        m = self.SECONDS.search(line.rstrip())
        if m is None:
            return
        batch_s, total = float(m.group(1)), self.bar.total
        left = (total - self.done) / n * batch_s
        print(
            f"htlm launch train: {total:,} episodes in batches of {n}, {format_duration(self.bar.elapsed)} so far; "
            f"a batch takes {batch_s:.1f} s: about {format_duration(left)} more of "
            + (
                "play, besides each round's learning (the trainer says when a round is learned)"
                if self.rounds
                else "training"
            ),
            file=sys.stderr,
            flush=True,
        )

    def poll(self) -> None:
        for line in self.lines():
            m = self.PATTERN.search(line)
            if m is None:
                continue
            lo, hi = int(m.group(1)), int(m.group(2) or m.group(1))
            n = hi - lo + 1
            self.done = hi + 1 - self.first
            self.comp_sum += float(m.group(3)) * n
            self.failed += int(m.group(4) or ("(failed)" in line))
            if not self.told:
                self._tell(n, line)
            seen = max(self.done, 1)
            self.bar.update(
                self.done, completion=f"{self.comp_sum / seen:.2f}", failed=f"{self.failed / seen:.1%}", last=m.group(3)
            )

    def close(self) -> None:
        self.bar.close()


def _say(text: str) -> None:
    print(f"htlm launch: {text}", flush=True, file=sys.stderr)


def _backoff(cfg: LaunchConfig, in_a_row: int) -> float:
    """Seconds before the restart that follows `in_a_row` restarts in a row."""
    return float(min(cfg.respawn_delay * 2**in_a_row, max(RESPAWN_DELAY_MAX, cfg.respawn_delay)))


def run_team(cfg: LaunchConfig) -> int:
    """Start the team, supervise it until it finishes, stop it cleanly; returns the exit code (EXIT_CODES).

    A process that dies before the run is over is started again when `restarts` says so, after a back-off
    (`_backoff`), at most `cfg.max_restarts` times in a row; every other process goes on meanwhile. A process that
    exits 2 (bad parameters or store) stops the launch with 2; one that fails where a restart cannot help, or past
    the limit, stops it with 1, naming the process, its exit code and the line of its log that says why."""
    got: list[int] = []

    def on_signal(signum: int, _frame: Any) -> None:
        got.append(signum)

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    slots: list[_Slot] = []
    try:
        slots = _start_slots(cfg)
        env = ros_env(cfg)
        names = ", ".join(s.name for s in slots)
        for module, what in ((AGENTS_NODE, "agents"), (ROBOTS_NODE, "robots")):
            composed = [s for s in slots if s.spec.module == module]
            if composed:
                hosted = sum(len(s.spec.hosted) for s in composed)
                names += f" ({hosted} {what} in {len(composed)} processes of at most {per_process(cfg)})"
        print(
            f"htlm launch {cfg.mode}: {names} on ROS_DOMAIN_ID={cfg.domain_id} "
            f"(discovery {cfg.discovery}{', peers ' + cfg.peers if cfg.peers else ''}); logs in {cfg.run_dir / 'logs'}",
            flush=True,
            file=sys.stderr,
        )
        tails: list[_Tail] = []
        if cfg.echo:
            for s in slots:
                if s.name == "world" and cfg.mode == "train" and cfg.episodes:
                    rounds = in_rounds(cfg.learner)
                    tails.append(_ProgressTail(s.proc.log, cfg.episodes, cfg.first_episode, rounds=rounds))
                elif s.name == "world":
                    tails.append(_Tail(s.proc.log, ("episode", "ERROR"), "[world] ", cfg.echo_to_stderr))
                elif s.name == "trainer":
                    tails.append(
                        _Tail(
                            s.proc.log, ("ERROR", "resumed", "validation", "expert:"), "[trainer] ", cfg.echo_to_stderr
                        )
                    )
        world = next((s for s in slots if s.name == "world"), None)
        start_t = time.monotonic()
        ended_at: float | None = None
        code: int | None = None
        failed: list[str] = []

        def procs() -> list[Proc]:
            return [s.proc for s in slots]

        while code is None:
            time.sleep(0.1)
            for t in tails:
                t.poll()
            if got:
                sig = got[0]
                _say(f"{signal.Signals(sig).name}: stopping the team")
                world_first = [s.proc for s in slots if s.name == "world"] + [
                    s.proc for s in slots if s.name != "world"
                ]
                stop(world_first, signal.SIGINT, wait=cfg.grace if cfg.mode == "train" else 10.0)
                code = 128 + sig
                break
            now = time.monotonic()
            for s in slots:
                if s.done:
                    continue
                rc = s.proc.popen.poll()
                if rc is None:
                    if s.in_a_row and now - s.started >= RESPAWN_STABLE:
                        s.in_a_row = 0  # recovered: the next death starts the back-off again
                    continue
                s.done, s.last_rc = True, rc
                if rc == 0:
                    if s is world and ended_at is None:
                        ended_at = now  # the world finished its run
                    continue
                if ended_at is not None:  # the run is over: no restart; a kill while it ends is no failure
                    if rc > 0:
                        failed.append(s.name)
                        _say(f"{s.name} exited with {rc}; see {s.proc.log}")
                    continue
                if rc == 2:
                    _say(
                        f"{s.name} exited with 2 (bad parameters or store): {last_error(s.proc.log)}; see {s.proc.log}"
                    )
                    code = 2
                    break
                if not restarts(s.spec, rc):
                    why = last_error(s.proc.log)
                    _say(
                        f"{s.name} exited with {rc}: {why}; in {cfg.mode} a process that fails by itself is not "
                        f"restarted: stopping the team (see {s.proc.log})"
                    )
                    code = 1
                    break
                if s.in_a_row >= cfg.max_restarts:
                    _say(
                        f"{s.name} exited with {rc} after {s.in_a_row} restarts in a row (--max-restarts "
                        f"{cfg.max_restarts}): stopping the team (see {s.proc.log})"
                    )
                    code = 1
                    break
                delay = _backoff(cfg, s.in_a_row)
                s.due = now + delay
                _say(
                    f"{s.name} exited with {rc}; restarting it in {delay:g} s "
                    f"(restart {s.in_a_row + 1} in a row of at most {cfg.max_restarts}); see {s.proc.log}"
                )
            if code is not None:
                stop(procs(), signal.SIGINT)
                break
            for s in slots:
                if s.due is None or now < s.due:
                    continue
                s.due = None
                if ended_at is not None:
                    continue
                s.in_a_row += 1
                s.total += 1
                note = f"--- htlm launch: restart {s.total} after exit {s.last_rc} ---"
                s.proc = spawn(s.spec, s.params_file, s.proc.log, env, note)
                s.started, s.done = time.monotonic(), False
                _say(f"{s.name} restarted (pid {s.proc.popen.pid}, restart {s.total} of the launch)")
            if world is None and ended_at is None and all(s.done and s.due is None for s in slots):
                ended_at = now  # no world on this host: the run is over when every process here finished
            if ended_at is not None:
                for s in slots:
                    s.due = None  # the run is over: nothing starts again
                if all(s.proc.popen.poll() is not None for s in slots):
                    code = 1 if failed else 0
                    break
                if time.monotonic() - ended_at > cfg.grace:
                    late = [s.name for s in slots if s.proc.popen.poll() is None]
                    _say(f"{', '.join(late)} still running {cfg.grace:.0f} s after the world; stopping")
                    stop(procs(), signal.SIGINT)
                    code = 1
                    break
            if cfg.timeout and time.monotonic() - start_t > cfg.timeout:
                _say(f"timeout after {cfg.timeout:.0f} s: stopping the team")
                stop(procs(), signal.SIGINT)
                code = 124
                break
        for t in tails:
            t.poll()
            if isinstance(t, _ProgressTail):
                t.close()
        restarted = {s.name: s.total for s in slots if s.total}
        if restarted:
            _say("restarts: " + ", ".join(f"{n} {k}" for n, k in restarted.items()))
        assert code is not None
        return code
    finally:
        stop([s.proc for s in slots], signal.SIGKILL, wait=1.0)  # nothing survives the launcher
        for sig_, h in old.items():
            signal.signal(sig_, h)


def summarize(run_dir: Path) -> dict[str, Any]:
    """Aggregate the world's episode log (world.jsonl) of a run directory (`reassign_before_mean`: the team's moves
    to another site before completion, per episode)."""
    f = run_dir / "world.jsonl"
    if not f.exists():
        return {"episodes": 0}
    logged = [json.loads(line)["metrics"] for line in f.read_text().splitlines() if line.strip()]
    eps = [e for e in logged if e.get("severity") != "unknown"]  # external operation without a severity source
    if not eps:
        return {"episodes": len(logged), "severity_unknown": len(logged)}
    comp = [e["completion"] for e in eps]
    batches: dict[float, list[int]] = {}  # the episodes of one batch share their absences and seconds
    for e in eps:
        batches.setdefault(e["seconds"], e["absent"])
    return {
        "episodes": len(eps),
        "completion_mean": sum(comp) / len(comp),
        "failure_rate": sum(e["failed"] for e in eps) / len(eps),
        "unused_fraction_mean": sum(e["unused_fraction"] for e in eps) / len(eps),
        "reassign_before_mean": sum(e.get("reassign_before", 0) for e in eps) / len(eps),
        "absent_agent_steps": sum(sum(a) for a in batches.values()),
        "seconds": sum(batches),
    }
