"""No contact by construction, on scenarios made to break it (docs/safety.md).

Each bundled scenario below touched, or came within millimetres, before every body in
range was guarded and the safety filter became the agents' last layer (the table in
docs/safety.md). Judged here on physical facts: surface-to-surface gaps over the whole
run (never below 0; the filter keeps its margin where the robots follow their commands),
contacts counted by pybullet's own collision detection, and, where the formation can be
reached, every robot's tracking error settled before sqrt(2) T_p and its formation error
within the settling band at the end.
"""

from __future__ import annotations

import numpy as np
import pytest

from deploy.contract.scenario import load_scenario
from deploy.contract.scenario_variants import perturbed, with_obstacle_pair
from deploy.report.metrics import compute_metrics
from deploy.run.runner import run_in_process

pytestmark = [pytest.mark.slow]

# robots whose formation point can be reached (narrowing sends robots 2 and 3 to one
# spot; clutter's gap cannot hold the robot with lab's obstacle distance and margin)
REACHABLE = {"narrowing": [0], "clutter": [], "gap": [0, 1, 2], "head-on": [0, 1],
             "tight-start": [0, 1, 2]}


def _run(sc, plant: str, duration: float | None = None):
    res = run_in_process(sc, plant, duration)
    m = compute_metrics(sc, res.series, res.plant, "lockstep", res.wall_time_s,
                        contact_log=res.contacts)
    return res.series, m


def _formation_error_at_end(ts, seconds: float, dt: float) -> np.ndarray:
    err = np.linalg.norm(ts.q[:, :, :2] - ts.target, axis=2)
    return err[-int(seconds / dt):].max(axis=0)


def _judge(name: str, sc, ts, m, reachable) -> None:
    print(f"\n{name}: contacts {m['contacts']}, least gaps obstacle "
          f"{m['min_obstacle_gap_m']} m, robot {m['min_robot_gap_m']} m, filter "
          f"{m['safety_filter']['active_time_s']} s, settling {m['settling_time_s']}")
    assert m["contacts"] == 0
    for gap in (m["min_obstacle_gap_m"], m["min_robot_gap_m"]):
        assert gap is None or gap > 0.0
    band = sc.spec.metrics.settle_threshold
    end = _formation_error_at_end(ts, 0.5, sc.dt)
    for i in reachable:
        assert m["settling_time_s"][i] is not None
        assert m["settling_time_s"][i] < m["settling_bound_s"]
        assert end[i] < band, (i, end)


@pytest.mark.parametrize("name", sorted(REACHABLE))
def test_no_contact_on_the_model_plant(name):
    sc = load_scenario(name)
    ts, m = _run(sc, "model")
    _judge(name, sc, ts, m, REACHABLE[name])


@pytest.mark.parametrize("name", ["clutter", "head-on", "narrowing"])
def test_no_contact_on_pybullet(name):
    sc = load_scenario(name)
    ts, m = _run(sc, "pybullet")
    assert m["contact_source"] == "physics"
    _judge(name, sc, ts, m, REACHABLE[name])


def test_the_filter_is_what_keeps_the_margin_at_a_gap_too_narrow_to_enter():
    """The 1.05x pair 12 cm off the path: with the filter off, the avoidance behaviors
    alone let robot 1 within 2 mm of an obstacle (the pushes of the two obstacles fight
    at the entrance); with it, the margin holds and the filter says it acted."""
    import msgspec

    from deploy.contract.scenario import parse_scenario
    from deploy.contract.scenario_variants import scenario_toml_of

    sc = with_obstacle_pair(load_scenario("gap"), 1.05, 0.12)
    off = parse_scenario(scenario_toml_of(msgspec.structs.replace(
        sc.spec, safety=msgspec.structs.replace(sc.spec.safety, filter=False))), "no filter")
    _, m_off = _run(off, "model")
    _, m_on = _run(sc, "model")
    margin = sc.spec.safety.margin_m
    print(f"\nleast obstacle gap: {m_off['min_obstacle_gap_m']:.4f} m without the filter, "
          f"{m_on['min_obstacle_gap_m']:.4f} m with it (margin {margin} m)")
    assert m_off["min_obstacle_gap_m"] < 0.1 * margin
    assert m_on["min_obstacle_gap_m"] > 0.8 * margin
    assert m_on["safety_filter"]["active_steps"][0] > 0
    assert not any(m_off["safety_filter"]["active_steps"])


