"""Hosts file, deploy plan, certificates and the ACL table (no network)."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import pytest
from procs import finish, start

from deploy.cli.fleet import make_hosts_certs
from deploy.contract.hosts import HostsError, load_hosts
from deploy.contract.keyring import Keyring, read_file
from deploy.contract.scenario import load_scenario
from deploy.contract.wire import Keys
from deploy.fleet.acl import access_control, fleet_roles, receives
from deploy.fleet.certs import common_name
from deploy.fleet.deploy_plan import RunOptions, plan_text, write_configs

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "deploy" / "hosts" / "example.toml"


@pytest.fixture(scope="module")
def paper():
    return load_scenario("paper")


def test_the_plan_gives_every_machine_its_exact_commands(paper):
    hosts = load_hosts(EXAMPLE, paper)
    text = plan_text(hosts, paper, RunOptions("paper", duration_s=5.0))
    sections = {}
    for block in text.split("\n## ")[1:]:
        head, *cmds = block.strip().splitlines()
        sections[head.split()[0]] = [shlex.split(c) for c in cmds]
    assert set(sections) == {"base", "robot1", "robot2", "robot3"}
    assert [c[1] for c in sections["base"]] == ["record", "plant", "leader"]
    agent2 = sections["robot2"][0]
    assert agent2[:2] == ["omnifleet", "agent"]
    assert agent2[agent2.index("--robot") + 1] == "2"
    assert agent2[agent2.index("--zenoh-config") + 1] == "/etc/omnifleet/lab1/agent-2.json5"
    assert agent2[agent2.index("--keys") + 1] == "/etc/omnifleet/lab1/agent-2.keys"
    for cmds in sections.values():  # every node agrees on fleet, scenario and duration
        for c in cmds:
            assert c[c.index("--fleet") + 1] == "lab1" and c[c.index("--duration") + 1] == "5.0"
            assert c[c.index("--scenario") + 1] == "paper"
            assert c[1] == "record" or "--wait-recorder" in c


def test_configs_and_certificates_match_the_hosts_file(paper, tmp_path):
    hosts = load_hosts(EXAMPLE, paper)
    write_configs(hosts, paper, tmp_path)
    make_hosts_certs(hosts, tmp_path)
    agent = json.loads((tmp_path / "robot2" / "agent-2.json5").read_text())
    assert agent["listen"]["endpoints"] == ["tls/192.168.10.12:7447"]
    assert agent["connect"]["endpoints"] == ["tls/192.168.10.1:7448"]  # the plant
    assert agent["scouting"]["multicast"]["enabled"] is False
    assert agent["transport"]["link"]["tls"]["enable_mtls"] is True
    assert agent["transport"]["link"]["protocols"] == ["tls"]
    assert agent["transport"]["link"]["tx"]["lease"] == 2000
    assert agent["access_control"]["default_permission"] == "deny"
    # each machine gets the CA's certificate and its own roles' keys, nothing else
    assert sorted(p.name for p in (tmp_path / "robot2").iterdir()) == [
        "agent-2.json5", "agent-2.key", "agent-2.keys", "agent-2.pem", "ca.pem"]
    # its keyring: a key with every other node (not the router, which forwards), only
    # its owner may read it, and the master stays with the CA
    keys = tmp_path / "robot2" / "agent-2.keys"
    assert keys.stat().st_mode & 0o077 == 0
    ring = Keyring.from_text(read_file(keys), str(keys), "agent-2", paper, Keys("lab1"))
    assert sorted(ring._pair) == ["agent-1", "agent-2", "agent-3", "launcher", "leader",
                                  "plant"]
    assert (tmp_path / "ca" / "fleet.master").stat().st_mode & 0o077 == 0
    assert not list(tmp_path.glob("robot*/fleet.master"))
    assert sorted(p.name for p in (tmp_path / "base").glob("*.key")) == [
        "launcher.key", "leader.key", "plant.key"]
    assert common_name(tmp_path / "robot2" / "agent-2.pem") == "agent-2"
    assert (tmp_path / "robot2" / "agent-2.key").stat().st_mode & 0o077 == 0


def test_the_acl_follows_the_graph(paper):
    """paper: a = [[0,0,0],[1,0,0],[1,1,0]], b = [1,0,0]."""
    k = Keys("f")
    roles = fleet_roles(paper)
    tail = lambda keys: {x.split("/", 2)[2] for x in keys}  # noqa: E731
    ctl = {"ctl/start", "ctl/tick", "ctl/end", "ctl/stop", "ctl/estop"}
    # an agent hears its robot's sample and its neighbours' replies (their shares)
    assert tail(receives("agent-1", paper, k, roles)) == {
        "robot/1/sample", "leader/state"} | ctl
    assert tail(receives("agent-2", paper, k, roles)) == {
        "robot/2/sample", "robot/1/cmd"} | ctl
    assert tail(receives("agent-3", paper, k, roles)) == {
        "robot/3/sample", "robot/1/cmd", "robot/2/cmd"} | ctl
    acl = access_control(paper, "f", "plant", roles)
    rules = {r["id"]: r for r in acl["rules"]}
    assert tail(rules["from:agent-2"]["key_exprs"]) == {"robot/2/cmd"}
    assert tail(rules["to:agent-2"]["key_exprs"]) == {"robot/2/sample",
                                                     "ctl/start", "ctl/tick", "ctl/end",
                                                     "ctl/stop", "ctl/estop"}
    assert "from:leader" not in rules  # the plant takes nothing from the leader


@pytest.mark.parametrize("edit, key", [
    ('address = "192.168.10.12"', "machines.robot2.address"),
    ('adress = "x"', "machines.robot2"),
    ('roles = ["agent-7"]', "machines.robot2.roles"),
    ('roles = ["agent-1"]', "machines.robot2.roles"),
    ('roles = ["pilot"]', "machines.robot2.roles"),
    ('roles = []', "machines"),
])
def test_a_bad_hosts_file_names_the_file_and_the_key(paper, tmp_path, edit, key):
    text = EXAMPLE.read_text()
    block = text.split("[machines.robot2]")[1].split("[machines.robot3]")[0]
    if edit.startswith("address"):
        new = block.replace('address = "192.168.10.12"', 'address = "not an address!"')
    elif edit.startswith("adress"):
        new = block + 'adress = "x"\n'
    else:
        new = block.replace('roles = ["agent-2"]', edit)
    bad = tmp_path / "hosts.toml"
    bad.write_text(text.replace(block, new))
    with pytest.raises(HostsError) as err:
        load_hosts(bad, paper)
    assert str(bad) in str(err.value) and key in str(err.value)


def test_a_hosts_file_that_is_not_utf8_is_a_hosts_error(paper, tmp_path):
    bad = tmp_path / "hosts.toml"
    bad.write_bytes(b"\x80" + EXAMPLE.read_bytes())
    with pytest.raises(HostsError, match="not UTF-8") as err:
        load_hosts(bad, paper)
    assert str(bad) in str(err.value)


def test_deploy_plan_exits_2_on_a_bad_hosts_file(tmp_path):
    bad = tmp_path / "hosts.toml"
    bad.write_text('fleet = "a/b"\n[machines.x]\naddress = "10.0.0.1"\nroles = ["leader"]\n')
    rc, _, err = finish(start("deploy", "plan", str(bad), "paper"), timeout=60)
    assert rc == 2 and str(bad) in err and "fleet" in err
    rc, out, err = finish(start("deploy", "plan", str(EXAMPLE), "paper"), timeout=60)
    assert rc == 0 and "omnifleet agent" in out, err


def test_a_node_refuses_a_keyring_others_may_read_or_another_roles(paper, tmp_path):
    """Before opening a session: exit 2 naming the file and what is wrong with it."""
    from deploy.contract.keyring import keyring_text, new_master, write_file

    ring = write_file(tmp_path / "agent-2.keys",
                      keyring_text(new_master(), "f", "agent-2", ["plant", "leader"]))
    ring.chmod(0o644)
    rc, _, err = finish(start("agent", "--scenario", "paper", "--fleet", "f", "--robot", "2",
                              "--keys", str(ring)), timeout=60)
    assert rc == 2 and f"{ring}: mode 0644: others may read its keys" in err, err
    ring.chmod(0o600)
    rc, _, err = finish(start("agent", "--scenario", "paper", "--fleet", "f", "--robot", "3",
                              "--keys", str(ring)), timeout=60)
    assert rc == 2 and "keys of agent-2, not of agent-3" in err, err
    rc, _, err = finish(start("agent", "--scenario", "paper", "--fleet", "f", "--robot", "2",
                              "--keys", str(tmp_path / "none.keys")), timeout=60)
    assert rc == 2 and "none.keys: cannot read" in err and "deploy certs" in err, err
