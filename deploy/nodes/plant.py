"""The simulated plant as a process: every robot of the scenario, one zenoh peer.

Publishes one ``robot/i/sample`` (state + perception) per robot each step and
takes ``robot/i/cmd`` (the agent's reply). It is the time master of a lockstep
run (docs/distributed.md): step k publishes the samples at t_k (their arrival is the
agents' tick), waits for every robot's command of step k (per-step deadline; a
missing one is counted late), then integrates to t_{k+1}; ``ctl/tick`` goes out
every ``TICK_EVERY`` steps only, to pace the leader's batches. The robot states
go to observers in batches (``log/plant``), off the control path. In realtime
it steps on its own monotonic clock, uses the newest command of each robot, and
zeroes a robot's torques when its newest command is older than the command
timeout. A step whose command is missing (late or lost)
gets the look-ahead torques the newest command predicted for it
(agents/look_ahead.py); past them the last torques are held (or zeroed, lockstep
with ``plant.missed_command = "zero"``).

A command is applied through :class:`plant.command.CommandBounds` (each wheel
torque clamped to the scenario's limit, v_cmd to the speed limits), whatever the
bytes that decoded as a command.
"""

from __future__ import annotations

import time

import numpy as np

from deploy.contract.fault_plan import FaultPlan
from deploy.contract.options import DEFAULT_COMMAND_TIMEOUT_S
from deploy.contract.scenario import Scenario
from deploy.contract.wire import (
    LAUNCHER_ROLE,
    MAX_CONTACTS,
    PLANT_ROLE,
    WIRE_VERSION,
    ContactRecord,
    Reply,
    Sample,
    StateLog,
    StateRow,
    agent_role,
    control,
    log_rows_per_batch,
    run_roles,
    sensed_bodies,
    within_wire_bound,
)
from deploy.nodes.leader import TICK_EVERY
from deploy.runtime.fault_model import FaultModel
from deploy.runtime.lockstep_inputs import HeldInput
from deploy.runtime.node_runtime import (
    START_LEAD_S,
    ControlInbox,
    FaultGate,
    Periodic,
    StopFlag,
    Timing,
    publish_report,
)
from deploy.runtime.plants import contact_log, make_plant, sensor_for
from deploy.runtime.priority import hand_over
from deploy.runtime.step_costs import LAW, TELEMETRY, now_ns
from deploy.runtime.step_guard import SEQ_SLACK
from deploy.runtime.transport import Node
from deploy.runtime.wire_spool import SpoolWriter, spool_path
from plant.command import (
    CommandBounds,
    ZeroTorqueSpans,
    exceeds,
    torques_at,
    velocity_exceeds,
)

SENT_STAMPS_KEPT = 64  # samples per robot whose answers still count for the latency


