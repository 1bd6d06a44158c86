"""The fleet across machines: each machine a network namespace (veth + bridge),
nodes started with the exact commands of ``omnifleet deploy plan``, every link
mutual TLS with the generated access control.

Root only; skipped with the reason otherwise. Namespaces, links and processes
are removed/ended whatever happens (tests/netns.py)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from netns import machines, netns_problem, omnifleet, stop
from procs import assert_same_series, finish, start

from deploy.cli.fleet import make_hosts_certs
from deploy.contract.hosts import load_hosts
from deploy.contract.scenario import load_scenario
from deploy.fleet.deploy_plan import RunOptions, command_for, write_configs
from deploy.report.metrics import control_figures
from deploy.report.timeseries import TimeSeries

pytest.importorskip("zenoh")
problem = netns_problem()
pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.root,
              pytest.mark.skipif(problem is not None, reason=problem or "")]

MACHINES = ["base", "robot1", "robot2", "robot3"]
ROLES = {"base": ["recorder", "plant", "leader"], "robot1": ["agent-1"],
         "robot2": ["agent-2"], "robot3": ["agent-3"]}
ORDER = ["router", "recorder", "plant", "leader", "agent-1", "agent-2", "agent-3"]


def _hosts_file(path: Path, ms, fleet: str, deploy_dir: Path, lease_ms: int | None,
                tls: bool = True, router: bool = False) -> Path:
    lines = [f'fleet = "{fleet}"', "port = 7447", f"tls = {str(tls).lower()}",
             f'dir = "{deploy_dir}/{{machine}}"']
    if lease_ms is not None:
        lines.append(f"lease_ms = {lease_ms}")
    for name in MACHINES:
        roles = ", ".join(f'"{r}"' for r in (["router"] if router and name == "base" else [])
                          + ROLES[name])
        lines += [f"[machines.{name}]", f'address = "{ms[name].address}"', f"roles = [{roles}]"]
    path.write_text("\n".join(lines) + "\n")
    return path


def _run_fleet(ms, tmp: Path, fleet: str, run: RunOptions, lease_ms: int | None = None,
               tls: bool = True, router: bool = False):
    """Certificates, configs and one process per node, each in its machine's
    namespace with the plan's command; returns {role: Popen} and the logs' folder."""
    sc = load_scenario(run.scenario)
    deploy_dir = tmp / "deploy"
    hosts = load_hosts(_hosts_file(tmp / "hosts.toml", ms, fleet, deploy_dir, lease_ms, tls, router),
                       sc)
    make_hosts_certs(hosts, deploy_dir)
    write_configs(hosts, sc, deploy_dir)
    hosts.spec.command = " ".join(omnifleet())
    logs = tmp / "logs"
    logs.mkdir()
    procs = {}
    for p in sorted(hosts.placements, key=lambda p: ORDER.index(p.role)):
        procs[p.role] = ms[p.machine].start(command_for(hosts, sc, p, run), logs / f"{p.role}.log")
    return procs, logs


def _wait_all(procs: dict, timeout: float) -> dict[str, int]:
    deadline = time.monotonic() + timeout
    codes = {}
    for role, p in procs.items():
        try:
            codes[role] = p.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            codes[role] = None
    return codes


def _logs(logs: Path) -> str:
    return "\n".join(f"--- {f.name}\n{f.read_text(errors='replace')[-1500:]}"
                     for f in sorted(logs.glob("*.log")))


DURATION = "0.3"
# the rogue starts once the fleet is up and must be linked while it runs: 0.3 s of paper
# ended before a rogue had linked in one suite run (its log empty), 3 s leaves it seconds
ROGUE_DURATION = "3"


@pytest.mark.load_safe
@pytest.mark.parametrize("router", [False, True], ids=["peers", "router"])
def test_lockstep_across_namespaces_equals_the_single_host_run(tmp_path, router):
    """Leader, plant and recorder on one machine, each agent on its own, over mutual
    TLS with the ACL (every node connecting to the plant, or to `omnifleet router`
    on the base machine): the same time series and metrics as `omnifleet run` on
    one host."""
    rc, _, err = finish(start("run", "paper", "--plant", "model", "--duration", DURATION,
                              "--out", str(tmp_path / "ref"), "--no-figures", "--no-record"))
    assert rc == 0, err
    out = tmp_path / "netns-run"
    run = RunOptions("paper", duration_s=float(DURATION), plant_kind="model",
                     record_out=str(out))
    with machines(MACHINES) as ms:
        procs, logs = _run_fleet(ms, tmp_path, f"nsq{int(time.time()) % 100000}", run,
                                 router=router)
        router_proc = procs.pop("router", None)
        try:
            codes = _wait_all(procs, 120)
        finally:
            stop(list(procs.values()) + ([router_proc] if router_proc else []))
    assert all(c == 0 for c in codes.values()), f"{codes}\n{_logs(logs)}"
    a = TimeSeries.load(out / "timeseries.npz")
    b = TimeSeries.load(tmp_path / "ref" / "timeseries.npz")
    assert a.steps == b.steps == 300
    assert_same_series(a, b)
    ma = json.loads((out / "metrics.json").read_text())
    mb = json.loads((tmp_path / "ref" / "metrics.json").read_text())
    assert control_figures(ma) == control_figures(mb)
    assert ma["messages"]["late"] == ma["messages"]["invalid"] == ma["messages"]["dropped"] == 0
    # the recorder really was on another machine than the agents: it heard them over TLS
    # every node reported to the recorder across the namespaces, and heard only its graph
    heard = {p["role"]: {k.split("/", 2)[2] for k in p["received"]} for p in ma["processes"]
             if p["role"] != "launcher"}
    assert set(heard) == {"plant", "leader", "agent-1", "agent-2", "agent-3"}
    assert heard["agent-2"] == {"robot/2/sample", "robot/1/cmd", "ctl/tick", "ctl/end"}


@pytest.mark.parametrize("tls", [True, False], ids=["tls-acl", "plain-tcp"])
def test_an_agent_with_valid_credentials_commands_no_other_robot(tmp_path, tls):
    """Agent 3's machine is taken over: a rogue process there holds agent 3's keyring
    (and, with TLS, its certificate), throws its own access control away and floods
    robot 2's key with replies (tests/rogue_agent.py). With TLS the plant's ACL drops
    them before anything sees them; over plain TCP the keys refuse them, counted. Either
    way robot 2 moves as in the in-process reference, bit for bit."""
    from deploy.fleet.certs import role_files
    from deploy.fleet.zenoh_configs import node_config, write_config

    # the reference in process: a fleet on one host equals it bit for bit
    # (tests/e2e/test_distributed.py), and it costs a tenth of the CPU
    rc, _, err = finish(start("run", "paper", "--plant", "model", "--in-process", "--duration",
                              ROGUE_DURATION, "--out", str(tmp_path / "ref"), "--no-figures",
                              "--no-record"))
    assert rc == 0, err
    out = tmp_path / "netns-run"
    fleet = f"nsr{int(time.time()) % 100000}"
    run = RunOptions("paper", duration_s=float(ROGUE_DURATION), plant_kind="model",
                     record_out=str(out))
    with machines(MACHINES) as ms:
        procs, logs = _run_fleet(ms, tmp_path, fleet, run, tls=tls)
        hosts = load_hosts(tmp_path / "hosts.toml", load_scenario("paper"))
        d = tmp_path / "deploy" / "robot3"
        cfg = write_config(tmp_path / "rogue.json5", node_config(
            [], [hosts.hub.endpoint(tls)], role_files(d, "agent-3") if tls else None, None))
        rogue = ms["robot3"].start(
            [sys.executable, str(Path(__file__).resolve().parents[1] / "rogue_agent.py"),
             "--scenario", "paper", "--fleet", fleet, "--keys", str(d / "agent-3.keys"),
             "--role", "agent-3", "--zenoh-config", str(cfg), "--steps", "300",
             "--seconds", "20"], logs / "rogue.log")
        try:
            codes = _wait_all(procs, 120)
        finally:
            stop([*procs.values(), rogue])
    assert all(c == 0 for c in codes.values()), f"{codes}\n{_logs(logs)}"
    assert_same_series(TimeSeries.load(out / "timeseries.npz"),
                       TimeSeries.load(tmp_path / "ref" / "timeseries.npz"))
    m = json.loads((out / "metrics.json").read_text())
    plant = {why: n for why, n in m["messages"].get("refused", {}).items()
             if why.startswith("plant: reply")}
    # the rogue was in the fleet: linked with its nodes (its own certificate is valid)
    assert int((logs / "rogue.log").read_text().split("peers ")[-1].split()[0]) > 0
    if tls:  # the ACL refused them on the link: nothing reached the plant's handlers
        assert plant == {}, plant
    else:  # nothing but the keys: refused, counted
        assert plant.get("plant: reply: not signed by a sender of this key", 0) > 0, plant
        assert plant.get("plant: reply: MAC does not check", 0) > 0, plant
    print(f"\n{'TLS + ACL' if tls else 'plain TCP'}: the plant refused {plant or 'nothing'}")


def _wait_for_step(log: Path, k: int, proc: subprocess.Popen, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        steps = [int(m) for m in re.findall(r"record: step (\d+)/", log.read_text())]
        if steps and steps[-1] >= k:
            return
        assert proc.poll() is None, log.read_text()
        time.sleep(0.05)
    raise TimeoutError(f"the run did not reach step {k}")


CUT_S = 3.0
LEASE_MS = 1000
# s of scenario time: the cut after step 150; the steps after it take a few seconds
# of wall time once agent-2 is back, so the run's end (everybody leaving) comes well
# after the cut's window
CUT_DURATION = 4.0


def test_a_cut_agent_link_is_detected_counted_and_the_run_goes_on(tmp_path):
    """agent-2's machine loses its link (``ip link set ... down``) for 3 s mid-run.
    With a 1 s lease, liveliness declares agent-2 lost (counted by the recorder,
    on the plant's machine) and nobody else; the plant goes on at its step
    deadline holding agent-2's last command; zenoh reconnects when the link is
    back (agent-2 stays thanks to --lost-peer-grace) and the token returns; the
    run finishes every step. The states published while the link was dead are
    lost (counted from the reports), and agent-2 resumes: its lockstep loop
    catches up on the newest state instead of waiting for the lost one."""
    from mcap.reader import make_reader

    out = tmp_path / "cut-run"
    fleet = f"nsc{int(time.time()) % 100000}"
    run = RunOptions("paper", duration_s=CUT_DURATION, plant_kind="model", record_out=str(out),
                     step_deadline_s=0.05, lost_peer_grace_s=60.0)
    with machines(MACHINES) as ms:
        procs, logs = _run_fleet(ms, tmp_path, fleet, run, lease_ms=LEASE_MS)
        try:
            _wait_for_step(logs / "recorder.log", 150, procs["recorder"], 120)
            cut_ns = time.time_ns()
            ms["robot2"].cut()
            time.sleep(CUT_S)  # the fault's duration (not a synchronisation)
            ms["robot2"].restore()
            restored_ns = time.time_ns()
            codes = _wait_all(procs, 150)
        finally:
            stop(list(procs.values()))
    assert all(c == 0 for c in codes.values()), f"{codes}\n{_logs(logs)}"
    m = json.loads((out / "metrics.json").read_text())
    assert m["steps"] == round(CUT_DURATION * 1000)  # the run went on to its end
    with open(out / "recording.mcap", "rb") as f:
        # publish time: the wall clock (log time is simulation time in lockstep)
        messages = [(ch.topic, msg.publish_time) for _s, ch, msg in make_reader(f).iter_messages()]
    cmd_times = [t for topic, t in messages if topic.endswith("/robot/2/cmd")]
    end_ns = min([t for topic, t in messages if topic.endswith("/ctl/end")] or [2**63])
    live = m["liveliness"]["agent-2"]
    # losses between the cut and one lease after the link is back (the run's end,
    # when nodes leave, comes later)
    assert end_ns > restored_ns + 2e9, "the run ended too soon after the cut to judge"
    window_end = restored_ns + 2e9
    during = {role: [t for t in r["lost_at_unix_ns"] if cut_ns < t < window_end]
              for role, r in m["liveliness"].items()}
    # Nobody else is cut off. A token the recorder heard relayed through agent-2's
    # session (zenoh linked those two peers through it) goes at the same lease
    # expiry: seen once in about six runs, for agent-1. Such a loss must come back;
    # it is printed, and docs/multihost.md says so.
    relayed = {r: ts for r, ts in during.items() if ts and r != "agent-2"}
    for role, ts in relayed.items():
        assert all(any(b > t for b in m["liveliness"][role]["back_at_unix_ns"]) for t in ts), role
    if relayed:
        print(f"\nalso lost during the cut (relayed through agent-2): {sorted(relayed)}")
    assert len(during["agent-2"]) == 1, live  # detected once, during the cut (lease expiry)
    lost_at = during["agent-2"][0]
    assert lost_at < restored_ns
    back_at = min(t for t in live["back_at_unix_ns"] if t > lost_at)
    assert back_at > restored_ns  # and the token came back once the link did
    reports = {p["role"]: p for p in m["processes"] if p["role"] != "launcher"}
    plant, agent2 = reports["plant"], reports["agent-2"]
    key = lambda tail: next(k for k in plant["received"] if k.endswith(tail))  # noqa: E731
    states_lost = plant["steps"] - agent2["received"][key("/robot/2/cmd").replace("cmd", "sample")]
    cmds_lost = agent2["steps"] - plant["received"][key("/robot/2/cmd")]
    assert states_lost > 0  # published while the link was dead: gone
    assert plant["late"] > 0  # the plant went on with agent-2's held command
    after = [t for t in cmd_times if t > restored_ns]
    print(f"\nlink cut {CUT_S} s, lease {LEASE_MS} ms: detected {(lost_at - cut_ns) * 1e-9:.3f} s "
          f"after the cut; token back {(back_at - restored_ns) * 1e-9:.3f} s after the link; "
          f"states to agent-2 lost {states_lost}, its commands lost {cmds_lost}; plant late "
          f"{plant['late']}; agent-2 steps {agent2['steps']}/{plant['steps']}; agent-2 commands "
          f"after the link was back: {len(after)}"
          + (f" (first {(after[0] - restored_ns) * 1e-9:.3f} s after)" if after else ""))
    # agent-2 resumed: it caught up on the newest state instead of waiting for the lost one
    assert after, "agent-2 sent no command after the link came back"
