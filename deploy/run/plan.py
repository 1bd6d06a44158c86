"""The run's plan: which processes a run starts, with which arguments, and who links
to whom (docs/distributed.md). Pure: nothing is started here (deploy/run/supervisor.py starts
and watches them; deploy/run/launcher.py puts the two together).

Every node listens on a unix socket of its own in the run's private directory and
connects to exactly the nodes it talks to: an agent to its plant (or bridge), the
leader iff b_i != 0, its graph neighbours both ways; the leader to the plant; every
node to the launcher, which observes.
"""

from __future__ import annotations

import os
import socket
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bridges.drivers import DEFAULT_DRIVER
from bridges.udp_can import INTERFACE as CAN_INTERFACE
from deploy.contract.fault_plan import FaultPlan
from deploy.contract.options import DEFAULT_STARTUP_TIMEOUT_S, DEFAULT_STEP_DEADLINE_S
from deploy.contract.scenario import Scenario
from deploy.contract.wire import LAUNCHER_ROLE, LEADER_ROLE, PLANT_ROLE, agent_role, bridge_role
from deploy.runtime.own_python import python_module
from deploy.runtime.plants import CAN_EMULATED
from deploy.runtime.priority import EMULATOR_PRIORITY, REALTIME_PRIORITY, world_priority

ENCODER_RATE_HZ = 100.0  # the driver emulator's encoder estimates (can-emulated)
TAIL_LINES = 15


@dataclass
class Child:
    """One process of the run: what it is, how it is started, and (once started and
    ended) what became of it."""

    role: str
    robot: int | None
    argv: list[str]
    log_path: Path
    proc: Any = None  # subprocess.Popen once started
    exit_code: int | None = None
    peak_rss_mb: float | None = None
    log: Any = None
    zenoh: bool = True  # a zenoh peer with liveliness tokens (an emulator speaks CAN only)
    links: list[str] = field(default_factory=list)  # roles it connects to (beside the launcher)
    talks_with: list[str] = field(default_factory=list)  # every role it has a link with
    stop_after_run: bool = False  # runs until stopped (an emulator): SIGTERM after the run
    killed: bool = False  # killed by the fault plan: its exit status is expected
    restarted: bool = False  # started again by the fault plan, while the fleet runs
    never_rejoined: bool = False  # restarted, and still starting when the run ended: stopped
    cpu_s: float | None = None  # its whole life's CPU time, from the kernel as it was reaped

    def tail(self, n: int = TAIL_LINES) -> str:
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(f"    {ln}" for ln in lines[-n:])


@dataclass
class LaunchOptions:
    """How a run is launched: what every node is told (scenario, fleet, clock, plant,
    deadlines, duration, rate, faults, priority, transport) and what the launcher does
    itself (where it listens, whether it records)."""

    scenario_arg: str
    plant: str
    clock: str
    out: Path
    duration_s: float | None = None
    control_rate_hz: float | None = None
    step_deadline_s: float = DEFAULT_STEP_DEADLINE_S
    startup_timeout_s: float = DEFAULT_STARTUP_TIMEOUT_S
    fleet: str | None = None  # default: the scenario's name
    endpoint: str | None = None  # where the launcher listens (default: its private socket)
    record: bool = True
    gui: bool = False  # pybullet plant: open its window
    driver: str = DEFAULT_DRIVER  # can-emulated: the drives' protocol (bridges/drivers.py)
    extra_agent_args: list[str] = field(default_factory=list)
    faults: FaultPlan | None = None  # given to every node; kills done by the launcher
    realtime_priority: int = REALTIME_PRIORITY  # nice -N for every node on the realtime clock
    # realtime: a spinner below everything on each core the run may use, while the fleet
    # runs (deploy/runtime/idle_poll.py)
    keep_cores_awake: bool = False
    # zenoh's low-latency transport on every link: off, it lost 1 in 24 messages over 64 kB
    # (a node's end-of-run report) in zenoh 1.10.2 (docs/distributed.md)
    lowlatency: bool = False
    # the per-step data as unix datagrams between the nodes of the run's directory
    # (deploy/runtime/datagrams.py); off: everything on zenoh
    datagrams: bool = True
    # a recording run: the plant (on CAN: each bridge) keeps the samples it sends and the
    # replies it hears in the run's directory for the recording
    # (deploy/runtime/wire_spool.py); off: the launcher hears them on the wire like the rest
    spool: bool = True
    # a McapRecorder made (and closed) by the caller, who adds the run's scene to it at
    # the end; None: the launcher makes its own and closes it
    recorder: Any = None
    # a leader steered from outside (path = "ros2"): the newest command as (its number,
    # [vx, vy, wz]) or None, read by the launcher's loop and passed on as ``ctl/steer``
    steering: Any = None

    def steps(self, sc: Scenario) -> int:
        return sc.steps if self.duration_s is None else int(round(self.duration_s / sc.dt))


