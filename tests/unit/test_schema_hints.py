"""Every file a user writes suggests the nearest key (deploy/contract/schema_hints.py): the
scenario did, the fault plan and the hosts file did not (``unknown field `drop``` came
with nothing); a key written outside its table says which tables have it."""

from __future__ import annotations

import pytest

from deploy.contract.fault_plan import FaultPlanError, decode_plan
from deploy.contract.hosts import HostsError, load_hosts
from deploy.contract.scenario import load_scenario

LAB = load_scenario("lab")


@pytest.mark.parametrize("plan, says", [
    ("[defaults]\ndrpo = 0.1\n", "did you mean `drop`?"),
    ("drop = 0.1\n", "`drop` is a key of [defaults], [[link]]"),
    ("[[kill]]\nprocess = 'agent-2'\nat_s = 1.0\npause = 2.0\n", "did you mean `pause_s`?"),
    ("[can]\nframe_los = 0.1\n", "did you mean `frame_loss`?"),
])
def test_a_fault_plans_unknown_key_comes_with_the_nearest_or_where_it_belongs(plan, says):
    with pytest.raises(FaultPlanError) as refused:
        decode_plan(plan, LAB, "plan.toml")
    assert says in str(refused.value)


def test_a_hosts_files_unknown_key_comes_with_the_nearest(tmp_path):
    from pathlib import Path

    example = Path(__file__).resolve().parents[2] / "deploy" / "hosts" / "example.toml"
    f = tmp_path / "hosts.toml"
    f.write_text(example.read_text().replace("address", "adress", 1))
    with pytest.raises(HostsError, match="did you mean `address`"):
        load_hosts(f, LAB)
