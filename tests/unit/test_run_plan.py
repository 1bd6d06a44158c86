"""The run's plan, drawn without starting anything (deploy/run/plan.py): links as the
graph (docs/distributed.md), one socket per node in the run's private directory, and a
restarted node that dials every peer it talks with."""

from __future__ import annotations

from pathlib import Path

import pytest

from deploy.contract.scenario import load_scenario
from deploy.run.plan import LaunchOptions, endpoint_of, plan_run, restart_of

RUN_DIR = Path("/run/omnifleet-test")
LAUNCHER = endpoint_of(RUN_DIR, "launcher")


def _connects(argv: list[str]) -> list[str]:
    return [argv[i + 1] for i, a in enumerate(argv) if a == "--connect"]


def _plan(name: str, plant: str = "model"):
    sc = load_scenario(name)
    opts = LaunchOptions(name, plant, "lockstep", Path("/tmp/out"))
    return sc, plan_run(sc, opts, LAUNCHER, RUN_DIR)


def test_each_node_listens_on_its_own_socket_and_dials_the_launcher():
    _, plan = _plan("paper")
    for c in plan.children:
        listen = c.argv[c.argv.index("--listen") + 1]
        assert listen == f"unixsock-stream/{RUN_DIR / f'{c.role}.sock'}"
        assert _connects(c.argv)[0] == LAUNCHER  # every node reports to the launcher


def test_links_are_the_graph_each_pair_opened_once():
    """paper: a_21 = a_31 = a_32 = 1, b = (1, 0, 0). Agent i talks with the plant, the
    leader iff b_i != 0 and its neighbours either way; the leader with the plant."""
    _, plan = _plan("paper")
    talks = {c.role: set(c.talks_with) for c in plan.children}
    assert talks["agent-1"] == {"plant", "leader", "agent-2", "agent-3"}
    assert talks["agent-2"] == {"plant", "agent-1", "agent-3"}
    assert talks["agent-3"] == {"plant", "agent-1", "agent-2"}
    assert talks["leader"] == {"plant", "agent-1"}
    opened = [frozenset((c.role, o)) for c in plan.children for o in c.links]
    assert len(opened) == len(set(opened))  # one link per pair
    assert set(opened) == {frozenset((a, b)) for a, ts in talks.items() for b in ts}
    for c in plan.children:  # a node dials exactly its links (beside the launcher)
        assert _connects(c.argv)[1:] == [endpoint_of(RUN_DIR, o) for o in c.links]


def test_a_restarted_agent_dials_every_peer_it_talks_with():
    """Peers that had dialled the dead node never dial again (zenoh re-dials only
    what a session connects to): the restarted one dials them all."""
    _, plan = _plan("paper")
    dead = next(c for c in plan.children if c.role == "agent-2")
    again = restart_of(dead, RUN_DIR)
    assert "--rejoin" in again.argv and again.restarted
    assert set(_connects(again.argv)[1:]) == {endpoint_of(RUN_DIR, o) for o in dead.talks_with}
    assert again.log_path.name == "agent-2.restart.log"


def test_can_emulated_is_one_emulator_and_a_bridge_per_robot_each_on_its_own_bus():
    sc, plan = _plan("lab", "can-emulated")
    emulators = [c for c in plan.children if c.role == "emulator"]
    assert len(emulators) == 1  # one process plays every robot's drives
    assert not emulators[0].zenoh and emulators[0].stop_after_run
    bridges = [c for c in plan.children if c.role.startswith("bridge-")]
    assert [c.robot for c in bridges] == sc.robot_ids
    buses = {(c.argv[c.argv.index("--can-channel") + 1], c.argv[c.argv.index("--can-arg") + 1])
             for c in bridges}
    assert len(buses) == sc.n  # robots never hear each other's frames
    assert set(plan.truth_files) == set(sc.robot_ids)
    agents = [c for c in plan.children if c.role.startswith("agent-")]
    for a in agents:  # an agent's plant is its robot's bridge
        assert a.argv[a.argv.index("--plant-role") + 1] == f"bridge-{a.robot}"


