"""In-process reference runner: leader, plant and every agent in one loop.

It follows the lockstep contract of DESIGN §4 exactly (own state at t_k,
neighbours' shares from step k-1, leader at t_k), so the distributed runtime
can be checked against it number for number.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from agents.core import AgentCore
from agents.formation import offsets, scale_at
from agents.leader import LeaderGenerator
from deploy.scenario import PLANT_KINDS, Scenario
from deploy.timeseries import TimeSeries
from plant.command import applied_command
from plant.disturbance import make_disturbance
from plant.model_plant import KinematicPlant, ModelPlant
from plant.perception import sensor_for

__all__ = ["PLANT_KINDS", "RunResult", "make_plant", "run_in_process"]


@dataclass
class RunResult:
    scenario: Scenario
    plant: str
    series: TimeSeries
    wall_time_s: float
    contacts: list[dict] | None = None  # physical contact events (pybullet); None: not simulated


def make_plant(sc: Scenario, kind: str, gui: bool = False):
    """The scenario's robots (and, for pybullet, obstacles) in a plant of ``kind``.

    A pybullet plant holds a physics client: call its ``close()`` when done.
    """
    q, qd = sc.initial_state()
    d = sc.spec.disturbance
    disturbance = make_disturbance(d.kind, d.scale, tuple(d.constant_nm))
    if kind == "pybullet":
        from plant.pybullet_plant import PybulletPlant

        return PybulletPlant(
            [sc.model()] * sc.n, q, qd, disturbance, [sc.spec.robot.body_radius_m] * sc.n,
            sc.robot_ids, sc.obstacle_bodies(), sc.spec.plant.substeps, gui=gui,
        )
    if kind == "model":
        return ModelPlant([sc.model()] * sc.n, q, qd, disturbance, sc.spec.plant.substeps)
    if kind == "kinematic":
        return KinematicPlant(q, qd)
    raise ValueError(f"unknown plant {kind!r}; choose one of {', '.join(PLANT_KINDS)}")


def contact_log(plant) -> list[dict] | None:
    """The plant's contact events as plain records, or None when the plant has no
    bodies that can touch (model and kinematic plants: contacts come from geometry)."""
    events = getattr(plant, "contacts", None)
    if events is None:
        return None
    return [asdict(e) for e in events]


def make_agents(sc: Scenario) -> list[AgentCore]:
    q, qd = sc.initial_state()
    model = sc.model()
    agents = []
    for i in range(sc.n):
        q0h, v0h = sc.initial_estimates(i)
        agents.append(AgentCore(sc.agent_config(i, model), q[i], qd[i], q0h, v0h))
    return agents


class FormationTargets:
    """x_0 + rho_i with the true leader heading (for the formation error metric)."""

    def __init__(self, sc: Scenario) -> None:
        f = sc.spec.formation
        self.initial = (f.initial_scale[0], f.initial_scale[1])
        self.changes = sc.scale_changes()
        self.r = [np.array(r.offset, float) for r in sc.spec.robots]

    def at(self, t: float, q0: np.ndarray, v0: np.ndarray) -> np.ndarray:
        s, sd = scale_at(t, self.initial, self.changes)
        out = np.empty((len(self.r), 2))
        for i, r_i in enumerate(self.r):
            zeta, _ = offsets(r_i, 0.0, float(q0[2]), float(v0[2]), s, sd)
            out[i] = q0[:2] + zeta[:2]
        return out


def run_in_process(
    sc: Scenario,
    plant_kind: str | None = None,
    duration_s: float | None = None,
    progress: Callable[[int, int], None] | None = None,
    gui: bool = False,
) -> RunResult:
    plant_kind = plant_kind or sc.spec.plant.kind
    dt = sc.dt
    steps = sc.steps if duration_s is None else int(round(duration_s / dt))
    plant = make_plant(sc, plant_kind, gui=gui)
    try:
        return _run(sc, plant, plant_kind, steps, progress)
    finally:
        getattr(plant, "close", lambda: None)()


def _run(sc: Scenario, plant, plant_kind: str, steps: int,
         progress: Callable[[int, int], None] | None) -> RunResult:
    dt = sc.dt
    agents = make_agents(sc)
    leader = LeaderGenerator(sc.leader_spec(), dt)
    sense = sensor_for(plant, sc)
    ids = sc.robot_ids
    shares = {rid: a.initial_share for rid, a in zip(ids, agents, strict=False)}
    series = TimeSeries.allocate(steps, sc.n)
    b = sc.leader_weights
    torques = np.zeros((sc.n, 4))
    v_cmd = np.zeros((sc.n, 3))
    targets = FormationTargets(sc)

    start = time.perf_counter()
    for k in range(steps):
        t = k * dt
        q0, v0 = leader.state()
        new_shares = {}
        for i, agent in enumerate(agents):
            robots_seen, obstacles_seen = sense(i)
            out = agent.step(
                t, plant.q[i].copy(), plant.q_dot[i].copy(),
                {j: shares[j] for j, _ in agent.cfg.neighbours},
                (q0, v0) if b[i] != 0.0 else None,
                obstacles_seen, robots_seen,
            )
            torques[i], v_cmd[i] = applied_command(out.torques, out.v_cmd, sc.spec.limits)
            new_shares[ids[i]] = out.share
            series.record_agent(k, i, out, agent)
        series.record_world(
            k, t, q0, v0, plant.q, plant.q_dot, targets.at(t, q0, v0)
        )
        plant.step(t, dt, torques, v_cmd)
        leader.advance()
        shares = new_shares
        if progress is not None:
            progress(k + 1, steps)
    wall = time.perf_counter() - start
    return RunResult(sc, plant_kind, series, wall, contact_log(plant))


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
