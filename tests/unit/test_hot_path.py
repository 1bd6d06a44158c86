"""The compiled law (agents/law_kernel.pyx, plant/fleet_kernel.pyx) against the numpy oracle.

The kernel holds each equation once, on C doubles, one section a file. The tests' build of
it (tests/law_probe: the same sections, each callable) hands each section's arithmetic out
through tests/kernel_forms.py; the numpy oracle (tests/paper_oracle.py) is the paper's
matrix form, written independently, which the other test modules check against the paper's
equations and physical facts. Here each section is checked at its own boundary against its
numpy form, and the product's whole step (AgentCore, the product's kernel) against their
composition (``ReferenceCore``), output by output on a closed loop that engages every
behavior.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from kernel_forms import (
    avoidance_task_of,
    control_term_vec,
    desired_formation_vec,
    eso_step_vec,
    estimator_step_vec,
    formation_task,
    fuse_tasks,
    implicit_sign_scalar,
    offsets_vec,
    scale_at_vec,
    sig_scalar,
    supervise_tasks,
)
from law_probe import load
from paper_oracle import (
    AVOIDANCE,
    ReferenceCore,
    allocate,
    avoidance_behavior,
    control_term,
    desired_formation,
    eso_step,
    estimator_step,
    formation_behavior,
    fuse,
    implicit_sign,
    offsets,
    order_by_priority,
    saturate_torques,
    saturate_velocity,
    sig,
    supervise,
)
from plant.fleet_kernel import acceleration_of

from agents.controller import ControlConstants, ControllerGains
from agents.core import AgentConfig, AgentCore, AgentOutput
from agents.eso import EsoGains
from agents.estimator import EstimatorGains
from agents.formation import ScaleChange, scale_at
from agents.leader import Harmonic, LeaderGenerator, LeaderSpec
from plant.bodies import Body
from plant.limits import saturate_velocity_vec
from plant.mecanum import MecanumModel, RobotParams

SETTINGS = settings(max_examples=60, deadline=None)
RTOL = 1e-12

comp = st.floats(-5.0, 5.0, allow_nan=False)
vec2 = st.tuples(comp, comp)
vec3 = st.tuples(comp, comp, comp)
angle = st.floats(-math.pi, math.pi, allow_nan=False)

LAW = load()  # the tests' build of the law kernel, each section callable (tests/law_probe)


def close(a, b, rtol=RTOL):
    a, b = np.asarray(a, float), np.asarray(b, float)
    np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * (1.0 + np.abs(b).max(initial=0.0)))


# --- signals, estimator (14), ESO (39) ------------------------------------------------


@pytest.mark.parametrize("power", [0.0, 0.4, 0.7, 1.0, 1.5])
def test_sig_scalar_equals_sig(power):
    xs = [0.0, -0.0, 1e-300, -2.5, 3.0, 7e5, -math.inf, math.inf]
    # numpy's vectorised pow may round differently in the last bit
    got = [sig_scalar(x, power) for x in xs]
    np.testing.assert_allclose(got, sig(np.array(xs), power), rtol=1e-15, atol=0)
    assert math.isnan(sig_scalar(math.nan, power))


@pytest.mark.parametrize("reach", [0.0, 1e-3, 0.5])
def test_implicit_sign_scalar_equals_implicit_sign(reach):
    es = [0.0, 2e-4, -2e-4, 0.3, -0.3, 4.0, -4.0]
    got = [implicit_sign_scalar(e, reach) for e in es]
    np.testing.assert_array_equal(got, implicit_sign(np.array(es), reach))
    assert math.isnan(implicit_sign_scalar(math.nan, reach))


@SETTINGS
@given(q=vec3, v=vec3, nq=st.lists(st.tuples(vec3, vec3, st.floats(0.1, 2.0)), max_size=2),
       b=st.sampled_from([0.0, 1.0, 0.5]), lq=vec3, lv=vec3, leader=st.booleans(),
       dt=st.floats(1e-4, 0.05))
def test_estimator_step_vec_equals_estimator_step(q, v, nq, b, lq, lv, leader, dt):
    nb_q, nb_v, w = [x[0] for x in nq], [x[1] for x in nq], [x[2] for x in nq]
    a = np.array
    got = estimator_step_vec(q, v, nb_q, nb_v, w, b, lq if leader else None, lv if leader else None,
                             EstimatorGains(), dt)
    want = estimator_step(a(q), a(v), [a(x) for x in nb_q], [a(x) for x in nb_v], w, b,
                          a(lq) if leader else None, a(lv) if leader else None, EstimatorGains(), dt)
    close(got[0], want[0])
    close(got[1], want[1])


@SETTINGS
@given(z1=vec3, z2=vec3, m=vec3, g=vec3, dt=st.floats(1e-4, 0.05))
def test_eso_step_vec_equals_eso_step(z1, z2, m, g, dt):
    for gains in (EsoGains(), EsoGains(1.2, 0.5, 0.5)):  # r1 = 0.5: r2 = 0
        got = eso_step_vec(z1, z2, m, g, gains, dt)
        want = eso_step(np.array(z1), np.array(z2), np.array(m), np.array(g), gains, dt)
        close(got[0], want[0])
        close(got[1], want[1])


# --- formation (13), (16) ------------------------------------------------------------------

CHANGES = (
    ScaleChange(1.0, 2.0, (1.0, 0.5)), ScaleChange(2.2, 3.0, (0.3, 0.0)), ScaleChange(4.0, 5.0, (1.0, 1.0))
)


@SETTINGS
@given(t=st.floats(-1.0, 6.0), r=vec2, xi=angle, psi=st.floats(-20.0, 20.0), psi_dot=comp)
def test_formation_vec_equals_formation(t, r, xi, psi, psi_dot):
    (s, sd) = scale_at_vec(t, (1.0, 1.0), CHANGES)
    S, Sd = scale_at(t, (1.0, 1.0), CHANGES)
    close(s, S)
    close(sd, Sd)
    got = offsets_vec(r, xi, psi, psi_dot, s, sd)
    want = offsets(np.array(r), xi, psi, psi_dot, S, Sd)
    close(got[0], want[0])
    close(got[1], want[1])


@SETTINGS
@given(q0=vec3, v0=vec3, z=vec3, zd=vec3, nbrs=st.lists(st.tuples(vec3, vec3, vec3, vec3), max_size=2),
       kappa2=st.sampled_from([0.0, 0.5, 2.0]))
def test_desired_formation_vec_equals_desired_formation(q0, v0, z, zd, nbrs, kappa2):
    w = [1.0, 0.5][: len(nbrs)]
    cols = [[n[k] for n in nbrs] for k in range(4)]
    got = desired_formation_vec(1.0, kappa2, q0, v0, z, zd, w, *cols)
    a = np.array
    want = desired_formation(1.0, kappa2, a(q0), a(v0), a(z), a(zd), w, *[[a(x) for x in c] for c in cols])
    close(got[0], want[0])
    close(got[1], want[1])


def test_desired_formation_vec_rejects_zero_normalisation():
    z = (0.0, 0.0, 0.0)
    with pytest.raises(ValueError):
        desired_formation_vec(0.0, 1.0, z, z, z, z, [], [], [], [], [])


# --- behaviors (15)-(25), fusion (26) ---------------------------------------------------------


def _same_behavior(task, out):
    assert task.name == out.name and out.active
    close(task.to_output().jacobian, out.jacobian)
    close(task.velocity, out.velocity)
    assert task.task_error == pytest.approx(out.task_error, rel=RTOL, abs=RTOL)


@SETTINGS
@given(q=st.tuples(comp, comp, angle), fd=st.tuples(comp, comp, angle), v_fd=vec3, on_target=st.booleans())
def test_formation_task_equals_formation_behavior(q, fd, v_fd, on_target):
    if on_target:  # the zero-gradient case
        fd = (q[0], q[1], fd[2])
    _same_behavior(formation_task(q, fd, v_fd, (12.0, 0.25)),
                   formation_behavior(np.array(q), np.array(fd), np.array(v_fd), (12.0, 0.25)))


@SETTINGS
@given(q=st.tuples(comp, comp, angle), bearing=angle, d=st.floats(0.0, 3.0), phi_d=angle, phi_d_dot=comp)
def test_avoidance_task_equals_avoidance_behavior(q, bearing, d, phi_d, phi_d_dot):
    other = (q[0] + d * math.cos(bearing), q[1] + d * math.sin(bearing))
    args = (1.0, 2.0, phi_d, phi_d_dot, (24.0, 0.25))
    task = avoidance_task_of("FOCB", q, other, *args)
    ref = avoidance_behavior("FOCB", np.array(q), np.array(other), *args)
    if not ref.active:
        assert task is None
    else:
        _same_behavior(task, ref)


def _tasks(q, target, v_fd, obstacle, robot):
    q = (q[0], q[1], q[2])
    tasks = [formation_task(q, target, v_fd, (12.0, 0.25))]
    for name, other, contact, safe in (("FOCB", obstacle, 0.5, 2.0), ("FRCB", robot, 1.0, 1.6)):
        t = avoidance_task_of(name, q, other, contact, safe, target[2], v_fd[2], (24.0, 0.25))
        if t is not None:
            tasks.append(t)
    return tasks


def _closing_rate_tie(ranked) -> bool:
    """Whether an avoidance behavior's closing rate J v is zero to rounding for the
    velocity fused from a chain "approaching" can reach: there J v < 0 is a tie, which
    the compiled kernel and numpy round either way (found with q = (1, 0, 0), target
    (0, 1, 0), the obstacle at (1, 1) and the robot at (2, 1): J v = 0 exactly for FRCB
    while FDB alone drives)."""
    avoid = [b for b in ranked if b.name in AVOIDANCE]
    for r in range(len(avoid) + 1):
        for engaged in itertools.combinations(avoid, r):
            v = fuse([b for b in ranked if b.name not in AVOIDANCE or any(b is e for e in engaged)])
            scale = 1.0 + float(np.abs(v).sum())
            if any(abs(float(b.jacobian[0] @ v)) <= 1e-9 * scale for b in avoid):
                return True
    return False


@SETTINGS
@given(q=st.tuples(comp, comp, angle), target=st.tuples(comp, comp, angle), v_fd=vec3,
       obstacle=st.tuples(st.floats(-2.0, 2.0), st.floats(-2.0, 2.0)),
       robot=st.tuples(st.floats(-1.5, 1.5), st.floats(-1.5, 1.5)), v=vec3)
@example(q=(1.0, 0.0, 0.0), target=(0.0, 1.0, 0.0), v_fd=(0.0, 0.0, 0.0), obstacle=(0.0, 1.0),
         robot=(1.0, 1.0), v=(0.0, 0.0, 0.0))  # a tie of FRCB's closing rate (_closing_rate_tie)
def test_fusion_vec_equals_fusion(q, target, v_fd, obstacle, robot, v):
    obstacle = (q[0] + obstacle[0], q[1] + obstacle[1])
    robot = (q[0] + robot[0], q[1] + robot[1])
    tasks = _tasks(q, target, v_fd, obstacle, robot)
    outputs = [t.to_output() for t in tasks]
    close(fuse_tasks(tasks), fuse(outputs), rtol=1e-10)
    for priority in (("FOCB", "FRCB", "FDB"), ("FDB", "FRCB", "FOCB")):
        ranked_tasks = sorted(tasks, key=lambda t: priority.index(t.name))
        ranked = order_by_priority(outputs, priority)
        for engage in ("inside", "approaching"):
            if engage == "approaching" and _closing_rate_tie(ranked):
                continue  # either chain is right: the two roundings may decide it apart
            chain, fused = supervise_tasks(ranked_tasks, engage)
            ref_chain = supervise(ranked, engage)
            assert [t.name for t in chain] == [b.name for b in ref_chain]
            close(fused, fuse(ref_chain), rtol=1e-10)
    with pytest.raises(ValueError):
        supervise_tasks(tasks, "sometimes")


@SETTINGS
@given(v=vec3, vmax=st.sampled_from([0.5, 2.0, math.inf]), wmax=st.sampled_from([0.3, math.inf]))
@example(v=(3.834281987004144, 3.834281987004144, 0.0), vmax=0.5, wmax=0.3)  # 1 ulp apart (CI)
def test_saturate_velocity_vec_equals_saturate_velocity(v, vmax, wmax):
    want = saturate_velocity(np.array(v), vmax, wmax)
    # math.hypot and numpy's norm may differ in the last bit
    np.testing.assert_allclose(saturate_velocity_vec(v, vmax, wmax), want, rtol=1e-14, atol=0)


# --- controller (36), (40)-(42) and the model terms of (4) ----------------------------------


@SETTINGS
@given(e=vec3, e_dot=vec3, z2=vec3, tiny=st.booleans())
def test_control_term_vec_equals_control_term(e, e_dot, z2, tiny):
    if tiny:  # where the eps regularisation of erratum 5 matters
        e = tuple(1e-5 * x for x in e)
    for g in (ControllerGains(), ControllerGains(alpha=0.3, mu=5.0, T_p=2.0, upsilon=0.8)):
        gamma, s = control_term_vec(e, e_dot, z2, ControlConstants.from_gains(g))
        ref_gamma, ref_s = control_term(np.array(e), np.array(e_dot), np.array(z2), g)
        close(s, ref_s, rtol=1e-11)
        close(gamma, ref_gamma, rtol=1e-11)
    zero = (0.0, 0.0, 0.0)
    close(control_term_vec(zero, zero, z2, ControlConstants.from_gains(ControllerGains()))[0],
          control_term(np.zeros(3), np.zeros(3), np.array(z2), ControllerGains())[0])


MODELS = [MecanumModel.from_params(RobotParams()),
          MecanumModel.from_params(RobotParams(wheel_radius_m=0.05, mass_kg=4.0, half_track_m=0.1))]


@pytest.mark.parametrize("model", MODELS, ids=["paper", "other"])
@SETTINGS
@given(phi=st.floats(-10.0, 10.0), q_dot=vec3, generalised=vec3)
def test_model_terms_equal_the_model(model, phi, q_dot, generalised):
    close(LAW.coulomb_term_of(model, phi, q_dot), model.A1(phi, np.array(q_dot)))
    u = LAW.allocate_of(model, phi, generalised)
    close(u, allocate(model.augmented_input(phi), np.array(generalised)), rtol=1e-11)


@pytest.mark.parametrize("model", MODELS, ids=["paper", "other"])
@SETTINGS
@given(phi=st.floats(-10.0, 10.0), q_dot=vec3, u=st.tuples(comp, comp, comp, comp))
def test_acceleration_equals_the_model(model, phi, q_dot, u):
    """The plant kernel's eq. (4), which the model plant and the look-ahead integrate."""
    close(acceleration_of(model, (1.0, -2.0, phi), q_dot, u),
          model.acceleration(np.array([1.0, -2.0, phi]), np.array(q_dot), np.array(u),
                             np.zeros(4)), rtol=1e-11)


