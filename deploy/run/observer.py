"""Hearing a run from outside its control path: every sample the launcher (or the
recorder across hosts) subscribes to goes through :meth:`Observer.on_sample`, which
checks who sent it (deploy/contract/keyring.py), decodes it, records it, judges it
(reports filed by their key, state logs from the node that holds those robots, rows
no further than the run can have reached on our own clock) and files what is kept
in the :class:`Collector`. What it refused is counted, by reason.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from deploy.contract.keyring import Keyring
from deploy.contract.scenario import Scenario
from deploy.contract.wire import (
    PLANT_ROLE,
    Codec,
    Control,
    Keys,
    NodeReport,
    StateLog,
    bridge_role,
    run_roles,
)
from deploy.nodes.leader import TICK_EVERY
from deploy.run.collector import Collector
from deploy.runtime.plants import CAN_EMULATED
from deploy.runtime.step_guard import CLOCK_SKEW_S
from deploy.runtime.transport import WHAT
from deploy.runtime.wire_spool import SpoolReader

MAX_KINDS_KEPT = 4096  # keys whose message type is remembered
# state rows the launcher holds before it files them together (~1.7 s of a CAN fleet at
# 200 Hz, 0.3 s of paper at 1 kHz; the live views file them at each look)
DEFER_STATE_ROWS = 1024


class Observer:
    """What the run's listener knows: the series and reports (``collector``), the run's
    clock (``run_t0`` realtime, ``t0_mono`` when the launcher keeps the time, ``tick_k``
    lockstep), whether it has ended or been stopped, and what it refused."""

    def __init__(self, sc: Scenario, keys: Keys, clock: str, plant: str, steps: int,
                 keyring: Keyring | None, recorder: Any = None, record_all: bool = False,
                 spooled: bool = False) -> None:
        self.sc, self.keys, self.clock, self.plant = sc, keys, clock, plant
        self.codec = Codec(sc.robot_ids)
        # the launcher's keys: what it hears is taken only from a sender of its key, tagged
        # for the launcher (deploy/contract/keyring.py). None (a recorder across hosts given
        # no --keys): the ACL alone says who may publish what (deploy/fleet/acl.py)
        self.keyring = keyring
        self.recorder = recorder  # McapRecorder or None
        self.record_all = record_all  # subscribe to every key (recording)
        # the plant (on CAN: each bridge) keeps its samples and replies for the recording
        # (SpooledWire): they are not heard here
        self.spooled = spooled
        self.steps = steps
        self.collector = Collector(sc, steps)
        self.collector.horizon = self.horizon
        self.collector.defer_rows = DEFER_STATE_ROWS  # filed together (Collector.defer_rows)
        self.invalid = 0  # samples that did not decode, or were refused
        self.ended = False
        self.end_unix_ns: int | None = None  # when ``end`` was heard (wall clock)
        self.progress_k = -1
        self.run_t0: float | None = None  # t = 0 of the run on our clock (``ctl/start``)
        self.t0_mono: float | None = None  # t = 0 when the launcher keeps the time (CAN)
        self.tick_k = -1  # lockstep: the newest signed ctl/tick (the plant's step)
        self.stopped_by: dict[str, Any] | None = None  # a genuine ctl/stop or ctl/estop
        self.unsigned: dict[str, int] = {}  # refused before decoding: authentication, by reason
        self.misfiled = 0  # reports and state logs whose key is not their sender's
        self.forged_reports = 0  # reports of no role of the run, or not signed by its nodes
        self.on_report: Callable[[str], None] = lambda role: None  # a report was filed
        self._kinds: dict[str, tuple[type, int | None]] = {}  # key -> Keys.kind_of(key)

    def listened_keys(self) -> list[str]:
        """Recording: every key of the fleet, but the samples and replies when the plant
        or the bridges keep them (``spooled``: what is left is the list below). Otherwise
        only what the series and the metrics need (each message heard costs CPU in every
        listener)."""
        k = self.keys
        if self.record_all and not self.spooled:
            return [k.everything]
        return [k.leader_state, k.state_log_all, f"{k.root}/agent/*/telemetry",
                k.ctl_all, f"{k.root}/report/*"]

    def on_sample(self, arrived: tuple[str, bytes] | tuple[str, bytes, str | None]) -> None:
        """A message heard on ``key``; ``sender``: the role of the authenticated connection
        it came on (deploy/runtime/datagrams.py), its bytes untagged; None: tagged."""
        key, data = arrived[0], arrived[1]
        sender = arrived[2] if len(arrived) > 2 else None
        found = self._kinds.get(key)
        if found is None:
            found = self.keys.kind_of(key)
            if found is None:
                return
            if len(self._kinds) < MAX_KINDS_KEPT:  # a forger's made-up keys stay bounded
                self._kinds[key] = found
        kind, robot = found
        if self.keyring is not None and sender is None:  # before anything decodes or files it
            payload, why = self.keyring.open(data, key)
            if payload is None:
                reason = f"{WHAT[kind]}: {why}"
                self.unsigned[reason] = self.unsigned.get(reason, 0) + 1
                return
            data = payload
        msg = self.codec.decode(kind, data, robot)
        if msg is None:
            self.invalid += 1
            return
        if self.recorder is not None:
            self.recorder.add(key, time.time_ns(), msg)
        if isinstance(msg, Control):
            self._on_control(msg)
        elif isinstance(msg, NodeReport):
            self._on_report(key, msg)
        elif isinstance(msg, StateLog) and not self._state_source(key, msg):
            self.invalid += 1  # robot states from a node that does not hold them
            self.misfiled += 1
        else:
            if isinstance(msg, StateLog) and self.clock == "realtime":
                self.progress_k = max(self.progress_k, msg.rows[-1].k)
            self.collector.add(msg)

    def note_unrecorded(self) -> None:
        """Once the reports are in: the samples and replies the plant (on CAN: a bridge)
        could not keep for the recording (``spooled``) make the recording incomplete, and
        the run fail."""
        if self.recorder is None:
            return
        for role, report in sorted(self.collector.reports.items()):
            if report.unrecorded:
                self.recorder.missed(
                    f"the {role} could not keep {report.unrecorded} of its samples and replies "
                    f"for the recording (its record of them failed to write: logs/{role}.log)",
                    report.unrecorded)

    def _on_control(self, msg: Control) -> None:
        if msg.command == "start" and self.run_t0 is None:
            self.run_t0 = time.monotonic() + (msg.start_unix_ns - time.time_ns()) * 1e-9
        elif msg.command == "tick":
            self.progress_k = max(self.progress_k, msg.k)
            self.tick_k = max(self.tick_k, msg.k)
        elif msg.command == "end":
            # the plant's end carries the steps it simulated (progress never claims more)
            self.progress_k = max(self.progress_k, min(msg.k, self.steps) - 1)
            self.ended = True
            self.end_unix_ns = self.end_unix_ns or time.time_ns()
        elif msg.command in ("stop", "estop") and self.stopped_by is None:
            # from the plant or the launcher (authenticated): the run ends early, and says so
            self.stopped_by = {"command": msg.command, "sender": msg.sender,
                               "k": self.progress_k, "t_s": self.run_time()}

    def _on_report(self, key: str, msg: NodeReport) -> None:
        if key != self.keys.report(msg.role):
            # a report is filed under the role of the key it came on, never the role its
            # body claims (a "plant" report on report/agent-2 put a fake contact in
            # metrics.json); across hosts the ACL lets each role put only its own key
            self.invalid += 1
            self.misfiled += 1
            return
        if msg.role not in self._report_roles():
            # only the run's roles (the table of reports stays bounded); with keys, only
            # the role itself can have tagged it (a report on report/plant with a fake
            # contact is refused before it is decoded)
            self.invalid += 1
            self.forged_reports += 1
            return
        self.collector.add(msg)
        self.on_report(msg.role)

    def _report_roles(self) -> set[str]:
        """The roles whose reports a run files: its nodes (a plant or bridges)."""
        ids = self.sc.robot_ids
        return {*run_roles(ids), *(bridge_role(r) for r in ids)}

    def _state_source(self, key: str, msg: StateLog) -> bool:
        """Whether ``msg`` came on the key of a node that holds those robots' states:
        the plant (any robots), or robot i's CAN bridge (robot i only)."""
        if key == self.keys.state_log(PLANT_ROLE):
            return self.plant != CAN_EMULATED
        return self.plant == CAN_EMULATED and len(msg.robots) == 1 and (
            key == self.keys.state_log(bridge_role(msg.robots[0])))

    def horizon(self) -> int | None:
        """The newest step the run can have reached now, on our clock: realtime from
        t = 0 (no node runs ahead of the wall clock), lockstep from the plant's newest
        signed tick (rows follow it by less than a batch: agents answer its samples).
        None with keys: every row is then its own node's (the MAC checked it), and a
        row that arrived ahead of a tick held up on another link is real (a peer's flood
        of forged replies once made the lockstep recorder refuse 31 real telemetry rows)."""
        if self.keyring is not None:
            return None
        t0 = self.run_t0 if self.run_t0 is not None else self.t0_mono
        if self.clock == "realtime":
            if t0 is None:
                return None
            return int((time.monotonic() - t0 + CLOCK_SKEW_S) / self.sc.dt) + 1
        return max(self.tick_k, 0) + 3 * TICK_EVERY

    def run_time(self) -> float | None:
        """Run time now: realtime from ``ctl/start``; lockstep from the plant's ticks."""
        if self.run_t0 is not None:
            return time.monotonic() - self.run_t0
        if self.t0_mono is not None:
            return time.monotonic() - self.t0_mono
        return None if self.progress_k < 0 else self.progress_k * self.sc.dt

    def refused(self) -> dict[str, int]:
        """What the listener refused, by reason (metrics.json ``messages.refused``)."""
        out = {f"launcher: {why}": n for why, n in self.unsigned.items()}
        if self.misfiled:
            out["launcher: report or state log on another node's key"] = self.misfiled
        if self.forged_reports:
            out["launcher: report not from a node of the run"] = self.forged_reports
        for why, n in self.collector.refused.items():
            out[f"launcher: {why}"] = n
        return out


class SpooledWire:
    """The plant's (on CAN: each bridge's) own record of the samples it sent and the
    replies it heard (deploy/runtime/wire_spool.py), decoded for the recorder: a source of
    ``McapRecorder.add_source``, read on the recorder's thread (with a codec of its own).
    A record that does not decode (none should: the plant wrote what it sent or had
    decoded) comes as None, which the recorder counts as failed."""

    def __init__(self, sc: Scenario, keys: Keys, reader: SpoolReader) -> None:
        self.keys, self.reader = keys, reader
        self.codec = Codec(sc.robot_ids)
        # key -> Keys.kind_of(key), parsed once: the plant's record holds its robots'
        # sample and reply keys only
        self._kinds: dict[str, tuple[type, int | None] | None] = {}

    def read(self) -> list[tuple[str, int, Any]]:
        out = []
        kinds = self._kinds
        for key, unix_ns, payload in self.reader.read():
            if key in kinds:
                found = kinds[key]
            else:
                found = self.keys.kind_of(key)
                if len(kinds) < MAX_KINDS_KEPT:
                    kinds[key] = found
            out.append((key, unix_ns, None if found is None else
                        self.codec.decode(found[0], payload, found[1])))
        return out

    def close(self) -> None:
        self.reader.close()