class PlantNode:
    def __init__(self, sc: Scenario, kind: str, node: Node, stop: StopFlag,
                 with_recorder: bool = False,
                 command_timeout_s: float = DEFAULT_COMMAND_TIMEOUT_S,
                 gui: bool = False, faults: FaultPlan | None = None,
                 realtime: bool = False, spool_dir: str | None = None) -> None:
        """``spool_dir``: keep a record of every sample sent and every reply heard
        there, for the recording of the launcher on this host (wire_spool.py)."""
        self.sc, self.node, self.stop, self.kind = sc, node, stop, kind
        self.plant = make_plant(sc, kind, gui=gui)
        self.sense = sensor_for(self.plant, sc)
        self.ids = sc.robot_ids
        self.sample_keys = [node.keys.sample(rid) for rid in self.ids]
        if spool_dir is not None:
            node.spool = SpoolWriter(spool_path(spool_dir, PLANT_ROLE), {
                *self.sample_keys, *(node.keys.cmd(rid) for rid in self.ids)})
        self.torques = np.zeros((sc.n, 4))
        # per robot: every step integrated since its last sample ran on the torques its
        # agent computed for that step (Sample.own_torques)
        self.own_torques = [True] * sc.n
        self.v_cmd = np.zeros((sc.n, 3))
        self.commands: dict[tuple[int, int], Reply] = {}
        self.published_k = -1  # the newest step whose samples went out
        self.newest: dict[int, Reply] = {}
        self.newest_at: dict[int, float] = {}
        self.command_timeout_s = command_timeout_s
        self.timing = Timing()
        self.steps_done = 0
        self.last_state_seq: dict[int, int] = {}
        # our own stamps of the recent samples, by robot and seq: the state-to-command
        # latency of any command that answers one of them, on our clock (the stamp the
        # command echoes is not trusted)
        self.sent_stamps: dict[int, dict[int, int]] = {rid: {} for rid in self.ids}
        self.log_rows: list[StateRow] = []  # robot states for observers, sent in batches
        self.log_every = log_rows_per_batch(sc.n)
        self.peers = [r for r in run_roles(self.ids) if r != PLANT_ROLE]
        if with_recorder:
            self.peers.append(LAUNCHER_ROLE)
        # faults on the agent -> plant edges: lockstep picks each step's command
        # through the links, realtime judges commands as they arrive
        self.faults = FaultModel(faults, sc.dt)
        self.command_links = [
            HeldInput(self.faults, self.faults.edge(agent_role(rid), PLANT_ROLE),
                      exempt_first=False) for rid in self.ids]
        self.keep_steps = 1 + self.faults.max_lag_steps
        # how far back a command may answer: the fault plan's lag (lockstep), or the
        # command timeout (realtime: an older command would be zeroed anyway)
        self.window_steps = max(self.keep_steps, int(command_timeout_s / sc.dt) + 2)
        self.gate = FaultGate(self.faults, node.mailbox) if realtime and faults else None
        self.unpowered: set[int] = set()  # realtime: robots whose commands stopped coming
        # the largest wheel torque ever applied (plant/command.py), and per robot the
        # commands that asked for more (clipped to it; in metrics.json)
        self.bounds = CommandBounds.of(sc.spec.limits)
        self.clipped: dict[int, int] = {}
        self.command_stops: list[tuple[int, float, float]] = []  # (robot, command age, t)
        self.zero_torque = ZeroTorqueSpans()  # how long each stop lasted
        self.unanswered = [0] * sc.n  # realtime: per robot, steps whose state went unanswered
        for rid in self.ids:
            on_cmd = self._on_cmd if self.gate is None else self.gate.wrap(
                agent_role(rid), PLANT_ROLE, self._on_cmd)
            node.subscribe(node.keys.cmd(rid), Reply, on_cmd, robot=rid)
        self.control = ControlInbox(node, stop)
        node.declare_alive()

    def _on_cmd(self, m: Reply) -> None:  # on the node's thread
        if m.k < 0:
            return  # an initial share: no command in it
        # a command answers a sample already sent: a later step is forged (it could
        # otherwise pin the newest command or fill the table), and one older than the
        # table keeps is of no use; either costs only itself
        if m.k > self.published_k:
            self.node.refuse("future step")
            return
        if m.seq > self.published_k + SEQ_SLACK:
            # one reply per step: an agent's seq never runs past our step (one restarted
            # after a crash numbers from 0 again and is heard); nothing orders by seq
            self.node.refuse("seq ahead of our clock")
            return
        if m.k < self.published_k - self.window_steps:
            self.node.refuse("stale step")
            return
        if (m.robot, m.k) in self.commands:
            # the first command for a step is the one (a second, forged or replayed,
            # can no longer replace it: it costs only itself)
            self.node.refuse("second command for a step")
            return
        if exceeds(m.torques, m.plan, self.bounds.torque):
            self.clipped[m.robot] = self.clipped.get(m.robot, 0) + 1
            self.node.refuse("torque beyond the bound (clipped)", dropped=False)
        if velocity_exceeds(m.v_cmd):  # what a kinematic plant moves at
            self.node.refuse("velocity beyond the bound (clipped)", dropped=False)
        self.commands[(m.robot, m.k)] = m
        old = self.newest.get(m.robot)
        # newer by step (an agent restarted after a crash numbers its messages from 0
        # again, but answers the current step); the same step: the first one stays
        if old is None or m.k > old.k:
            arrived = self.node.arrival_ns()  # realtime: read at our next period, not as it came
            arrived = time.monotonic_ns() if arrived is None else arrived
            self.newest[m.robot] = m
            self.newest_at[m.robot] = arrived * 1e-9
            sent = self.sent_stamps.get(m.robot, {}).pop(m.state_seq, None)
            if sent is not None:
                # answers a recent state: state-to-command latency on our clock. (Only the
                # answer to the latest state counted before: a plant that runs late, the
                # paper at 1 kHz on 2 cores, publishes its next sample before the answers
                # to the last arrive, and reported no latency at all.)
                self.timing.add_latency(max(0, arrived - sent))
        else:
            self.node.counters.dropped += 1  # out of order: never acted on

    def handshake(self, timeout_s: float) -> None:
        """Everyone alive, say ready, then wait until everyone is ready."""
        missing = self.node.wait_for_roles(self.peers, "alive", timeout_s, self.stop)
        if not missing:
            self.node.declare_ready()
            missing = self.node.wait_for_roles(self.peers, "ready", timeout_s, self.stop)
        if missing and not self.stop():
            raise TimeoutError(f"plant: no sign of {', '.join(sorted(missing))} "
                               f"after {timeout_s:.0f} s")

    def _publish_world(self, k: int, t: float, hand_over_after: bool = False) -> None:
        """Step k's samples; ``hand_over_after`` (lockstep): the agents they woke get the
        core before the state log's bookkeeping (priority.hand_over)."""
        node = self.node
        plant_q, plant_qd = self.plant.q, self.plant.q_dot
        # the whole state within the wire's bound, checked once: every float of the
        # samples comes from it (perception: positions, velocities, the scenario's radii)
        q, qd = plant_q.tolist(), plant_qd.tolist()
        checked = within_wire_bound(q, qd)
        stamps_of, last_seq = self.sent_stamps, self.last_state_seq
        own, self.own_torques = self.own_torques, [True] * len(self.ids)
        costs, t0 = node.costs, now_ns()
        sensed = self.sense()
        costs.add(LAW, t0)  # perception: the plant's, as its integration
        for i, (rid, key, (robots, obstacles)) in enumerate(
                zip(self.ids, self.sample_keys, sensed, strict=True)):
            if self.unpowered:  # a robot nobody drives is an obstacle to the others
                off = np.isin(robots[:, 0], list(self.unpowered))
                obstacles = np.concatenate([obstacles, robots[off]])
                robots = robots[~off]
            msg = node.publish(key, lambda seq, stamp, i=i, rid=rid, r=robots, o=obstacles: Sample(
                WIRE_VERSION, 0, seq, stamp, rid, k, t, tuple(q[i]), tuple(qd[i]),
                sensed_bodies(r), sensed_bodies(o), False, own[i]), checked)
            if msg is None and not np.isfinite(q[i] + qd[i]).all():
                node.note_nonfinite(f"state of robot {rid} at t = {t:.3f} s (the plant "
                                    "diverged; its sample is not sent)")
            if msg is not None:
                last_seq[rid] = msg.seq
                stamps = stamps_of[rid]
                stamps[msg.seq] = msg.stamp_ns
                if len(stamps) > SENT_STAMPS_KEPT:
                    del stamps[next(iter(stamps))]  # the oldest (dicts keep insertion order)
        self.published_k = k
        if hand_over_after:
            hand_over()
        # lists of 3 floats as they come (the wire writes a list as it writes a tuple)
        t0, mark = now_ns(), costs.mark()
        self.log_rows.append(StateRow(k, t, q, qd, [False] * len(self.ids)))
        if len(self.log_rows) >= self.log_every:
            self.flush_log()
        costs.charge(TELEMETRY, t0, mark)

    def flush_log(self) -> None:
        """The robot states gathered so far, to observers, in one message."""
        rows, self.log_rows = self.log_rows, []
        if rows:
            self.node.publish(self.node.keys.state_log(PLANT_ROLE), lambda seq, stamp: StateLog(
                WIRE_VERSION, 0, seq, stamp, robots=list(self.ids), rows=rows))

    def _control(self, command: str, k: int = 0, t: float = 0.0, start_unix_ns: int = 0) -> None:
        self.node.publish(self.node.keys.ctl(command), lambda seq, stamp: control(
            command, seq, stamp, k=k, t=t, start_unix_ns=start_unix_ns))

    # -- lockstep -------------------------------------------------------------------
    def run_lockstep(self, steps: int, step_deadline_s: float) -> None:
        box, dt, stop, commands, ids = self.node.mailbox, self.sc.dt, self.stop, self.commands, self.ids
        k = 0

        def answered() -> bool:  # every robot's command of step k is in (or we stop)
            if stop():
                return True
            for r in ids:
                if (r, k) not in commands:
                    return False
            return True

        for k in range(steps):
            if stop():
                return
            t = k * dt
            if k % TICK_EVERY == 0:  # paces the leader's batches (deploy/nodes/leader.py)
                self._control("tick", k, t)
            self._publish_world(k, t, hand_over_after=True)
            box.wait_until(answered, step_deadline_s, ready_first=True)
            self._take_lockstep_commands(k)
            self.plant.step(t, dt, self.torques, self.v_cmd)
            self.steps_done += 1
        self.flush_log()
        self._control("end", self.steps_done, self.steps_done * dt)

    def _take_lockstep_commands(self, k: int) -> None:
        """Each robot's command of step k. For a missing one (late: counted) or one
        a faulty link lost (lockstep_inputs.py), the look-ahead torques for step k
        of the newest command (agents/look_ahead.py); past its plan, that command's
        last torques are held, or zero torque with ``plant.missed_command = "zero"``."""
        zero_missed = self.sc.spec.plant.missed_command == "zero"
        commands, links = self.commands, self.command_links
        with self.node.mailbox.lock:
            for i, rid in enumerate(self.ids):
                cmd = commands.get((rid, k))
                if cmd is not None and links[i].take_present(k, cmd):  # in, on a sound link
                    self.torques[i], self.v_cmd[i] = self.bounds.applied(cmd.torques, cmd.v_cmd)
                    continue
                if cmd is None:
                    self.node.counters.late += 1
                cmd, age = links[i].take(k, lambda idx, rid=rid: commands.get((rid, idx)))
                self.own_torques[i] = cmd is not None and age == 0
                if cmd is None:
                    continue
                k_cmd = k - age
                planned = torques_at(k_cmd, cmd.torques, cmd.plan, k,
                                     "zero" if zero_missed else "hold")
                if planned is None:  # "zero": past the newest command's plan
                    self.torques[i], self.v_cmd[i] = 0.0, 0.0
                else:  # its own command, its look-ahead for step k, or held past it
                    self.torques[i], self.v_cmd[i] = self.bounds.applied(planned, cmd.v_cmd)
            for rid in self.ids:
                self.commands.pop((rid, k - self.keep_steps), None)
            if k % 256 == 0:  # and any that came in late for a step already forgotten
                for key in [key for key in self.commands if key[1] <= k - self.keep_steps]:
                    del self.commands[key]

    # -- realtime -------------------------------------------------------------------
    def run_realtime(self, steps: int) -> None:
        dt = self.sc.dt
        # woken by its clock alone: the commands of a period are read at the next one
        # (where they act), stamped by the kernel as they came (the latency's end)
        self.node.wake_on(())
        self.node.stamp_arrivals()
        self.node.connect_ahead([*self.sample_keys, self.node.keys.state_log(PLANT_ROLE)])
        start_unix_ns = time.time_ns() + int(START_LEAD_S * 1e9)
        t0 = time.monotonic() + START_LEAD_S
        self._control("start", start_unix_ns=start_unix_ns)
        ticker = Periodic(t0, dt, self.timing, self.node.mailbox)
        k_prev = None
        costs = self.node.costs
        while not self.stop():
            k = ticker.wait_next(self.stop)
            if k is None or k >= steps:
                break
            if k_prev is not None:
                # integrate [t_prev, t_k] with what the agents answered meanwhile:
                # an answer within one period acts as in lockstep
                t0 = now_ns()
                self._apply_newest_commands(time.monotonic())
                for _ in range(k - k_prev):
                    self._play_plans(self.steps_done)
                    self.plant.step(self.steps_done * dt, dt, self.torques, self.v_cmd)
                    self.steps_done += 1
                costs.add(LAW, t0)
            self._publish_world(k, k * dt)
            k_prev = k
            if k == steps - 1:
                # the last sample is out: say end now, not a period later (the agents
                # waited that period for a sample that never came, each counting a miss)
                break
        self.flush_log()
        self._control("end", self.steps_done, self.steps_done * dt)

    def _apply_newest_commands(self, now: float) -> None:
        with self.node.mailbox.lock:
            for i, rid in enumerate(self.ids):
                cmd = self.newest.get(rid)
                if cmd is None or now - self.newest_at[rid] > self.command_timeout_s:
                    self.torques[i] = 0.0  # no command, or a stale one: stop pushing
                    self.v_cmd[i] = 0.0
                    if cmd is not None and rid not in self.unpowered:
                        self.unpowered.add(rid)
                        age, t = now - self.newest_at[rid], self.steps_done * self.sc.dt
                        self.command_stops.append((rid, age, t))
                        self.zero_torque.begin(rid, t)
                        print(f"plant: t = {t:.3f} s: newest command from {agent_role(rid)} is "
                              f"{age * 1e3:.1f} ms old: torques zeroed; the others now perceive "
                              f"robot {rid} as an obstacle", flush=True)
                else:
                    self.torques[i], self.v_cmd[i] = self.bounds.applied(cmd.torques, cmd.v_cmd)
                    if rid in self.unpowered:
                        self.unpowered.discard(rid)
                        self.zero_torque.end(rid, self.steps_done * self.sc.dt)
                if cmd is None or cmd.state_seq != self.last_state_seq.get(rid):
                    # the latest state went unanswered: the agent's lateness (or silence),
                    # not a miss of this loop (its own: Periodic's skipped periods)
                    self.unanswered[i] += 1
            self.commands.clear()

    def _play_plans(self, k: int) -> None:
        """Realtime: a robot whose newest command answers an earlier step than the
        one being integrated (its later ones are late or lost) plays that
        command's look-ahead torques for step k; past its plan the last of them is
        held, as in lockstep (until the command timeout zeroes the robot). A robot
        not on its agent's own command for step k (a look-ahead, or zero torque: none,
        or a stale one) is noted for its next sample (Sample.own_torques)."""
        with self.node.mailbox.lock:
            for i, rid in enumerate(self.ids):
                cmd = self.newest.get(rid)
                if cmd is not None and rid not in self.unpowered and cmd.k >= k:
                    continue  # its agent's own command for step k
                self.own_torques[i] = False  # zero torque, or a look-ahead below
                if cmd is None or rid in self.unpowered:
                    continue
                planned = torques_at(cmd.k, cmd.torques, cmd.plan, k)
                self.torques[i], self.v_cmd[i] = self.bounds.applied(planned, cmd.v_cmd)

    def finish(self, linger_s: float = 5.0) -> None:
        """Report, then stay until the other nodes have left after ``end``, so
        none of them mistakes our leaving for a crash of the plant."""
        log = contact_log(self.plant)
        contacts = None if log is None else [ContactRecord(**e) for e in log[:MAX_CONTACTS]]
        self.plant.close()
        if self.gate is not None:
            self.gate.close()
        spool = self.node.spool
        if spool is not None:  # its record of the samples and replies, whole before the report
            spool.flush()
        publish_report(self.node, -1, self.steps_done, self.timing, contacts=contacts,
                       contacts_total=0 if log is None else len(log),
                       faults=self.faults.report(), command_stops=self.command_stops[:1000],
                       zero_torque=self.zero_torque.close(self.steps_done * self.sc.dt),
                       torque_clipped={str(r): n for r, n in self.clipped.items()},
                       unanswered=self.unanswered,
                       unrecorded=0 if spool is None else spool.lost)
        others = set(self.peers) - {LAUNCHER_ROLE}
        self.node.mailbox.wait_until(lambda: not (others & self.node.peers_alive), linger_s)
