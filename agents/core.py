"""One robot's agent as a pure step function: estimator -> formation reference ->
behaviors -> fusion -> controller -> torques. No I/O: the in-process runner and
the distributed node both call :meth:`AgentCore.step` with the same inputs.

Data flow per control step k (DESIGN §4, lockstep): own state at t_k, the
neighbours' shares of step k-1, the leader state at t_k iff b_i != 0, and what
perception sees at t_k. The share published at step k carries the estimate
already advanced to k+1, so estimator consensus runs as the synchronous Euler
scheme of the authors' code while positions arrive one step late.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from agents.behaviors import BehaviorOutput, avoidance_behavior, formation_behavior
from agents.controller import (
    ControllerGains,
    allocate,
    control_term,
    saturate_torques,
)
from agents.eso import EsoGains, eso_step
from agents.estimator import EstimatorGains, estimator_step
from agents.formation import ScaleChange, desired_formation, offsets, scale_at
from agents.fusion import (
    DEFAULT_PRIORITY,
    fuse,
    order_by_priority,
    saturate_velocity,
    supervise,
)
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


@dataclass(frozen=True)
class Body:
    """A sensed body: another robot or an obstacle."""

    ident: int
    position: np.ndarray  # (2,)
    velocity: np.ndarray  # (2,)
    radius: float


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


class AgentCore:
    """State and step of one agent (estimator, reference, ESO)."""

    def __init__(
        self,
        cfg: AgentConfig,
        q_init: np.ndarray,
        q_dot_init: np.ndarray,
        q0_hat_init: np.ndarray,
        v0_hat_init: np.ndarray,
    ) -> None:
        self.cfg = cfg
        self.q0_hat = np.array(q0_hat_init, dtype=float)
        self.v0_hat = np.array(v0_hat_init, dtype=float)
        self.q_d = np.array(q_init, dtype=float)  # CLIK reference starts at the robot
        self.v_d_prev: np.ndarray | None = None
        self.z1_hat: np.ndarray | None = None  # set to the first measurement (see eso.py)
        self.z2_hat = np.zeros(3)
        self._r_i = np.array(cfg.offset, dtype=float)
        self._weights = [w for _, w in cfg.neighbours]
        zeta, zeta_dot = self._offsets(0.0)
        self.initial_share = Share(
            self.q0_hat.copy(), self.v0_hat.copy(), np.array(q_init, float),
            np.array(q_dot_init, float), zeta, zeta_dot,
        )

    def _offsets(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.cfg
        scale, scale_dot = scale_at(t, cfg.initial_scale, cfg.scale_changes)
        return offsets(
            self._r_i, cfg.heading_offset, float(self.q0_hat[2]), float(self.v0_hat[2]),
            scale, scale_dot,
        )

    def _behaviors(
        self,
        q: np.ndarray,
        q_fd: np.ndarray,
        v_fd: np.ndarray,
        obstacles: Sequence[Body],
        robots: Sequence[Body],
    ) -> list[BehaviorOutput]:
        cfg = self.cfg
        out: list[BehaviorOutput] = []
        if "FDB" in cfg.enabled:
            out.append(formation_behavior(q, q_fd, v_fd, cfg.fdb_gains))
        # R_a is measured from an obstacle's surface (the paper's obstacles are
        # points), R_c from the other robot's centre, as printed.
        for name, bodies, safe, surface, gains in (
            ("FOCB", obstacles, cfg.obstacle_safe_m, True, cfg.focb_gains),
            ("FRCB", robots, cfg.robot_safe_m, False, cfg.frcb_gains),
        ):
            if name not in cfg.enabled or not bodies:
                continue
            nearest = min(bodies, key=lambda b: float(np.hypot(*(q[:2] - b.position))) - b.radius)
            out.append(
                avoidance_behavior(
                    name, q, nearest.position,
                    cfg.robot_radius_m + nearest.radius,
                    safe + (nearest.radius if surface else 0.0),
                    float(q_fd[2]), float(v_fd[2]), gains,
                )
            )
        return out

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
    ) -> AgentOutput:
        """One control step. ``dt`` is the time to the next step: the configured
        period unless given (a realtime agent passes the time its plant actually
        advanced, so a missed period does not stretch the observer's clock)."""
        cfg = self.cfg
        h = cfg.dt if dt is None else dt
        nbr = [shares[j] for j, _ in cfg.neighbours]

        # formation reference, eqs. (13), (16)
        zeta, zeta_dot = self._offsets(t)
        q_fd, v_fd = desired_formation(
            cfg.kappa1, cfg.kappa2, self.q0_hat, self.v0_hat, zeta, zeta_dot, self._weights,
            [s.q for s in nbr], [s.q_dot for s in nbr], [s.zeta for s in nbr],
            [s.zeta_dot for s in nbr],
        )

        # behaviors (15)-(25), supervisor + fusion (26), explicit limits
        chain = supervise(
            order_by_priority(self._behaviors(q, q_fd, v_fd, obstacles, robots), cfg.priority),
            cfg.avoidance_engage,
        )
        v_d = saturate_velocity(fuse(chain), cfg.max_speed_mps, cfg.max_yaw_rate_radps)

        # dynamic level, eqs. (36), (40)-(42)
        model = cfg.model
        phi = float(q[2])
        # Reference q_d(t): first-order hold of the v_d samples, one period late
        # (see controller.py): velocity v_d(k-1) at t_k, constant acceleration
        # q_d_ddot over [t_k, t_k+1] that the zero-order-hold torque can realise.
        v_ref = v_d if self.v_d_prev is None else self.v_d_prev
        q_d_ddot = (v_d - v_ref) / h
        e = q - self.q_d
        e_dot = q_dot - v_ref
        if self.z1_hat is None:
            self.z1_hat = e_dot.copy()
        gamma, s = control_term(e, e_dot, self.z2_hat, cfg.controller)
        generalised = q_d_ddot + model.A0 @ q_dot + model.A1(phi, q_dot) + gamma
        torques = saturate_torques(
            allocate(model.augmented_input(phi), generalised), cfg.max_wheel_torque_nm
        )
        nonfinite = not bool(np.all(np.isfinite(torques)))
        if nonfinite:
            torques = np.zeros(4)

        # observer (39) and reference integration (CLIK, eq. 11)
        self.z1_hat, self.z2_hat = eso_step(
            self.z1_hat, self.z2_hat, e_dot, gamma, cfg.eso, h
        )
        q_d_now = self.q_d
        self.q_d = self.q_d + 0.5 * h * (v_ref + v_d)
        self.v_d_prev = v_d

        # leader estimator (14), advanced to k+1 and shared
        lq, lv = leader if leader is not None else (None, None)
        self.q0_hat, self.v0_hat = estimator_step(
            self.q0_hat, self.v0_hat, [s.q0_hat for s in nbr], [s.v0_hat for s in nbr],
            self._weights, cfg.leader_weight, lq, lv, cfg.estimator, h,
        )
        share = Share(
            self.q0_hat.copy(), self.v0_hat.copy(), q.copy(), q_dot.copy(), zeta, zeta_dot
        )
        if not bool(np.all(np.isfinite(v_d))):
            nonfinite = True
            v_d = np.zeros(3)  # a kinematic plant takes v_cmd: never a NaN either
        return AgentOutput(
            torques=torques, v_cmd=v_d, share=share, tracking_error=e, sliding=s,
            q_d=q_d_now, q_fd=q_fd,
            order=tuple(b.name for b in chain),
            task_errors={b.name: b.task_error for b in chain},
            z2_hat=self.z2_hat, nonfinite=nonfinite,
        )
