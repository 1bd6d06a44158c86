"""``omnifleet agent|plant|leader``: one node of a fleet, runnable alone.

The same command works on one machine (the launcher starts it with loopback
endpoints) and across machines (``--listen``/``--connect`` or
``--zenoh-config``). Every node of a run must be given the same scenario, fleet
name, clock, and --duration/--control-rate/--step-deadline if any (a lockstep agent
judges how far ahead the plant can be by the plant's step deadline: step_guard.py).
"""

from __future__ import annotations

import argparse
import os
import sys
import threading

from deploy.contract.fault_plan import FaultPlan
from deploy.contract.keyring import Keyring, KeysError, read_fd, read_file
from deploy.contract.options import EXIT_BAD_INPUT, add_option, check_duration
from deploy.contract.plant_registry import add_plant_option, find_plant
from deploy.contract.scenario import Scenario, load_scenario
from deploy.contract.wire import LEADER_ROLE, PLANT_ROLE, Codec, Keys, agent_role
from deploy.runtime.datagrams import DatagramError, DatagramPath
from deploy.runtime.heap import freeze_startup_heap
from deploy.runtime.node_runtime import CLOCKS, LOOP, StopFlag, install_signal_handlers
from deploy.runtime.parent_death import die_with_parent
from deploy.runtime.priority import (
    REALTIME_PRIORITY,
    add_priority_argument,
    batch_scheduling,
    leave_realtime_scheduling,
    raise_priority,
)
from deploy.runtime.transport import Node, zenoh_config

EXIT_PEER_LOST = 3
EXIT_STARTUP = 4


def run_scenario(args: argparse.Namespace) -> Scenario:
    """The scenario of ``args.scenario`` at ``--control-rate`` if given, for a run of
    ``--duration`` (OptionError when that is shorter than one control period)."""
    sc = load_scenario(args.scenario)
    if getattr(args, "law", None):  # every agent on another law (docs/laws.md)
        sc = sc.with_law(args.law)
    if args.control_rate is not None:
        sc = sc.with_control_rate(args.control_rate)
    check_duration(args.duration, sc.spec.control_rate_hz)
    return sc


def fault_plan(args: argparse.Namespace, sc: Scenario) -> FaultPlan | None:
    """The ``--faults`` plan validated for ``sc`` (FaultPlanError: exit 2)."""
    if not getattr(args, "faults", None):
        return None
    from deploy.contract.fault_plan import load_plan

    return load_plan(args.faults, sc)


def steps_of(sc: Scenario, args: argparse.Namespace) -> int:
    return sc.steps if args.duration is None else int(round(args.duration / sc.dt))


def keyring_of(args: argparse.Namespace, sc: Scenario, role: str) -> Keyring | None:
    """This node's keys (``--keys-fd`` from the launcher, ``--keys FILE`` across hosts),
    or None (started by hand without keys). KeysError (exit 2) names what is wrong."""
    keys = Keys(args.fleet or sc.name)
    if getattr(args, "keys_fd", None) is not None:
        return Keyring.from_text(read_fd(args.keys_fd), f"--keys-fd {args.keys_fd}", role, sc,
                                 keys)
    if getattr(args, "keys", None):
        return Keyring.from_text(read_file(args.keys), args.keys, role, sc, keys)
    return None


def _open(args: argparse.Namespace, sc: Scenario, role: str, sender: int,
          keyring: Keyring | None) -> Node:
    if args.with_recorder:
        if not die_with_parent():  # the launcher is already gone
            sys.exit(EXIT_PEER_LOST)
    cfg = zenoh_config(args.zenoh_config, args.listen, args.connect, gossip=not args.no_gossip,
                       lowlatency=args.lowlatency)
    lossless = args.clock == "lockstep"
    datagrams = None if args.datagrams is None else DatagramPath(args.datagrams, role, lossless)
    return Node(role, Keys(args.fleet or sc.name), Codec(sc.robot_ids), cfg, sender,
                lossless=lossless, keyring=keyring, datagrams=datagrams)


