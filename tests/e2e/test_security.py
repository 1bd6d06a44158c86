"""Mutual TLS and the access control generated from the scenario's graph, on
loopback, with the configurations ``omnifleet deploy`` writes (certificates of
deploy/fleet/certs.py, ACL of deploy/fleet/acl.py, configs of deploy/fleet/zenoh_configs.py, read
back through deploy/runtime/transport.py as every node does).

Each negative check runs next to a positive control in the same window: the
allowed message arrives (waited for), the forbidden one did not, after the
allowed one and a further grace period."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest

from deploy.contract.scenario import load_scenario
from deploy.contract.wire import Keys
from deploy.fleet.acl import access_control, fleet_roles
from deploy.fleet.certs import make_fleet_certs, role_files
from deploy.fleet.zenoh_configs import node_config, write_config
from deploy.run.plan import free_tcp_port
from deploy.runtime.transport import zenoh_config

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.load_safe]

zenoh = pytest.importorskip("zenoh")

FLEET = "sec"
GRACE_S = 1.0  # after the positive control arrived, how much longer a forbidden message gets


class Heard:
    """What a subscriber heard: (key, payload), with a condition to wait on."""

    def __init__(self) -> None:
        self.items: list[tuple[str, bytes]] = []
        self.cond = threading.Condition()

    def __call__(self, sample) -> None:
        with self.cond:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))
            self.cond.notify_all()

    def wait_for(self, key: str, payload: bytes | None = None, timeout: float = 10.0) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: any(
                k == key and (payload is None or p == payload) for k, p in self.items), timeout)

    def keys(self) -> set[str]:
        with self.cond:
            return {k for k, _ in self.items}


@pytest.fixture
def fleet(tmp_path):
    """Certificates and per-role configs of the paper scenario's fleet on loopback;
    the plant listens, everyone connects to it (gossip links the rest)."""
    d = tmp_path
    sc = load_scenario("paper")
    roles = fleet_roles(sc, bridges=False, router=False)
    make_fleet_certs(d / "certs", FLEET, {r: [] for r in roles})
    make_fleet_certs(d / "rogue-ca", "rogue", {"agent-1": []})  # a CA nobody trusts
    hub = f"tls/127.0.0.1:{free_tcp_port()}"

    def config(role: str, acl: bool = True, certs: Path | None = None) -> str:
        listen = [hub] if role == "plant" else ["tls/127.0.0.1:0"]
        connect = [] if role == "plant" else [hub]
        cfg = node_config(listen, connect, role_files(certs or d / "certs", role),
                          access_control(sc, FLEET, role, roles) if acl else None)
        return str(write_config(d / f"{role}-{acl}-{certs is not None}.json5", cfg))

    sessions = []

    def open_as(role: str, **kw):
        s = zenoh.open(zenoh_config(config(role, **kw)))
        sessions.append(s)
        return s

    def open_raw(cfg: dict):
        c = zenoh.Config.from_json5(json.dumps(cfg))
        s = zenoh.open(c)
        sessions.append(s)
        return s

    yield open_as, open_raw, hub, d
    for s in sessions:
        s.close()


def _wait(cond, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return False


def test_a_peer_without_a_valid_certificate_cannot_join(fleet):
    open_as, open_raw, hub, d = fleet
    keys = Keys(FLEET)
    plant = open_as("plant")
    heard = Heard()
    plant.declare_subscriber(keys.everything, heard)
    intruders = {
        # a certificate with a fleet role's name, signed by another CA
        "foreign CA": open_as("agent-1", acl=False, certs=d / "rogue-ca"),
        # TLS that trusts the fleet's CA but shows no certificate of its own
        "no certificate": open_raw(node_config([], [hub]) | {"transport": {"link": {"tls": {
            "root_ca_certificate": str(d / "certs" / "ca.pem")}}}}),
        # plain TCP to the TLS port
        "plain tcp": open_raw(node_config([], [hub.replace("tls/", "tcp/")])),
    }
    legit = open_as("agent-1")  # the positive control, in the same window
    assert _wait(lambda: str(legit.info.zid()) in {str(z) for z in plant.info.peers_zid()})

    def attempt() -> bool:
        for name, s in intruders.items():
            s.put(keys.cmd(1), name.encode())
        legit.put(keys.cmd(1), b"legit")
        return heard.wait_for(keys.cmd(1), b"legit", timeout=0.05)

    assert _wait(attempt)
    time.sleep(GRACE_S)  # the intruders' puts went out before legit's, and this long after
    peers = {str(z) for z in plant.info.peers_zid()}
    for name, s in intruders.items():
        assert str(s.info.zid()) not in peers, f"{name} joined"
        assert s.info.peers_zid() == [] or str(plant.info.zid()) not in {
            str(z) for z in s.info.peers_zid()}, f"{name} reached the plant"
    assert {p for _k, p in heard.items} == {b"legit"}


def test_an_agent_cannot_command_another_robot_the_plant_never_sees_it(fleet):
    """agent-2 holds its real certificate but has thrown its own ACL away: the
    plant's ingress rule for subject agent-2 still refuses robot/1/cmd."""
    open_as, _raw, _hub, _d = fleet
    keys = Keys(FLEET)
    plant = open_as("plant")
    heard = Heard()
    plant.declare_subscriber(f"{keys.root}/robot/*/cmd", heard)
    rogue = open_as("agent-2", acl=False)
    assert _wait(lambda: str(rogue.info.zid()) in {str(z) for z in plant.info.peers_zid()})

    def attempt() -> bool:
        rogue.put(keys.cmd(1), b"hijack")
        rogue.put(keys.cmd(3), b"forged share")  # agent 3's reply carries its share
        rogue.put(keys.cmd(2), b"own")  # its own command is allowed: the positive control
        return heard.wait_for(keys.cmd(2), b"own", timeout=0.05)

    assert _wait(attempt)  # until the plant's subscription is known to the rogue
    time.sleep(GRACE_S)
    assert keys.cmd(1) not in heard.keys()
    assert {p for _k, p in heard.items} == {b"own"}


