"""A law of the lab's own in the agent's place (agents/law_api.py, docs/laws.md): what the
runtime wraps around it, with the face of :class:`agents.core.AgentCore`, so the
in-process runner, a lockstep or realtime agent process and a robot behind a CAN bridge
step it as they step the paper's law.

Each step the law gets copies of its inputs and returns a velocity (behavior level) or
torques (torque level); the compiled law (agents/law_kernel.pyx) does the rest as it does
for the paper's own fused velocity (``Law.drive``: the explicit limits, the safety filter,
the fully actuated controller with its observer). A torque-level law's torques are put
to the same safety filter by the velocity they would reach in one period (eq. 4, RK4):
where the filter would change it, the controller brakes to the filtered velocity instead.

**Containment.** A law that raises, or returns something that is not a finite velocity
below ``MAX_SPEED_MPS`` (torques below ``MAX_TORQUE_NM``) or a share of finite numbers,
does not reach the wheels: its robot brakes that step (the controller is given v_d = 0,
through the safety filter), the fault is counted (``law_errors``, ``law_refused``) and the
first of each kind is kept as one line (``law_error``: the exception's type, message and
where it was raised). A step whose computing (the thread's CPU time) takes longer than its period is counted
(``law_overruns``); its output is still used (a late command: the loop's pace, the plant's
command timeout and the look-ahead judge what lateness costs). The run's verdict fails
on any error or refusal, naming the law.
"""

from __future__ import annotations

import math
import time
import traceback
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from agents.controller import ControlConstants
from agents.core import AgentConfig, AgentOutput, Bodies, Share
from agents.degradation import InputAges
from agents.formation import scale_at
from agents.law_api import BEHAVIOR, BehaviorOutput, ControlLaw, LawInputs, TorqueOutput
from agents.law_kernel import Law
from agents.safety_filter import SafetyResult
from agents.signals import Vec3, Vec4
from plant.bodies import body_rows

MAX_SPEED_MPS = 1e3  # a velocity a law asks for beyond this is absurd (refused, braked)
MAX_TORQUE_NM = 1e7  # likewise a torque (the plant never applies more: plant/command.py)
BRAKE: Vec3 = (0.0, 0.0, 0.0)
ZERO4: Vec4 = (0.0, 0.0, 0.0, 0.0)


class LawFaults:
    """What a law did wrong, counted by kind, with the first of each as one line."""

    def __init__(self) -> None:
        self.errors = 0  # raised
        self.refused = 0  # returned a non-finite or absurd output
        self.overruns = 0  # took longer than its period
        self.first: dict[str, str] = {}

    def note(self, kind: str, line: str) -> None:
        setattr(self, kind, getattr(self, kind) + 1)
        self.first.setdefault(kind, line)

    def as_json(self) -> dict:
        """Per robot, for metrics.json (``law_faults``)."""
        return {"errors": self.errors, "refused": self.refused, "overruns": self.overruns,
                "error": self.error_line}

    @property
    def error_line(self) -> str:
        """The first error's line, else the first refusal's, else ""."""
        return self.first.get("errors") or self.first.get("refused") or ""


def _vec(x: Any, n: int) -> tuple[float, ...] | None:
    """``x`` as n floats, all finite, or None."""
    try:
        v = tuple(map(float, x))
    except (TypeError, ValueError):
        return None
    return v if len(v) == n and math.isfinite(sum(v)) else None  # NaN and inf carry to the sum


_SHARE_VECTORS = ("q0_hat", "v0_hat", "q", "q_dot", "zeta", "zeta_dot")


def _share(s: Any) -> Share | None:
    """A law's share as the wire carries it (floats), or None when it is not one of 19
    finite numbers."""
    try:
        parts = [tuple(map(float, getattr(s, f))) for f in _SHARE_VECTORS]
        age = float(getattr(s, "info_age_s", 0.0))
    except (AttributeError, TypeError, ValueError):
        return None
    if any(len(p) != 3 for p in parts) or not math.isfinite(sum(map(sum, parts)) + age):
        return None
    return Share(*parts, info_age_s=age)  # type: ignore[arg-type]