@SETTINGS
@given(u=st.tuples(comp, comp, comp, comp), limit=st.sampled_from([0.5, 3.0, math.inf]))
def test_saturate_torques_equals_saturate_torques(u, limit):
    np.testing.assert_array_equal(LAW.saturate_torques_of(u, limit), saturate_torques(np.array(u), limit))


# --- the whole step -----------------------------------------------------------------------------




DT = 0.01
OFFSETS = [(0.0, 0.0), (-1.0, -1.0), (-1.0, 1.0)]
GRAPH = [(), ((1, 1.0),), ((1, 1.0), (2, 0.5))]  # (robot id j, a_ij)


def _configs(**over) -> list[AgentConfig]:
    model = MecanumModel.from_params(RobotParams())
    return [
        replace(
            AgentConfig(
                robot_id=i + 1, dt=DT, model=model, neighbours=GRAPH[i], leader_weight=(1.0, 0.0, 0.7)[i],
                offset=OFFSETS[i], heading_offset=0.1 * i, kappa2=0.5,
                scale_changes=(ScaleChange(0.5, 1.5, (1.0, 0.6)), ScaleChange(2.0, 2.5, (0.8, 1.0))),
            ),
            **over,
        )
        for i in range(3)
    ]


OBSTACLES = [
    Body(-1, np.array([2.6, 1.6]), np.zeros(2), 0.2),
    Body(-2, np.array([0.5, 3.2]), np.zeros(2), 0.3),
    Body(-3, np.array([-20.0, 0.0]), np.zeros(2), 0.3),
]