def test_a_non_neighbour_share_never_reaches_an_agent_even_with_a_wildcard(fleet):
    """paper: agent 2 hears agent 1 only (a_21 != 0, a_23 = 0). agent-2 subscribes
    to every reply (command + share, ``robot/*/cmd``) with a wildcard and holds no
    ACL itself: agent-3's egress rule never sends it agent 3's reply; agent-1's
    (a neighbour's) arrives."""
    open_as, _raw, _hub, _d = fleet
    keys = Keys(FLEET)
    plant = open_as("plant")
    a1, a3 = open_as("agent-1"), open_as("agent-3")
    curious = open_as("agent-2", acl=False)
    heard = Heard()
    curious.declare_subscriber(f"{keys.root}/robot/*/cmd", heard)
    honest = Heard()  # agent-1 (no neighbours) with its ACL, also with a wildcard
    a1.declare_subscriber(f"{keys.root}/robot/*/cmd", honest)
    listener = Heard()  # agent-3 hears 1 and 2: proves a3 is linked to them
    a3.declare_subscriber(f"{keys.root}/robot/*/cmd", listener)
    everyone = {str(s.info.zid()) for s in (plant, a1, a3, curious)}
    assert _wait(lambda: all(
        everyone - {str(s.info.zid())} <= {str(z) for z in s.info.peers_zid()}
        for s in (a1, a3, curious)))  # gossip linked every pair directly

    def publish_all() -> bool:
        a3.put(keys.cmd(3), b"share of 3")
        a1.put(keys.cmd(1), b"share of 1")
        curious.put(keys.cmd(2), b"share of 2")
        return (heard.wait_for(keys.cmd(1), timeout=0.05)
                and listener.wait_for(keys.cmd(2), timeout=0.05)
                and listener.wait_for(keys.cmd(1), timeout=0.05))

    # until every subscription is known everywhere (a put before that reaches nobody)
    assert _wait(publish_all)
    time.sleep(GRACE_S)
    assert heard.keys() == {keys.cmd(1), keys.cmd(2)}  # a neighbour's, and its own
    assert honest.keys() == {keys.cmd(1)}  # only its own: it has no neighbours
