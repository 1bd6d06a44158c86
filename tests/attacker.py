"""An outside peer that forges messages into a running fleet (docs/hardening.md).

What a hostile or faulty local process can do: read the run's
``logs/endpoints.json``, connect a zenoh peer of its own to the nodes' endpoints,
join the run's datagram path (deploy/runtime/datagrams.py: the nodes' sockets are
beside their zenoh sockets; it binds one of its own there, says what it hears and
declares itself alive, so the nodes send it what it asked for), listen to the
fleet's traffic and send well-formed messages with the project's own wire codec,
plain or in an envelope (deploy/contract/mac.py) tagged under keys it made up (a
guessed keyring: the run's keys travel on pipes, it holds none of them), answering
each sample of a robot within a hop (:meth:`Attacker.race`). A data message goes
the way the nodes send it (datagrams to those that hear its key, when the run has
them; zenoh otherwise), everything else on zenoh. The tests of
tests/e2e/test_forged.py use it to probe a run from outside and judge what the run
did about each message.

:func:`fleet_under_attack` starts ``omnifleet run`` and yields once every node is
ready; every process it started is ended by pid on the way out.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from procs import kill_run, start

from deploy.contract.keyring import Keyring, keyring_text, new_master
from deploy.contract.scenario import Scenario, load_scenario
from deploy.contract.wire import (
    LAUNCHER_ROLE,
    WIRE_VERSION,
    Codec,
    Control,
    Keys,
    LeaderState,
    NodeReport,
    Reply,
    Sample,
    Share,
    StateLog,
    StateRow,
    Telemetry,
    TelemetryRow,
    encode,
    run_roles,
)
from deploy.runtime.datagrams import DATA_KINDS, DatagramPath

ZERO3 = (0.0, 0.0, 0.0)
READY_TIMEOUT_S = 60.0


def guessed_keys(sc: Scenario, fleet: str, master: bytes | None = None) -> dict[str, Keyring]:
    """Keyrings for every role of a run of ``sc`` under ``master`` (default: a made-up
    one: what a forger without the run's keys can tag with)."""
    roles = [*run_roles(sc.robot_ids), LAUNCHER_ROLE]
    master = master if master is not None else new_master()
    return {r: Keyring.from_text(keyring_text(master, fleet, r, roles), "guessed", r, sc,
                                 Keys(fleet)) for r in roles}


@dataclass
class Attacker:
    """A zenoh session linked to every node of a run, and the forgeries it can send.
    ``as_role``: the keyrings it tags with, by the role it claims to be (a forgery
    ``as_`` a role is put in an envelope under that keyring; else plain)."""

    fleet: str
    session: object
    sc: Scenario
    keys: Keys = field(init=False)
    codec: Codec = field(init=False)
    newest_sample: dict[int, Sample] = field(default_factory=dict)
    endpoints: dict[str, str] = field(default_factory=dict)  # role -> where it listens
    as_role: dict[str, Keyring] = field(default_factory=dict)
    datagrams: DatagramPath | None = None  # its end of the run's datagram path, if any

    def __post_init__(self) -> None:
        self.keys = Keys(self.fleet)
        self.codec = Codec(list(range(1, 65)))
        self._subs: list[object] = []
        self._watched: set[int] = set()
        self._racers: dict[int, Callable[[Sample], None]] = {}
        self._closed = threading.Event()
        self._token = None
        if not self.as_role:
            self.as_role = guessed_keys(self.sc, self.fleet)
        self._listener: threading.Thread | None = None
        if self.datagrams is not None:
            self._listener = threading.Thread(target=self._listen, daemon=True,
                                              name="prober-dgram")
            self._listener.start()

    # -- listening: what step the fleet is at --------------------------------------
    def watch_samples(self, *robots: int) -> None:
        """Keep the newest sample of each of ``robots`` (the fleet's step, as a forger
        learns it)."""
        new = [r for r in robots if r not in self._watched]
        if not new:
            return
        self._watched.update(new)
        for robot in new:
            self._subs.append(self.session.declare_subscriber(
                self.keys.sample(robot),
                lambda s, robot=robot: self._heard(robot, s.payload.to_bytes())))
        if self.datagrams is not None:
            self.datagrams.hear([self.keys.sample(r) for r in new])
            # the nodes read who hears what when a peer appears or goes: all the keys
            # first, then the token (declared again when keys are added later)
            if self._token is not None:
                self._token.undeclare()
            self._token = self.session.liveliness().declare_token(
                self.keys.alive(self.datagrams.role))

    def _heard(self, robot: int, data: bytes) -> None:  # zenoh's or the listener's thread
        m = self.codec.decode(Sample, _payload_of(data), robot)
        if m is not None:
            racer = self._racers.get(robot)
            if racer is not None:
                racer(m)
            old = self.newest_sample.get(robot)
            if old is None or m.k > old.k:
                self.newest_sample[robot] = m

    def _listen(self) -> None:
        """The samples the nodes send its datagram socket."""
        assert self.datagrams is not None
        while not self._closed.is_set():
            frame = self.datagrams.recv_wait(0.1)
            if not frame:
                continue
            n = frame[0]
            key = frame[1:1 + n].decode(errors="replace")
            parts = key.split("/")
            if key.endswith("/sample") and parts[-2].isdigit():
                self._heard(int(parts[-2]), frame[1 + n:])

    def step_of(self, robot: int, after: int = 0, timeout_s: float = 30.0) -> int:
        """The newest step of ``robot``'s samples, once it is past ``after``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            m = self.newest_sample.get(robot)
            if m is not None and m.k > after:
                return m.k
            time.sleep(0.005)  # polling what another thread writes; not a sync stand-in
        raise TimeoutError(f"no sample of robot {robot} past step {after}")

    # -- forgeries --------------------------------------------------------------------
    def put(self, key: str, msg, as_: str | None = None) -> None:
        """``msg`` on ``key``: plain, or in an envelope of the keyring it holds for
        role ``as_`` (guessed keys, unless the test gave it real ones)."""
        data = encode(msg)
        self.raw(key, data if as_ is None else self.as_role[as_].seal(data, key))

    def sample(self, robot: int, k: int, seq: int = 0, q=(50.0, 50.0, 0.0),
               as_: str | None = None) -> Sample:
        """A well-formed sample of ``robot`` for step ``k`` (a robot far from where it is)."""
        m = Sample(WIRE_VERSION, 0, seq, time.monotonic_ns(), robot=robot, k=k, t=k * 1e-3,
                   q=q, q_dot=ZERO3, robots=[], obstacles=[])
        self.put(self.keys.sample(robot), m, as_)
        return m

    def cmd(self, robot: int, k: int, seq: int = 0, torque: float = 1.0,
            plan_steps: int = 0, as_: str | None = None, q0_hat=ZERO3) -> Reply:
        """A well-formed command (and share: ``q0_hat``, its leader estimate) of
        ``robot``'s agent for step ``k``."""
        share = Share(q0_hat, ZERO3, ZERO3, ZERO3, ZERO3, ZERO3)
        u = (torque,) * 4
        m = Reply(WIRE_VERSION, robot, seq, time.monotonic_ns(), robot=robot, k=k, t=0.0,
                  torques=u, v_cmd=ZERO3, state_seq=0, state_stamp_ns=0, share=share,
                  plan=[u] * plan_steps)
        self.put(self.keys.cmd(robot), m, as_)
        return m

    def leader(self, k: int, steps: int = 32, q=(5000.0, 5000.0, 0.0), as_: str | None = None
               ) -> None:
        """A batch of leader states for steps k..k+steps-1, the leader at ``q``."""
        self.put(self.keys.leader_state, LeaderState(
            WIRE_VERSION, 0, k, time.monotonic_ns(), k=k, t=k * 1e-3, q=[q] * steps,
            q_dot=[ZERO3] * steps), as_)

    def control(self, command: str, seq: int = 0, k: int = 0, as_: str | None = None) -> None:
        """A control message, plain or tagged under keys the attacker holds as ``as_``."""
        self.put(self.keys.ctl(command), Control(WIRE_VERSION, 0, seq, time.monotonic_ns(),
                                                 command=command, k=k), as_)

    def race(self, robot: int, forgeries: int, make: Callable[[Sample], None]) -> threading.Event:
        """From now on, answer each of ``robot``'s samples at once with ``make(sample)``
        (on a thread of its own, a hop after the sample appears), ``forgeries`` times;
        the returned event is set once all went out."""
        self.watch_samples(robot)
        todo: queue.SimpleQueue = queue.SimpleQueue()
        done = threading.Event()

        def answer() -> None:
            for _ in range(forgeries):
                make(todo.get())
            self._racers.pop(robot, None)
            done.set()

        threading.Thread(target=answer, daemon=True, name=f"race-{robot}").start()
        self._racers[robot] = todo.put
        return done

    def report(self, on_role: str, body_role: str, **fields) -> None:
        """A report on ``report/<on_role>`` whose body says ``body_role``; ``fields`` may
        hold what the type refuses (a negative count): it is written field by field."""
        import msgspec

        m = NodeReport(WIRE_VERSION, 0, 0, 0, role=body_role, robot=-1, sent=1, dropped=0,
                       late=0, invalid=0, steps=1)
        names = NodeReport.__struct_fields__
        row = list(msgspec.structs.astuple(m))
        for name, value in fields.items():
            row[names.index(name)] = value
        self.raw(self.keys.report(on_role), msgspec.msgpack.encode(row))

    def state_log(self, role: str, robots: list[int], steps: list[int],
                  q=(50.0, 50.0, 0.0), as_: str | None = None) -> None:
        """Robot states for observers on ``log/<role>``, every robot at ``q``."""
        rows = [StateRow(k, k * 1e-3, [q] * len(robots), [ZERO3] * len(robots),
                         [False] * len(robots)) for k in steps]
        self.put(self.keys.state_log(role), StateLog(WIRE_VERSION, 0, 0, 0, robots=robots,
                                                     rows=rows), as_)

    def telemetry(self, robot: int, steps: list[int], nonfinite: bool = True,
                  as_: str | None = None) -> None:
        """Telemetry rows of ``robot`` that say its law diverged."""
        rows = [TelemetryRow(k=k, t=k * 1e-3, q_d=ZERO3, e=(9.0, 9.0, 0.0), s=ZERO3,
                             v_cmd=ZERO3, torques=(0.0,) * 4, q0_hat=ZERO3, q_fd=ZERO3,
                             fdb_error=None, order="", nonfinite=nonfinite) for k in steps]
        self.put(self.keys.telemetry(robot), Telemetry(WIRE_VERSION, robot, 0, 0, robot=robot,
                                                       rows=rows), as_)

    def raw(self, key: str, data: bytes) -> None:
        """Send ``data`` on ``key`` as the nodes would: a data key as datagrams to the
        nodes that hear it (when the run has a datagram path), anything else on zenoh,
        blocking rather than dropping when a link is busy (zenoh's default drops: a flood
        would lose the forgeries sent after it)."""
        import zenoh

        found = self.keys.kind_of(key)
        if self.datagrams is not None and found is not None and found[0] in DATA_KINDS:
            self.datagrams.refresh()  # who hears what now
            self.datagrams.send(key, data)
            self.datagrams.flush(wait_s=5.0)
            return
        self.session.put(key, data, congestion_control=zenoh.CongestionControl.BLOCK)

    def close(self) -> None:
        self._racers.clear()
        self._closed.set()
        if self._token is not None:
            self._token.undeclare()
        for s in self._subs:
            s.undeclare()
        self.session.close()
        if self._listener is not None:
            self._listener.join(5.0)  # it looks at the flag every 0.1 s
        if self.datagrams is not None:
            self.datagrams.close()


def environments(fleet: str) -> dict[int, dict[str, str]]:
    """The environment of every process of the run (by pid), as any process of the same
    user reads it from /proc/PID/environ."""
    from procs import pids_with

    out = {}
    for pid in pids_with(fleet):
        try:
            raw = Path(f"/proc/{pid}/environ").read_bytes()
        except OSError:
            continue
        out[pid] = dict(item.decode(errors="replace").partition("=")[::2]
                        for item in raw.split(b"\0") if item)
    return out


def _payload_of(data: bytes) -> bytes:
    """The message in an envelope (what a listener reads; nothing is checked)."""
    from deploy.contract import mac

    head = mac.parse_head(data)
    return data if head is None else data[:head[0]]


def _wait_ready(attacker: Attacker, roles: set[str], proc: subprocess.Popen,
                timeout_s: float) -> None:
    """Until every role is ready, or the fleet is already stepping (its samples reach
    us: a short realtime run can be under way before a query sees every token)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        if attacker.newest_sample:
            return
        replies = attacker.session.liveliness().get(f"omr/{attacker.fleet}/ready/*", timeout=0.5)
        seen = {str(r.ok.key_expr).rsplit("/", 1)[-1] for r in replies if r.ok is not None}
        if roles <= seen:
            return
        time.sleep(0.02)
    raise TimeoutError(f"fleet {attacker.fleet} not ready"
                       + ("" if proc.poll() is None else f" (the run exited {proc.returncode})"))


@contextlib.contextmanager
def fleet_under_attack(scenario: str, out: Path, *args: str, robots: int = 3
                       ) -> Iterator[tuple[subprocess.Popen, Attacker]]:
    """``omnifleet run SCENARIO --out OUT ARGS`` on its default (private) endpoints; yields
    (launcher process, an :class:`Attacker` linked to every node) once all are ready."""
    import zenoh

    from deploy.runtime.transport import zenoh_config

    fleet = f"t-attack-{os.getpid()}-{out.name}"
    proc = start("run", scenario, "--no-figures", "--fleet", fleet, "--out", str(out), *args)
    attacker = None
    try:
        where = out / "logs" / "endpoints.json"
        deadline = time.monotonic() + READY_TIMEOUT_S
        while not where.exists() and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)  # polling for a file another process writes
        endpoints = json.loads(where.read_text())
        # connect once every node listens: a connect to a socket not there yet is retried
        # by zenoh with a growing back-off, and a short run could end meanwhile
        socks = [Path(e.removeprefix("unixsock-stream/")) for e in endpoints.values()
                 if e.startswith("unixsock-stream/")]
        while (not all(x.exists() for x in socks) and time.monotonic() < deadline
               and proc.poll() is None):
            time.sleep(0.02)  # polling for files other processes create
        session = zenoh.open(zenoh_config(connect=list(endpoints.values()), gossip=False))
        run_dir = socks[0].parent if socks else None
        # the run's data goes over its datagram path unless it was told otherwise (its
        # nodes' sockets may not be bound yet: they are not what says so)
        on_zenoh = any(a == "--data-path" and b == "zenoh" for a, b in zip(args, args[1:]))
        dgram = (DatagramPath(run_dir, f"prober-{os.getpid()}", lossless=False)
                 if run_dir is not None and not on_zenoh else None)
        attacker = Attacker(fleet, session, load_scenario(scenario), endpoints=endpoints,
                            datagrams=dgram)
        attacker.watch_samples(*range(1, robots + 1))  # before the fleet starts stepping
        roles = {"plant", "leader", *(f"agent-{r}" for r in range(1, robots + 1))}
        _wait_ready(attacker, roles, proc, READY_TIMEOUT_S)
        yield proc, attacker
    finally:
        if attacker is not None:
            attacker.close()
        kill_run(proc, fleet)
