"""Fuzz the fault-plan decoder (deploy/contract/fault_plan.py): edited valid plans,
mutated bytes and random text give a FaultPlanError or a plan whose every
probability is in [0, 1], every window ordered and finite, every edge one of
the run's; never another exception."""

from __future__ import annotations

import math

from fuzzing import fuzz_decoder, fuzz_settings, mutated_bytes
from hypothesis import given
from hypothesis import strategies as st
from test_fuzz_scenario import edited_document

from deploy.contract.fault_plan import FaultPlan, FaultPlanError, decode_plan, run_edges
from deploy.contract.scenario import load_scenario
from deploy.runtime.fault_model import FaultModel

SCENARIO = load_scenario("paper")
EDGES = set(run_edges(SCENARIO))

PLANS = {
    "loss": """seed = 7
[defaults]
drop = 0.1
[[link]]
from = "leader"
to = "agent-1"
partitions = [[8.0, 10.0]]
burst = { p_enter = 0.02, p_exit = 0.3, loss_bad = 1.0, loss_good = 0.0 }
delay_s = 0.01
[[link]]
from = "agent-*"
to = "plant"
drop = 0.3
""",
    "kill": """seed = 1
[[kill]]
process = "agent-2"
at_s = 10.0
restart_after_s = 4.0
[can]
frame_loss = 0.01
corrupt = 0.001
""",
}


def check_plan(plan: FaultPlan) -> None:
    for edge, f in plan.links.items():
        assert edge in EDGES
        assert 0.0 <= f.drop <= 1.0 and 0.0 <= f.delay_s <= 10.0
        for a, b in f.partitions:
            assert math.isfinite(a) and math.isfinite(b) and 0.0 <= a < b
        if f.burst is not None:
            for p in (f.burst.p_enter, f.burst.p_exit, f.burst.loss_bad, f.burst.loss_good):
                assert 0.0 <= p <= 1.0
            assert f.burst.p_exit > 0.0
    for k in plan.kills:
        assert 0.0 <= k.at_s < SCENARIO.spec.duration_s
    assert 0.0 <= plan.can.frame_loss <= 1.0 and 0.0 <= plan.can.corrupt <= 1.0
    model = FaultModel(plan, SCENARIO.dt)  # and the decisions it drives run
    for e in model.edges.values():
        for k in (0, 1, 8000, 9999):
            model.judge(e, k)


def decode(raw: bytes) -> FaultPlan | None:
    return fuzz_decoder("fault plan", lambda b: decode_plan(b, SCENARIO, "fuzz.toml"), raw,
                        rejects=(FaultPlanError,), check=check_plan)


@fuzz_settings(300)
@given(data=st.data())
def test_edited_plans(data: st.DataObject) -> None:
    text = PLANS[data.draw(st.sampled_from(sorted(PLANS)))]
    decode(data.draw(edited_document(text)))


@fuzz_settings(200)
@given(data=st.data())
def test_mutated_plan_bytes(data: st.DataObject) -> None:
    raw = PLANS[data.draw(st.sampled_from(sorted(PLANS)))].encode()
    decode(data.draw(mutated_bytes(raw)))


@fuzz_settings(100)
@given(raw=st.one_of(st.binary(max_size=300), st.text(max_size=300).map(str.encode)))
def test_random_text(raw: bytes) -> None:
    decode(raw)


def test_the_example_plans_decode() -> None:
    for text in PLANS.values():
        assert decode(text.encode()) is not None