def _sensed(bodies: Bodies) -> tuple[tuple[float, ...], ...]:
    """Perceived bodies as rows of floats (ident, x, y, vx, vy, radius): immutable copies."""
    rows = body_rows(bodies) if not isinstance(bodies, np.ndarray) else bodies
    return tuple(tuple(r) for r in np.asarray(rows, dtype=float).tolist())


class PluggedCore:
    """A law of the lab's in the place of :class:`agents.core.AgentCore`."""

    def __init__(self, cfg: AgentConfig, law: ControlLaw, q_init: Any, q_dot_init: Any,
                 q0_hat_init: Any, v0_hat_init: Any) -> None:
        self.cfg, self.plugged = cfg, law
        self.name = type(law).law_name()
        self._law = Law(cfg, ControlConstants.from_gains(cfg.controller))
        q = tuple(np.asarray(q_init, dtype=float).tolist())
        qd = tuple(np.asarray(q_dot_init, dtype=float).tolist())
        q0 = tuple(np.asarray(q0_hat_init, dtype=float).tolist())
        v0 = tuple(np.asarray(v0_hat_init, dtype=float).tolist())
        self._law.set_state(q0, v0, q)  # the controller's reference starts at the robot
        self.faults = LawFaults()
        self.overrun_s = cfg.dt  # a step longer than the period is an overrun
        share = self._guard(lambda: law.start(q, qd, q0, v0), "start")
        self.initial_share = _share(share) or Share(q0, v0, q, qd, (0.0, 0.0, 0.0),
                                                    (0.0, 0.0, 0.0))
        self._last_share = self.initial_share

    # what the agent node asks of a core ------------------------------------------------
    @property
    def law(self) -> Law:
        return self._law

    @property
    def q0_hat_vec(self) -> Vec3:
        return self._last_share.q0_hat

    @property
    def v0_hat_vec(self) -> Vec3:
        return self._last_share.v0_hat

    def fork(self) -> PluggedCore:
        other = PluggedCore.__new__(PluggedCore)
        other.cfg, other.name, other.overrun_s = self.cfg, self.name, self.overrun_s
        other.plugged = self.plugged.fork()
        other._law = self._law.fork()
        other.faults = LawFaults()  # a fork's faults are its own (the plan is discarded)
        other.initial_share, other._last_share = self.initial_share, self._last_share
        return other

    def recover(self, q: Any, q_dot: Any, shares: Mapping[int, Share],
                leader: Any) -> tuple[str, ...]:
        """The controller's state from the measurement (a non-finite step; the law keeps
        its own)."""
        qv = tuple(np.asarray(q, dtype=float).tolist())
        if all(map(math.isfinite, qv)):
            self._law.restore("q_d", qv)
        self._law.restore("v_d_prev", None)
        self._law.restore("z1_hat", None)
        self._law.restore("z2_hat", (0.0, 0.0, 0.0))
        return ("reference", "observer")

    # the step ---------------------------------------------------------------------------
    def _guard(self, call: Any, what: str) -> Any:
        """``call()``, or None when it raised (counted, its line kept)."""
        try:
            return call()
        except Exception as exc:  # noqa: BLE001 - a lab's law may raise anything
            where = traceback.extract_tb(exc.__traceback__)[-1]
            self.faults.note("errors", f"{self.name}.{what}: {type(exc).__name__}: {exc} "
                                       f"({where.filename}:{where.lineno})")
            return None

    def _inputs(self, t: float, q: Vec3, q_dot: Vec3, shares: Mapping[int, Share],
                leader: Any, obstacles: Bodies, robots: Bodies, h: float,
                ages: InputAges | None) -> LawInputs:
        lead = None if leader is None else (tuple(map(float, leader[0])),
                                            tuple(map(float, leader[1])))
        mine = {j: shares[j] for j, _ in self.cfg.neighbours if j in shares}
        cfg = self.cfg
        if cfg.scale_changes:  # eq. (13)'s S(t), where the scenario makes it vary
            scale, rate = scale_at(t, cfg.initial_scale, cfg.scale_changes)
            scale, rate = scale.tolist(), rate.tolist()
        else:
            scale, rate = cfg.initial_scale, (0.0, 0.0)
        r = cfg.offset
        return LawInputs(t, h, q, q_dot, lead, mine, _sensed(obstacles), _sensed(robots),
                         0.0 if ages is None else ages.leader_s,
                         {} if ages is None else dict(ages.shares_s),
                         (scale[0] * r[0], scale[1] * r[1]), (rate[0] * r[0], rate[1] * r[1]))

    def step(self, t: float, q: Any, q_dot: Any, shares: Mapping[int, Share], leader: Any,
             obstacles: Bodies = (), robots: Bodies = (), dt: float | None = None,
             ages: InputAges | None = None, horizon: float | None = None,
             speed_cap: float = 1.0, own_torques: bool = True) -> AgentOutput:
        """As :meth:`agents.core.AgentCore.step`."""
        h = self.cfg.dt if dt is None else dt
        qv = tuple(map(float, q))
        qdv = tuple(map(float, q_dot))
        if not own_torques:  # the torques of the last step never acted (AgentCore.step)
            self._law.restore("z1_hat", None)
        x = self._inputs(t, qv, qdv, shares, leader, obstacles, robots, h, ages)
        # the law's own computing, in this thread's CPU time: a host that starves the
        # process stretches the wall time of every step, the law's or not (the loop's
        # late commands and the host's stolen time say that), and is not the law's fault
        started = time.thread_time()
        out = self._guard(lambda: self.plugged.step(x), "step")
        if time.thread_time() - started > self.overrun_s:
            self.faults.note("overruns", f"{self.name}.step took longer than its period "
                                         f"({self.overrun_s * 1e3:.1f} ms) at t = {t:.3f} s")
        v_d, torques, share, target = self._checked(out, t)
        hz = h if horizon is None else horizon
        law_v = BRAKE if v_d is None else v_d
        torque_level = self.plugged.level != BEHAVIOR
        if torque_level:
            # the velocity the law's torques would reach over this command's horizon, put
            # to the safety filter. The controller is kept a plain velocity tracker from
            # where the robot is (its reference at the robot, no feed-forward of a last
            # command), so that where the filter acts it brakes from here at once
            self._law.restore("q_d", qv)
            self._law.restore("v_d_prev", None)
            if torques is not None:
                lim = self.cfg.max_wheel_torque_nm
                torques = tuple(min(max(a, -lim), lim) for a in torques)  # clamped first
                _, law_v = self._law.predicted(qv, qdv, torques, hz)
        (u, v_cmd, e, s, q_d, z2, nonfinite, safety) = self._law.drive(
            t, qv, qdv, law_v, _rows(obstacles), _rows(robots), h, hz, speed_cap)
        filtered = safety is not None and safety[1]
        if torque_level and not nonfinite:
            # the law's own torques, or where the filter acts (or the law failed) the
            # torques that take the robot to the filtered velocity in one period, at most
            # at the scenario's acceleration limit: a brake from where it is
            u = (self._brake(qv, qdv, (safety[0][0], safety[0][1]) if filtered else
                             (0.0, 0.0), h) if filtered or torques is None else torques)
        if torque_level:  # no reference of the controller's: the error to where the law aims
            e = (tuple(a - b for a, b in zip(qv, target, strict=True)) if target is not None
                 else (0.0, 0.0, 0.0))
        if share is not None:
            self._last_share = share
        return AgentOutput(
            torques=ZERO4 if nonfinite else u, v_cmd=v_cmd, share=self._last_share,
            tracking_error=e, sliding=s, q_d=q_d, q_fd=target or qv, order=(self.name,),
            task_errors={}, z2_hat=z2, nonfinite=nonfinite,
            safety=None if safety is None else SafetyResult(*safety))

    def _brake(self, q: Vec3, q_dot: Vec3, v: tuple[float, float], h: float) -> Vec4:
        """Torques that bring the planar velocity to ``v`` and the yaw rate to 0 in one
        period ``h``, at most at the acceleration limits, by eq. (4) inverted (the
        minimum-norm allocation of eq. 34, erratum 3), within the torque limit."""
        cfg, m = self.cfg, self.cfg.model
        ax, ay = (v[0] - q_dot[0]) / h, (v[1] - q_dot[1]) / h
        norm = math.hypot(ax, ay)
        if norm > cfg.max_accel_mps2:
            ax, ay = ax * cfg.max_accel_mps2 / norm, ay * cfg.max_accel_mps2 / norm
        aw = max(-cfg.max_yaw_accel_radps2, min(cfg.max_yaw_accel_radps2, -q_dot[2] / h))
        qd = np.asarray(q_dot, dtype=float)
        rhs = np.array([ax, ay, aw]) + m.A0 @ qd + m.A1(q[2], qd)
        u = np.linalg.solve(m.augmented_input(q[2]), np.append(rhs, 0.0))
        lim = cfg.max_wheel_torque_nm
        return tuple(min(max(float(a), -lim), lim) for a in u)  # type: ignore[return-value]

    def _checked(self, out: Any, t: float
                 ) -> tuple[Vec3 | None, Vec4 | None, Share | None, Vec3 | None]:
        """(v_d, torques, share, target) of a law's output: v_d None (brake) when it raised
        or gave something unusable (counted)."""
        if out is None:  # it raised: counted in _guard
            return None, None, None, None
        level = self.plugged.level
        kind = BehaviorOutput if level == BEHAVIOR else TorqueOutput
        share = _share(getattr(out, "share", None)) if isinstance(out, kind) else None
        target = _vec(getattr(out, "target", None), 3) if getattr(out, "target", None) else None
        if level == BEHAVIOR:
            v = _vec(out.v_d, 3) if isinstance(out, kind) else None
            if v is None or math.hypot(v[0], v[1]) > MAX_SPEED_MPS or abs(v[2]) > MAX_SPEED_MPS:
                v = None
            torques = None
        else:
            torques = _vec(out.torques, 4) if isinstance(out, kind) else None
            if torques is not None and max(map(abs, torques)) > MAX_TORQUE_NM:
                torques = None
            v = BRAKE if torques is None else None
        if (level == BEHAVIOR and v is None) or (level != BEHAVIOR and torques is None) \
                or share is None:
            self.faults.note("refused", f"{self.name}.step at t = {t:.3f} s returned "
                                        f"{_describe(out, kind)}")
            return None, None, None, None
        return v, torques, share, target  # type: ignore[return-value]

    def plan(self, out: AgentOutput, t: float, q: Any, q_dot: Any,
             shares: Mapping[int, Share], leader: Any, obstacles: Bodies, robots: Bodies,
             ages: InputAges | None, horizon: int) -> list[Vec4]:
        """As :meth:`agents.core.AgentCore.plan`: a fork of the law and its controller
        stepped H times on the state eq. (4) predicts under the torques just made, the
        same inputs older by each step, the bodies moved on."""
        sim = self.fork()
        h = self.cfg.dt
        qv, qdv = tuple(map(float, q)), tuple(map(float, q_dot))
        u = out.torques
        obs, rob = body_rows(obstacles).copy(), body_rows(robots).copy()
        planned: list[Vec4] = []
        for m in range(1, horizon + 1):
            qv, qdv = self._law.predicted(qv, qdv, u, h)
            for rows in (obs, rob):
                rows[:, 1:3] += h * rows[:, 3:5]
            aged = InputAges(0.0, (0.0 if ages is None else ages.leader_s) + m * h,
                             {j: (0.0 if ages is None else ages.shares_s.get(j, 0.0)) + m * h
                              for j, _ in self.cfg.neighbours})
            step = sim.step(t + m * h, qv, qdv, shares, leader, obs, rob, h, aged)
            if step.nonfinite or sim.faults.errors or sim.faults.refused:
                break
            u = step.torques
            planned.append(u)
        return planned


def _rows(bodies: Bodies) -> np.ndarray:
    return body_rows(bodies) if not isinstance(bodies, np.ndarray) else bodies


def _describe(out: Any, kind: type) -> str:
    if not isinstance(out, kind):
        return f"a {type(out).__name__}, not a {kind.__name__}"
    return f"{out!r}"[:200]


def make_core(cfg: AgentConfig, law: type[ControlLaw] | None, params: Any, q: Sequence[float],
              q_dot: Sequence[float], q0_hat: Sequence[float], v0_hat: Sequence[float]):
    """The agent's core: the paper's compiled law (``law`` None), or a plugged one."""
    from agents.core import AgentCore

    if law is None:
        return AgentCore(cfg, np.asarray(q, float), np.asarray(q_dot, float),
                         np.asarray(q0_hat, float), np.asarray(v0_hat, float))
    return PluggedCore(cfg, law(cfg, params), q, q_dot, q0_hat, v0_hat)
