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

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from math import isfinite

import numpy as np

from agents.controller import ControlConstants, ControllerGains
from agents.degradation import DegradationConfig, InputAges
from agents.eso import EsoGains
from agents.estimator import EstimatorGains
from agents.formation import ScaleChange
from agents.fusion import DEFAULT_PRIORITY
from agents.law_kernel import Law
from agents.safety_filter import SafetyResult
from agents.share import Share
from agents.signals import Vec3, Vec4
from plant.bodies import Body, body_rows
from plant.mecanum import MecanumModel


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


@dataclass(slots=True)
class AgentOutput:
    # floats as the compiled law gives them (every consumer sends or stores floats: a
    # numpy round trip cost two array builds and two tolist calls a step)
    torques: Vec4  # wheel torques, N m, finite and within limits
    v_cmd: Vec3  # fused velocity command v_d (what a kinematic plant takes)
    share: Share
    # telemetry
    tracking_error: Vec3  # e = q - q_d
    sliding: Vec3  # s
    q_d: Vec3
    q_fd: Vec3
    order: tuple[str, ...]  # active behaviors, highest priority first
    task_errors: dict[str, float]
    z2_hat: Vec3
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


# Body objects (or anything with ident, position, velocity, radius: the wire's sensed
# bodies), or rows (ident, x, y, vx, vy, radius)
Bodies = Sequence[Body] | np.ndarray


