"""``omnifleet run``: start leader, plant and one agent process per robot on
this machine, watch them, record, and write the run's folder.

Topology (links as the graph, DESIGN §3): every node, the launcher included,
listens on a unix socket of its own in a private run directory (mode 0700: other
users' processes cannot connect) and connects to exactly the nodes it talks to —
an agent to its plant (or bridge), the leader iff b_i != 0, its graph neighbours
both ways, and the launcher; the leader to the plant; every node to the launcher,
which observes. Gossip and multicast scouting are off, so no other link forms and
two runs on one machine never see each other (the fleet name, hence every topic,
is the scenario's name). Children are started in their own session (a Ctrl-C
reaches only the launcher, which stops them in order) and get SIGTERM if the
launcher itself dies.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from deploy.contract.fault_plan import FaultPlan
from deploy.contract.options import (
    DEFAULT_COMMAND_TIMEOUT_S,
    DEFAULT_STARTUP_TIMEOUT_S,
    DEFAULT_STEP_DEADLINE_S,
)
from deploy.contract.run_secret import RUN_SECRET_ENV, control_is_genuine, new_secret, report_is_genuine
from deploy.contract.scenario import Scenario
from deploy.contract.wire import (
    LAUNCHER_ROLE,
    LEADER_ROLE,
    PLANT_ROLE,
    Codec,
    Control,
    Keys,
    NodeReport,
    StateLog,
    agent_role,
    bridge_role,
    control,
    run_roles,
)
from deploy.nodes.leader import TICK_EVERY
from deploy.run.collector import Collector
from deploy.run.kill_schedule import PAUSE, RESUME, KillSchedule
from deploy.runtime.fault_model import fault_metrics, merge_reports
from deploy.runtime.node_runtime import START_LEAD_S, StopFlag, peak_rss_kb
from deploy.runtime.priority import EMULATOR_PRIORITY, REALTIME_PRIORITY
from deploy.runtime.step_guard import CLOCK_SKEW_S
from deploy.runtime.transport import Node, zenoh_config

STOP_GRACE_S = 3.0
REJOIN_GRACE_S = 3.0  # a restarted node may exit this long after the others
# zenoh's runtime pools cut to one worker each: a node needs no more, and every
# thread is a wake-up competing for 2 cores (the hop 80 -> 60 µs p50, ping-pong)
ZENOH_RUNTIME = ("(app: (worker_threads: 1), acc: (worker_threads: 1), "
                 "tx: (worker_threads: 1), rx: (worker_threads: 1), net: (worker_threads: 1))")
ENCODER_RATE_HZ = 100.0  # the driver emulator's encoder estimates (can-emulated)
CAN_EMULATED = "can-emulated"  # every robot through a CAN bridge + driver emulator
TAIL_LINES = 15


class RunFailed(RuntimeError):
    """A child died, or the fleet never came up."""


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM reached the launcher; every child has been stopped."""

    def __init__(self, signal_name: str) -> None:
        super().__init__(signal_name)
        self.signal_name = signal_name


@dataclass
class Child:
    role: str
    robot: int | None
    argv: list[str]
    log_path: Path
    proc: subprocess.Popen | None = None
    exit_code: int | None = None
    peak_rss_mb: float | None = None
    log: Any = None
    zenoh: bool = True  # a zenoh peer with liveliness tokens (an emulator speaks CAN only)
    links: list[str] = field(default_factory=list)  # roles it connects to (beside the launcher)
    talks_with: list[str] = field(default_factory=list)  # every role it has a link with
    stop_after_run: bool = False  # runs until stopped (an emulator): SIGTERM after the run
    killed: bool = False  # killed by the fault plan: its exit status is expected
    restarted: bool = False  # started again by the fault plan, while the fleet runs

    def tail(self, n: int = TAIL_LINES) -> str:
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(f"    {ln}" for ln in lines[-n:])


