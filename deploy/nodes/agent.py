"""One robot's agent as a process: a zenoh peer around :class:`AgentCore`.

Hears only what the scenario's graph gives it (docs/distributed.md): its robot's sample
(state + perception), the replies of the j with a_ij != 0 (their shares), the
leader iff b_i != 0, and ``ctl/*``. Publishes one reply per step (its robot's
wheel command with the share its listeners read) and batched telemetry.

lockstep: step k waits for sample k, the leader at k (sent in batches ahead of
need) and the neighbours' shares of step k-1, so it computes exactly what the
in-process reference computes. An input missing at the per-step deadline is
counted as late and the step goes on with what it last had.

realtime: a step runs as soon as a new sample arrives (or one and a half periods
after the last step, with what it has); t is this process's clock since start.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import msgspec
import numpy as np

from agents.core import AgentOutput, Share
from agents.degradation import InputAges, predict
from agents.look_ahead import LookAhead
from agents.pace import LoopPace
from agents.plugged import make_core
from agents.rehearsal import rehearsal_wait, rehearse
from deploy.contract.fault_plan import FaultPlan
from deploy.contract.options import DEFAULT_STEP_DEADLINE_S
from deploy.contract.scenario import Scenario
from deploy.contract.wire import (
    LAUNCHER_ROLE,
    LEADER_ROLE,
    MAX_LAW_ERROR_CHARS,
    PLANT_ROLE,
    WIRE_VERSION,
    LeaderState,
    Reply,
    Sample,
    Telemetry,
    TelemetryRow,
    Vec3,
    Vec4,
    agent_role,
)
from deploy.nodes.leader import LOOKAHEAD, TICK_EVERY
from deploy.runtime.fault_model import FaultModel
from deploy.runtime.lockstep_inputs import AgentLinks
from deploy.runtime.node_runtime import (
    ControlInbox,
    FaultGate,
    StopFlag,
    Timing,
    process_age_s,
    publish_report,
)
from deploy.runtime.priority import hand_over
from deploy.runtime.step_costs import LAW, TELEMETRY, now_ns
from deploy.runtime.step_guard import CLOCK_SKEW_S, JUMP_OK, OwnClock, StepGuard
from deploy.runtime.transport import Node

KEEP_STEPS = 4  # lockstep inputs kept behind the current step
FORGET_EVERY = 32  # lockstep: older inputs are dropped every this many steps (a scan)
# how far past the newest sample a stored input may be: the leader's batches run up to
# LOOKAHEAD + TICK_EVERY steps ahead; a neighbour answers the samples we get too
LEADER_AHEAD_STEPS = LOOKAHEAD + TICK_EVERY + JUMP_OK
SHARE_AHEAD_STEPS = JUMP_OK + 1
REALTIME_SHARES_KEPT = 8  # realtime: a neighbour's newest shares kept by step
TELEMETRY_HZ = 100.0  # realtime telemetry rate (lockstep: every step)
# realtime: the samples a late loop steps its law on before the newest (AgentNode._catch_up);
# past them, the oldest step over the periods between (a loop that far behind is overloaded,
# and each costs the law's step again)
MAX_CATCH_UP = 3
TELEMETRY_BATCH_S = 0.1  # telemetry rows go out in batches of this much run time (at most)
# ... and at most this many rows (lockstep: 8 steps a message, ~2.1 kB): zenoh 1.10 grows a
# process by 16-44 MB the first time it moves a message of more than ~3 kB (measured), so
# no message of the regular traffic is that large
TELEMETRY_BATCH_MAX = 8


class LeaderPoint(NamedTuple):
    """The leader at one step, unpacked from a (batched) :class:`LeaderState`."""

    k: int
    t: float
    q: Vec3
    q_dot: Vec3


def leader_points(m: LeaderState, dt: float) -> list[LeaderPoint]:
    return [LeaderPoint(m.k + i, m.t + i * dt, q, qd)
            for i, (q, qd) in enumerate(zip(m.q, m.q_dot, strict=True))]


def step_input(by_step: dict[int, Any], k: int) -> tuple[Any, int]:
    """Realtime: the input of step ``k`` and its step, else the newest before it (None,
    -1: none); older ones are forgotten (the table keeps what is still to come)."""
    found = by_step.get(k)
    if found is not None:
        kk = k
    else:
        kk = max((s for s in by_step if s < k), default=-1)
        found = by_step.get(kk)
    for s in [s for s in by_step if s < kk]:
        del by_step[s]
    return found, kk


def step_ages(k: int, leader_k: int, shares: dict[int, Reply], dt: float) -> InputAges:
    """Realtime: how much older each input is than the one a lockstep step k takes (the
    leader at k, each neighbour's share of k - 1), by the steps the messages carry (the
    nodes' clocks tick together from the same start)."""
    return InputAges(0.0, 0.0 if leader_k < 0 else max(0.0, (k - leader_k) * dt),
                     {j: max(0.0, (k - 1 - m.k) * dt) for j, m in shares.items()})


def _no_clock() -> float:
    """Lockstep streams are judged by step alone (StepGuard without a period)."""
    return 0.0


def _stale(ages: InputAges | None) -> int:
    """Inputs older than in a fault-free run."""
    if ages is None:
        return 0
    return int(ages.state_s > 0) + int(ages.leader_s > 0) + sum(a > 0 for a in ages.shares_s.values())


def _finite_row(r: TelemetryRow) -> TelemetryRow:
    """The row with every non-finite number zeroed and ``nonfinite`` set (the wire
    refuses NaN; the verdict must still see that the law diverged)."""
    import math

    def fix(v):
        if isinstance(v, float):
            return v if math.isfinite(v) else 0.0
        if isinstance(v, tuple):
            return tuple(fix(x) for x in v)
        return v
    bad = any(fix(getattr(r, f)) != getattr(r, f) for f in r.__struct_fields__
              if isinstance(getattr(r, f), float | tuple))
    fixed = {f: fix(getattr(r, f)) for f in r.__struct_fields__ if f != "nonfinite"}
    return msgspec.structs.replace(r, **fixed, nonfinite=r.nonfinite or bad)


class MissedStep(NamedTuple):
    """A sample a realtime agent answered too late, with the inputs of its step."""

    state: Sample
    leader: LeaderPoint | None
    leader_k: int
    shares: dict[int, Reply]


@dataclass
class AgentInputs:
    """Everything received, keyed by step (lockstep) and the newest (realtime).
    Written by the handlers on the node's thread as it waits."""

    states: dict[int, Sample]
    leaders: dict[int, LeaderPoint]
    shares: dict[tuple[int, int], Reply]  # lockstep: by (neighbour, step)
    newest_share: dict[int, Reply]  # per neighbour, by step
    newest_state: Sample | None = None
    newest_leader: LeaderPoint | None = None
    # realtime: per neighbour, its shares by step, the newest few (step_input takes them)
    shares_of: dict[int, dict[int, Reply]] = field(default_factory=dict)

    @classmethod
    def empty(cls) -> AgentInputs:
        return cls({}, {}, {}, {})


class AgentNode:
    def __init__(self, sc: Scenario, robot_id: int, node: Node, stop: StopFlag,
                 with_recorder: bool = False, plant_role: str = PLANT_ROLE,
                 faults: FaultPlan | None = None, realtime: bool = False,
                 step_deadline_s: float = DEFAULT_STEP_DEADLINE_S) -> None:
        """``plant_role``: who publishes this robot's state (the plant, or a CAN bridge);
        ``faults``: the run's fault plan (this agent applies the faults of the
        edges it receives on: in lockstep when it picks a step's inputs, in
        realtime as messages arrive); ``step_deadline_s``: the plant's (lockstep),
        which bounds how far ahead of our last answer the plant can be."""
        self.sc, self.node, self.stop = sc, node, stop
        self.plant_role = plant_role
        self.index = sc.index_of(robot_id)
        self.rid = robot_id
        q, qd = sc.initial_state()
        q0h, v0h = sc.initial_estimates(self.index)
        self._law, self._law_params = sc.law()  # the paper's (None), or a lab's own
        self.core = make_core(sc.agent_config(self.index), self._law, self._law_params,
                              q[self.index], qd[self.index], q0h, v0h)
        self.neighbours = [j for j, _ in self.core.cfg.neighbours]
        self.hears_leader = self.core.cfg.leader_weight != 0.0
        self.inputs = AgentInputs.empty()
        self.last_shares: dict[int, Share] = {}
        self.faults = FaultModel(faults, sc.dt)
        self.links: AgentLinks = AgentLinks(self.faults, robot_id, self.neighbours,
                                            self.hears_leader)
        self.keep_steps = KEEP_STEPS + self.faults.max_lag_steps
        self.gate = FaultGate(self.faults, node.mailbox) if realtime and faults else None
        # commands can be lost or late only with a fault plan or on the realtime clock
        horizon = sc.spec.degradation.command_horizon if (faults or realtime) else 0
        self.look_ahead = LookAhead(self.core, horizon) if horizon else None
        self.timing = Timing()
        # the newest step of each input stream (lockstep starts before step 0; a
        # realtime agent may join a running fleet: it takes the first step it hears)
        period = sc.dt if realtime else None  # realtime streams may skip steps (step_guard.py)
        self.guards: dict[str, StepGuard] = {
            "sample": StepGuard(newest=None if realtime else -1, period_s=period),
            "leader": StepGuard(period_s=period)}
        # the newest step any sender can be at, on our own clock (step_guard.OwnClock):
        # lockstep from our last answer and the plant's deadline, realtime from t = 0
        self.clock = OwnClock(sc.dt, None if realtime else step_deadline_s,
                              answered_at=time.monotonic())
        # the law restarted from the robot: after a gap longer than the inputs stay fresh
        # (realtime), or from a non-finite state (AgentCore.recover)
        self.law_resets = 0
        self.nonfinite_commands = 0  # steps whose law gave NaN/Inf: zero torques sent
        self.stale_samples = 0  # realtime: samples older than stale_after_s, not answered
        self.caught_up = 0  # realtime: samples answered a period late, the law stepped on them
        self.overloaded_steps = 0  # realtime: steps of a loop slower than its period (pace.py)
        self.rejoin_s = -1.0  # rejoining: its process start to its first command, s
        self.steps_done = 0
        self.telemetry_every = 1  # realtime decimates (see run_realtime)
        self.telemetry_batch = TELEMETRY_BATCH_MAX
        self._rows: list[TelemetryRow] = []
        self.peers = [plant_role, *(agent_role(j) for j in self.neighbours),
                      *(agent_role(j) for j in sc.listeners(self.index))]
        if self.hears_leader:
            self.peers.append(LEADER_ROLE)
        if with_recorder:
            self.peers.append(LAUNCHER_ROLE)
        self._warned_ahead: set[str] = set()  # the kinds refused as ahead, said once each
        self._subscribe()
        self.control = ControlInbox(node, stop)
        node.declare_alive()

    # -- subscriptions: exactly the graph's ------------------------------------------
    def _subscribe(self) -> None:
        keys, inp, rid = self.node.keys, self.inputs, self.rid

        dt, guards, own = self.sc.dt, self.guards, self.clock
        refuse, refuse_ahead = self.node.refuse, self._refuse_ahead
        period = self.guards["sample"].period_s
        share_guards = {j: StepGuard(period_s=period) for j in self.neighbours}  # one per neighbour
        clock = time.monotonic if period is not None else _no_clock
        now = time.monotonic
        # lockstep stores inputs by step until they are used: those far ahead of our own
        # sample stream are refused so the tables stay bounded. Realtime keeps only the
        # newest of each stream (its own guard) and clears the tables every step, and a
        # CAN bridge's or a late agent's steps are not ours: no cross-stream check there
        lockstep = period is None

        # What becomes the newest, and what is stored, is judged by the step a message
        # carries against the stream so far (deploy/runtime/step_guard.py): a forged step far
        # ahead is held until confirmed, never adopted by itself, so it cannot hang a
        # lockstep agent or silence a realtime one; what is stored stays near the
        # newest (bounded tables), and a step already stored is not overwritten.
        def on_sample(m: Sample) -> None:
            why = own.refusal(m.k, m.seq, now())
            if why is not None:  # cannot be real yet: costs only itself
                refuse_ahead("sample", why)
                return
            g = guards["sample"]
            if g.admit(m.k, clock()):
                inp.states[m.k] = m
                inp.newest_state = m
            elif g.newest is not None and g.newest - self.keep_steps < m.k <= g.newest:
                inp.states.setdefault(m.k, m)  # late, but still of use (a delayed link)
            else:
                refuse("sample step")

        def on_leader(m: LeaderState) -> None:
            g, ahead, at = guards["leader"], guards["sample"], clock()
            why = own.refusal(m.k + len(m.q) - 1, m.seq, now(), LEADER_AHEAD_STEPS)
            if why is not None:
                refuse_ahead("leader", why)
                return
            for p in leader_points(m, dt):
                if lockstep and not ahead.within(p.k, LEADER_AHEAD_STEPS):
                    refuse("leader step")
                    continue
                inp.leaders.setdefault(p.k, p)
                if g.admit(p.k, at):
                    inp.newest_leader = p

        def on_share(m: Reply) -> None:
            why = own.refusal(m.k, m.seq, now())
            if why is not None:
                refuse_ahead("share", why)
                return
            at = clock()
            if lockstep:
                if not guards["sample"].within(m.k, SHARE_AHEAD_STEPS):
                    refuse("share step")
                    return
                inp.shares.setdefault((m.robot, m.k), m)
                if share_guards[m.robot].admit(m.k, at):
                    inp.newest_share[m.robot] = m
                return
            g = share_guards[m.robot]
            mine = inp.shares_of.setdefault(m.robot, {})
            if g.admit(m.k, at):
                inp.newest_share[m.robot] = m
                mine[m.k] = m
                if len(mine) > REALTIME_SHARES_KEPT:  # step_input forgets as it takes
                    del mine[min(mine)]
            elif g.newest is not None and g.newest - REALTIME_SHARES_KEPT < m.k < g.newest:
                mine.setdefault(m.k, m)  # late, but maybe still the one of its step

        me, gate = agent_role(rid), self._gated
        self.node.subscribe(keys.sample(rid), Sample,
                            gate(self.plant_role, me, on_sample), robot=rid)
        if self.hears_leader:
            self.node.subscribe(keys.leader_state, LeaderState, gate(LEADER_ROLE, me, on_leader))
        for j in self.neighbours:
            self.node.subscribe(keys.cmd(j), Reply, gate(agent_role(j), me, on_share), robot=j)

    def _refuse_ahead(self, what: str, why: str) -> None:
        """Refuse (and count) a message whose step cannot be real yet by our clock; say
        so once per kind: a real sender here means clocks that disagree."""
        self.node.refuse(f"{what}: {why}")
        if what not in self._warned_ahead:
            self._warned_ahead.add(what)
            print(f"{self.node.role}: refused a {what} ({why}; counted): forged, or "
                  "on the realtime clock a host whose wall clock is ahead of ours by "
                  f"more than {CLOCK_SKEW_S * 1e3:.0f} ms (NTP)", file=sys.stderr,
                  flush=True)

    def _gated(self, src: str, dst: str, on_message):
        """Realtime with a fault plan: the edge's faults act as messages arrive
        (one decision per edge and step)."""
        if self.gate is None:
            return on_message
        return self.gate.wrap(src, dst, on_message)

    # -- start --------------------------------------------------------------------
    def handshake(self, timeout_s: float) -> None:
        """Wait for the peers we talk with, say ready, publish the initial share."""
        missing = self.node.wait_for_roles(self.peers, "alive", timeout_s, self.stop)
        if missing and not self.stop():
            raise TimeoutError(f"{self.node.role}: no sign of {', '.join(sorted(missing))} "
                               f"after {timeout_s:.0f} s")
        self._publish_reply(-1, 0.0, None, None, self.core.initial_share, [])
        self.node.declare_ready()

    # -- publishing ---------------------------------------------------------------
    def _publish_reply(self, k: int, t: float, state: Sample | None, out: AgentOutput | None,
                       s: Share, plan: list[Vec4]) -> None:
        """The step's one message: command (none before the first step: k = -1,
        zero torques) and share."""
        rid = self.rid
        torques = (0.0, 0.0, 0.0, 0.0) if out is None else out.torques
        v_cmd = (0.0, 0.0, 0.0) if out is None else out.v_cmd
        self.clock.answer(k, time.monotonic())  # lockstep: the plant can be one step past it
        self.node.publish(self.node.keys.cmd(rid), lambda seq, stamp: Reply(
            WIRE_VERSION, rid, seq, stamp, robot=rid, k=k, t=t, torques=torques, v_cmd=v_cmd,
            state_seq=-1 if state is None else state.seq,
            # the share as the core made it: every core builds its shares of float tuples
            # (AgentCore from the kernel's, PluggedCore through its check of a law's)
            state_stamp_ns=0 if state is None else state.stamp_ns, share=s, plan=plan))

    def _publish_step(self, k: int, t: float, state: Sample, out: AgentOutput,
                      plan: list[Vec4], stale: int) -> None:
        self._publish_reply(k, t, state, out, out.share, plan)
        hand_over()  # the receivers it woke first, then telemetry (priority.hand_over)
        if out.nonfinite:  # the law gave NaN/Inf: zero torques went out instead
            self.nonfinite_commands += 1
            self.node.note_nonfinite(f"command at t = {t:.3f} s (step {k}): the control law "
                                     "diverged, zero torques sent instead")
        if out.reset:
            self.law_resets += 1
            if self.law_resets <= 3:
                print(f"{self.node.role}: t = {t:.3f} s (step {k}): non-finite "
                      f"{', '.join(out.reset)} restarted from the robot's state",
                      file=sys.stderr, flush=True)
        if k % self.telemetry_every:
            return
        costs = self.node.costs
        t0, mark = now_ns(), costs.mark()
        self._telemetry_row(k, t, out, stale)
        costs.charge(TELEMETRY, t0, mark)

    def _telemetry_row(self, k: int, t: float, out: AgentOutput, stale: int) -> None:
        fdb = out.task_errors.get("FDB")
        f = out.safety
        acted = f is not None and f.active
        # every vector of the output is a float tuple from the compiled law
        self._rows.append(TelemetryRow(
            k, t, out.q_d, out.tracking_error, out.sliding, out.v_cmd, out.torques,
            out.share.q0_hat, out.q_fd, None if fdb is None else float(fdb), ">".join(out.order),
            out.nonfinite, stale, out.input_age_s, out.speed_factor, out.left_out,
            f.dv if acted else 0.0, f.infeasible if acted else False,
            self.timing.deadline_misses))
        if len(self._rows) >= self.telemetry_batch:
            self.flush_telemetry()

    def flush_telemetry(self) -> None:
        """Send the telemetry rows gathered so far, in one message. A row that is
        not finite (a diverged law) is sent with its non-finite numbers zeroed and
        ``nonfinite`` set, so the run's verdict sees it."""
        rows, self._rows, rid = self._rows, [], self.rid
        if not rows:
            return
        sent = self.node.publish(self.node.keys.telemetry(rid), lambda seq, stamp: Telemetry(
            WIRE_VERSION, rid, seq, stamp, robot=rid, rows=rows))
        if sent is None:  # a non-finite value: send the rows with it zeroed, flagged
            self.node.note_nonfinite(f"telemetry row (steps {rows[0].k}-{rows[-1].k}), sent "
                                     "with its non-finite numbers zeroed and flagged")
            safe = [_finite_row(r) for r in rows]
            self.node.publish(self.node.keys.telemetry(rid), lambda seq, stamp: Telemetry(
                WIRE_VERSION, rid, seq, stamp, robot=rid, rows=safe))

    def _leader_input(self, leader: LeaderPoint | None) -> tuple | None:
        """The leader a step takes: the one heard, else (never heard yet) the agent's own
        estimate of it, or None for an agent that does not hear the leader."""
        if leader is not None:
            return leader.q, leader.q_dot
        return (self.core.q0_hat_vec, self.core.v0_hat_vec) if self.hears_leader else None

    def _compute(self, t: float, state: Sample, leader: LeaderPoint | None,
                 dt: float | None = None, ages: InputAges | None = None,
                 horizon: float | None = None, speed_cap: float = 1.0,
                 ) -> tuple[AgentOutput, list[Vec4]]:
        """The step's output and its look-ahead torques (empty when off); ``horizon``,
        ``speed_cap``: the realtime loop's pace (agents/pace.py)."""
        # the wire's sensed bodies as they are: the kernel reads their fields
        robots, obstacles = state.robots, state.obstacles
        lead = self._leader_input(leader)
        q, q_dot = state.q, state.q_dot
        t0 = now_ns()
        out = self.core.step(t, q, q_dot, self.last_shares, lead, obstacles, robots, dt, ages,
                             horizon, speed_cap, state.own_torques)
        plan = [] if self.look_ahead is None else self.look_ahead.plan(
            self.core, out, t, q, q_dot, self.last_shares, lead, obstacles, robots, ages)
        self.node.costs.add(LAW, t0)
        return out, plan

    # -- lockstep -----------------------------------------------------------------
    def _lockstep_ready(self, k: int) -> bool:
        inp = self.inputs
        return (self.stop() or (
            k in inp.states
            and (not self.hears_leader or k in inp.leaders)
            and all((j, k - 1) in inp.shares for j in self.neighbours)
        ))

    def run_lockstep(self, step_deadline_s: float) -> None:
        inp, box, stop, counters = self.inputs, self.node.mailbox, self.stop, self.node.counters
        states, leaders, shares_in = inp.states, inp.leaders, inp.shares
        neighbours, hears_leader, dt = self.neighbours, self.hears_leader, self.sc.dt
        k = 0

        def newest() -> int:  # the plant's newest step heard (the sample guard's)
            return k if inp.newest_state is None else inp.newest_state.k

        def has_sample() -> bool:  # the plant's step k, or a later one, is in
            return stop() or (inp.newest_state is not None and inp.newest_state.k >= k)

        def ready() -> bool:  # everything step k uses is in
            if stop():
                return True
            if k not in states or (hears_leader and k not in leaders):
                return False
            for j in neighbours:
                if (j, k - 1) not in shares_in:
                    return False
            return True

        heard_all = not neighbours
        while not stop():
            if not ready():
                # wait for the plant's step k or a later one (with no deadline: the plant
                # may be slow to start or to step; it ends the run with ``end``). A later
                # one: step k's state was lost (a cut link): catch up, counted late.
                box.wait_until(has_sample, 3600.0, ready_first=True)
                if stop():
                    break
                if newest() > k:
                    counters.late += newest() - k
                    k = newest()
                box.wait_until(ready, step_deadline_s, ready_first=True)
            with box.lock:
                if newest() > k:  # we fell behind the plant: skip to its newest step
                    counters.late += newest() - k
                    k = newest()
                # the arrival of step k's messages is the clock; the links pick
                # the samples a faulty edge lets through (deploy/runtime/lockstep_inputs.py)
                state, leader, shares, ages = self.links.take(
                    k, states.get, leaders.get, shares_in.get, dt)
                missing = int(hears_leader and k not in leaders)
                for j in neighbours:
                    missing += (j, k - 1) not in shares_in
                if k % FORGET_EVERY == 0:
                    self._forget_before(k - self.keep_steps)
            counters.late += missing
            for j, msg in shares.items():
                if msg is not None:
                    self.last_shares[j] = msg.share
            if not heard_all:
                unheard = [j for j in neighbours if j not in self.last_shares]
                if unheard:  # never heard from a neighbour: cannot compute eq. (16)
                    print(f"{self.node.role}: no share ever received from {unheard}",
                          file=sys.stderr)
                    continue
                heard_all = True
            t = k * dt
            out, plan = self._compute(t, state, leader, ages=ages)
            self._publish_step(k, t, state, out, plan, missing if ages is None
                               else missing + _stale(ages))
            self.steps_done += 1
            k += 1

    def _forget_before(self, k: int) -> None:
        inp = self.inputs
        for d in (inp.states, inp.leaders):
            for kk in [kk for kk in d if kk < k]:
                del d[kk]
        for key in [key for key in inp.shares if key[1] < k]:
            del inp.shares[key]

    # -- realtime -----------------------------------------------------------------
    def run_realtime(self, t0_mono: float | None, telemetry_hz: float = TELEMETRY_HZ,
                     steps: int | None = None) -> None:
        """``t0_mono`` None: this agent rejoins a running fleet (restarted after a
        crash): t = 0 is read from the plant's first state, and the leader
        estimate and reference restart from what the leader or neighbours say
        (:meth:`_resync`). ``steps``: the run's (the scenario's unless said).

        Each step is built as a lockstep step is: the sample of step k, the leader at
        step k (its batches run ahead) and each neighbour's share of step k - 1 (its
        answer to the sample before ours). One that is not in is taken from the newest
        before it, predicted to its step by its true age (agents/degradation.py). Taking
        whatever came last instead (the leader of k or k - 1, a neighbour's share of k
        when it ran first) switched the finite-time terms of eq. (14) from step to step:
        the wheel torques' second difference was 10-100x lockstep's (docs/bench-history.md)."""
        steps = self.sc.steps if steps is None else steps
        inp, box, dt = self.inputs, self.node.mailbox, self.sc.dt
        self._realtime_telemetry(telemetry_hz)
        # woken by its robot's sample only: the leader's batches and the neighbours'
        # shares wait in their sockets until then (deploy/runtime/datagrams.py)
        self.node.wake_on([self.node.keys.sample(self.rid)])
        keys = self.node.keys
        self.node.connect_ahead([keys.cmd(self.rid), keys.telemetry(self.rid)])
        if t0_mono is not None:
            self._rehearse(t0_mono)
        last_k = -1
        last_step = None
        pace = LoopPace(dt)
        stale_after = self.core.cfg.degradation.stale_after_s
        last_t: float | None = None
        share_msgs: dict[int, Reply] = {}
        synced = t0_mono is not None
        rejoining = False  # until a rejoining agent's first command is out
        self.clock.t0_s = t0_mono  # no sender is past the wall clock (step_guard.OwnClock)
        stop, monotonic = self.stop, time.monotonic

        def has_new_sample() -> bool:
            return stop() or (inp.newest_state is not None and inp.newest_state.k > last_k)

        while not stop():
            if not self._await_sample(has_new_sample, last_k, steps) or stop():
                continue  # (a stop ends the loop)
            box.drain()  # what came meanwhile without waking us: shares, the leader
            now = monotonic()
            missed = self._missed_inputs(last_k)
            state, leader, leader_k = self._step_inputs(share_msgs)
            if state is None:
                continue
            if synced and self._stale_sample(state, now - t0_mono, stale_after):
                last_k = state.k  # skip to a fresh one, which restarts the law once (below)
                continue
            if last_step is not None:
                self.timing.add_jitter(int(abs((now - last_step) - dt) * 1e9))
                pace.note(now - last_step)
            last_step = now
            last_k = state.k
            # the observer and the reference advance by the plant's own step
            # between the states we answer (more than dt when we missed some)
            h = dt if last_t is None or state.t <= last_t else state.t - last_t
            last_t = state.t
            if any(j not in share_msgs for j in self.neighbours):
                continue
            ages = step_ages(state.k, leader_k, share_msgs, dt)
            if synced and h > stale_after and self._restart_after_gap(state, leader,
                                                                      share_msgs, ages):
                h = dt
            if not synced:
                if not self._resync(state, leader, share_msgs, ages):
                    continue
                t0_mono, synced, rejoining = now - state.t, True, True
                self.clock.t0_s = t0_mono
            elif missed and dt < h <= stale_after:  # one period after, unless one never came
                h = state.t - self._catch_up(missed, state.t - h, pace, now - t0_mono)
            for j, msg in share_msgs.items():
                self.last_shares[j] = msg.share
            cap = pace.speed_cap()
            if cap < 1.0:  # the loop cannot keep its period: slow the robot, say so
                self._note_overloaded(pace, cap)
            # the law's time is the sample's (as in lockstep), how late we answer it the
            # horizon's (agents/pace.py); fresh inputs, as a fault-free lockstep step has
            # them: no ages at all (the kernel skips the degradation's bookkeeping)
            out, plan = self._compute(state.t, state, leader, h, None if ages.fresh else ages,
                                      pace.horizon(now - t0_mono - state.t), cap)
            self._publish_step(state.k, state.t, state, out, plan, _stale(ages))
            self.steps_done += 1
            if rejoining:  # the first command of a restarted agent: how long it took
                rejoining = False
                self._note_rejoined()

    def _rehearse(self, t0_mono: float) -> None:
        """Just before t = 0, the paper's law stepped on a scratch core (agents/rehearsal.py):
        the run's first answers come sooner and at fewer different steps. Waits on the
        mailbox until then (a stop ends the wait)."""
        wait = rehearsal_wait(t0_mono, time.monotonic())
        if self._law is not None or wait is None:  # a lab's own law: stepped by the run alone
            return
        if wait > 0.0:
            self.node.mailbox.wait_until(self.stop, wait)
        if self.stop():
            return
        q, qd = self.sc.initial_state()
        q0h, v0h = self.sc.initial_estimates(self.index)
        i = self.index
        shares = {j: self.core.initial_share for j in self.neighbours}  # their shape
        horizon = 0 if self.look_ahead is None else self.look_ahead.horizon
        rehearse(self.core.cfg, q[i], qd[i], q0h, v0h, shares, self._leader_input(None),
                 self.sc.obstacle_bodies(), horizon)

    def _await_sample(self, has_new_sample: Callable[[], bool], last_k: int,
                      steps: int) -> bool:
        """Realtime: wait at most 1.5 periods for a new sample (True: it came, or a stop).
        None came: stepping again on the old one would integrate the observer on stale
        data; the agent waits (the plant zeroes its torques after its command timeout)
        and counts the miss (none before the first sample; after the run's last step,
        only ``end`` comes)."""
        if self.node.mailbox.wait_until(has_new_sample, 1.5 * self.sc.dt, ready_first=True):
            return True
        if not self.stop() and self.inputs.newest_state is not None and last_k < steps - 1:
            self.timing.deadline_misses += 1
        return False

    def _stale_sample(self, state: Sample, run_time_s: float, stale_after_s: float) -> bool:
        """A sample older than the inputs stay fresh, by our clock (counted): the backlog
        of a process that was off the CPU (SIGSTOP, a starved host). Answering it computed
        commands from where the robot was seconds ago (a paused lab agent stepped 3
        backlog samples 0.3-0.8 s old, restarting its law on each)."""
        if run_time_s - state.t <= stale_after_s:
            return False
        self.stale_samples += 1
        return True

    def _restart_after_gap(self, state: Sample, leader: LeaderPoint | None,
                           shares: dict[int, Reply], ages: InputAges) -> bool:
        """This process was off the CPU (paused, starved) longer than its inputs stay
        fresh: the plant has zeroed the robot meanwhile. Integrating the observer, the
        estimator and the reference across the gap left a paused lab agent 5 cm off for
        good (SIGSTOP 2 s): they start again from where the robot and the leader are now,
        as a restarted agent's do (counted as a law reset). Whether they did."""
        if not self._resync(state, leader, shares, ages):
            return False
        self.law_resets += 1
        return True

    def _missed_inputs(self, last_k: int) -> list[MissedStep]:
        """Realtime, before :meth:`_step_inputs`: the samples between the last one answered
        and the newest that came and went unanswered (this loop was late), oldest first, at
        most ``MAX_CATCH_UP``, each with the leader at its step and the neighbours' shares
        of the step before it (else the newest before each). Taken first: the tables
        forget what is older than what is taken."""
        inp = self.inputs
        with self.node.mailbox.lock:
            newest = inp.newest_state
            if newest is None:
                return []
            first = max(last_k + 1, newest.k - MAX_CATCH_UP)
            missed = []
            for k in range(first, newest.k):
                state = inp.states.get(k)
                if state is None:
                    continue
                leader, leader_k = step_input(inp.leaders, k)
                shares: dict[int, Reply] = {}
                self._shares_of_step(k - 1, shares)
                missed.append(MissedStep(state, leader, leader_k, shares))
        return missed

    def _catch_up(self, missed: list[MissedStep], last_t: float, pace: LoopPace,
                  run_time_s: float) -> float:
        """The law's step on each sample this loop answered too late (a newer one came
        meanwhile), their commands never sent, so that the newest's step is one period
        long, as in lockstep. One step over the periods missed instead integrated the
        reference (eq. 11) and the observer (39) over them ahead of one: ``paper`` at
        1 kHz on one core, an agent answering 1-3 % of its samples a period late, kept its
        robot 5-14 cm off its reference for hundreds of ms at a time and never settled
        (docs/bench-history.md). ``last_t``: the time of the sample answered before.
        Returns the time of the last sample stepped on, ``last_t`` if none was: one is not
        stepped on before every neighbour was heard (as the newest is not), and the next
        step then spans its period too."""
        dt = self.sc.dt
        for step in missed:
            state = step.state
            if any(j not in step.shares for j in self.neighbours):
                continue
            for j, msg in step.shares.items():
                self.last_shares[j] = msg.share
            ages = step_ages(state.k, step.leader_k, step.shares, dt)
            lead = self._leader_input(step.leader)
            h = dt if state.t <= last_t else state.t - last_t
            t0 = now_ns()
            self.core.step(state.t, state.q, state.q_dot, self.last_shares, lead,
                           state.obstacles, state.robots, h, None if ages.fresh else ages,
                           pace.horizon(run_time_s - state.t), pace.speed_cap(),
                           state.own_torques)
            self.node.costs.add(LAW, t0)
            self.caught_up += 1
            last_t = state.t
        return last_t

    def _step_inputs(self, share_msgs: dict[int, Reply]
                     ) -> tuple[Sample | None, LeaderPoint | None, int]:
        """Realtime: the newest sample (None: none yet), the leader at its step and its
        step, and into ``share_msgs`` each neighbour's share of the step before (else the
        newest before it); the tables the handlers fill are cleared as they are taken."""
        inp = self.inputs
        with self.node.mailbox.lock:
            state = inp.newest_state
            if state is None:
                return None, None, -1
            inp.states.clear()
            leader, leader_k = step_input(inp.leaders, state.k)
            self._shares_of_step(state.k - 1, share_msgs)
        return state, leader, leader_k

    def _shares_of_step(self, k: int, into: dict[int, Reply]) -> None:
        """Realtime, under the mailbox's lock: into ``into``, each neighbour's share of
        step ``k``, else the newest before it; nothing for one never heard (a rejoining
        agent whose neighbour is gone: a missing table raised KeyError here)."""
        shares_of = self.inputs.shares_of
        for j in self.neighbours:
            heard = shares_of.get(j)
            m = None if heard is None else step_input(heard, k)[0]
            if m is not None:
                into[j] = m

    def _realtime_telemetry(self, telemetry_hz: float) -> None:
        """Telemetry is for people and the recorder: at most ``telemetry_hz`` rows a
        second, sent in batches, so the control traffic keeps the CPU (the run's series
        fill the gaps forward)."""
        self.telemetry_every = max(1, round(1.0 / (self.sc.dt * telemetry_hz)))
        self.telemetry_batch = max(1, min(TELEMETRY_BATCH_MAX,
                                          round(TELEMETRY_BATCH_S * telemetry_hz)))

    def _note_overloaded(self, pace: LoopPace, cap: float) -> None:
        """A step of a loop that cannot keep its period, counted; said once."""
        self.overloaded_steps += 1
        if self.overloaded_steps == 1:
            print(f"{self.node.role}: the loop cannot keep its period ({self.sc.dt * 1e3:.2f} "
                  f"ms; {pace.typical_s * 1e3:.2f} ms between steps, the median): the robot is "
                  f"slowed to {cap:.0%} of its speed while it lasts (counted: overloaded_steps)",
                  file=sys.stderr, flush=True)

    def _note_rejoined(self) -> None:
        """A restarted agent's first command is out: how long after its process started."""
        age = process_age_s()
        if age is not None:
            self.rejoin_s = age
            print(f"{self.node.role}: first command {age:.3f} s after its process started",
                  file=sys.stderr, flush=True)

    def _resync(self, state: Sample, leader: LeaderPoint | None,
                shares: dict[int, Reply], ages: InputAges) -> bool:
        """A restarted agent: the leader estimate from the leader (predicted to
        now) or else the mean of the neighbours' estimates (predicted likewise),
        the reference and observer from the robot where it stands. False while
        none of them has been heard."""
        if self.hears_leader and leader is not None:
            q0 = predict(leader.q, leader.q_dot, ages.leader_s)
            v0 = leader.q_dot
        elif shares:
            est = [predict(m.share.q0_hat, m.share.v0_hat, ages.shares_s.get(j, 0.0))
                   for j, m in shares.items()]
            q0 = tuple(np.mean(est, axis=0).tolist())
            v0 = tuple(np.mean([m.share.v0_hat for m in shares.values()], axis=0).tolist())
        else:
            return False
        self.core = make_core(self.core.cfg, self._law, self._law_params, state.q,
                              state.q_dot, q0, v0)
        print(f"{self.node.role}: rejoined at t = {state.t:.3f} s (plant step {state.k})",
              file=sys.stderr)
        return True

    def finish(self) -> None:
        self.flush_telemetry()
        if self.gate is not None:
            self.gate.close()
        if self.law_resets:
            print(f"{self.node.role}: law restarted from the robot's state {self.law_resets} "
                  "time(s) (a gap longer than its inputs stay fresh, or a non-finite state)",
                  file=sys.stderr)
        if self.stale_samples:
            print(f"{self.node.role}: {self.stale_samples} sample(s) older than "
                  f"{self.core.cfg.degradation.stale_after_s * 1e3:.0f} ms on arrival left "
                  "unanswered", file=sys.stderr)
        if self.caught_up:
            print(f"{self.node.role}: {self.caught_up} sample(s) came while it was a period "
                  "late: the law stepped on each, its command not sent", file=sys.stderr)
        held = self.guards["sample"].held
        if held:
            self.node.refused["unconfirmed jump"] = held
        publish_report(self.node, self.rid, self.steps_done, self.timing,
                       faults=self.faults.report(), law_resets=self.law_resets,
                       nonfinite_commands=self.nonfinite_commands,
                       stale_samples=self.stale_samples, overloaded_steps=self.overloaded_steps,
                       rejoin_s=self.rejoin_s, **self._law_report())

    def _law_report(self) -> dict:
        """A law of the lab's: what it did wrong (agents/plugged.py), said once more here."""
        faults = getattr(self.core, "faults", None)
        if faults is None:
            return {}
        line = faults.error_line[:MAX_LAW_ERROR_CHARS]
        if faults.errors or faults.refused or faults.overruns:
            print(f"{self.node.role}: law {self.core.name}: raised {faults.errors}, refused "
                  f"{faults.refused}, overran {faults.overruns} step(s)"
                  + (f"; first: {line}" if line else ""), file=sys.stderr, flush=True)
        return {"law_errors": faults.errors, "law_refused": faults.refused,
                "law_overruns": faults.overruns, "law_error": line}