class AgentCore:
    """State and step of one agent (estimator, reference, ESO): the Python face of the
    compiled law (agents/law_kernel.pyx, ``Law``), which holds the state and does the
    arithmetic of every equation; this class turns the step's inputs into the kernel's and
    its outputs into an :class:`AgentOutput`, and restarts a diverged state."""

    def __init__(
        self,
        cfg: AgentConfig,
        q_init: np.ndarray,
        q_dot_init: np.ndarray,
        q0_hat_init: np.ndarray,
        v0_hat_init: np.ndarray,
    ) -> None:
        self.cfg = cfg
        self._law = Law(cfg, ControlConstants.from_gains(cfg.controller))
        q = _vec3(np.asarray(q_init, dtype=float))
        self._law.set_state(_vec3(np.asarray(q0_hat_init, dtype=float)),
                            _vec3(np.asarray(v0_hat_init, dtype=float)),
                            q)  # the CLIK reference starts at the robot
        self._neighbours = tuple(j for j, _ in cfg.neighbours)
        self._last_h: float | None = None  # the step the observer last integrated over
        zeta, zeta_dot = self._law.offsets(0.0)
        self.initial_share = Share(self.q0_hat_vec, self.v0_hat_vec, q,
                                   _vec3(np.asarray(q_dot_init, dtype=float)), zeta, zeta_dot)

    def fork(self) -> AgentCore:
        """An independent copy to step ahead of this one (agents/look_ahead.py)."""
        other = AgentCore.__new__(AgentCore)
        other.cfg, other._neighbours, other.initial_share = (
            self.cfg, self._neighbours, self.initial_share)
        other._law = self._law.fork()
        other._last_h = self._last_h
        return other

    @property
    def law(self) -> Law:
        """The compiled law (its state and step)."""
        return self._law

    @property
    def q0_hat_vec(self) -> Vec3:
        return self._law.state()["q0_hat"]

    @property
    def v0_hat_vec(self) -> Vec3:
        return self._law.state()["v0_hat"]

    @property
    def q0_hat(self) -> np.ndarray:
        """The leader pose estimate (advanced to the next step after a step)."""
        return np.array(self.q0_hat_vec)

    @property
    def v0_hat(self) -> np.ndarray:
        """The leader velocity estimate (advanced to the next step after a step)."""
        return np.array(self.v0_hat_vec)

    def kernel_inputs(self, shares: Mapping[int, Share], ages: InputAges | None
                      ) -> tuple[list[Share], tuple | None]:
        """The neighbours' shares in the configuration's order and the ages as the kernel
        takes them."""
        nbr = [shares[j] for j in self._neighbours]
        if ages is None:
            return nbr, None
        return nbr, (ages.state_s, ages.leader_s,
                     [ages.shares_s.get(j, 0.0) for j in self._neighbours])

    def kernel_call(self, t: float, q: np.ndarray | Vec3, q_dot: np.ndarray | Vec3,
                    shares: Mapping[int, Share],
                    leader: tuple[np.ndarray, np.ndarray] | tuple[Vec3, Vec3] | None,
                    obstacles: Bodies = (), robots: Bodies = ()) -> Callable[[], object]:
        """The compiled law's own step on these inputs, prepared as :meth:`step` prepares
        them, as a call without arguments: what the kernel alone costs (``omnifleet
        bench``, the floor under the agent's budget). Each call advances the law's state."""
        h, law = self.cfg.dt, self._law
        args = self._kernel_args(t, q, q_dot, shares, leader, obstacles, robots, None, h, h,
                                 1.0)
        return lambda: law.step(*args)

    def _kernel_args(self, t: float, q: np.ndarray | Vec3, q_dot: np.ndarray | Vec3,
                     shares: Mapping[int, Share],
                     leader: tuple[np.ndarray, np.ndarray] | tuple[Vec3, Vec3] | None,
                     obstacles: Bodies, robots: Bodies, ages: InputAges | None, h: float,
                     horizon: float, speed_cap: float) -> tuple:
        """A step's inputs as the compiled law's ``step`` takes them, in its order."""
        nbr, kernel_ages = self.kernel_inputs(shares, ages)
        lead = None if leader is None else (_vec3(leader[0]), _vec3(leader[1]))
        return (t, _vec3(q), _vec3(q_dot), nbr, kernel_ages, lead, _bodies(obstacles),
                _bodies(robots), h, horizon, speed_cap)

    def step(
        self,
        t: float,
        q: np.ndarray | Vec3,
        q_dot: np.ndarray | Vec3,
        shares: Mapping[int, Share],
        leader: tuple[np.ndarray, np.ndarray] | tuple[Vec3, Vec3] | None,
        obstacles: Bodies = (),
        robots: Bodies = (),
        dt: float | None = None,
        ages: InputAges | None = None,
        horizon: float | None = None,
        speed_cap: float = 1.0,
        own_torques: bool = True,
    ) -> AgentOutput:
        """One control step. ``dt`` is the time to the next step: the configured
        period unless given (a realtime agent passes the time its plant actually
        advanced, so a missed period does not stretch the observer's clock).
        ``ages``: how stale the inputs are (None: all fresh); see degradation.py.
        ``horizon``: how long this command will act before the next can brake (the
        avoidance engagement and the safety filter's barrier use it; at least ``dt``;
        agents/pace.py measures it on a realtime loop); ``speed_cap``: a planar speed
        scale for a loop that cannot keep its period (1: none).
        ``own_torques``: whether the robot reached this state under the torques this law
        computed at its previous step (False: a look-ahead, held or zero torques acted,
        its command late or lost; ``Sample.own_torques``). Either that, or a ``dt`` other
        than the previous step's, restarts the observer's z1_hat from this measurement.
        ``obstacles``, ``robots``: what perception sees (Body objects, or rows
        (ident, x, y, vx, vy, radius) as plant/perception.py gives them).

        A law that diverges gives zero torques and ``nonfinite``, never an exception;
        the state it left non-finite is restarted from the measurement (``reset``)."""
        h = self.cfg.dt if dt is None else dt
        args = self._kernel_args(t, q, q_dot, shares, leader, obstacles, robots, ages, h,
                                 h if horizon is None else horizon, speed_cap)
        qv, qdv = args[1], args[2]
        last_h, self._last_h = self._last_h, h
        if not own_torques or (last_h is not None and abs(h - last_h) > 1e-9 * h):
            # eq. (39) advanced z1_hat over last_h with the Gamma of the previous step:
            # if those torques never acted, or this sample came after h and not last_h
            # (a realtime agent that skipped one, or the step after), the innovation
            # z1 - z1_hat is that input's effect, not a disturbance, and z2_hat integrates
            # it until z1_hat has crept back (`paper` at 1 kHz, a first command of
            # 1.9e5 N m a period late: 211 m/s off, ~8 s at mu1 = 0.6, r1 = 0.7, the robot
            # never settling meanwhile). Ours, not the paper's: z1_hat restarts from this
            # measurement, as at the first one; z2_hat is kept (docs/errata.md)
            self._law.restore("z1_hat", None)
        raw = self._law.step(*args)
        (torques, v_cmd, e, s, q_d, q_fd, zeta, zeta_dot, q0h, v0h, z2, order, errors,
         nonfinite, info_age, input_age, speed, left_out, safety) = raw
        out = AgentOutput(
            torques=torques, v_cmd=v_cmd,
            share=Share(q0h, v0h, qv, qdv, zeta, zeta_dot, info_age),
            tracking_error=e, sliding=s, q_d=q_d, q_fd=q_fd, order=order, task_errors=errors,
            z2_hat=z2, nonfinite=nonfinite, input_age_s=input_age, speed_factor=speed,
            left_out=left_out, safety=None if safety is None else SafetyResult(*safety),
        )
        if nonfinite or not self._law.state_finite():
            # a step that left anything non-finite (its command, or the state it carries
            # on: the estimator overflowing on an absurd input) diverged: zero commands,
            # counted. Never stay diverged: a NaN in an integrator stays there for good (a
            # paused realtime agent sent zero torques for the rest of its run); the next
            # step starts from the measurement, and the share carries the restarted estimate
            out.nonfinite = True
            out.torques = (0.0, 0.0, 0.0, 0.0)
            out.v_cmd = (0.0, 0.0, 0.0)
            out.reset = self.recover(q, q_dot, shares, leader)
            st = self._law.state()
            out.share = Share(st["q0_hat"], st["v0_hat"], qv, qdv, zeta, zeta_dot, info_age)
        return out

    def plan(self, out: AgentOutput, t: float, q: np.ndarray | Vec3, q_dot: np.ndarray | Vec3,
             shares: Mapping[int, Share], leader, obstacles: Bodies, robots: Bodies,
             ages: InputAges | None, horizon: int) -> list[tuple[float, float, float, float]]:
        """The look-ahead torques after ``out`` (agents/look_ahead.py)."""
        nbr, kernel_ages = self.kernel_inputs(shares, ages)
        lead = None if leader is None else (_vec3(leader[0]), _vec3(leader[1]))
        return self._law.plan(out.torques, t, _vec3(q), _vec3(q_dot), nbr,
                              kernel_ages, lead, _bodies(obstacles), _bodies(robots),
                              horizon)

    def recover(self, q: np.ndarray | Vec3, q_dot: np.ndarray | Vec3,
                shares: Mapping[int, Share],
                leader: tuple[np.ndarray, np.ndarray] | None) -> tuple[str, ...]:
        """Restart from the newest measurement after a step that diverged (a non-finite
        command, or a non-finite state left behind). Returns what was restarted:

        - "reference": q_d := q, the measured pose (eq. 11's integrator; e = 0), and the
          last command v_d forgotten (the first order hold restarts from v_d);
        - "observer": z1_hat from the next measurement, z2_hat := 0 (eq. 39, as at start);
        - "estimator", when it is not finite: q0_hat, v0_hat from the leader when heard,
          else the mean of the neighbours' finite estimates, else the robot's own pose at
          rest (eq. 14);
        - "speed", when it is not finite: the degradation speed factor from 0 (it ramps
          back up)."""
        done: list[str] = []
        law, st = self._law, self._law.state()
        q_v = _vec3(q)
        if _finite(q_v):
            law.restore("q_d", q_v)
            done.append("reference")
        law.restore("v_d_prev", None)
        law.restore("z1_hat", None)
        law.restore("z2_hat", (0.0, 0.0, 0.0))
        done.append("observer")
        if not (_finite(st["q0_hat"]) and _finite(st["v0_hat"])):
            q0, v0 = self._estimate_from(q_v, shares, leader)
            law.restore("q0_hat", q0)
            law.restore("v0_hat", v0)
            done.append("estimator")
        if not isfinite(st["speed_factor"]):
            law.restore("speed_factor", 0.0)
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


def _bodies(bodies: Bodies) -> Bodies:
    """What the kernel reads perceived bodies from: rows as a contiguous float array
    (checked), or a list of objects with ident, position, velocity and radius (a Body, the
    wire's sensed body) as it is."""
    return body_rows(bodies) if isinstance(bodies, np.ndarray) else bodies


def _vec3(x: np.ndarray | Vec3 | Sequence[float]) -> Vec3:
    """A 3-vector as floats (``tolist`` is the cheapest way out of numpy; a tuple,
    as the wire delivers it, is taken as it is)."""
    if type(x) is tuple:
        return x  # type: ignore[return-value]
    if isinstance(x, np.ndarray):
        return tuple(x.tolist())  # type: ignore[return-value]
    return (float(x[0]), float(x[1]), float(x[2]))


def _finite(x: Sequence[float]) -> bool:
    return all(map(isfinite, x))