@dataclass
class RunPlan:
    children: list[Child]
    truth_files: dict[int, Path]  # can-emulated: each emulator's ground truth, by robot


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _unstarted() -> Path:
    """The run directory of a plan drawn before the directory exists (a placeholder)."""
    return Path(tempfile.gettempdir()) / "omnifleet-unstarted"


def endpoint_of(run_dir: Path | None, role: str) -> str:
    """Where ``role`` listens: a unix socket in the run's private directory (a plan
    drawn before the directory exists names a placeholder)."""
    where = run_dir or _unstarted()
    return f"unixsock-stream/{where / f'{role}.sock'}"


def plan_run(sc: Scenario, a: LaunchOptions, launcher_endpoint: str,
             run_dir: Path | None = None) -> RunPlan:
    """The leader, the plant (or a driver emulator and a CAN bridge per robot) and
    one agent per robot, each with its arguments, log file (under ``a.out``) and links."""
    cmd = python_module("deploy.nodes")  # the node commands alone: a lighter start
    common = _common_args(sc, a, launcher_endpoint)
    out = a.out
    logs = out / "logs"
    on_can = a.plant == CAN_EMULATED
    truth: dict[int, Path] = {}
    others = _priority(a, a.realtime_priority)
    plan = [Child(LEADER_ROLE, None, [*cmd, "leader", *common, *others,
                                      *(["--plant-role", LAUNCHER_ROLE] if on_can else [])],
                  logs / "leader.log")]
    if on_can:
        plan += _can_plan(sc, a, cmd, common, out, truth, run_dir)
    else:
        plan.append(Child(PLANT_ROLE, None, [*cmd, "plant", *common, "--plant", a.plant,
                                             *_priority(a, world_priority(a.realtime_priority)),
                                             *(["--gui"] if a.gui else []),
                                             *_spool(a, run_dir)],
                          logs / "plant.log"))
    for r in sc.robot_ids:
        source = ["--plant-role", bridge_role(r)] if on_can else []
        plan.append(Child(agent_role(r), r, [*cmd, "agent", *common, *others, "--robot", str(r),
                                             *source, *a.extra_agent_args],
                          logs / f"{agent_role(r)}.log"))
    _links(sc, plan, on_can, run_dir, a.datagrams)
    return RunPlan(plan, truth)


def _spool(a: LaunchOptions, run_dir: Path | None) -> list[str]:
    """The ``--spool`` of the node that holds the robots' samples and replies."""
    return ["--spool", str(run_dir or _unstarted())] if spools(a) else []


def spools(a: LaunchOptions) -> bool:
    """Whether the plant (on CAN: each bridge) keeps its samples and the replies it hears
    for the launcher's recording, which then does not hear them on the wire."""
    return a.record and a.spool


def key_roles(sc: Scenario, plant: str) -> list[str]:
    """Every role of a run that holds keys (deploy/contract/keyring.py): the leader, the
    plant or a CAN bridge per robot, the agents, and the launcher."""
    ids = sc.robot_ids
    sources = [bridge_role(r) for r in ids] if plant == CAN_EMULATED else [PLANT_ROLE]
    return [LEADER_ROLE, *sources, *(agent_role(r) for r in ids), LAUNCHER_ROLE]


def expected_links(children: list[Child], role: str) -> set[str]:
    """The roles ``role`` has a link with (both directions), the launcher included."""
    out = {LAUNCHER_ROLE}
    for c in children:
        if c.role == role:
            out |= set(c.links)
        elif role in c.links:
            out.add(c.role)
    return out


def restart_of(dead: Child, run_dir: Path | None) -> Child:
    """The process that takes a killed one's place while the fleet runs (fault plan)."""
    argv = [*dead.argv, "--rejoin"] if dead.role.startswith("agent-") else dead.argv
    # The peers that had opened their link to the dead node do not open it again
    # (zenoh re-dials only the endpoints a session connects to, not the ones it
    # accepted on): a restarted agent 2 never heard agent 3, waited for its
    # liveliness token until the run ended and took no step. It dials them all.
    argv = [*argv, *(x for other in dead.talks_with if other not in dead.links
                     for x in ("--connect", endpoint_of(run_dir, other)))]
    return Child(dead.role, dead.robot, argv,
                 dead.log_path.with_name(f"{dead.role}.restart.log"),
                 links=dead.talks_with, talks_with=dead.talks_with, restarted=True)


def _common_args(sc: Scenario, a: LaunchOptions, endpoint: str) -> list[str]:
    # stable topic names: runs are kept apart by their private endpoints, not the name
    args = ["--scenario", a.scenario_arg, "--fleet", a.fleet or sc.name, "--clock", a.clock,
            "--connect", endpoint, "--no-gossip", "--with-recorder",
            *(["--lowlatency"] if a.lowlatency else []),
            "--step-deadline", str(a.step_deadline_s),
            "--startup-timeout", str(a.startup_timeout_s)]
    if a.duration_s is not None:
        args += ["--duration", repr(a.duration_s)]
    if a.control_rate_hz is not None:
        args += ["--control-rate", repr(a.control_rate_hz)]
    if a.faults is not None:
        args += ["--faults", str(Path(a.faults.path).resolve())]
    return args


