"""``omnifleet run``: start leader, plant and one agent process per robot on this
machine, watch them, hear them, and hand the run's figures back.

Three parts, each in its own module: the plan (deploy/run/plan.py: which processes,
which arguments, who links to whom), the supervisor (deploy/run/supervisor.py:
start, watch, fault-plan kills, stop by pid) and the observer
(deploy/run/observer.py: hear, judge and file the fleet's messages). This module
puts them together on one clock.

Topology (links as the graph, docs/distributed.md): every node, the launcher included,
listens on a unix socket of its own in a private run directory (mode 0700: other
users' processes cannot connect) and connects to exactly the nodes it talks to.
Gossip and multicast scouting are off, so no other link forms and two runs on one
machine never see each other (the fleet name, hence every topic, is the
scenario's name).
"""

from __future__ import annotations

import os
import shutil
import signal
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from deploy.contract.keyring import Keyring, keyring_text, new_master
from deploy.contract.scenario import Scenario
from deploy.contract.wire import LAUNCHER_ROLE, WIRE_VERSION, Keys, LeaderSteer, control
from deploy.report.run_folder import RECORDING
from deploy.report.timeseries import TimeSeries
from deploy.run.awake import STARTING_GRACE_S, cores_kept_awake, refused_realtime
from deploy.run.early_load import EarlyLoad, EarlyLoadProbe
from deploy.run.kill_schedule import KillSchedule
from deploy.run.observer import Observer, SpooledWire
from deploy.run.plan import LaunchOptions, endpoint_of, key_roles, plan_run, spools
from deploy.run.run_figures import run_figures
from deploy.run.supervisor import Interrupted, RunFailed, Supervisor
from deploy.runtime.datagrams import DatagramPath
from deploy.runtime.node_runtime import START_LEAD_S, LoopClock, StopFlag
from deploy.runtime.plants import CAN_EMULATED
from deploy.runtime.transport import Node, zenoh_config
from deploy.runtime.wire_spool import SpoolReader

__all__ = ["Interrupted", "LaunchOptions", "Launcher", "RunFailed", "observing"]

Progress = Callable[[int, int], None] | None
HEAR_SWITCH_INTERVAL_S = 2e-4
HEAR_EVERY_S = 0.002  # while the fleet's frames keep coming (Mailbox.wait_until)


def make_observer(sc: Scenario, opts: LaunchOptions, keyring: Keyring | None) -> Observer:
    return Observer(sc, Keys(opts.fleet or sc.name), opts.clock, opts.plant, opts.steps(sc),
                    keyring, record_all=opts.record, spooled=spools(opts))


