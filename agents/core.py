"""One robot's agent as a pure step function: estimator -> formation reference ->
behaviors -> fusion -> controller -> torques. No I/O: the in-process runner and
the distributed node both call :meth:`AgentCore.step` with the same inputs.

Data flow per control step k (docs/distributed.md, lockstep): own state at t_k, the
neighbours' shares of step k-1, the leader state at t_k iff b_i != 0, and what
perception sees at t_k. The share published at step k carries the estimate
already advanced to k+1, so estimator consensus runs as the synchronous Euler
scheme of the authors' code while positions arrive one step late.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from copy import copy
from dataclasses import dataclass, field
from math import cos, hypot, isfinite, sin, sqrt

import numpy as np

from agents.behaviors import Task, avoidance_task_of, formation_task
from agents.controller import (
    ControlConstants,
    ControllerGains,
    ModelTerms,
    allocate_vec,
    control_term_vec,
    coulomb_term,
    matvec3,
    saturate_torques_vec,
)
from agents.degradation import (
    DegradationConfig,
    InputAges,
    freshest_source,
    next_speed_factor,
    predict,
    reacquire,
    slow_down,
)
from agents.eso import EsoGains, eso_advance_vec
from agents.estimator import EstimatorGains, estimator_step_vec
from agents.formation import ScaleChange, desired_formation_vec, offsets_vec, scale_at_vec
from agents.fusion import DEFAULT_PRIORITY, supervise_tasks
from agents.safety_filter import Guarded, SafetyLimits, SafetyResult, safety_filter, stopping_distance
from agents.signals import Vec2, Vec3
from plant.bodies import Body
from plant.limits import saturate_velocity_vec
from plant.mecanum import MecanumModel


@dataclass(frozen=True)
class Share:
    """What agent j sends to the agents that listen to it (a_ij != 0)."""

    q0_hat: np.ndarray
    v0_hat: np.ndarray
    q: np.ndarray
    q_dot: np.ndarray
    zeta: np.ndarray
    zeta_dot: np.ndarray
    info_age_s: float = 0.0  # how old the sender's leader information is (degradation.py)


@dataclass(frozen=True)
class AgentConfig:
    robot_id: int
    dt: float
    model: MecanumModel
    neighbours: tuple[tuple[int, float], ...]  # (j, a_ij), a_ij != 0, j != i
    leader_weight: float  # b_i
    offset: tuple[float, float]  # r_i
    heading_offset: float = 0.0  # Xi_i
    initial_scale: tuple[float, float] = (1.0, 1.0)
    scale_changes: tuple[ScaleChange, ...] = ()
    kappa1: float = 1.0
    kappa2: float = 0.0
    enabled: frozenset[str] = frozenset({"FDB", "FOCB", "FRCB"})
    priority: tuple[str, ...] = DEFAULT_PRIORITY
    avoidance_engage: str = "approaching"  # | "inside" (see fusion.py)
    fdb_gains: tuple[float, float] = (12.0, 0.25)
    focb_gains: tuple[float, float] = (24.0, 0.25)
    frcb_gains: tuple[float, float] = (32.0, 0.25)
    obstacle_safe_m: float = 2.0  # R_a
    robot_safe_m: float = 1.6  # R_c
    robot_radius_m: float = 0.5  # r
    estimator: EstimatorGains = field(default_factory=EstimatorGains)
    eso: EsoGains = field(default_factory=EsoGains)
    controller: ControllerGains = field(default_factory=ControllerGains)
    max_speed_mps: float = float("inf")
    max_yaw_rate_radps: float = float("inf")
    max_wheel_torque_nm: float = float("inf")
    max_accel_mps2: float = float("inf")  # on v_d, planar (see AgentCore._step)
    max_yaw_accel_radps2: float = float("inf")
    max_tracking_error: float = float("inf")  # on ||q - q_d|| (anti-windup, see AgentCore._step)
    degradation: DegradationConfig = field(default_factory=DegradationConfig)
    # docs/safety.md: which bodies the avoidance behaviors guard ("every" body
    # in range, one task each, nearest first; "nearest": only the nearest, as the
    # authors' script), and the safety filter, the last layer of the agent
    guard: str = "every"
    safety_filter: bool = True
    safety_margin_m: float = 0.05  # kept on top of contact by the filter and the engagement
    safety_exit_time_s: float = 0.5  # inside the margin: leave it at gap / exit_time


@dataclass
class AgentOutput:
    torques: np.ndarray  # (4,) wheel torques, N m, finite and within limits
    v_cmd: np.ndarray  # (3,) fused velocity command v_d (what a kinematic plant takes)
    share: Share
    # telemetry
    tracking_error: np.ndarray  # e = q - q_d
    sliding: np.ndarray  # s
    q_d: np.ndarray
    q_fd: np.ndarray
    order: tuple[str, ...]  # active behaviors, highest priority first
    task_errors: dict[str, float]
    z2_hat: np.ndarray
    nonfinite: bool  # the law produced a NaN/Inf: torques were zeroed instead
    # degradation (agents/degradation.py)
    input_age_s: float = 0.0  # age of the agent's freshest leader information, or its state
    speed_factor: float = 1.0  # 1: full speed; 0: down to the degraded speed
    left_out: int = 0  # inputs too old for eq. (14) this step
    # the safety filter (agents/safety_filter.py): None when it had nothing to guard
    safety: SafetyResult | None = None
    # what this step found non-finite in the agent's state and restarted from the newest
    # measurement (AgentCore.recover): empty when nothing was
    reset: tuple[str, ...] = ()


class AgentCore:
    """State and step of one agent (estimator, reference, ESO).

    The step works on floats: its vectors have 2 to 4 components, where a numpy
    call costs more than the arithmetic. The numpy functions of the other modules
    are the reference form of each equation; tests/unit/test_hot_path.py checks the
    float forms used here against them, and this step against their composition.
    """

    def __init__(
        self,
        cfg: AgentConfig,
        q_init: np.ndarray,
        q_dot_init: np.ndarray,
        q0_hat_init: np.ndarray,
        v0_hat_init: np.ndarray,
    ) -> None:
        self.cfg = cfg
        self._q0_hat: Vec3 = _vec3(np.asarray(q0_hat_init, dtype=float))
        self._v0_hat: Vec3 = _vec3(np.asarray(v0_hat_init, dtype=float))
        self._q_d: Vec3 = _vec3(np.asarray(q_init, dtype=float))  # CLIK reference starts at the robot
        self._v_d_prev: Vec3 | None = None
        self._z1_hat: Vec3 | None = None  # set to the first measurement (see eso.py)
        self._z2_hat: Vec3 = (0.0, 0.0, 0.0)
        self._speed_factor = 1.0
        self._info_lost = False  # its information went stale (degradation.py)
        self._reacquiring = False
        self._reacquire_s = 0.0  # time spent re-acquiring
        # constants of the step
        self._r_i = (float(cfg.offset[0]), float(cfg.offset[1]))
        self._scale0 = (float(cfg.initial_scale[0]), float(cfg.initial_scale[1]))
        self._weights = [float(w) for _, w in cfg.neighbours]
        self._rank = {name: k for k, name in enumerate(cfg.priority)}
        self._law = ControlConstants.from_gains(cfg.controller)
        self._limits_rate = isfinite(cfg.max_accel_mps2) or isfinite(cfg.max_yaw_accel_radps2)
        self._safety = SafetyLimits(cfg.safety_margin_m, cfg.max_accel_mps2, cfg.max_speed_mps,
                                    cfg.safety_exit_time_s)
        self._model = ModelTerms.from_model(cfg.model)
        zeta, zeta_dot = self._offsets(0.0)
        self.initial_share = Share(
            self.q0_hat, self.v0_hat, np.array(q_init, float), np.array(q_dot_init, float),
            np.array(zeta), np.array(zeta_dot),
        )

    def fork(self) -> AgentCore:
        """An independent copy to step ahead of this one (agents/look_ahead.py).

        A shallow copy is enough: the step replaces its state (float tuples),
        it never mutates it, and the configuration is shared read-only.
        """
        return copy(self)

    @property
    def q0_hat(self) -> np.ndarray:
        """The leader pose estimate (advanced to the next step after a step)."""
        return np.array(self._q0_hat)

    @property
    def v0_hat(self) -> np.ndarray:
        """The leader velocity estimate (advanced to the next step after a step)."""
        return np.array(self._v0_hat)

    def _offsets(self, t: float) -> tuple[Vec3, Vec3]:
        scale, scale_dot = scale_at_vec(t, self._scale0, self.cfg.scale_changes)
        return offsets_vec(
            self._r_i, self.cfg.heading_offset, self._q0_hat[2], self._v0_hat[2], scale, scale_dot
        )

    def _behaviors(
        self,
        q: Vec3,
        q_dot: Vec3,
        q_fd: Vec3,
        v_fd: Vec3,
        obstacles: Sequence[Body],
        robots: Sequence[Body],
        h: float,
    ) -> list[Task]:
        """The active behaviors, highest priority first; within FOCB and FRCB one task
        per guarded body, nearest (smallest gap) first."""
        cfg = self.cfg
        out: list[Task] = []
        if "FDB" in cfg.enabled:
            out.append(formation_task(q, q_fd, v_fd, cfg.fdb_gains))
        # R_a is measured from an obstacle's surface (the paper's obstacles are
        # points), R_c from the other robot's centre, as printed.
        for name, bodies, safe, surface, gains in (
            ("FOCB", obstacles, cfg.obstacle_safe_m, True, cfg.focb_gains),
            ("FRCB", robots, cfg.robot_safe_m, False, cfg.frcb_gains),
        ):
            if name not in cfg.enabled or not bodies:
                continue
            guarded = bodies if cfg.guard == "every" else [_nearest(bodies, q[0], q[1])[0]]
            tasks = []
            for body in guarded:
                bx, by = body.position.tolist()
                contact = cfg.robot_radius_m + body.radius
                threshold = max(safe + (body.radius if surface else 0.0),
                                self._engage_distance(q, q_dot, bx, by, body, contact, h))
                task = avoidance_task_of(name, q, (bx, by), contact, threshold,
                                         q_fd[2], v_fd[2], gains, body=body.ident)
                if task is not None:
                    tasks.append((hypot(q[0] - bx, q[1] - by) - body.radius, task))
            out.extend(task for _, task in sorted(tasks, key=lambda gt: gt[0]))
        rank = self._rank
        return sorted(out, key=lambda b: rank[b.name])  # stable: nearest first within one

    def _engage_distance(self, q: Vec3, q_dot: Vec3, bx: float, by: float, body: Body,
                         contact: float, h: float) -> float:
        """Centre distance at which avoiding ``body`` must begin (docs/safety.md): contact, the
        margin, and the gap that closing at the present speed uses up before braking at
        the scenario's acceleration limit stops it (agents/safety_filter.stopping_distance).
        The closing speed is the larger of the command's (the last v_d) and the robot's
        measured one, relative to the body's perceived velocity. Below the behavior's own
        threshold (R_a, R_c) this changes nothing: the paper's radius holds for a robot
        slow enough to stop within it."""
        dx, dy = q[0] - bx, q[1] - by
        dist = hypot(dx, dy)
        if dist < 1e-12:
            return contact
        ux, uy = dx / dist, dy / dist
        bvx, bvy = body.velocity.tolist()
        closing = -(ux * (q_dot[0] - bvx) + uy * (q_dot[1] - bvy))
        if self._v_d_prev is not None:
            v = self._v_d_prev
            closing = max(closing, -(ux * (v[0] - bvx) + uy * (v[1] - bvy)))
        return contact + self.cfg.safety_margin_m + stopping_distance(
            closing, self.cfg.max_accel_mps2, h)

    def _limited(self, v: Vec3, h: float) -> Vec3:
        """The fused velocity as commanded: the explicit speed limit, the degradation
        slow-down, and the acceleration limit from the last command."""
        cfg = self.cfg
        v_d = saturate_velocity_vec(v, cfg.max_speed_mps, cfg.max_yaw_rate_radps)
        if self._speed_factor < 1.0:
            v_d = slow_down(v_d, self._speed_factor, cfg.degradation.degraded_speed_mps)
        if self._v_d_prev is not None and self._limits_rate:
            # explicit acceleration limits: v_d moves toward the fused command no
            # faster than the torque limit can follow, so the reference q_d does not
            # run ahead of the robot at a behavior switch (ours, not the paper's)
            prev = self._v_d_prev
            dv = saturate_velocity_vec(_sub(v_d, prev), cfg.max_accel_mps2 * h,
                                       cfg.max_yaw_accel_radps2 * h)
            v_d = (prev[0] + dv[0], prev[1] + dv[1], prev[2] + dv[2])
        return v_d

    def _filtered(self, v_d: Vec3, q: Vec3, obstacles: Sequence[Body],
                  robots: Sequence[Body], h: float) -> tuple[Vec3, SafetyResult | None]:
        """The safety filter, the agent's last layer (agents/safety_filter.py): every
        perceived body guarded from where the robot is. (Guarding the reference q_d too
        was tried: in the paper's first 15 ms q_d runs 1.7 m ahead of a robot at 600
        m/s, and the filter then changed the paper's own run; the tracking error of a
        limited robot is what ``safety.margin_m`` is for.)"""
        if not self.cfg.safety_filter or not (obstacles or robots):
            return v_d, None
        guarded = [Guarded(*b.position.tolist(), *b.velocity.tolist(), b.radius)
                   for b in obstacles]
        guarded += [Guarded(*b.position.tolist(), *b.velocity.tolist(), b.radius, True)
                    for b in robots]  # robots the plant drives: they run this filter too
        prev = None if self._v_d_prev is None else (self._v_d_prev[0], self._v_d_prev[1])
        result = safety_filter((v_d[0], v_d[1]), prev, q[0], q[1], self.cfg.robot_radius_m,
                               guarded, self._safety, h)
        if result.active:
            v_d = (result.v[0], result.v[1], v_d[2])
        return v_d, result

    def step(
        self,
        t: float,
        q: np.ndarray,
        q_dot: np.ndarray,
        shares: Mapping[int, Share],
        leader: tuple[np.ndarray, np.ndarray] | None,
        obstacles: Sequence[Body] = (),
        robots: Sequence[Body] = (),
        dt: float | None = None,
        ages: InputAges | None = None,
    ) -> AgentOutput:
        """One control step. ``dt`` is the time to the next step: the configured
        period unless given (a realtime agent passes the time its plant actually
        advanced, so a missed period does not stretch the observer's clock).
        ``ages``: how stale the inputs are (None: all fresh); see degradation.py.

        A law that diverges gives zero torques and ``nonfinite``, never an
        exception: the float hot path raises where numpy would return inf/NaN
        (x**r overflowing in sig(), cos(inf)), and that is the same outcome."""
        try:
            out = self._step(t, q, q_dot, shares, leader, obstacles, robots, dt, ages)
        except (ArithmeticError, ValueError):
            out = self._diverged(q, q_dot)
        if out.nonfinite or not self._state_finite():
            # never stay diverged: a NaN in an integrator stays there for good (a paused
            # realtime agent sent zero torques for the rest of its run); this step's
            # torques are zero (counted), the next starts from the measurement
            out.reset = self.recover(q, q_dot, shares, leader)
        return out

    def _state_finite(self) -> bool:
        """The integrators' and observers' state holds no NaN/Inf (a sum of finite
        floats of this size is finite; one NaN or Inf makes it so)."""
        return isfinite(sum(self._q0_hat) + sum(self._v0_hat) + sum(self._q_d)
                        + sum(self._z2_hat) + (0.0 if self._z1_hat is None else sum(self._z1_hat))
                        + (0.0 if self._v_d_prev is None else sum(self._v_d_prev))
                        + self._speed_factor)

    def recover(self, q: np.ndarray, q_dot: np.ndarray, shares: Mapping[int, Share],
                leader: tuple[np.ndarray, np.ndarray] | None) -> tuple[str, ...]:
        """Restart from the newest measurement what a diverged step left non-finite, and
        the dynamic level (reference and observer) whenever the law gave a non-finite
        command. Returns what was restarted:

        - "reference": q_d := q, the measured pose (eq. 11's integrator; e = 0), and the
          last command v_d forgotten (the first order hold restarts from v_d);
        - "observer": z1_hat from the next measurement, z2_hat := 0 (eq. 39, as at start);
        - "estimator": q0_hat, v0_hat from the leader when heard, else the mean of the
          neighbours' finite estimates, else the robot's own pose at rest (eq. 14);
        - "speed": the degradation speed factor from 0 (it ramps back up)."""
        done: list[str] = []
        q_v, finite = _vec3(np.asarray(q, float)), self._state_finite()
        if not (_finite(self._q_d) and (self._v_d_prev is None or _finite(self._v_d_prev))) \
                or finite:
            # finite state but a non-finite command: the step itself diverged (a huge h)
            if _finite(q_v):
                self._q_d = q_v
                done.append("reference")
            self._v_d_prev = None
        if not (_finite(self._z2_hat) and (self._z1_hat is None or _finite(self._z1_hat))) \
                or finite:
            self._z1_hat, self._z2_hat = None, (0.0, 0.0, 0.0)
            done.append("observer")
        if not (_finite(self._q0_hat) and _finite(self._v0_hat)):
            self._q0_hat, self._v0_hat = self._estimate_from(q_v, shares, leader)
            done.append("estimator")
        if not isfinite(self._speed_factor):
            self._speed_factor = 0.0
            done.append("speed")
        return tuple(done)

    def _estimate_from(self, q: Vec3, shares: Mapping[int, Share],
                       leader: tuple[np.ndarray, np.ndarray] | None) -> tuple[Vec3, Vec3]:
        """A leader estimate to restart eq. (14) from: the leader as heard, the mean of
        the neighbours' finite estimates, or (nothing finite heard) the robot itself."""
        if leader is not None and self.cfg.leader_weight != 0.0:
            lq, lv = _vec3(leader[0]), _vec3(leader[1])
            if _finite(lq) and _finite(lv):
                return lq, lv
        est = [(_vec3(sh.q0_hat), _vec3(sh.v0_hat)) for j, _ in self.cfg.neighbours
               if (sh := shares.get(j)) is not None]
        est = [(x, v) for x, v in est if _finite(x) and _finite(v)]
        if est:
            n = float(len(est))
            return (tuple(sum(x[i] for x, _ in est) / n for i in range(3)),  # type: ignore[return-value]
                    tuple(sum(v[i] for _, v in est) / n for i in range(3)))
        return (q if _finite(q) else (0.0, 0.0, 0.0)), (0.0, 0.0, 0.0)

    def _diverged(self, q: np.ndarray, q_dot: np.ndarray) -> AgentOutput:
        nan3 = np.full(3, np.nan)
        zero3 = np.zeros(3)
        return AgentOutput(
            torques=np.zeros(4), v_cmd=zero3.copy(),
            share=Share(self.q0_hat, self.v0_hat, q.copy(), q_dot.copy(), zero3.copy(),
                        zero3.copy()),
            tracking_error=nan3.copy(), sliding=nan3.copy(), q_d=np.array(self._q_d),
            q_fd=nan3.copy(), order=(), task_errors={}, z2_hat=np.array(self._z2_hat),
            nonfinite=True,
        )

    def _step(
        self,
        t: float,
        q: np.ndarray,
        q_dot: np.ndarray,
        shares: Mapping[int, Share],
        leader: tuple[np.ndarray, np.ndarray] | None,
        obstacles: Sequence[Body],
        robots: Sequence[Body],
        dt: float | None,
        ages: InputAges | None = None,
    ) -> AgentOutput:
        cfg = self.cfg
        h = cfg.dt if dt is None else dt
        nbr = [shares[j] for j, _ in cfg.neighbours]
        nbr_age = [0.0] * len(nbr) if ages is None else [
            ages.shares_s.get(j, 0.0) for j, _ in cfg.neighbours]
        q_dot_v: Vec3 = _vec3(q_dot)
        qv: Vec3 = _vec3(q) if ages is None else predict(_vec3(q), q_dot_v, ages.state_s)
        lead_v3 = (_vec3(leader[0]), _vec3(leader[1])) if leader is not None else None
        nbr_q0 = [_vec3(sh.q0_hat) for sh in nbr]  # the neighbours' leader estimates
        nbr_v0 = [_vec3(sh.v0_hat) for sh in nbr]
        fresh = None
        info_age = 0.0  # of the freshest leader information
        if ages is not None:
            fresh = freshest_source(
                lead_v3 if cfg.leader_weight != 0.0 else None, ages.leader_s,
                [(x, v, a, sh.info_age_s)
                 for x, v, a, sh in zip(nbr_q0, nbr_v0, nbr_age, nbr, strict=True)])
            info_age = fresh.age_s if fresh is not None else 0.0
            if info_age > cfg.degradation.stale_after_s:
                self._info_lost, self._reacquiring = True, False
            elif self._info_lost:
                self._info_lost, self._reacquiring, self._reacquire_s = False, True, 0.0

        # formation reference, eqs. (13), (16); stale neighbours predicted to now
        zeta, zeta_dot = self._offsets(t)
        if cfg.kappa2 != 0.0:
            nbr_q_dot = [_vec3(sh.q_dot) for sh in nbr]
            nbr_zeta_dot = [_vec3(sh.zeta_dot) for sh in nbr]
            nbr_terms = [
                [predict(_vec3(sh.q), v, a) for sh, v, a in zip(nbr, nbr_q_dot, nbr_age,
                                                               strict=True)],
                nbr_q_dot,
                [predict(_vec3(sh.zeta), v, a) for sh, v, a in zip(nbr, nbr_zeta_dot, nbr_age,
                                                                  strict=True)],
                nbr_zeta_dot]
        else:  # eq. (16) without its neighbour sum
            nbr_terms = [[], [], [], []]
        q_fd, v_fd = desired_formation_vec(
            cfg.kappa1, cfg.kappa2, self._q0_hat, self._v0_hat, zeta, zeta_dot, self._weights,
            *nbr_terms,
        )

        # behaviors (15)-(25), supervisor + fusion (26), explicit limits (the
        # supervisor judges engagement on the command after them), safety filter
        input_age = 0.0 if ages is None else max(info_age, ages.state_s)
        if ages is not None or self._speed_factor < 1.0:  # degraded, or recovering
            self._speed_factor = next_speed_factor(self._speed_factor, input_age,
                                                   cfg.degradation, h)
        chain, v_d = supervise_tasks(
            self._behaviors(qv, q_dot_v, q_fd, v_fd, obstacles, robots, h),
            cfg.avoidance_engage, lambda v: self._limited(v, h))
        v_d, safety = self._filtered(v_d, qv, obstacles, robots, h)

        # dynamic level, eqs. (36), (40)-(42)
        model = self._model
        c, s_phi = cos(qv[2]), sin(qv[2])
        # Reference q_d(t): first-order hold of the v_d samples, one period late
        # (see controller.py): velocity v_d(k-1) at t_k, constant acceleration
        # q_d_ddot over [t_k, t_k+1] that the zero-order-hold torque can realise.
        v_ref = v_d if self._v_d_prev is None else self._v_d_prev
        e = _sub(qv, self._q_d)
        e_norm = sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
        if e_norm > cfg.max_tracking_error:
            # anti-windup on the reference (ours, not the paper's): eq. (11) integrates
            # q_d open loop, so a robot held back (its agent or bridge off the CPU for
            # 200 ms, its torques saturated) left q_d running ahead at v_d, and with v_d
            # at the speed limit the robot never caught up; the position term then pulled
            # it along q_d's path, through what avoidance had steered around (6 contacts
            # in a loaded can-emulated lab run). q_d is kept within the bound of the robot.
            pull = 1.0 - cfg.max_tracking_error / e_norm
            self._q_d = (self._q_d[0] + pull * e[0], self._q_d[1] + pull * e[1],
                         self._q_d[2] + pull * e[2])
            e = _sub(qv, self._q_d)
        e_dot = _sub(q_dot_v, v_ref)
        if self._z1_hat is None:
            self._z1_hat = e_dot
        gamma, s = control_term_vec(e, e_dot, self._z2_hat, self._law)
        # u = B_bar^-1 [q_d_ddot + A0 q_dot + A1 + Gamma; 0], q_d_ddot = (v_d - v_ref) / h
        a0 = matvec3(model.A0, q_dot_v)
        a1 = coulomb_term(model, c, s_phi, q_dot_v)
        generalised = (
            (v_d[0] - v_ref[0]) / h + a0[0] + a1[0] + gamma[0],
            (v_d[1] - v_ref[1]) / h + a0[1] + a1[1] + gamma[1],
            (v_d[2] - v_ref[2]) / h + a0[2] + a1[2] + gamma[2],
        )
        torques = saturate_torques_vec(
            allocate_vec(model, c, s_phi, generalised), cfg.max_wheel_torque_nm
        )
        nonfinite = not _finite(torques)
        if nonfinite:
            torques = (0.0, 0.0, 0.0, 0.0)

        # observer (39) and reference integration (CLIK, eq. 11)
        self._z1_hat, self._z2_hat = eso_advance_vec(
            self._z1_hat, self._z2_hat, e_dot, gamma, cfg.eso, h, cfg.dt
        )
        q_d_now = self._q_d
        half_h = 0.5 * h
        self._q_d = (
            q_d_now[0] + half_h * (v_ref[0] + v_d[0]),
            q_d_now[1] + half_h * (v_ref[1] + v_d[1]),
            q_d_now[2] + half_h * (v_ref[2] + v_d[2]),
        )
        self._v_d_prev = v_d

        # leader estimator (14), advanced to k+1 and shared; stale inputs predicted
        # to now, those older than stale_after_s left out (degradation.py)
        lq, lv = lead_v3 if lead_v3 is not None else (None, None)
        weights = self._weights
        left_out = 0
        if ages is not None:
            stale_after = cfg.degradation.stale_after_s
            if lq is not None and lv is not None:
                if ages.leader_s > stale_after:
                    lq = lv = None
                    left_out += 1
                else:
                    lq = predict(lq, lv, ages.leader_s)
            keep = [a <= stale_after for a in nbr_age]
            left_out += keep.count(False)
            nbr_q0 = [predict(x, v, a) for x, v, a, ok in zip(nbr_q0, nbr_v0, nbr_age, keep,
                                                              strict=True) if ok]
            nbr_v0 = [v for v, ok in zip(nbr_v0, keep, strict=True) if ok]
            weights = [w for w, ok in zip(weights, keep, strict=True) if ok]
        self._q0_hat, self._v0_hat = estimator_step_vec(
            self._q0_hat, self._v0_hat, nbr_q0, nbr_v0, weights, cfg.leader_weight, lq, lv,
            cfg.estimator, h,
        )
        if self._reacquiring and fresh is not None:
            self._q0_hat, self._v0_hat, far = reacquire(
                self._q0_hat, self._v0_hat, fresh.q0, fresh.v0, cfg.degradation, h)
            self._reacquire_s += h
            self._reacquiring = far or self._reacquire_s < cfg.degradation.reacquire_min_s
        share = Share(
            self.q0_hat, self.v0_hat, q.copy(), q_dot.copy(), np.array(zeta), np.array(zeta_dot),
            info_age,
        )
        if not _finite(v_d):
            nonfinite = True
            v_d = (0.0, 0.0, 0.0)  # a kinematic plant takes v_cmd: never a NaN either
        return AgentOutput(
            torques=np.array(torques), v_cmd=np.array(v_d), share=share,
            tracking_error=np.array(e), sliding=np.array(s),
            q_d=np.array(q_d_now), q_fd=np.array(q_fd),
            order=tuple(dict.fromkeys(b.name for b in chain)),  # FOCB once, however many
            task_errors=_first_errors(chain),
            z2_hat=np.array(self._z2_hat), nonfinite=nonfinite,
            input_age_s=input_age, speed_factor=self._speed_factor, left_out=left_out,
            safety=safety,
        )


def _nearest(bodies: Sequence[Body], x: float, y: float) -> tuple[Body, Vec2]:
    """The body whose surface is closest to (x, y) (the first of equals), and its position."""
    best: tuple[Body, Vec2] | None = None
    best_gap = 0.0
    for b in bodies:
        bx, by = b.position.tolist()
        gap = hypot(x - bx, y - by) - b.radius
        if best is None or gap < best_gap:
            best, best_gap = (b, (bx, by)), gap
    assert best is not None, "no bodies"
    return best


def _first_errors(chain: Sequence[Task]) -> dict[str, float]:
    """Each behavior's task error, of its highest-priority (nearest) task."""
    out: dict[str, float] = {}
    for b in chain:
        out.setdefault(b.name, b.task_error)
    return out


def _vec3(x: np.ndarray | Vec3) -> Vec3:
    """A 3-vector as floats (``tolist`` is the cheapest way out of numpy; a tuple,
    as the wire delivers it, is taken as it is)."""
    return x if type(x) is tuple else tuple(x.tolist())  # type: ignore[return-value]


def _sub(a: Vec3, b: Vec3) -> Vec3:
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


def _finite(x: Sequence[float]) -> bool:
    return all(map(isfinite, x))