@dataclass
class LaunchOptions:
    scenario_arg: str
    plant: str
    clock: str
    out: Path
    duration_s: float | None = None
    control_rate_hz: float | None = None
    step_deadline_s: float = DEFAULT_STEP_DEADLINE_S
    startup_timeout_s: float = DEFAULT_STARTUP_TIMEOUT_S
    fleet: str | None = None
    endpoint: str | None = None  # where the launcher listens (default: a free loopback port)
    record: bool = True
    gui: bool = False  # pybullet plant: open its window
    extra_agent_args: list[str] = field(default_factory=list)
    faults: FaultPlan | None = None  # given to every node; kills done by the launcher
    realtime_priority: int = REALTIME_PRIORITY  # nice -N for every node on the realtime clock
    # zenoh's low-latency transport on every link: off, it lost 1 in 24 messages over 64 kB
    # (a node's end-of-run report) in zenoh 1.10.2 (docs/distributed.md)
    lowlatency: bool = False
    # --- issue 18 hook: a McapRecorder made (and closed) by the caller, who adds the run's
    # scene to it at the end; None: the launcher makes its own and closes it
    recorder: Any = None


def agent_figures(agents: list[NodeReport | None]) -> dict[str, Any]:
    """What each robot's agent counted (metrics.json): how often its law restarted from
    the robot (a gap longer than its inputs stay fresh, a non-finite state), the
    commands it computed non-finite (zero torques sent), the realtime samples too old
    on arrival to answer. Reports that never came count as None."""
    def each(name: str) -> list[int | None]:
        return [None if r is None else int(getattr(r, name)) for r in agents]
    return {"law_resets": each("law_resets"),
            "nonfinite_commands_reported": each("nonfinite_commands"),
            "stale_samples": each("stale_samples")}


def zero_torque_figures(reports: list[NodeReport], robot_ids: list[int]) -> dict[str, Any]:
    """Each stretch a robot ran on zero torque for want of a fresh command (plant or CAN
    bridge, realtime), and per robot the longest (0 when none): the verdict compares it
    with the command timeout (deploy/report/verdict.py)."""
    spans = sorted((s for r in reports for s in r.zero_torque), key=lambda s: s[1])
    longest = {rid: 0.0 for rid in robot_ids}
    for rid, _, d in spans:
        if rid in longest:
            longest[rid] = max(longest[rid], d)
    out: dict[str, Any] = {"zero_torque_longest_s": [round(longest[r], 4) for r in robot_ids],
                           "command_timeout_s": DEFAULT_COMMAND_TIMEOUT_S}
    if spans:
        out["zero_torque"] = [{"robot": r, "t_s": round(t, 4), "duration_s": round(d, 4)}
                              for r, t, d in spans]
    return out


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _percentiles_ms(samples: list[int]) -> dict[str, float | None]:
    if not samples:
        return {"p50": None, "p99": None}
    a = np.asarray(samples, float) * 1e-6
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99))}