@contextmanager
def observing(obs: Observer, opts: LaunchOptions, node: Node, stop: StopFlag) -> Iterator[None]:
    """While inside: ``node`` hears the fleet through ``obs`` (recording when asked),
    and SIGINT/SIGTERM set ``stop``. On the way out, however left: the signal handlers
    are restored, ``node`` closed and the recording flushed (unless it is the caller's)."""
    from deploy.report.recorder import McapRecorder

    if opts.record:
        obs.recorder = opts.recorder or McapRecorder(opts.out / RECORDING)
    previous = {s: signal.signal(s, lambda n, _f: stop.set(signal.Signals(n).name))
                for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        for key in obs.listened_keys():
            node.subscribe_raw(key, obs.on_sample)
        node.declare_alive()
        node.declare_ready()
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        node.close()
        if obs.recorder is not None and opts.recorder is None:  # else the caller closes it
            obs.recorder.close()


class Launcher:
    """Runs a scenario's fleet on this machine: :meth:`run` returns the figures the
    run adds to metrics.json; ``observer.collector`` holds its series, ``observer.run_t0``
    its t = 0 on this host's monotonic clock."""

    def __init__(self, sc: Scenario, opts: LaunchOptions) -> None:
        self.sc, self.opts = sc, opts
        # the run's keys (deploy/contract/keyring.py): a master drawn for this run, a keyring
        # per node derived from it and handed over on a pipe; the master stays here
        fleet, master, roles = opts.fleet or sc.name, new_master(), key_roles(sc, opts.plant)

        def keyring_of(role: str) -> str:
            return keyring_text(master, fleet, role, roles)

        self.keyring = Keyring.from_text(keyring_of(LAUNCHER_ROLE), "the launcher's keys",
                                         LAUNCHER_ROLE, sc, Keys(fleet))
        self.observer = make_observer(sc, opts, self.keyring)
        self.supervisor = Supervisor(keyring_of)
        self.stop = StopFlag()
        self.steps = opts.steps(sc)
        self.kills = KillSchedule(opts.faults.kills if opts.faults else ())
        self.truth_files: dict[int, Path] = {}  # can-emulated: each emulator's ground truth
        self.loop_clock = LoopClock()
        self.early: EarlyLoad | None = None  # realtime: the fleet's first second
        self.awake_cores: list[int] = []  # --keep-cores-awake: the cores kept from halting
        self.spool: SpoolReader | None = None  # the samples and replies kept (recording)
        # called once with the run's final series, as soon as every node's report (and so
        # all of its data) is in, while the nodes are still leaving: a caller starts
        # drawing the figures then
        self.on_heard: Callable[[TimeSeries], None] = lambda series: None
        self._series: TimeSeries | None = None

    def run(self, progress: Progress = None) -> dict[str, Any]:
        """Run to the end; returns the figures the launcher adds to metrics.json.
        Raises RunFailed; Interrupted (a KeyboardInterrupt) after stopping every child."""
        # this thread hears the fleet while the recorder's thread encodes: every receive
        # gives the interpreter up, and getting it back took up to the default switch
        # interval (5 ms) while the encoder ran: ~200 messages a second, where a
        # recorded lockstep run sends thousands (the fleet's frames for it piled up).
        # Not when the plant keeps its samples and replies for the recording: a tenth
        # of the frames are heard here then, and the short interval's hand-overs cost
        # more than they bought (README command 1: 15.0-16.4 s against 14.5-15.6 s with
        # the default interval, 6 pairs side by side; docs/bench-history.md)
        switch = sys.getswitchinterval()
        if self.observer.record_all and not self.observer.spooled:
            sys.setswitchinterval(HEAR_SWITCH_INTERVAL_S)
        try:
            return self._run(progress)
        finally:
            sys.setswitchinterval(switch)

    def _run(self, progress: Progress) -> dict[str, Any]:
        o, obs, sup = self.opts, self.observer, self.supervisor
        o.out.mkdir(parents=True, exist_ok=True)
        run_dir = Path(tempfile.mkdtemp(prefix="omnifleet-"))  # 0700: ours alone
        sup.run_dir = run_dir
        endpoint = o.endpoint or endpoint_of(run_dir, LAUNCHER_ROLE)
        try:
            # it imports what the nodes need meanwhile
            sup.start_forks()
            lossless = o.clock == "lockstep"
            datagrams = DatagramPath(run_dir, LAUNCHER_ROLE, lossless) if o.datagrams else None
            node = Node(LAUNCHER_ROLE, obs.keys, obs.codec,
                        zenoh_config(listen=[endpoint], gossip=False, lowlatency=o.lowlatency),
                        keyring=self.keyring, datagrams=datagrams)
        except BaseException:
            sup.stop_all()
            shutil.rmtree(run_dir, ignore_errors=True)
            raise
        zid = node.zid
        obs.on_report = node.declare_filed  # its node may close: the report is in hand
        try:
            with observing(obs, o, node, self.stop):
                if obs.spooled and obs.recorder is not None:
                    self.spool = SpoolReader(run_dir)
                    obs.recorder.add_source(SpooledWire(self.sc, obs.keys, self.spool))
                try:
                    wall = self._run_fleet(node, endpoint, run_dir, progress)
                finally:
                    sup.stop_all()  # by pid, before the launcher leaves the fleet
                    if self.spool is not None:  # readable after the run's directory is gone
                        self.spool.open_all()
        finally:
            shutil.rmtree(run_dir, ignore_errors=True)
        out = run_figures(obs, sup.children, zid, wall, o.faults, self.kills.events,
                          listener_cpu=self.loop_clock)
        if self.early is not None:
            out["early_load"] = self.early.as_json()
        if o.keep_cores_awake:
            out["cores_kept_awake"] = self.awake_cores
        return out

    def _run_fleet(self, node: Node, endpoint: str, run_dir: Path, progress: Progress) -> float:
        """Start the fleet, supervise it to the end and collect its reports; returns
        the wall time from all-ready to the end."""
        o, sup = self.opts, self.supervisor
        plan = plan_run(self.sc, o, endpoint, run_dir)
        self.truth_files = plan.truth_files
        _write_endpoints(o.out, endpoint, plan.children, run_dir)
        sup.start(plan.children)
        roles = [c.role for c in plan.children if c.zenoh]
        self._wait_ready(node, roles)
        start = time.perf_counter()
        self.loop_clock.costs = node.costs
        awake = self._cores_to_keep_awake() if o.keep_cores_awake else None
        with cores_kept_awake(awake), self.loop_clock:  # this process's CPU over the run
            if o.plant == CAN_EMULATED:
                self._announce_start(node)
            self._supervise(node, progress)
        wall = time.perf_counter() - start
        if progress is not None:  # the steps the plant says it simulated, no more
            progress(self.observer.progress_k + 1, self.steps)
        reports = self.observer.collector.reports

        def hear(s: float) -> None:  # while the nodes leave
            node.mailbox.wait_until(self.stop, s)
            if len(reports) >= len(roles):
                self._heard_all(node)

        sup.wait_for_exit(self.stop, hear)
        # reports travel before the session closes; wait for stragglers (a launcher
        # behind on a large fleet's traffic reads them late)
        node.mailbox.wait_until(lambda: len(reports) >= len(roles), 10.0)
        self._heard_all(node)
        self.observer.note_unrecorded()
        return wall

    def _heard_all(self, node: Node) -> None:
        """Once: the last of the fleet's data read, the final series built and handed
        to ``on_heard``."""
        if self._series is not None:
            return
        # a node sends its data before its report, but on another socket than zenoh's:
        # what it sent is in our connections now, read it all
        node.mailbox.drain()
        self.on_heard(self.final_series())

    def final_series(self) -> TimeSeries:
        """The run's series as heard (built once, after the run)."""
        if self._series is None:
            self._series = self.observer.collector.series(realtime=self.opts.clock == "realtime")
        return self._series

    def _wait_ready(self, node: Node, roles: list[str]) -> None:
        deadline = time.monotonic() + self.opts.startup_timeout_s
        while node.wait_for_roles(roles, "ready", 0.1, self.stop):
            self.supervisor.check(self.observer.ended)
            if self.stop():
                raise Interrupted(self.stop.reason)
            if time.monotonic() > deadline:
                missing = node.wait_for_roles(roles, "ready", 0.0)
                raise RunFailed(f"not ready after {self.opts.startup_timeout_s:.0f} s: "
                                f"{', '.join(sorted(missing))}")

    def _supervise(self, node: Node, progress: Progress) -> None:
        """Until the run ends: watch the children, keep the run's time when no plant
        does (CAN), carry out the fault plan, report progress; the fleet's messages
        are heard here meanwhile (the handlers run on this thread, off the fleet's path)."""
        obs = self.observer
        probe = None
        if self.opts.clock == "realtime":
            # the fleet's frames come batched and decimated, and nothing waits on the
            # launcher: it looks every 50 ms (the wait below), not at each frame, whose
            # every wake after a sleep cost ~150-250 µs here (caches cold). zenoh's messages
            # (control, reports) still wake it at once
            node.wake_on(())
        if self.opts.clock == "realtime":  # does this machine keep the fleet's clock?
            pids = {c.role: c.proc.pid for c in self.supervisor.children if c.proc is not None}
            probe = EarlyLoadProbe({**pids, LAUNCHER_ROLE: os.getpid()}, self.sc.dt)
        steered = -1  # the number of the last steering command passed on
        while not obs.ended:
            if self.stop():
                raise Interrupted(self.stop.reason)
            obs.ended = self.supervisor.check(obs.ended)
            if self.opts.steering is not None and obs.run_t0 is not None:
                steered = self._pass_steering(node, steered)
            if probe is not None and obs.run_t0 is not None:
                self._judge_early_load(probe, obs.run_t0)
            if obs.t0_mono is not None and time.monotonic() >= obs.t0_mono + self.steps * self.sc.dt:
                self._control(node, "end")  # no plant: the launcher keeps the run's time
                obs.ended = True
            if obs.run_t0 is not None and self.kills.pending:
                self.supervisor.apply_kills(self.kills, time.monotonic() - obs.run_t0)
            if progress is not None:
                progress(obs.progress_k + 1, self.steps)
            # the fleet heard in batches (not woken by each frame), but a kill of the fault
            # plan carried out to the millisecond
            node.mailbox.wait_until(lambda: obs.ended or self.stop(),
                                    0.05 if not self.kills.pending else 0.005, bounded=True,
                                    coalesce_s=0.0 if self.kills.pending else HEAR_EVERY_S)

    def _cores_to_keep_awake(self) -> set[int] | None:
        """--keep-cores-awake: the cores this run may use, if every node of it runs under
        SCHED_FIFO (deploy/run/awake.py); else none, and why on stderr."""
        started = [c for c in self.supervisor.children if c.proc is not None]
        refused = refused_realtime({c.role: c.proc.pid for c in started if c.zenoh},
                                   {c.role: c.proc.pid for c in started if not c.zenoh},
                                   STARTING_GRACE_S, self.stop)
        if refused:
            print(f"omnifleet run: --keep-cores-awake: not kept: {', '.join(refused)} not "
                  "under SCHED_FIFO (the host refused it), and a spinner would take the core "
                  "each such node hands over", file=sys.stderr, flush=True)
            return None
        self.awake_cores = sorted(os.sched_getaffinity(0))
        return set(self.awake_cores)

    def _pass_steering(self, node: Node, passed: int) -> int:
        """A steered leader's newest command (deploy/ros2/gateway.py), to the leader when
        it is newer than the last one passed (its number); returns that number."""
        newest = self.opts.steering()
        if newest is None or newest[0] == passed:
            return passed
        velocity = newest[1]
        node.publish(self.observer.keys.leader_steer, lambda seq, stamp: LeaderSteer(
            WIRE_VERSION, 0, seq, stamp, velocity=velocity))
        return newest[0]

    def _judge_early_load(self, probe: EarlyLoadProbe, run_t0: float) -> None:
        """At the run's start, and a second later: say at once when this machine cannot
        keep the fleet's clock (deploy/run/early_load.py)."""
        now = time.monotonic()
        if probe.started_at is None and now >= run_t0:
            probe.start(now)
        elif probe.due(now):
            self.early = probe.finish(now)
            if self.early is not None and self.early.behind:
                print(f"omnifleet run: {self.early.message(1.0 / self.sc.dt)}",
                      file=sys.stderr, flush=True)

    def _announce_start(self, node: Node) -> None:
        start_unix_ns = time.time_ns() + int(START_LEAD_S * 1e9)
        self.observer.t0_mono = time.monotonic() + START_LEAD_S
        # the fault plan's clock too: waiting to hear our own start back left run_t0 unset
        # (or set late), and an agent killed "at 4 s" was killed at ~11 s and restarted
        # after the run had ended (it waited for peers that had left: "did not exit")
        self.observer.run_t0 = self.observer.t0_mono
        self._control(node, "start", start_unix_ns)

    def _control(self, node: Node, command: str, start_unix_ns: int = 0) -> None:
        node.publish(self.observer.keys.ctl(command), lambda seq, stamp: control(
            command, seq, stamp, start_unix_ns=start_unix_ns))


def _write_endpoints(out: Path, launcher_endpoint: str, children, run_dir: Path) -> None:
    """logs/endpoints.json: where each node of the run listens (a tool that must
    reach the fleet itself, a probe, connects to those it needs). Written whole, then
    renamed: a tool that sees the file never reads half of it (or none)."""
    import json
    import os

    where = {LAUNCHER_ROLE: launcher_endpoint}
    where |= {c.role: endpoint_of(run_dir, c.role) for c in children if c.zenoh}
    path = out / "logs" / "endpoints.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(where, indent=1) + "\n")
    os.replace(tmp, path)
