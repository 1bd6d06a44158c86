"""What a realtime agent that answers some samples a period late must do with its law:
step it on each sample, as lockstep does, not once over the periods between
(deploy/nodes/agent.py, ``AgentNode._catch_up``; tests/unit/test_realtime_catch_up.py
holds the agent to it). Measured in process on ``paper`` (model plant): robot 3's
commands of 2 % of the steps never act (the plant plays the step before's look-ahead,
as it does for a command that comes late), and its law either still steps on those
samples or, as a late realtime loop that answers only the newest sample did, skips them
and steps over two periods at the next. The first keeps the robot within the scenario's
settling band (5 cm) of its reference, as a run without late commands does; the second
pushes it out for hundreds of ms after settling: its reference (eq. 11) and observer
(39) run a period ahead (robots at ~27 m/s move 2.7 cm a period)."""

from __future__ import annotations

import numpy as np

from deploy.contract.fault_plan import load_plan
from deploy.contract.scenario import load_scenario
from deploy.run import runner
from deploy.runtime.fault_model import FaultModel
from deploy.runtime.plants import make_plant

SETTLE_BAND_M = 0.05  # paper.toml's settle_threshold
LATE_SHARE = 0.02


def _max_tracking_error_after_settling(tmp_path, steps_each_sample: bool) -> float:
    sc = load_scenario("paper")
    plan_file = tmp_path / "late.toml"
    plan_file.write_text(f'seed = 3\n[[link]]\nfrom = "agent-3"\nto = "plant"\n'
                         f'drop = {LATE_SHARE}\n')
    model = FaultModel(load_plan(plan_file, sc), sc.dt)
    late = model.edge("agent-3", "plant")  # the steps whose command never acts
    steps = int(round(4.0 / sc.dt))
    plant = make_plant(sc, "model")
    try:
        loop = runner._ReferenceLoop(sc, plant, steps, model)
        agent = loop.agents[sc.robot_ids.index(3)]
        step, last = agent.step, {}

        def late_loop_step(t, *args, **kw):
            k = int(round(t / sc.dt))
            if not late.delivered(k) and "out" in last:  # (the fault plan's own decision)
                return last["out"]  # no step on a sample answered late: skipped
            if k > 0 and not late.delivered(k - 1):
                kw["dt"] = 2 * sc.dt  # the next steps over both periods
            last["out"] = step(t, *args, **kw)
            return last["out"]

        if not steps_each_sample:
            agent.step = late_loop_step
        for k in range(steps):
            loop.step(k)
    finally:
        plant.close()
    e = np.linalg.norm(loop.series.e[:, 2, :], axis=1)
    return float(np.max(e[int(round(1.0 / sc.dt)):]))  # after 1 s (settled by ~0.4 s)


def test_a_late_agent_steps_its_law_on_each_sample(tmp_path):
    each = _max_tracking_error_after_settling(tmp_path, steps_each_sample=True)
    skipped = _max_tracking_error_after_settling(tmp_path, steps_each_sample=False)
    assert each < SETTLE_BAND_M / 2  # as on time: within the band, with room
    assert skipped > SETTLE_BAND_M  # out of the band: never settled by the verdict's rule
