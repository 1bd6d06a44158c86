"""``omnifleet record``: the launcher's recorder without the launcher, for a fleet
whose nodes run on several machines.

It joins the fleet as role ``launcher`` (so nodes started with
``--wait-recorder`` wait for it and the recording misses nothing), hears the
fleet's keys, and when the plant ends the run writes the same folder as
``omnifleet run``: ``metrics.json``, ``timeseries.npz``, ``recording.mcap``,
figures. It also writes what liveliness told it: every role that disappeared
and reappeared, with wall-clock times (``liveliness`` in metrics.json).
"""

from __future__ import annotations

import sys
import time
from typing import Any

from deploy.contract.keyring import Keyring
from deploy.contract.scenario import Scenario
from deploy.contract.wire import LAUNCHER_ROLE, run_roles
from deploy.run.launcher import Interrupted, LaunchOptions, make_observer, observing
from deploy.run.run_figures import run_figures
from deploy.runtime.node_runtime import StopFlag
from deploy.runtime.transport import Node, zenoh_config


class Recorder:
    """The launcher's :class:`Observer` without its plan or supervisor: the nodes run
    elsewhere, and this peer joins them through ``listen``/``connect`` endpoints or a
    zenoh configuration file (TLS and access control across hosts, deploy/fleet/)."""

    def __init__(self, sc: Scenario, opts: LaunchOptions, zenoh_file: str | None = None,
                 listen: list[str] | None = None, connect: list[str] | None = None,
                 keyring: Keyring | None = None) -> None:
        self.sc, self.opts = sc, opts
        self.zenoh_file, self.listen, self.connect = zenoh_file, listen, connect
        # the nodes run elsewhere, started by hand or by systemd: with the launcher's
        # keyring of `omnifleet deploy certs` (--keys) what they tag for it is checked;
        # without, the ACL alone says who may publish what (deploy/fleet/acl.py)
        self.keyring = keyring
        self.observer = make_observer(sc, opts, keyring)
        self.observer.on_report = self._on_report
        self.stop = StopFlag()
        self.reported_ns: dict[str, int] = {}  # role -> when its report arrived (wall, ns)

    def _on_report(self, role: str) -> None:
        # a node reports as it leaves, on the same link as its token: a token that goes
        # after the report is a departure, not a loss
        self.reported_ns.setdefault(role, time.time_ns())

    def run(self, progress=None) -> dict[str, Any]:
        o, obs = self.opts, self.observer
        o.out.mkdir(parents=True, exist_ok=True)
        node = Node(LAUNCHER_ROLE, obs.keys, obs.codec,
                    zenoh_config(self.zenoh_file, self.listen, self.connect),
                    keyring=self.keyring)
        zid = node.zid
        roles = run_roles(self.sc.robot_ids)
        with observing(obs, o, node, self.stop):
            missing = node.wait_for_roles(roles, "ready", o.startup_timeout_s, self.stop)
            if self.stop():
                raise Interrupted(self.stop.reason)
            if missing:
                raise TimeoutError(f"not ready after {o.startup_timeout_s:.0f} s: "
                                   f"{', '.join(sorted(missing))}")
            start = time.perf_counter()
            # the run ends with the plant's ``end``, or early with a genuine stop or estop
            # (no ``end`` follows one: the nodes leave, each sending its report)
            while not obs.ended and obs.stopped_by is None:
                if self.stop():
                    raise Interrupted(self.stop.reason)
                if progress is not None:
                    progress(obs.progress_k + 1, obs.steps)
                node.mailbox.wait_until(
                    lambda: obs.ended or obs.stopped_by is not None or self.stop(), 0.1)
            wall = time.perf_counter() - start
            if progress is not None:  # the steps the plant says it simulated, no more
                progress(obs.progress_k + 1, obs.steps)
            # every node reports as it ends; wait for those still alive
            node.mailbox.wait_until(
                lambda: set(obs.collector.reports) >= set(roles) or self.stop(), 10.0)
            closing_ns = time.time_ns()  # tokens seen to go after this: our own closing
        out = run_figures(obs, [], zid, wall, expected_roles=list(roles))
        out["processes"] += [  # the nodes ran elsewhere: what each reported
            {"role": r.role, "robot": None if r.robot < 0 else r.robot, "pid": None,
             "peak_rss_mb": round(r.peak_rss_kb / 1024.0, 1) if r.peak_rss_kb else None,
             "exit_code": None, "reported": True, "steps": r.steps, "sent": r.sent,
             "late": r.late, "received": dict(r.received)}
            for r in sorted(obs.collector.reports.values(), key=lambda r: r.role)]
        out["liveliness"] = liveliness_summary(
            [e for e in node.peer_events if e[0] < min(closing_ns, obs.end_unix_ns or closing_ns)
             and e[1] != LAUNCHER_ROLE],
            self.reported_ns)
        return out


def liveliness_summary(events: list[tuple[int, str, bool]],
                       reported_ns: dict[str, int]) -> dict[str, Any]:
    """Per role: how often its token went away during the run, and when it went
    and came back (wall clock, ns), from the node's liveliness events (time,
    role, alive), those after the run's end already left out. A token that goes
    after the role's report arrived is the node leaving: not counted either. (A
    node that leaves before the recorder has read ``end`` — a recorder behind on
    traffic — is still counted once, with no return.)"""
    out: dict[str, Any] = {}
    for t, role, alive in events:
        if t >= reported_ns.get(role, 1 << 62):
            continue
        r = out.setdefault(role, {"lost": 0, "lost_at_unix_ns": [], "back_at_unix_ns": []})
        if not alive:
            r["lost"] += 1
            r["lost_at_unix_ns"].append(t)
        elif r["lost"]:  # a return after a loss (the first appearance is not one)
            r["back_at_unix_ns"].append(t)
    return {role: r for role, r in out.items() if r["lost"]}


def log_progress(every_s: float = 1.0):
    """Progress as log lines (``record: step K/N``), at most one per ``every_s``:
    a recorder under systemd or in a test has no terminal."""
    last = [0.0]

    def update(done: int, total: int) -> None:
        now = time.monotonic()
        if now - last[0] >= every_s or done >= total:
            last[0] = now
            print(f"record: step {done}/{total}", file=sys.stderr, flush=True)
    return update









