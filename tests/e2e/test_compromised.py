"""A compromised agent cannot command another robot or stop the run (docs/hardening.md).

The fleet is started by hand on one machine with the exact commands of ``omnifleet
deploy plan`` (plain TCP on loopback, no TLS and no access control, so the per-node
keys are the only defence), its keyrings from ``omnifleet deploy certs``. The rogue
(tests/rogue_agent.py) is agent 3 taken over: it holds agent 3's real keyring and
uses every key in it. Every process is ended by pid, whatever happens."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from netns import omnifleet, stop
from procs import REPO, assert_same_series, finish, start

from deploy.cli.fleet import make_hosts_certs
from deploy.contract.hosts import load_hosts
from deploy.contract.keyring import Keyring, read_file
from deploy.contract.scenario import load_scenario
from deploy.contract.wire import WIRE_VERSION, Control, Keys, encode
from deploy.fleet.deploy_plan import RunOptions, command_for, write_configs
from deploy.report.timeseries import TimeSeries
from deploy.runtime.transport import zenoh_config

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

pytest.importorskip("zenoh")

ROLES = ["recorder", "plant", "leader", "agent-1", "agent-2", "agent-3"]
BAD = "MAC does not check"
NOT_ITS = "not signed by a sender of this key"


def _free_ports(n: int) -> int:
    """The first of ``n`` consecutive free TCP ports on loopback."""
    for _ in range(100):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            base = s.getsockname()[1]
        if base + n > 65535:
            continue
        socks = []
        try:
            for i in range(n):
                t = socket.socket()
                socks.append(t)
                t.bind(("127.0.0.1", base + i))
            return base
        except OSError:
            continue
        finally:
            for t in socks:
                t.close()
    raise RuntimeError("no free port range")


class Fleet:
    """One machine's fleet of ``lab``, by hand: certificates and keyrings, configs, the
    nodes with the plan's commands, their logs."""

    def __init__(self, tmp: Path, duration_s: float) -> None:
        self.sc = load_scenario("lab")
        self.fleet = f"cmp{int(time.time() * 1000) % 10**8}"
        self.deploy = tmp / "deploy"
        self.out = tmp / "run"
        base = _free_ports(len(ROLES))
        roles = ", ".join(f'"{r}"' for r in ROLES)
        hosts_file = tmp / "hosts.toml"
        hosts_file.write_text(f'fleet = "{self.fleet}"\nport = {base}\ntls = false\n'
                              f'dir = "{self.deploy}/{{machine}}"\n'
                              f'[machines.host]\naddress = "127.0.0.1"\nroles = [{roles}]\n')
        self.hosts = load_hosts(hosts_file, self.sc)
        make_hosts_certs(self.hosts, self.deploy)
        write_configs(self.hosts, self.sc, self.deploy)
        self.hosts.spec.command = " ".join(omnifleet())
        self.run = RunOptions("lab", duration_s=duration_s, plant_kind="model",
                              record_out=str(self.out))
        self.logs = tmp / "logs"
        self.logs.mkdir()
        self.procs: dict[str, subprocess.Popen] = {}

    def keys_of(self, role: str) -> Path:
        return self.deploy / "host" / f"{role}.keys"

    @property
    def plant_endpoint(self) -> str:
        return self.hosts.find("plant").endpoint(False)

    def start(self) -> None:
        for p in sorted(self.hosts.placements, key=lambda p: ROLES.index(p.role)):
            with open(self.logs / f"{p.role}.log", "wb") as f:
                self.procs[p.role] = subprocess.Popen(
                    command_for(self.hosts, self.sc, p, self.run), cwd=REPO, stdout=f,
                    stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)

    def rogue(self, *extra: str, seconds: float) -> subprocess.Popen:
        return subprocess.Popen(
            [sys.executable, str(REPO / "tests" / "rogue_agent.py"), "--scenario", "lab",
             "--fleet", self.fleet, "--keys", str(self.keys_of("agent-3")), "--role", "agent-3",
             "--connect", self.plant_endpoint, "--seconds", str(seconds), *extra],
            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            start_new_session=True)

    def wait_for_step(self, k: int, timeout: float = 120.0) -> None:
        log = self.logs / "recorder.log"
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            steps = [int(x.split("/")[0]) for x in log.read_text().split("record: step ")[1:]]
            if steps and steps[-1] >= k:
                return
            assert self.procs["recorder"].poll() is None, self.text()
            time.sleep(0.05)  # polling a log another process writes
        raise TimeoutError(f"the run did not reach step {k}\n{self.text()}")

    def wait(self, timeout: float) -> dict[str, int | None]:
        deadline = time.monotonic() + timeout
        codes = {}
        for role, p in self.procs.items():
            try:
                codes[role] = p.wait(timeout=max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                codes[role] = None
        return codes

    def text(self) -> str:
        return "\n".join(f"--- {f.name}\n{f.read_text(errors='replace')[-1500:]}"
                         for f in sorted(self.logs.glob("*.log")))

    def metrics(self) -> dict:
        return json.loads((self.out / "metrics.json").read_text())


def refused(m: dict, node: str) -> dict[str, int]:
    return {why.split(": ", 1)[1]: n for why, n in m["messages"].get("refused", {}).items()
            if why.startswith(f"{node}: ")}


DURATION = 2.0  # 400 lockstep steps of lab


def test_agent_3s_own_keys_command_no_other_robot(tmp_path: Path):
    """Agent 3 taken over floods robot 2's key with replies for every step: tagged as
    itself, and claiming to be agent 2 with each key it holds. The plant (and agent 3's
    real process, which reads robot 2's replies, and the recorder) refuse every one,
    counted; robot 2 moves exactly as in the in-process reference."""
    rc, _, err = finish(start("run", "lab", "--plant", "model", "--in-process", "--duration",
                              str(DURATION), "--out", str(tmp_path / "ref"), "--no-figures",
                              "--no-record"))
    assert rc == 0, err
    f = Fleet(tmp_path, DURATION)
    rogue = None
    try:
        f.start()
        rogue = f.rogue("--victim", "2", "--steps", "400", seconds=6.0)
        codes = f.wait(180)
        out, _ = rogue.communicate(timeout=60)
    finally:
        stop([*f.procs.values(), *([rogue] if rogue else [])])
    assert all(c == 0 for c in codes.values()), f"{codes}\n{f.text()}"
    sent = int(out.split("sent ")[-1])
    m = f.metrics()
    plant = refused(m, "plant")
    # both kinds of forgery reached the plant in equal numbers, and all were refused
    # (a pair of forgeries can be cut by the plant's start or end of listening: one apart
    # at each end at most)
    assert set(plant) == {"reply: " + NOT_ITS, "reply: " + BAD}, plant
    assert plant["reply: " + NOT_ITS] > 0 and abs(
        plant["reply: " + NOT_ITS] - plant["reply: " + BAD]) <= 2, plant
    assert 2 * plant["reply: " + NOT_ITS] <= sent
    assert set(refused(m, "agent-3")) == {"reply: " + NOT_ITS, "reply: " + BAD}
    assert m["messages"]["late"] == 0
    # the in-process run's verdict, word for word (2 s of lab end before every robot is at
    # its formation position: the reference says so too, and nothing else)
    ref = json.loads((tmp_path / "ref" / "metrics.json").read_text())
    assert m["verdict"]["reasons"] == ref["verdict"]["reasons"], m["verdict"]
    print(f"\nrogue agent 3 sent {sent} replies for robot 2; the plant refused "
          f"{sum(plant.values())} (the rest arrived after the run)")
    assert_same_series(TimeSeries.load(f.out / "timeseries.npz"),
                       TimeSeries.load(tmp_path / "ref" / "timeseries.npz"))


def test_only_the_plant_or_the_launcher_can_stop_a_run_and_it_says_so(tmp_path: Path):
    """Before: the run's secret sat in every node's environment, so any of its processes
    (or any process of the same user) could sign a ``stop``; a genuine stop must still
    end the run and fail its verdict. Agent 3's keys tag a stop as the plant: refused by
    every node, counted, the run goes on. A stop tagged with the plant's own keyring
    ends it: ``stopped_by`` in metrics.json, verdict FAIL."""
    import zenoh

    f = Fleet(tmp_path, 30.0)
    rogue = session = None
    try:
        f.start()
        f.wait_for_step(100)
        rogue = f.rogue("--stop", "--steps", "0", seconds=1.0)
        out, _ = rogue.communicate(timeout=60)
        sent = int(out.split("sent ")[-1])
        f.wait_for_step(600)  # still running, well after the forged stops
        keys = Keys(f.fleet)
        plant = Keyring.from_text(read_file(f.keys_of("plant")), "plant.keys", "plant", f.sc, keys)
        session = zenoh.open(zenoh_config(connect=[f.plant_endpoint]))
        stop_msg = plant.seal(encode(Control(WIRE_VERSION, 0, 1 << 20, 0, command="stop")),
                              keys.ctl("stop"))
        # until a subscriber of ours is known to the fleet (then once), or the run ended
        # by itself (a failure, below); on a busy machine that took more than 5 s once
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            session.put(keys.ctl("stop"), stop_msg)
            if all(p.poll() is not None for r, p in f.procs.items() if r != "recorder"):
                break
            time.sleep(0.1)  # a pace between attempts, not a synchronisation
        codes = f.wait(60)
    finally:
        if session is not None:
            session.close()
        stop([*f.procs.values(), *([rogue] if rogue else [])])
    assert all(c == 0 for c in codes.values()), f"{codes}\n{f.text()}"
    m = f.metrics()
    assert m["stopped_by"]["command"] == "stop" and 600 <= m["steps"] < 6000
    assert not m["verdict"]["pass"]
    assert any("STOPPED by ctl/stop" in r for r in m["verdict"]["reasons"])
    for node in ("plant", "leader", "agent-1", "agent-2", "agent-3", "launcher"):
        got = {why: n for why, n in refused(m, node).items() if why.startswith("control")}
        assert set(got) == {"control: " + BAD} and 0 < got["control: " + BAD] <= sent, (node, got)
