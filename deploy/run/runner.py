"""In-process reference runner: leader, plant and every agent in one loop.

It follows the lockstep contract of docs/distributed.md exactly (own state at t_k,
neighbours' shares from step k-1, leader at t_k), so the distributed runtime
can be checked against it number for number.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agents.core import AgentCore, Share
from agents.leader import leader_generator
from agents.look_ahead import LookAhead
from agents.plugged import PluggedCore, make_core
from deploy.contract.fault_plan import FaultPlan
from deploy.contract.scenario import Scenario
from deploy.contract.wire import PLANT_ROLE, agent_role
from deploy.report.targets import FormationTargets
from deploy.report.timeseries import COLUMNS, TimeSeries
from deploy.runtime.fault_model import FaultModel
from deploy.runtime.lockstep_inputs import AgentLinks, HeldInput
from deploy.runtime.plants import contact_log, make_plant, sensor_for
from plant.command import CommandBounds, exceeds, torques_at

__all__ = ["RunResult", "contact_log", "make_plant", "run_in_process"]


@dataclass
class RunResult:
    scenario: Scenario
    plant: str
    series: TimeSeries
    wall_time_s: float
    contacts: list[dict] | None = None  # physical contact events (pybullet); None: not simulated
    faults: dict[str, dict[str, int]] | None = None  # injected faults per edge (with a plan)
    step_unix_ns: np.ndarray | None = None  # wall clock as each step began (the recording)
    law_resets: list[int] | None = None  # per robot: the law restarted from a non-finite state
    interrupted: str | None = None  # "SIGINT": stopped early, the series holds the steps done
    # per robot id, the commands that asked for more torque than the bound (clipped), as
    # the plant node counts them (plant/command.py); the agents' own: none on a bounded law
    torque_clipped: dict[int, int] | None = None
    # per robot, what a law of the lab's did wrong (agents/plugged.py); None: the paper's law
    law_faults: list[dict] | None = None


def make_agents(sc: Scenario) -> list[AgentCore | PluggedCore]:
    """Every robot's agent, on the scenario's law (``[law]``: the paper's compiled one, or
    a law of the lab's, agents/plugged.py)."""
    q, qd = sc.initial_state()
    model = sc.model()
    law, params = sc.law()
    agents = []
    for i in range(sc.n):
        q0h, v0h = sc.initial_estimates(i)
        agents.append(make_core(sc.agent_config(i, model), law, params, q[i], qd[i], q0h, v0h))
    return agents


def run_in_process(
    sc: Scenario,
    plant_kind: str | None = None,
    duration_s: float | None = None,
    progress: Callable[[int, int], None] | None = None,
    gui: bool = False,
    faults: FaultPlan | None = None,
    on_series: Callable[[TimeSeries], None] | None = None,
) -> RunResult:
    """The lockstep reference run; ``faults``: a fault plan (no process kills),
    applied exactly as the distributed run applies it; ``on_series``: called
    with the run's time series before the first step (a live view reads its rows
    0..k once ``progress(k + 1, steps)`` has been called)."""
    if faults is not None and faults.kills:
        raise ValueError("process kills need separate processes: run without --in-process")
    plant_kind = plant_kind or sc.spec.plant.kind
    dt = sc.dt
    steps = sc.steps if duration_s is None else int(round(duration_s / dt))
    plant = make_plant(sc, plant_kind, gui=gui)
    try:
        return _run(sc, plant, plant_kind, steps, progress, FaultModel(faults, dt), on_series)
    finally:
        plant.close()


PROGRESS_EVERY = 16  # steps between progress calls (a live view reads the rows up to there)


def _run(sc: Scenario, plant, plant_kind: str, steps: int,
         progress: Callable[[int, int], None] | None, model: FaultModel,
         on_series: Callable[[TimeSeries], None] | None = None) -> RunResult:
    run = _ReferenceLoop(sc, plant, steps, model)
    if on_series is not None:
        on_series(run.series)
    start = time.perf_counter()
    done, interrupted = 0, None
    try:  # Ctrl-C: what was measured so far is still the run's (deploy/cli/)
        for k in range(steps):
            run.step(k)
            if progress is not None and (k % PROGRESS_EVERY == 0 or k + 1 == steps):
                progress(k + 1, steps)
            done = k + 1
    except KeyboardInterrupt:
        interrupted = "SIGINT"
        run.keep_first(done)
    wall = time.perf_counter() - start
    series, agents = run.series, run.agents
    series.target[:] = run.targets.along(series.t, series.leader_q)  # reported only: after the run
    faults = [a.faults.as_json() for a in agents] if isinstance(agents[0], PluggedCore) else None
    return RunResult(sc, plant_kind, series, wall, contact_log(plant), model.report()
                     if model.plan is not None else None, run.step_unix_ns, run.law_resets,
                     interrupted, run.clipped, faults)


class _ReferenceLoop:
    """One in-process run's state from step to step, and its step: the leader's state,
    every robot's sample, each agent's step on the inputs its links deliver
    (:meth:`_agents`), the commands the plant acts on, the plant's step. What was sent is
    kept by step for a few steps, as the links pick from it (a delay reaches back)."""

    def __init__(self, sc: Scenario, plant, steps: int, model: FaultModel) -> None:
        self.sc, self.plant, self.model, self.dt = sc, plant, model, sc.dt
        self.agents = agents = make_agents(sc)
        # a steered leader gets no command here: it stays
        self.leader = leader_generator(sc.leader_spec(), sc.dt)
        self.sense = sensor_for(plant, sc)
        self.ids = ids = sc.robot_ids
        self.series = TimeSeries.allocate(steps, sc.n)
        self.step_unix_ns = np.zeros(steps, np.int64)
        self.b = b = sc.leader_weights
        self.torques = np.zeros((sc.n, 4))
        self.v_cmd = np.zeros((sc.n, 3))
        self.targets = FormationTargets(sc)
        self.keep = model.max_lag_steps + 2
        self.worlds: dict[int, list[tuple]] = {}  # k -> per robot (q, q_dot, robots, obstacles, own)
        self.leaders: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.shares: dict[int, dict[int, Share]] = {  # k -> robot id -> its share of step k
            -1: {rid: a.initial_share for rid, a in zip(ids, agents, strict=True)}}
        self.commands: dict[int, dict[int, tuple]] = {}  # k -> robot id -> (torques, v_cmd, plan)
        self.links = [AgentLinks(model, rid, [j for j, _ in a.cfg.neighbours], b[i] != 0.0)
                      for i, (rid, a) in enumerate(zip(ids, agents, strict=True))]
        self.neighbours = [[j for j, _ in a.cfg.neighbours] for a in agents]
        self.zero_missed = sc.spec.plant.missed_command == "zero"
        self.command_links = [HeldInput(model, model.edge(agent_role(rid), PLANT_ROLE),
                                        exempt_first=False) for rid in ids]
        # commands can only be lost with a fault plan: only then is the look-ahead worth its cost
        horizon = sc.spec.degradation.command_horizon if model.plan is not None else 0
        self.look_ahead = [LookAhead(a, horizon) for a in agents] if horizon else None
        self.law_resets = [0] * sc.n
        # per robot: the previous step ran on its agent's own command (Sample.own_torques)
        self.own_torques = [True] * sc.n
        # without a fault plan every link delivers step k's sample (the neighbours' of k-1)
        # at once: the links' bookkeeping is skipped, with the same inputs (AgentLinks.take)
        self.fault_free = model.plan is None
        self.bounds = CommandBounds.of(sc.spec.limits)
        self.clipped = dict.fromkeys(ids, 0)

    def step(self, k: int) -> None:
        plant, ids = self.plant, self.ids
        self.step_unix_ns[k] = time.time_ns()
        t = k * self.dt
        q0, v0 = self.leader.state_floats()
        self.leaders[k] = (q0, v0)
        qs, qds = plant.q.tolist(), plant.q_dot.tolist()
        # each robot's sample as the plant sends it, with its own_torques flag
        self.worlds[k] = [(tuple(q), tuple(qd), *seen, own)
                          for q, qd, seen, own in zip(qs, qds, self.sense(), self.own_torques,
                                                      strict=True)]
        commands_k = self._agents(k, t, q0, v0)
        self.series.record_world(k, t, q0, v0, plant.q, plant.q_dot)
        if self.fault_free:  # each robot's own command of step k, in one assignment each
            self.torques[:] = [commands_k[rid][0] for rid in ids]
            self.v_cmd[:] = [commands_k[rid][1] for rid in ids]
        else:
            _commands_through_links(k, ids, self.command_links, self.commands, self.zero_missed,
                                    self.own_torques, self.torques, self.v_cmd)
        plant.step(t, self.dt, self.torques, self.v_cmd)
        self.leader.advance()
        for by_step in (self.worlds, self.leaders, self.shares, self.commands):
            by_step.pop(k - self.keep, None)

    def _agents(self, k: int, t: float, q0: tuple, v0: tuple) -> dict[int, tuple]:
        """Every agent's step k on what its links deliver; the commands it gives, by robot."""
        ids, b, worlds, shares = self.ids, self.b, self.worlds, self.shares
        world_k, look_ahead, bounds, series = worlds[k], self.look_ahead, self.bounds, self.series
        shares_k, commands_k, shares_before = {}, {}, shares.get(k - 1, {})
        shares[k], self.commands[k] = shares_k, commands_k
        for i, agent in enumerate(self.agents):
            rid = ids[i]
            if self.fault_free:
                world, ages = world_k[i], None
                lead = (q0, v0) if b[i] != 0.0 else None
                shs = {j: shares_before.get(j) for j in self.neighbours[i]}
            else:
                world, lead, shs, ages = self.links[i].take(
                    k, lambda idx, i=i: worlds[idx][i] if idx in worlds else None,
                    self.leaders.get, lambda jk: shares.get(jk[1], {}).get(jk[0]), self.dt)
            q, q_dot, robots_seen, obstacles_seen, own = world
            out = agent.step(t, q, q_dot, shs, lead, obstacles_seen, robots_seen, ages=ages,
                             own_torques=own)
            plan = [] if look_ahead is None else look_ahead[i].plan(
                agent, out, t, q, q_dot, shs, lead, obstacles_seen, robots_seen, ages=ages)
            tq = out.torques
            if exceeds(tq, plan, bounds.torque):
                self.clipped[rid] += 1
            commands_k[rid] = (*bounds.applied(tq, out.v_cmd), bounds.plan(plan) if plan else plan)
            shares_k[rid] = out.share
            self.law_resets[i] += bool(out.reset)
            series.record_agent(k, i, out, agent)
        return commands_k

    def keep_first(self, done: int) -> None:
        """An interrupted run: the series and the wall clock of the steps done only."""
        self.series = TimeSeries(**{c: getattr(self.series, c)[:done].copy() for c in COLUMNS})
        self.step_unix_ns = self.step_unix_ns[:done]


def _commands_through_links(k: int, ids: list[int], command_links: list[HeldInput],
                            commands: dict[int, dict[int, tuple]], zero_missed: bool,
                            own_torques: list[bool], torques: np.ndarray,
                            v_cmd: np.ndarray) -> None:
    """With a fault plan: the torques and velocity each robot acts on at step k, from
    the command its link delivers (its own of step k, an older one with its look-ahead,
    or none: held, or zero past the plan with ``missed_command = "zero"``); and whether
    they are the agent's own command of step k (``own_torques``, the next sample's)."""
    for i, rid in enumerate(ids):
        cmd, age = command_links[i].take(k, lambda idx, rid=rid: commands.get(idx, {}).get(rid))
        own_torques[i] = cmd is not None and age == 0
        if cmd is None:
            continue
        planned = torques_at(k - age, cmd[0], cmd[2], k, "zero" if zero_missed else "hold")
        if planned is None:  # "zero": past the newest command's plan
            torques[i], v_cmd[i] = 0.0, 0.0
        else:  # its own command, its look-ahead for step k, or held past it
            torques[i], v_cmd[i] = planned, cmd[1]


def terminal_progress(total_label: str) -> Callable[[int, int], None] | None:
    """A tqdm progress callback on a terminal; None (quiet) when not a TTY."""
    if not sys.stderr.isatty():
        return None
    from tqdm import tqdm

    bar = tqdm(desc=total_label, unit="step", leave=False)

    def update(done: int, total: int) -> None:
        if bar.total is None:
            bar.total = total
        bar.update(done - bar.n)
        if done >= total:
            bar.close()

    return update


LOG_PROGRESS_EVERY_S = 5.0  # not on a terminal: one progress line this often


def log_progress(label: str, every_s: float = LOG_PROGRESS_EVERY_S,
                 clock: Callable[[], float] = time.monotonic) -> Callable[[int, int], None]:
    """Progress as plain lines on stderr (``LABEL: step K/N (P %), T s``), the first at
    once and then at most one per ``every_s``, and the last: piped output showed nothing
    for a minute."""
    start = clock()
    last = [None]

    def update(done: int, total: int) -> None:
        now = clock()
        if last[0] is not None and now - last[0] < every_s and done < total:
            return
        if done >= total and last[0] == float("inf"):
            return
        last[0] = float("inf") if done >= total else now
        pct = 100.0 * done / total if total else 100.0
        print(f"{label}: step {done}/{total} ({pct:.0f} %), {now - start:.0f} s",
              file=sys.stderr, flush=True)

    return update


def run_progress(label: str) -> Callable[[int, int], None]:
    """A progress bar on a terminal (tqdm), progress lines every few seconds otherwise."""
    return terminal_progress(label) or log_progress(label)