def _compare(a: AgentOutput, b: AgentOutput, rtol: float = 1e-9) -> None:
    for name in ("torques", "v_cmd", "tracking_error", "sliding", "q_d", "q_fd", "z2_hat"):
        close(getattr(a, name), getattr(b, name), rtol)
    for name in ("q0_hat", "v0_hat", "q", "q_dot", "zeta", "zeta_dot"):
        close(getattr(a.share, name), getattr(b.share, name), rtol)
    assert a.order == b.order and a.nonfinite == b.nonfinite
    assert a.task_errors == pytest.approx(b.task_errors, rel=rtol, abs=rtol)


@pytest.mark.parametrize("over", [
    {},
    {"avoidance_engage": "inside", "kappa2": 0.0},
    {"max_speed_mps": 0.8, "max_yaw_rate_radps": 0.5, "max_wheel_torque_nm": 2.0,
     "max_tracking_error": 2e-3},  # engages on 747 of 900 agent-steps (16 cm without)
], ids=["approaching", "inside", "limits"])
def test_agent_step_equals_reference_composition(over):
    """Three agents on a kinematic plant (q_dot = v_cmd) around a circling leader, with
    obstacles and each other in range: AgentCore.step and ReferenceCore.step, given the
    same inputs every step, agree output by output; every behavior is engaged."""
    configs = _configs(**over)
    leader = LeaderGenerator(LeaderSpec(Harmonic("cos", 3.0, 1.0), Harmonic("sin", 3.0, 1.0),
                                        theta_rate=0.5), DT)
    q = np.array([[3.5, 0.2, 0.0], [2.0, -1.5, 0.3], [2.2, 1.2, -0.2]])
    q_dot = np.zeros((3, 3))
    q0_hat = [np.array([3.0, 0.0, 1.6]), np.array([2.5, 0.5, 1.2]), np.array([3.5, -0.5, 1.8])]
    cores = [AgentCore(c, q[i], q_dot[i], q0_hat[i], np.zeros(3)) for i, c in enumerate(configs)]
    refs = [ReferenceCore(c, q[i], q_dot[i], q0_hat[i], np.zeros(3)) for i, c in enumerate(configs)]
    for a, b in zip(cores, refs, strict=True):
        close(a.q0_hat, b.q0_hat)
        close(a.initial_share.zeta, b.offsets(0.0)[0])
    shares = {c.robot_id: a.initial_share for c, a in zip(configs, cores, strict=True)}
    seen = set()
    for k in range(300):
        t = k * DT
        dt = None if k % 7 else DT * 1.5  # a realtime agent's late step
        q0, v0 = leader.state()
        new_shares = {}
        for i, (core, ref) in enumerate(zip(cores, refs, strict=True)):
            robots = [Body(j + 1, q[j, :2].copy(), q_dot[j, :2].copy(), 0.5) for j in range(3) if j != i]
            inputs = (t, q[i].copy(), q_dot[i].copy(), shares,
                      (q0, v0) if configs[i].leader_weight else None, OBSTACLES, robots, dt)
            out, want = core.step(*inputs), ref.step(*inputs)
            _compare(out, want)
            seen.update(want.order)
            new_shares[configs[i].robot_id] = want.share
            q_dot[i] = want.v_cmd
        q = q + DT * q_dot
        shares = new_shares
        leader.advance()
    assert seen == {"FDB", "FOCB", "FRCB"}