@pytest.mark.parametrize("ratio", [1.05, 1.2, 1.5])
@pytest.mark.parametrize("offset", [0.0, 0.12])
def test_obstacle_pairs_from_1_05_to_1_5_robot_widths(ratio, offset):
    """A column of three through a pair of obstacles, centred on the path or beside it.
    Where the gap holds the robot and the margin on both sides (1.5x), all three pass
    and reach the formation; where it does not (1.05x, 1.2x) they wait, and nothing
    touches either way."""
    sc = with_obstacle_pair(load_scenario("gap"), ratio, offset)
    ts, m = _run(sc, "model")
    width = 2 * sc.spec.robot.body_radius_m
    fits = ratio * width >= width + 2 * sc.spec.safety.margin_m
    _judge(sc.name, sc, ts, m, REACHABLE["gap"] if fits else [])
    if not fits:  # waited in front of the gap, clear of both obstacles
        assert m["min_obstacle_gap_m"] > 0.5 * sc.spec.safety.margin_m


@pytest.mark.parametrize("base, seeds, duration", [("lab", [0, 1], 15.0), ("paper", [0], 6.0)])
def test_seeded_perturbations_never_touch(base, seeds, duration):
    """A sample of `omnifleet safety sweep` (the full 100 + 40 seeds are in the closing
    note and docs/safety.md): obstacles and starts jittered, model plant."""
    for seed in seeds:
        sc = perturbed(load_scenario(base), seed)
        ts, m = _run(sc, "model", duration)
        print(f"\n{base} seed {seed}: least gaps {m['min_obstacle_gap_m']:.3f} / "
              f"{m['min_robot_gap_m']:.3f} m, filter {m['safety_filter']['active_time_s']} s")
        assert m["contacts"] == 0
        assert m["min_obstacle_gap_m"] > 0 and m["min_robot_gap_m"] > 0


def test_a_perturbation_is_reproducible_and_starts_clear():
    a, b = perturbed(load_scenario("lab"), 7), perturbed(load_scenario("lab"), 7)
    assert a.spec == b.spec and a.spec != perturbed(load_scenario("lab"), 8).spec
    q, _ = a.initial_state()
    r = a.spec.robot.body_radius_m
    d = np.linalg.norm(q[:, None, :2] - q[None, :, :2], axis=2) + np.eye(a.n) * 1e9
    assert d.min() - 2 * r >= 0.05
    for o in a.spec.obstacles:
        assert (np.linalg.norm(q[:, :2] - o.position, axis=1) - r - o.radius_m).min() >= 0.05


@pytest.mark.realtime
def test_no_contact_head_on_on_the_realtime_clock(tmp_path):
    """The same head-on swap, one process per node on the wall clock (what the clock
    allowed is judged first: tests/realtime_clock.py)."""
    import json

    from procs import finish, start
    from realtime_clock import judged

    def run():
        out = tmp_path / f"run-{len(list(tmp_path.iterdir()))}"
        rc, _, err = finish(start("run", "head-on", "--clock", "realtime", "--duration", "6",
                                  "--out", str(out), "--no-figures", "--no-record"), timeout=300)
        assert rc == 0, err
        return json.loads((out / "metrics.json").read_text())
    m = judged(run, lambda m: m, "head-on realtime")
    print(f"\nhead-on realtime: contacts {m['contacts']}, least robot gap "
          f"{m['min_robot_gap_m']} m, filter {m['safety_filter']['active_time_s']} s")
    assert m["contacts"] == 0 and m["min_robot_gap_m"] > 0