def _exit_code(stop: StopFlag) -> int:
    return {"": 0, "end": 0, "stop": 0, "estop": 0, "SIGINT": 130, "SIGTERM": 143}.get(
        stop.reason, EXIT_PEER_LOST)


def gui_problem(plant_kind: str, gui: bool) -> str | None:
    """Why ``--gui`` cannot be honoured (pybullet's window would end the process
    on a failed X connection), or None."""
    if not gui:
        return None
    entry = find_plant(plant_kind)
    if entry is None or not entry.gui:
        return f"--gui shows the pybullet plant; this run's plant is {plant_kind}"
    if not os.environ.get("DISPLAY"):
        return "--gui needs a display, and DISPLAY is not set"
    return None


def run_node(args: argparse.Namespace, role: str, sender: int, build, lockstep, realtime,
             batch: bool = False) -> int:
    """One node's life: keys, peer, handshake, its loop on the run's clock, its report.
    ``batch``: on the lockstep clock the node runs under SCHED_BATCH (the agents: see
    deploy/runtime/priority.py)."""
    sc = run_scenario(args)
    try:  # read first: the pipe's write end is the launcher's, whatever happens next
        keyring = keyring_of(args, sc, role)
    except KeysError as exc:
        print(f"omnifleet {role}: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    stop = StopFlag()
    if args.priority:
        print(f"omnifleet {role}: {raise_priority(args.priority)}", file=sys.stderr, flush=True)
    try:
        node = _open(args, sc, role, sender, keyring)
    except DatagramError as exc:
        print(f"omnifleet {role}: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    install_signal_handlers(stop, node)
    try:
        obj = build(sc, node, stop)
        try:
            obj.handshake(args.startup_timeout)
        except TimeoutError as exc:
            print(f"omnifleet {role}: {exc}", file=sys.stderr)
            return EXIT_STARTUP
        node.note_links()  # the links of the run (at its end, peers leave one by one)
        LOOP.costs = node.costs
        with LOOP:
            if args.clock == "lockstep":
                if batch:
                    batch_scheduling()
                lockstep(obj, sc)
            else:
                freeze_startup_heap()  # no collection burst in the first steps (heap.py)
                try:
                    realtime(obj, sc)
                finally:  # the loops still going keep their cores (priority.py)
                    leave_realtime_scheduling()
        obj.finish()
    finally:
        node.close()
    c = node.counters
    print(f"omnifleet {role}: {obj.steps_done} steps; messages sent {c.sent}, dropped "
          f"{c.dropped}, late {c.late}, invalid {c.invalid}"
          + (f"; NON-FINITE values computed {c.nonfinite}" if c.nonfinite else "")
          + ("" if stop.reason in ("", "end", "stop") else f"; stopped ({stop.reason})"),
          file=sys.stderr)
    return _exit_code(stop)


def _lost(stop: StopFlag, node: Node, grace_s: float = 0.0):
    """Losing a required peer ends the node: at once, or after ``grace_s`` if the
    peer's token has not come back by then (a link cut between machines)."""
    def give_up(role: str) -> None:  # on the node's thread
        if role not in node.peers_alive:
            stop.set(f"lost {role}")

    def give_up_later(role: str) -> None:  # the timer's thread: hand it to the node
        node.mailbox.post(give_up, role)

    def on_lost(role: str) -> None:  # on the node's thread
        if grace_s <= 0:
            give_up(role)
            return
        timer = threading.Timer(grace_s, give_up_later, (role,))
        timer.daemon = True
        timer.start()
    return on_lost


def _waits_for_recorder(args: argparse.Namespace) -> bool:
    return args.with_recorder or args.wait_recorder


def _cmd_agent(args: argparse.Namespace) -> int:
    from deploy.nodes.agent import AgentNode

    sc = run_scenario(args)
    sc.index_of(args.robot)  # fail fast, before opening a session

    if args.rejoin and args.clock != "realtime":
        print("omnifleet agent: --rejoin joins a running realtime fleet (--clock realtime)",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    plan = fault_plan(args, sc)

    def build(sc, node, stop):
        node.required, node.on_lost = {args.plant_role}, _lost(stop, node, args.lost_peer_grace)
        return AgentNode(sc, args.robot, node, stop, _waits_for_recorder(args),
                         args.plant_role, plan, realtime=args.clock == "realtime",
                         step_deadline_s=args.step_deadline)

    def realtime(obj, sc):
        if args.rejoin:  # the start was announced long ago: t = 0 comes from the plant
            obj.run_realtime(None, steps=steps_of(sc, args))
            return
        t0 = obj.control.wait_for_start(args.startup_timeout)
        if t0 is not None:
            obj.run_realtime(t0, steps=steps_of(sc, args))

    return run_node(args, agent_role(args.robot), args.robot, build,
                     lambda obj, sc: obj.run_lockstep(args.step_deadline), realtime, batch=True)


def _cmd_plant(args: argparse.Namespace) -> int:
    from deploy.nodes.plant import PlantNode

    problem = gui_problem(args.plant or run_scenario(args).spec.plant.kind, args.gui)
    if problem:
        print(f"omnifleet plant: {problem}", file=sys.stderr)
        return EXIT_BAD_INPUT

    plan = fault_plan(args, run_scenario(args))

    def build(sc, node, stop):
        return PlantNode(sc, args.plant or sc.spec.plant.kind, node, stop,
                         _waits_for_recorder(args), args.command_timeout, gui=args.gui,
                         faults=plan, realtime=args.clock == "realtime", spool_dir=args.spool)

    return run_node(args, PLANT_ROLE, 0, build,
                     lambda obj, sc: obj.run_lockstep(steps_of(sc, args), args.step_deadline),
                     lambda obj, sc: obj.run_realtime(steps_of(sc, args)))


def _cmd_leader(args: argparse.Namespace) -> int:
    from deploy.nodes.leader import LeaderNode

    def build(sc, node, stop):
        node.required, node.on_lost = {args.plant_role}, _lost(stop, node, args.lost_peer_grace)
        return LeaderNode(sc, node, stop, _waits_for_recorder(args))

    def realtime(obj, sc):
        t0 = obj.control.wait_for_start(args.startup_timeout)
        if t0 is not None:
            obj.run_realtime(t0, steps_of(sc, args))

    return run_node(args, LEADER_ROLE, 0, build,
                     lambda obj, sc: obj.run_lockstep(steps_of(sc, args)), realtime)


def add_node_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", required=True, help="scenario file or bundled name")
    p.add_argument("--fleet", help="fleet name: keys are omr/<fleet>/... (default: scenario name)")
    p.add_argument("--clock", choices=CLOCKS, default="lockstep", help="default: lockstep")
    p.add_argument("--zenoh-config", metavar="FILE", help="a zenoh JSON5 config file")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="zenoh endpoint of a peer to connect to (repeatable)")
    p.add_argument("--no-gossip", action="store_true",
                   help="link only to the --connect endpoints (no peer discovery through "
                   "them): `omnifleet run` gives each node the nodes it talks to")
    p.add_argument("--datagrams", metavar="DIR",
                   help="send and hear the per-step data (samples, replies, leader, telemetry, "
                   "state logs) as unix datagrams with the nodes of DIR on this host; zenoh "
                   "carries the rest. `omnifleet run` gives every node its private run "
                   "directory (docs/distributed.md)")
    p.add_argument("--lowlatency", action="store_true",
                   help="zenoh's low-latency transport (no transmit task, no QoS); every node "
                   "of a run must use it (`omnifleet run` does; docs/distributed.md)")
    add_option(p, "--duration")
    add_option(p, "--control-rate")
    add_option(p, "--step-deadline")
    add_option(p, "--startup-timeout")
    add_law_option(p)
    p.add_argument("--faults", metavar="PLAN",
                   help="a fault plan (TOML, docs/faults.md): this node applies the faults of "
                   "the links it receives on; give every node of a run the same plan")
    add_keys_options(p)
    p.add_argument("--with-recorder", action="store_true",
                   help="started by `omnifleet run`: wait for its recorder, die with it")
    p.add_argument("--wait-recorder", action="store_true",
                   help="wait for `omnifleet record` (on any machine) before starting")
    add_priority_argument(p, "for a control loop on the realtime clock on a host that "
                          f"runs other work (the launcher asks for {REALTIME_PRIORITY} there)")
    add_option(p, "--lost-peer-grace")


def add_spool_option(p: argparse.ArgumentParser, what: str) -> None:
    """``--spool DIR``: the node keeps ``what`` for a recording made on its host
    (deploy/runtime/wire_spool.py)."""
    p.add_argument("--spool", metavar="DIR",
                   help=f"keep {what} in a file of DIR (on this host) for the run's "
                   "recording: `omnifleet run` gives its run directory when it records, and "
                   "then does not hear them on the wire")


def add_law_option(p: argparse.ArgumentParser) -> None:
    """``--law``: every agent on another control law than the scenario's ``[law]``."""
    from agents.laws import NAMES

    p.add_argument("--law", metavar="LAW",
                   help=f"the agents' control law instead of the scenario's [law] use: "
                   f"{', '.join(NAMES)}, module:Class or path/to/file.py:Class (a class of "
                   "agents/law_api.py; the scenario's [law] params apply when it names the "
                   "same law; docs/laws.md)")


def add_keys_options(p: argparse.ArgumentParser) -> None:
    """``--keys FILE`` and ``--keys-fd N``: where this node's keys come from."""
    keys = p.add_mutually_exclusive_group()
    keys.add_argument("--keys", metavar="FILE",
                      help="this node's keyring (`omnifleet deploy certs` writes one per role, "
                      "mode 0600): every message is authenticated per sender and receiver "
                      "(docs/hardening.md); without it, nothing is")
    add_option(keys, "--keys-fd")  # type: ignore[arg-type]  # a group adds arguments alike


def add_node_commands(sub: argparse._SubParsersAction) -> None:
    agent = sub.add_parser("agent", help="run one robot's agent (a zenoh peer)",
                           description="One robot's agent: estimator, observer, behaviors, "
                           "controller. Hears only its graph neighbours.")
    add_node_options(agent)
    add_option(agent, "--robot", required=True)
    agent.add_argument("--plant-role", default=PLANT_ROLE, metavar="ROLE",
                       help="the node that publishes this robot's state: plant (default), or "
                       "bridge-<ID> when the robot is on CAN; losing it ends the agent")
    agent.add_argument("--rejoin", action="store_true",
                       help="realtime: join a fleet that is already running (an agent "
                       "restarted after a crash): t = 0 and the leader estimate come from the "
                       "plant, the leader and the neighbours")
    agent.set_defaults(func=_cmd_agent)

    plant = sub.add_parser("plant", help="run the simulated plant of every robot",
                           description="Simulates every robot and obstacle; the time master "
                           "of a lockstep run.")
    add_node_options(plant)
    add_plant_option(plant)
    plant.add_argument("--gui", action="store_true",
                       help="pybullet: open the simulator's window (needs a display)")
    add_option(plant, "--command-timeout")
    add_spool_option(plant, "every sample sent and every reply heard")
    plant.set_defaults(func=_cmd_plant)

    leader = sub.add_parser("leader", help="run the virtual leader (reference generator)")
    add_node_options(leader)
    leader.add_argument("--plant-role", default=PLANT_ROLE, metavar="ROLE",
                        help="the node whose loss ends the leader: plant (default), or the "
                        "launcher when every robot is on CAN")
    leader.set_defaults(func=_cmd_leader)