def test_agent_step_nonfinite_input_gives_zero_commands():
    """A NaN in the measured state: both forms flag it and command zero torques and velocity."""
    cfg = _configs()[0]
    q, z = np.array([0.0, 0.0, 0.0]), np.zeros(3)
    core, ref = AgentCore(cfg, q, z, z, z), ReferenceCore(cfg, q, z, z, z)
    bad = np.array([math.nan, 0.0, 0.0])
    lead = (np.array([1.0, 0.0, 0.0]), np.zeros(3))
    out, want = core.step(0.0, bad, z, {}, lead), ref.step(0.0, bad, z, {}, lead)
    assert out.nonfinite and want.nonfinite
    np.testing.assert_array_equal(out.torques, np.zeros(4))
    np.testing.assert_array_equal(out.v_cmd, want.v_cmd)


def test_agent_step_overflowing_law_gives_zero_commands_not_an_exception():
    """A finite but absurd input (a leader 1e300 m away): numpy would overflow to
    inf, the float path raises OverflowError inside sig(); the step must answer with
    zero commands and ``nonfinite``, and the agent must keep stepping."""
    cfg = _configs()[0]
    q, z = np.array([0.0, 0.0, 0.0]), np.zeros(3)
    core = AgentCore(cfg, q, z, z, z)
    far = (np.array([1e300, 0.0, 0.0]), np.zeros(3))
    for _ in range(3):
        out = core.step(0.0, q, z, {}, far)
        assert out.nonfinite
        np.testing.assert_array_equal(out.torques, np.zeros(4))
        np.testing.assert_array_equal(out.v_cmd, np.zeros(3))