class Launcher:
    def __init__(self, sc: Scenario, opts: LaunchOptions) -> None:
        self.sc, self.opts = sc, opts
        # stable topic names: runs are kept apart by their private endpoints, not the name
        self.fleet = opts.fleet or sc.name
        self.keys = Keys(self.fleet)
        self.codec = Codec(sc.robot_ids)
        self.stop = StopFlag()
        self.children: list[Child] = []
        self.recorder = None
        self.invalid = 0
        self.ended = False
        self.progress_k = -1
        self.steps = sc.steps if opts.duration_s is None else int(round(opts.duration_s / sc.dt))
        self.collector = Collector(sc, self.steps)
        self.truth_files: dict[int, Path] = {}  # can-emulated: each emulator's ground truth
        self.t0_mono: float | None = None  # can-emulated: t = 0 of the run (this host's clock)
        self.run_t0: float | None = None  # realtime: t = 0 of the run (from ``ctl/start``)
        self.kills = KillSchedule(opts.faults.kills if opts.faults else ())
        self.run_dir: Path | None = None  # the private directory of the run's sockets
        self.launcher_zid = ""  # our zenoh id (links in metrics.json name it "launcher")
        self.secret = new_secret()  # the run's: only its own nodes can sign ctl/* (run_secret.py)
        self.control_refused = 0  # control messages heard whose signature did not check
        self.stopped_by: dict[str, Any] | None = None  # a genuine ctl/stop or ctl/estop
        self.misfiled = 0  # reports and state logs whose key is not their sender's
        self.forged_reports = 0  # reports of no role of the run, or not signed by its nodes
        self.tick_k = -1  # lockstep: the newest signed ctl/tick (the plant's step)
        self.collector.horizon = self._horizon

    # -- children -------------------------------------------------------------------
    def _common_args(self, endpoint: str) -> list[str]:
        o = self.opts
        args = ["--scenario", o.scenario_arg, "--fleet", self.fleet, "--clock", o.clock,
                "--connect", endpoint, "--no-gossip", "--with-recorder",
                *(["--lowlatency"] if o.lowlatency else []),
                "--step-deadline", str(o.step_deadline_s),
                "--startup-timeout", str(o.startup_timeout_s)]
        if o.duration_s is not None:
            args += ["--duration", repr(o.duration_s)]
        if o.control_rate_hz is not None:
            args += ["--control-rate", repr(o.control_rate_hz)]
        if o.faults is not None:
            args += ["--faults", str(Path(o.faults.path).resolve())]
        if o.clock == "realtime" and o.realtime_priority:
            args += ["--priority", str(o.realtime_priority)]
        return args

    def _plan(self, endpoint: str) -> list[Child]:
        cmd = [sys.executable, "-m", "deploy.cli"]
        common = self._common_args(endpoint)
        logs = self.opts.out / "logs"
        on_can = self.opts.plant == CAN_EMULATED
        plan = [Child(LEADER_ROLE, None, [*cmd, "leader", *common,
                                          *(["--plant-role", LAUNCHER_ROLE] if on_can else [])],
                      logs / "leader.log")]
        if on_can:
            plan += self._can_plan(cmd, common, logs)
        else:
            plan.append(Child(PLANT_ROLE, None, [*cmd, "plant", *common, "--plant", self.opts.plant,
                                                 *(["--gui"] if self.opts.gui else [])],
                              logs / "plant.log"))
        for r in self.sc.robot_ids:
            source = ["--plant-role", bridge_role(r)] if on_can else []
            plan.append(Child(agent_role(r), r, [*cmd, "agent", *common, "--robot", str(r),
                                                 *source, *self.opts.extra_agent_args],
                              logs / f"{agent_role(r)}.log"))
        self._links(plan)
        return plan

    def endpoint_of(self, role: str) -> str:
        """Where ``role`` listens: a unix socket in the run's private directory (made
        by :meth:`run`; a plan drawn before it names a placeholder)."""
        where = self.run_dir or Path(tempfile.gettempdir()) / "omnifleet-unstarted"
        return f"unixsock-stream/{where / f'{role}.sock'}"

    def _links(self, plan: list[Child]) -> None:
        """Who connects to whom (beside the launcher): one link per pair of nodes
        that talk, opened by the later one in ``plan`` order."""
        on_can = self.opts.plant == CAN_EMULATED
        talk: dict[str, set[str]] = {c.role: set() for c in plan if c.zenoh}

        def pair(a: str, b: str) -> None:
            talk[a].add(b)
            talk[b].add(a)

        b = self.sc.leader_weights
        for i, r in enumerate(self.sc.robot_ids):
            me = agent_role(r)
            pair(me, bridge_role(r) if on_can else PLANT_ROLE)
            if b[i] != 0.0:
                pair(me, LEADER_ROLE)
            for j, _w in self.sc.agent_config(i).neighbours:
                pair(me, agent_role(j))
            if on_can:  # a bridge perceives the other robots from their samples
                for j in self.sc.robot_ids:
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
                c.argv += ["--listen", self.endpoint_of(c.role)]
                for other in c.links:
                    c.argv += ["--connect", self.endpoint_of(other)]

    def expected_links(self, role: str) -> set[str]:
        """The roles ``role`` has a link with (both directions), the launcher included."""
        out = {LAUNCHER_ROLE}
        for c in self.children:
            if c.role == role:
                out |= set(c.links)
            elif role in c.links:
                out.add(c.role)
        return out

    def _can_plan(self, cmd: list[str], common: list[str], logs: Path) -> list[Child]:
        """One driver emulator process for the whole fleet and a bridge per robot;
        every robot on a CAN bus of its own (udp_multicast: a group and a port per
        robot, so robots never hear each other). One emulator process, not one per
        robot: on a 2-core host three emulators waking at the physics rate each
        fell seconds behind the wall clock (docs/hardware.md)."""
        plan, emulate = [], [*cmd, "emulate", "--scenario", self.opts.scenario_arg,
                             "--can-interface", "udp_multicast",
                             # ODrive's default encoder message rate (10 ms): half the
                             # frames of 200 Hz; odometry from the angle estimates loses
                             # nothing by it (a 30 s lab run under load: lag p99 7 ms, drift
                             # median ~1 cm, no contact; at 200 Hz the fleet was CPU-bound)
                             "--encoder-rate", repr(min(ENCODER_RATE_HZ, 1.0 / self.sc.dt)),
                             # physics at the control rate: RK4 at 5 ms is within 5 mm of 1 ms
                             # over 10 s of random 2 N m torques, at a fifth of the CPU
                             "--physics-rate", repr(1.0 / self.sc.dt),
                             # the physics must not lag the wall clock when the host is short
                             # of CPU (best effort: needs CAP_SYS_NICE, else the log says so)
                             "--priority", str(EMULATOR_PRIORITY)]
        for i, r in enumerate(self.sc.robot_ids):
            group, port = f"239.74.{os.getpid() % 250 + 1}.{i + 1}", f"port={free_udp_port()}"
            truth = self.opts.out / f"truth-{r}.npz"
            self.truth_files[r] = truth
            emulate += ["--robot", str(r), "--can-channel", group, "--can-arg", port,
                        "--truth-out", str(truth)]
            plan.append(Child(bridge_role(r), r, [
                *cmd, "bridge", *common, "--robot", str(r), "--can-interface", "udp_multicast",
                "--can-channel", group, "--can-arg", port], logs / f"{bridge_role(r)}.log"))
        plan.insert(0, Child("emulator", None, [*emulate, *self._can_faults()],
                             logs / "emulator.log", zenoh=False, stop_after_run=True))
        return plan

    def _can_faults(self) -> list[str]:
        """The fault plan's [can] section for the driver emulator: frames it loses or
        corrupts (each robot seeded apart: the emulator adds the robot's index)."""
        plan = self.opts.faults
        if plan is None or not (plan.can.frame_loss or plan.can.corrupt):
            return []
        return ["--drop-rate", repr(plan.can.frame_loss), "--corrupt-rate",
                repr(plan.can.corrupt), "--seed", str(plan.seed * 1000)]

    def _spawn(self, child: Child) -> None:
        child.log_path.parent.mkdir(parents=True, exist_ok=True)
        child.log = open(child.log_path, "wb")  # noqa: SIM115 - closed in _reap
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env[RUN_SECRET_ENV] = self.secret  # signs the run's control messages (run_secret.py)
        env.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)
        child.proc = subprocess.Popen(
            child.argv, stdout=child.log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env=env, start_new_session=True,
        )

    def _reap(self, child: Child, block: bool) -> bool:
        """Collect the child's exit status; True once it has exited."""
        if child.exit_code is not None or child.proc is None:
            return True
        try:
            pid, status = os.waitpid(child.proc.pid, 0 if block else os.WNOHANG)
        except ChildProcessError:
            pid, status = child.proc.pid, 0
        if pid == 0:
            return False
        child.exit_code = os.waitstatus_to_exitcode(status)
        child.proc.returncode = child.exit_code
        if child.log is not None:
            child.log.close()
        return True

    def _check_children(self) -> None:
        for c in self.children:
            if c.killed:
                continue
            if self._reap(c, block=False) and not (self.ended and c.exit_code == 0):
                if c.exit_code == 0:
                    # a node that ended cleanly after ``end`` raced our flag; the plant
                    # exits 0 only after sending ``end``, which a launcher behind on a
                    # large fleet's traffic may not have read yet
                    self.ended = self.ended or c.role == PLANT_ROLE
                    continue
                raise RunFailed(
                    f"{c.role} (pid {c.proc.pid}) exited with code {c.exit_code}"
                    + (f"; its last output:\n{c.tail()}" if c.tail() else "")
                )

    def stop_children(self) -> None:
        """SIGTERM every live child by pid, SIGKILL after a grace period, reap all."""
        live = [c for c in self.children if c.proc is not None and not self._reap(c, False)]
        for c in live:
            try:
                os.kill(c.proc.pid, signal.SIGTERM)
                os.kill(c.proc.pid, signal.SIGCONT)  # a paused one (fault plan) hears it too
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + STOP_GRACE_S
        while live and time.monotonic() < deadline:
            live = [c for c in live if not self._reap(c, False)]
            time.sleep(0.02)
        for c in live:
            try:
                os.kill(c.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self._reap(c, block=True)

    # -- the wire -------------------------------------------------------------------
    def _on_sample(self, arrived: tuple[str, bytes]) -> None:
        key, data = arrived
        found = self.keys.kind_of(key)
        if found is None:
            return
        kind, robot = found
        msg = self.codec.decode(kind, data, robot)
        if msg is None:
            self.invalid += 1
            return
        if self.recorder is not None:
            self.recorder.add(key, time.time_ns(), msg)
        if isinstance(msg, Control):
            if not control_is_genuine(self.secret, msg):
                self.control_refused += 1
                return
            if msg.command == "start" and self.run_t0 is None:
                self.run_t0 = time.monotonic() + (msg.start_unix_ns - time.time_ns()) * 1e-9
            elif msg.command == "tick":
                self.progress_k = max(self.progress_k, msg.k)
                self.tick_k = max(self.tick_k, msg.k)
            elif msg.command == "end":
                self.ended = True
            elif msg.command in ("stop", "estop") and self.stopped_by is None:
                # signed by a holder of the run's secret: the run ends early, and says so
                self.stopped_by = {"command": msg.command, "sender": msg.sender,
                                   "k": self.progress_k, "t_s": self._run_time()}
            return
        if isinstance(msg, NodeReport) and key != self.keys.report(msg.role):
            # a report is filed under the role of the key it came on, never the role its
            # body claims (a "plant" report on report/agent-2 put a fake contact in
            # metrics.json); across hosts the ACL lets each role put only its own key
            self.invalid += 1
            self.misfiled += 1
            return
        if isinstance(msg, NodeReport) and (msg.role not in self._report_roles()
                                            or not report_is_genuine(self.secret, msg)):
            # only the run's roles (the table of reports stays bounded), signed with the
            # run's secret (a report on report/plant with a fake contact is refused)
            self.invalid += 1
            self.forged_reports += 1
            return
        if isinstance(msg, StateLog) and not self._state_source(key, msg):
            self.invalid += 1  # robot states from a node that does not hold them
            self.misfiled += 1
            return
        if isinstance(msg, StateLog) and self.opts.clock == "realtime":
            self.progress_k = max(self.progress_k, msg.rows[-1].k)
        self.collector.add(msg)

    def _report_roles(self) -> set[str]:
        """The roles whose reports a run files: its nodes (a plant or bridges)."""
        ids = self.sc.robot_ids
        return {*run_roles(ids), *(bridge_role(r) for r in ids)}

    def _state_source(self, key: str, msg: StateLog) -> bool:
        """Whether ``msg`` came on the key of a node that holds those robots' states:
        the plant (any robots), or robot i's CAN bridge (robot i only)."""
        if key == self.keys.state_log(PLANT_ROLE):
            return self.opts.plant != CAN_EMULATED
        return self.opts.plant == CAN_EMULATED and len(msg.robots) == 1 and (
            key == self.keys.state_log(bridge_role(msg.robots[0])))

    def _horizon(self) -> int | None:
        """The newest step the run can have reached now, on our clock: realtime from
        t = 0 (no node runs ahead of the wall clock), lockstep from the plant's newest
        signed tick (rows follow it by less than a batch: agents answer its samples)."""
        t0 = self.run_t0 if self.run_t0 is not None else self.t0_mono
        if self.opts.clock == "realtime":
            if t0 is None:
                return None
            return int((time.monotonic() - t0 + CLOCK_SKEW_S) / self.sc.dt) + 1
        return max(self.tick_k, 0) + 3 * TICK_EVERY

    def _run_time(self) -> float | None:
        """Run time now: realtime from ``ctl/start``; lockstep from the plant's ticks."""
        if self.run_t0 is not None:
            return time.monotonic() - self.run_t0
        if self.t0_mono is not None:
            return time.monotonic() - self.t0_mono
        return None if self.progress_k < 0 else self.progress_k * self.sc.dt

    # -- the run --------------------------------------------------------------------
    def run(self, progress=None) -> dict[str, Any]:
        """Run to the end; returns the figures the launcher adds to metrics.json.
        Raises RunFailed; KeyboardInterrupt after stopping every child."""
        from deploy.report.recorder import McapRecorder

        o = self.opts
        o.out.mkdir(parents=True, exist_ok=True)
        self.run_dir = Path(tempfile.mkdtemp(prefix="omnifleet-"))  # 0700: ours alone
        endpoint = o.endpoint or self.endpoint_of(LAUNCHER_ROLE)
        try:
            node = Node(LAUNCHER_ROLE, self.keys, self.codec,
                        zenoh_config(listen=[endpoint], gossip=False, lowlatency=o.lowlatency))
        except BaseException:
            shutil.rmtree(self.run_dir, ignore_errors=True)
            raise
        if o.record:
            self.recorder = o.recorder or McapRecorder(o.out / "recording.mcap")  # issue 18 hook
        previous = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        start = time.perf_counter()
        self.launcher_zid = node.zid
        try:
            for key in self._listened_keys():
                node.subscribe_raw(key, self._on_sample)
            node.declare_alive()
            node.declare_ready()
            self.children = self._plan(endpoint)
            self._write_endpoints(endpoint)
            for c in self.children:
                self._spawn(c)
            roles = [c.role for c in self.children if c.zenoh]
            deadline = time.monotonic() + o.startup_timeout_s
            while node.wait_for_roles(roles, "ready", 0.1, self.stop):
                self._check_children()
                if self.stop():
                    raise Interrupted(self.stop.reason)
                if time.monotonic() > deadline:
                    missing = node.wait_for_roles(roles, "ready", 0.0)
                    raise RunFailed(f"not ready after {o.startup_timeout_s:.0f} s: "
                                    f"{', '.join(sorted(missing))}")
            start = time.perf_counter()
            if o.plant == CAN_EMULATED:
                self._announce_start(node)
            while not self.ended:
                if self.stop():
                    raise Interrupted(self.stop.reason)
                self._check_children()
                if self.t0_mono is not None and time.monotonic() >= self.t0_mono + self.steps * self.sc.dt:
                    self._control(node, "end")  # no plant: the launcher keeps the run's time
                    self.ended = True
                self._apply_kills()
                if progress is not None:
                    progress(self.progress_k + 1, self.steps)
                # hear the fleet meanwhile (the handlers run here, off the fleet's path)
                node.mailbox.wait_until(lambda: self.ended or self.stop(),
                                        0.05 if not self.kills.pending else 0.005, bounded=True)
            wall = time.perf_counter() - start
            if progress is not None:
                progress(self.steps, self.steps)
            self._wait_for_exit(node, roles)
        finally:
            for s, h in previous.items():
                signal.signal(s, h)
            self.stop_children()
            node.close()
            shutil.rmtree(self.run_dir, ignore_errors=True)
            if self.recorder is not None and o.recorder is None:  # issue 18 hook: else the caller's
                self.recorder.close()  # flushed, also after Ctrl-C
        return self._figures(wall)

    def _write_endpoints(self, launcher_endpoint: str) -> None:
        """logs/endpoints.json: where each node of the run listens (a tool that must
        reach the fleet itself, a probe, connects to those it needs)."""
        import json

        where = {LAUNCHER_ROLE: launcher_endpoint}
        where |= {c.role: self.endpoint_of(c.role) for c in self.children if c.zenoh}
        path = self.opts.out / "logs" / "endpoints.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(where, indent=1) + "\n")

    def _apply_kills(self) -> None:
        """The fault plan's process kills (SIGKILL: a crash, no goodbye) and
        restarts (the agent rejoins the running fleet), on the run's clock."""
        if self.run_t0 is None or not self.kills.pending:
            return
        t = time.monotonic() - self.run_t0
        for event in self.kills.due(t):
            # kill or pause: the live process of that role; restart: the one killed
            child = [c for c in self.children if c.role == event.process
                     and c.killed == event.restart][-1]
            if event.restart:
                self.kills.log(event, t, self._restart(child))
            elif event.action in (PAUSE, RESUME):  # off the CPU and back, as a starved host
                os.kill(child.proc.pid, signal.SIGSTOP if event.action == PAUSE else signal.SIGCONT)
                self.kills.log(event, t, child.proc.pid)
            else:
                child.killed = True
                os.kill(child.proc.pid, signal.SIGKILL)
                self._reap(child, block=True)
                self.kills.log(event, t, child.proc.pid)

    def _restart(self, dead: Child) -> int:
        argv = [*dead.argv, "--rejoin"] if dead.role.startswith("agent-") else dead.argv
        # The peers that had opened their link to the dead node do not open it again
        # (zenoh re-dials only the endpoints a session connects to, not the ones it
        # accepted on): a restarted agent 2 never heard agent 3, waited for its
        # liveliness token until the run ended and took no step. It dials them all.
        argv = [*argv, *(a for other in dead.talks_with if other not in dead.links
                         for a in ("--connect", self.endpoint_of(other)))]
        if self.run_dir is not None:  # the killed node's socket file stays behind it
            (self.run_dir / f"{dead.role}.sock").unlink(missing_ok=True)
        child = Child(dead.role, dead.robot, argv,
                      dead.log_path.with_name(f"{dead.role}.restart.log"),
                      links=dead.talks_with, talks_with=dead.talks_with, restarted=True)
        self._spawn(child)
        self.children.append(child)
        return child.proc.pid

    def _listened_keys(self) -> list[str]:
        """Recording: every key of the fleet. Otherwise only what the series and
        the metrics need (each message heard costs CPU in every listener)."""
        k = self.keys
        if self.opts.record:
            return [k.everything]
        return [k.leader_state, k.state_log_all, f"{k.root}/agent/*/telemetry",
                k.ctl_all, f"{k.root}/report/*"]

    def _on_signal(self, signum: int, _frame: object) -> None:
        self.stop.set(signal.Signals(signum).name)

    def _announce_start(self, node: Node) -> None:
        start_unix_ns = time.time_ns() + int(START_LEAD_S * 1e9)
        self.t0_mono = time.monotonic() + START_LEAD_S
        # the fault plan's clock too: waiting to hear our own start back left run_t0 unset
        # (or set late), and an agent killed "at 4 s" was killed at ~11 s and restarted
        # after the run had ended (it waited for peers that had left: "did not exit")
        self.run_t0 = self.t0_mono
        self._control(node, "start", start_unix_ns)

    def _control(self, node: Node, command: str, start_unix_ns: int = 0) -> None:
        node.publish(self.keys.ctl(command), lambda seq, stamp: control(
            command, seq, stamp, self.secret, start_unix_ns=start_unix_ns))

    def _wait_for_exit(self, node: Node, roles: list[str], timeout_s: float = 20.0) -> None:
        """After ``end``: every node sends its report and exits 0; then the children
        that run until stopped (emulators) are stopped."""
        deadline = time.monotonic() + timeout_s
        nodes = [c for c in self.children if not c.stop_after_run]
        steady = [c for c in nodes if not c.restarted]
        others_done_at = None
        while time.monotonic() < deadline:
            if self.stop():
                raise Interrupted(self.stop.reason)
            if all(self._reap(c, False) for c in steady):
                others_done_at = others_done_at or time.monotonic()
                if (all(self._reap(c, False) for c in nodes)
                        or time.monotonic() > others_done_at + REJOIN_GRACE_S):
                    break
            node.mailbox.wait_until(self.stop, 0.02)
        for c in nodes:
            # a restarted node still starting when the run ended (a loaded host: imports and
            # the handshake took longer than the run had left) missed the end: stop it
            if c.restarted and not self._reap(c, False):
                c.proc.send_signal(signal.SIGTERM)
                until = time.monotonic() + 10.0
                while not self._reap(c, False) and time.monotonic() < until:
                    time.sleep(0.02)
                if c.exit_code in (-signal.SIGTERM, 143):
                    print(f"omnifleet run: {c.role} (restarted) was still rejoining when the run "
                          "ended: stopped", file=sys.stderr)
                    c.exit_code = 0
        for c in self.children:
            if c.stop_after_run and not self._reap(c, False):
                c.proc.send_signal(signal.SIGTERM)
                until = time.monotonic() + 10.0
                while not self._reap(c, False) and time.monotonic() < until:
                    time.sleep(0.02)
                if c.exit_code in (-signal.SIGTERM, 143):
                    c.exit_code = 0  # stopped as planned
        bad = [c for c in self.children if c.exit_code not in (0,) and not c.killed]
        if bad:
            raise RunFailed("; ".join(
                f"{c.role} (pid {c.proc.pid}) "
                + ("did not exit" if c.exit_code is None else f"exited with code {c.exit_code}")
                + (f"; its last output:\n{c.tail()}" if c.tail() else "") for c in bad))
        # reports travel before the session closes; wait for stragglers (a launcher
        # behind on a large fleet's traffic reads them late)
        node.mailbox.wait_until(lambda: len(self.collector.reports) >= len(roles), 10.0)

    def _figures(self, wall: float) -> dict[str, Any]:
        reports: dict[str, NodeReport] = dict(self.collector.reports)
        # a message for a step outside the run is never used: dropped
        messages = {"sent": 0, "dropped": self.collector.out_of_range, "late": 0,
                    "invalid": self.invalid}
        for c in self.children:
            r = reports.get(c.role)
            c.peak_rss_mb = r.peak_rss_kb / 1024.0 if r is not None and r.peak_rss_kb else None
        refused: dict[str, int] = {}
        for r in reports.values():
            messages["sent"] += r.sent
            messages["dropped"] += r.dropped
            messages["late"] += r.late
            messages["invalid"] += r.invalid
            for why, n in r.refused.items():
                refused[f"{r.role}: {why}"] = n
        agents = [reports.get(agent_role(r)) for r in self.sc.robot_ids]
        if self.control_refused:
            refused["launcher: forged control"] = self.control_refused
        if self.misfiled:
            refused["launcher: report or state log on another node's key"] = self.misfiled
        if self.forged_reports:
            refused["launcher: report not from a node of the run"] = self.forged_reports
        for why, n in self.collector.refused.items():
            refused[f"launcher: {why}"] = n
        if refused:  # counted in "dropped" too; here by node and reason
            messages["refused"] = refused
        # who had a link with whom, from each node's zenoh session (ids -> roles)
        role_of = {r.zid: role for role, r in reports.items() if r.zid}
        role_of[self.launcher_zid] = LAUNCHER_ROLE
        out: dict[str, Any] = {
            "wall_time_s": wall,
            "messages": messages,
            "processes": [
                {"role": c.role, "robot": c.robot, "pid": c.proc.pid,
                 "peak_rss_mb": None if c.peak_rss_mb is None else round(c.peak_rss_mb, 1),
                 "exit_code": c.exit_code, "killed": c.killed, "reported": c.role in reports,
                 "received": dict(reports[c.role].received) if c.role in reports else {},
                 "links": sorted(role_of.get(z, z) for z in reports[c.role].peers)
                 if c.role in reports else None}
                for c in self.children
            ] + [{"role": LAUNCHER_ROLE, "robot": None, "pid": os.getpid(),
                  "peak_rss_mb": round(peak_rss_kb() / 1024.0, 1), "exit_code": None,
                  "reported": True}],
        }
        # per robot, in the scenario's order (None: its agent's report never came); a
        # restarted agent reports for its second life too (the collector keeps the last)
        out |= agent_figures(agents)
        # commands that asked for more torque than the bound, clipped, per robot
        clipped = {str(r): 0 for r in self.sc.robot_ids}
        for rep in reports.values():
            for rid, n in rep.torque_clipped.items():
                if rid in clipped:
                    clipped[rid] += n
        out["torque_clipped"] = clipped
        if self.stopped_by is not None:
            out["stopped_by"] = self.stopped_by
        plant = reports.get(PLANT_ROLE)
        bridges = [reports[bridge_role(r)] for r in self.sc.robot_ids if bridge_role(r) in reports]
        out |= zero_torque_figures([r for r in [plant, *bridges] if r is not None],
                                   self.sc.robot_ids)
        stops = sorted((s for r in [plant, *bridges] if r is not None for s in r.command_stops),
                       key=lambda s: s[2])  # the plant's, or on CAN each bridge's, by run time
        if stops:
            out["command_stops"] = [{"robot": r, "command_age_s": a, "t_s": t} for r, a, t in stops]
        if plant is not None and plant.contacts is not None:
            out["contact_log"] = [msgspec.structs.asdict(c) for c in plant.contacts]
            out["contacts_total"] = plant.contacts_total
        if self.recorder is not None:
            out["recording"] = {"file": "recording.mcap", "messages": self.recorder.written}
        if self.opts.faults is not None:
            out["faults"] = fault_metrics(self.opts.faults,
                                          merge_reports([r.faults for r in reports.values()]),
                                          self.kills.events)
        if self.opts.clock == "realtime":
            out["latency_ms"] = _percentiles_ms(plant.latency_ns if plant else [])
            if bridges:  # on CAN: each command's arrival -> its torque frames on the bus
                out["bridge_latency_ms"] = _percentiles_ms([x for b in bridges for x in b.latency_ns])
            out["jitter_ms"] = _percentiles_ms([j for r in reports.values() for j in r.jitter_ns])
            out["deadline_misses"] = sum(r.deadline_misses for r in reports.values())
        return out