def _priority(a: LaunchOptions, n: int) -> list[str]:
    """A realtime node's ``--priority``: ``n`` (none on the lockstep clock, or 0)."""
    return ["--priority", str(n)] if a.clock == "realtime" and n else []


def _links(sc: Scenario, plan: list[Child], on_can: bool, run_dir: Path | None,
           datagrams: bool) -> None:
    """Who connects to whom (beside the launcher): one link per pair of nodes that
    talk, opened by the later one in ``plan`` order."""
    talk: dict[str, set[str]] = {c.role: set() for c in plan if c.zenoh}

    def pair(x: str, y: str) -> None:
        talk[x].add(y)
        talk[y].add(x)

    b = sc.leader_weights
    for i, r in enumerate(sc.robot_ids):
        me = agent_role(r)
        pair(me, bridge_role(r) if on_can else PLANT_ROLE)
        if b[i] != 0.0:
            pair(me, LEADER_ROLE)
        for j, _w in sc.agent_config(i).neighbours:
            pair(me, agent_role(j))
        if on_can:  # a bridge perceives the other robots from their samples
            for j in sc.robot_ids:
                if j != r:
                    pair(bridge_role(r), bridge_role(j))
    if not on_can:
        pair(LEADER_ROLE, PLANT_ROLE)  # ticks pace the leader's batches
    order = {c.role: n for n, c in enumerate(plan)}
    for c in plan:
        if c.zenoh:
            c.links = sorted((o for o in talk[c.role] if order[o] < order[c.role]),
                             key=order.get)
            c.talks_with = sorted(talk[c.role], key=order.get)
            c.argv += ["--listen", endpoint_of(run_dir, c.role)]
            if datagrams:
                c.argv += ["--datagrams", str(run_dir or _unstarted())]
            for other in c.links:
                c.argv += ["--connect", endpoint_of(run_dir, other)]


def _can_plan(sc: Scenario, a: LaunchOptions, cmd: list[str], common: list[str], out: Path,
              truth: dict[int, Path], run_dir: Path | None) -> list[Child]:
    """One driver emulator process for the whole fleet and a bridge per robot; every
    robot on a CAN bus of its own (``omnifleet_udp``, bridges/udp_can.py: a multicast
    group and a port per robot, so robots never hear each other; python-can's
    udp_multicast does the same at several times the CPU a frame, docs/bench-history.md). One
    emulator process, not one per robot: on a
    2-core host three emulators waking at the physics rate each fell seconds behind
    the wall clock (docs/hardware.md)."""
    logs = out / "logs"
    driver = ["--driver", a.driver]
    plan, emulate = [], [*cmd, "emulate", "--scenario", a.scenario_arg, *driver,
                         "--can-interface", CAN_INTERFACE,
                         # ODrive's default encoder message rate (10 ms): half the
                         # frames of 200 Hz; odometry from the angle estimates loses
                         # nothing by it (a 30 s lab run under load: lag p99 7 ms, drift
                         # median ~1 cm, no contact; at 200 Hz the fleet was CPU-bound)
                         "--encoder-rate", repr(min(ENCODER_RATE_HZ, 1.0 / sc.dt)),
                         # physics at the control rate: RK4 at 5 ms is within 5 mm of 1 ms
                         # over 10 s of random 2 N m torques, at a fifth of the CPU
                         "--physics-rate", repr(1.0 / sc.dt),
                         # the physics must not lag the wall clock when the host is short
                         # of CPU (best effort: needs CAP_SYS_NICE, else the log says so)
                         "--priority", str(EMULATOR_PRIORITY),
                         # it runs until stopped: a launcher killed outright cannot stop it
                         "--exit-with-parent"]
    for i, r in enumerate(sc.robot_ids):
        group, port = f"239.74.{os.getpid() % 250 + 1}.{i + 1}", f"port={free_udp_port()}"
        truth[r] = out / f"truth-{r}.npz"
        emulate += ["--robot", str(r), "--can-channel", group, "--can-arg", port,
                    "--truth-out", str(truth[r])]
        plan.append(Child(bridge_role(r), r, [
            *cmd, "bridge", *common, *_priority(a, a.realtime_priority), "--robot", str(r),
            *driver, "--can-interface", CAN_INTERFACE,
            "--can-channel", group, "--can-arg", port, *_spool(a, run_dir)],
            logs / f"{bridge_role(r)}.log"))
    plan.insert(0, Child("emulator", None, [*emulate, *_can_faults(a.faults)],
                         logs / "emulator.log", zenoh=False, stop_after_run=True))
    return plan


def _can_faults(plan: FaultPlan | None) -> list[str]:
    """The fault plan's [can] section for the driver emulator: frames it loses or
    corrupts (each robot seeded apart: the emulator adds the robot's index)."""
    if plan is None or not (plan.can.frame_loss or plan.can.corrupt):
        return []
    return ["--drop-rate", repr(plan.can.frame_loss), "--corrupt-rate",
            repr(plan.can.corrupt), "--seed", str(plan.seed * 1000)]