def test_the_driver_reaches_the_emulator_and_every_bridge():
    """``omnifleet run --plant can-emulated --driver cia402``: the one protocol on every bus."""
    sc = load_scenario("lab")
    for driver in ("odrive-cansimple", "cia402"):
        opts = LaunchOptions("lab", "can-emulated", "realtime", Path("/tmp/out"), driver=driver)
        plan = plan_run(sc, opts, LAUNCHER, RUN_DIR)
        can_nodes = [c for c in plan.children if c.role == "emulator" or c.role.startswith("bridge-")]
        assert len(can_nodes) == 1 + sc.n
        assert all(c.argv[c.argv.index("--driver") + 1] == driver for c in can_nodes)


def test_run_refuses_a_driver_without_can_bridges(capsys):
    from deploy.cli import main

    assert main(["run", "lab", "--plant", "model", "--driver", "cia402", "--in-process",
                 "--out", "/tmp/never-written"]) == 2
    assert "--driver cia402 drives CAN bridges: it needs --plant can-emulated" in capsys.readouterr().err


def test_endpoints_json_is_never_seen_half_written(tmp_path, monkeypatch):
    """A probe polls for logs/endpoints.json and reads it as soon as it exists: the file
    appears whole (written aside, then renamed), never empty. Every write is watched: at
    no write does the file the probe reads exist with other content than the final one."""
    import json

    from deploy.run import launcher

    _, plan = _plan("paper")
    path = tmp_path / "logs" / "endpoints.json"
    seen: list[str] = []
    write = Path.write_text

    def watched(self: Path, data: str, *a, **k):
        seen.append(path.read_text() if path.exists() else "<absent>")
        out = write(self, data, *a, **k)
        seen.append(path.read_text() if path.exists() else "<absent>")
        return out

    monkeypatch.setattr(Path, "write_text", watched)
    launcher._write_endpoints(tmp_path, LAUNCHER, plan.children, RUN_DIR)
    assert seen and set(seen) == {"<absent>"}  # nothing at the path until the rename
    where = json.loads(path.read_text())
    assert where["launcher"] == LAUNCHER and where["plant"] == endpoint_of(RUN_DIR, "plant")
    assert [p.name for p in path.parent.iterdir()] == ["endpoints.json"]


def _priorities(plan) -> dict[str, str | None]:
    return {c.role: c.argv[c.argv.index("--priority") + 1] if "--priority" in c.argv else None
            for c in plan.children}


@pytest.mark.parametrize("plant", ["model", "can-emulated"])
def test_on_the_realtime_clock_the_world_runs_above_the_agents(plant):
    """The plant (or, on CAN, the drive emulator) plays the world: its period is the fleet's
    clock, so it asks for a higher priority than the agents, the leader and the bridges,
    which ask for the run's --priority; none is raised on the lockstep clock or with 0."""
    sc = load_scenario("lab")
    for n, world, others in ((5, "10", "5"), (18, "20", "18"), (0, None, None)):
        opts = LaunchOptions("lab", plant, "realtime", Path("/tmp/out"), realtime_priority=n)
        got = _priorities(plan_run(sc, opts, LAUNCHER, RUN_DIR))
        if plant == "model":
            assert got.pop("plant") == world, n
        else:  # the emulator asks for its own, whatever the run's
            assert got.pop("emulator") == "10", n
        assert set(got.values()) == {others}, (n, got)
    lockstep = _priorities(_plan("lab")[1])
    assert set(lockstep.values()) == {None}


def test_a_recording_run_has_its_plant_keep_the_samples_and_replies_in_the_run_directory():
    """The plant's own record of them (on CAN: each bridge's) feeds the recording
    (deploy/runtime/wire_spool.py) and the launcher no longer subscribes to them; not
    recording, or ``spool`` off: no record, every key heard."""
    from deploy.run.launcher import make_observer

    sc = load_scenario("paper")

    def spooling(role, **kw):
        opts = LaunchOptions("paper", kw.pop("plant", "model"), "lockstep", Path("/tmp/out"), **kw)
        children = plan_run(sc, opts, LAUNCHER, RUN_DIR).children
        return next(c.argv for c in children if c.role == role), make_observer(
            sc, opts, None).listened_keys()

    for role, plant in (("plant", "model"), ("bridge-2", "can-emulated")):
        argv, heard = spooling(role, plant=plant)
        assert argv[argv.index("--spool") + 1] == str(RUN_DIR)
        assert not any(k.endswith(("/sample", "/cmd", "/**")) for k in heard)
        for kw in ({"record": False}, {"spool": False}):
            argv, heard = spooling(role, plant=plant, **kw)
            assert "--spool" not in argv
        assert heard == ["omr/paper/**"]  # spool off, recording: the launcher hears everything
