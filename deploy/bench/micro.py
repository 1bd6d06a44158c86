"""In-process costs underneath every figure of ``omnifleet bench``: one agent's
math per step, one plant step per robot (pybullet and model), and the wire
codec (encode + validated decode) per message type.

Each function returns samples (one per repeat), each sample the median over many
calls, so a short hiccup of a shared machine moves one sample, not the figure.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import numpy as np

from agents.core import AgentCore
from agents.plugged import PluggedCore
from deploy.contract.scenario import Scenario
from deploy.contract.wire import (
    WIRE_VERSION,
    Codec,
    LeaderState,
    Reply,
    Sample,
    SensedBody,
    Share,
    StateLog,
    StateRow,
    Telemetry,
    TelemetryRow,
    encode,
)
from deploy.run.runner import run_in_process
from deploy.runtime.plants import make_plant


def agent_step_us(sc: Scenario, duration_s: float, repeats: int) -> list[float]:
    """Median wall time of an agent's step (µs), in closed loop on the model plant: the
    compiled paper law's (AgentCore.step), or the scenario's own law's with what wraps it
    (PluggedCore.step, agents/plugged.py)."""
    samples = []
    core_class = AgentCore if sc.law_name == "paper" else PluggedCore
    original = core_class.step
    for _ in range(repeats):
        times: list[int] = []

        def timed(self, *args, times=times, **kwargs):
            t0 = time.perf_counter_ns()
            out = original(self, *args, **kwargs)
            times.append(time.perf_counter_ns() - t0)
            return out

        core_class.step = timed  # type: ignore[method-assign]
        try:
            run_in_process(sc, "model", duration_s)
        finally:
            core_class.step = original  # type: ignore[method-assign]
        samples.append(statistics.median(times) / 1e3)
    return samples


def _step_times(sc: Scenario, duration_s: float) -> tuple[list[int], list[bool]]:
    """Each AgentCore.step's wall time (ns) in closed loop on the model plant, and whether
    the safety filter changed that step's command."""
    original = AgentCore.step
    times: list[int] = []
    active: list[bool] = []

    def timed(self, *args, **kwargs):
        t0 = time.perf_counter_ns()
        out = original(self, *args, **kwargs)
        times.append(time.perf_counter_ns() - t0)
        active.append(out.safety is not None and out.safety.active)
        return out

    AgentCore.step = timed  # type: ignore[method-assign]
    try:
        run_in_process(sc, "model", duration_s)
    finally:
        AgentCore.step = original  # type: ignore[method-assign]
    return times, active


def safety_filter_us(sc: Scenario, duration_s: float, repeats: int
                     ) -> tuple[list[float], list[float]]:
    """What the safety filter adds to an agent step (µs; it runs inside the compiled law,
    agents/law_kernel.pyx, so it is timed as the step with it on minus the step with it
    off, back to back), in closed loop on the model plant: over every step, and over the
    steps where it changed the command (empty when it never did)."""
    from dataclasses import replace

    from msgspec.structs import replace as struct_replace

    off = replace(sc, spec=struct_replace(sc.spec, safety=struct_replace(sc.spec.safety,
                                                                        filter=False)))
    every, acting = [], []
    for _ in range(repeats):
        on_times, active = _step_times(sc, duration_s)
        off_times, _ = _step_times(off, duration_s)
        base = statistics.median(off_times)
        # a difference of medians: below the timer's noise it can come out negative, and a
        # cost is never below nothing
        every.append(max(0.0, (statistics.median(on_times) - base) / 1e3))
        acted = [t for t, a in zip(on_times, active, strict=True) if a]
        if acted:
            acting.append(max(0.0, (statistics.median(acted) - base) / 1e3))
    return every, acting


def plant_step_us_per_robot(sc: Scenario, kind: str, steps: int, repeats: int) -> list[float]:
    """Median wall time of one plant step divided by the number of robots (µs)."""
    rng = np.random.default_rng(1)
    torques = rng.uniform(-0.01, 0.01, size=(steps, sc.n, 4))
    v_cmd = np.zeros((sc.n, 3))
    samples = []
    for _ in range(repeats):
        plant = make_plant(sc, kind)
        try:
            times = []
            for k in range(steps):
                t0 = time.perf_counter_ns()
                plant.step(k * sc.dt, sc.dt, torques[k], v_cmd)
                times.append(time.perf_counter_ns() - t0)
        finally:
            plant.close()
        samples.append(statistics.median(times) / 1e3 / sc.n)
    return samples


BATCH = 32  # rows of a batched message here (leader states, telemetry, state log)


def sample_messages(sc: Scenario) -> dict[str, object]:
    """One realistic message of each type of wire v2: the two the control loop sends
    per robot and step (Sample, Reply), and the batched ones (``BATCH`` steps each)."""
    rid = sc.robot_ids[0]
    v3, v4 = (1.0, 2.0, 0.5), (0.1, -0.2, 0.3, -0.4)
    body = SensedBody(sc.robot_ids[-1], (1.0, 2.0), (0.5, 0.5), 0.5)
    obstacle = SensedBody(-1, (3.0, 1.0), (0.0, 0.0), 0.0)
    row = TelemetryRow(k=7, t=0.007, q_d=v3, e=v3, s=v3, v_cmd=v3, torques=v4, q0_hat=v3,
                       q_fd=v3, fdb_error=0.1, order="FOCB>FRCB>FDB", nonfinite=False)
    n = sc.n
    return {
        "Sample": Sample(WIRE_VERSION, 0, 7, 123, robot=rid, k=7, t=0.007, q=v3, q_dot=v3,
                         robots=[body, body], obstacles=[obstacle, obstacle]),
        "Reply": Reply(WIRE_VERSION, rid, 7, 123, robot=rid, k=7, t=0.007, torques=v4,
                       v_cmd=v3, state_seq=7, state_stamp_ns=123,
                       share=Share(v3, v3, v3, v3, v3, v3)),
        "LeaderState": LeaderState(WIRE_VERSION, 0, 7, 123, k=7, t=0.007, q=[v3] * BATCH,
                                   q_dot=[v3] * BATCH),
        "Telemetry": Telemetry(WIRE_VERSION, rid, 7, 123, robot=rid, rows=[row] * BATCH),
        "StateLog": StateLog(WIRE_VERSION, 0, 7, 123, robots=list(sc.robot_ids), rows=[
            StateRow(7, 0.007, [v3] * n, [v3] * n, [False] * n)] * BATCH),
    }


def codec_us(sc: Scenario, calls: int, repeats: int) -> dict[str, list[float]]:
    """Median µs of encode + validated decode, per message type."""
    codec = Codec(sc.robot_ids)
    out: dict[str, list[float]] = {}
    for name, msg in sample_messages(sc).items():
        kind = type(msg)
        robot = getattr(msg, "robot", None)
        out[name] = [_median_us(lambda m=msg, k=kind, r=robot: codec.decode(k, encode(m), r), calls)
                     for _ in range(repeats)]
        assert codec.decode(kind, encode(msg), robot) == msg  # a benchmark of a codec that works
    return out


def _median_us(fn: Callable[[], object], calls: int) -> float:
    times = []
    for _ in range(calls):
        t0 = time.perf_counter_ns()
        fn()
        times.append(time.perf_counter_ns() - t0)
    return statistics.median(times) / 1e3


def defence_us(sc: Scenario, calls: int, repeats: int) -> dict[str, list[float]]:
    """What the defences against forged messages cost (µs), in the form the nodes run
    them (docs/hardening.md):

    - ``guard_message``: one received control-path message judged against the
      receiver's own clock and its stream (``OwnClock.refusal`` + ``StepGuard.admit``,
      as an agent does for its sample and each neighbour's share);
    - ``guards_per_agent_step``: every guard an agent of ``sc`` runs in one step (its
      sample and the shares of its most-connected robot's neighbours);
    - ``mac_open``: checking one received Sample's envelope (``Keyring.open``: its tag
      under the key its sender shares with this node, on the raw bytes);
    - ``mac_seal_reply``: sealing one Reply for every receiver of it (the plant, the
      launcher and the agents that listen to it), for the robot with most listeners;
    - ``mac_per_agent_step``: every MAC one agent step costs, for the most-connected
      robot: its sample and its neighbours' shares checked, its reply sealed."""
    from deploy.contract.keyring import Keyring, keyring_text, new_master
    from deploy.contract.wire import LAUNCHER_ROLE, Keys, agent_role, run_roles
    from deploy.runtime.step_guard import OwnClock, StepGuard

    neighbours = max(len(sc.agent_config(i).neighbours) for i in range(sc.n))
    out: dict[str, list[float]] = {"guard_message": [], "guards_per_agent_step": [],
                                   "mac_open": [], "mac_seal_reply": [],
                                   "mac_per_agent_step": []}
    keys, master = Keys(sc.name), new_master()
    roles = [*run_roles(sc.robot_ids), LAUNCHER_ROLE]
    rings = {r: Keyring.from_text(keyring_text(master, sc.name, r, roles), "bench", r, sc, keys)
             for r in roles}
    msgs = sample_messages(sc)
    sample, reply = encode(msgs["Sample"]), encode(msgs["Reply"])
    # the robot whose step costs most MACs: most neighbours heard plus listeners tagged
    i = max(range(sc.n), key=lambda i: len(sc.agent_config(i).neighbours) + len(sc.listeners(i)))
    rid = sc.robot_ids[i]
    me = rings[agent_role(rid)]
    heard = [(rings["plant"].seal(sample, keys.sample(rid)), keys.sample(rid))]
    heard += [(rings[agent_role(j)].seal(reply, keys.cmd(j)), keys.cmd(j))
              for j, _w in sc.agent_config(i).neighbours]
    assert all(me.open(d, k)[0] is not None for d, k in heard)  # a benchmark of checks that pass
    sealer = max((rings[agent_role(r)] for r in sc.robot_ids),
                 key=lambda k: len(k.receivers[keys.cmd(int(k.role.split("-")[1]))]))
    sealer_key = keys.cmd(int(sealer.role.split("-")[1]))
    for _ in range(repeats):
        own = OwnClock(sc.dt, deadline_s=2.0, answered_at=time.monotonic())
        streams = [StepGuard(newest=-1) for _ in range(1 + neighbours)]
        k = [0]

        def one(streams=streams, own=own, k=k) -> None:
            now = time.monotonic()
            own.answer(k[0] - 1, now)
            for g in streams:
                if own.refusal(k[0], k[0], now) is None:
                    g.admit(k[0])
            k[0] += 1

        out["guards_per_agent_step"].append(_median_us(one, calls))
        single = StepGuard(newest=-1)
        k1 = [0]

        def message(g=single, own=own, k=k1) -> None:
            own.answer(k[0] - 1, 0.0)
            if own.refusal(k[0], k[0], time.monotonic()) is None:
                g.admit(k[0])
            k[0] += 1

        out["guard_message"].append(_median_us(message, calls))
        data, key = heard[0]
        out["mac_open"].append(_median_us(lambda d=data, k=key: me.open(d, k), calls))
        out["mac_seal_reply"].append(_median_us(
            lambda: sealer.seal(reply, sealer_key), calls))

        def step(heard=heard) -> None:
            for d, k in heard:
                me.open(d, k)
            me.seal(reply, keys.cmd(rid))

        out["mac_per_agent_step"].append(_median_us(step, calls))
    return out


def _captured_core(sc: Scenario, at_s: float) -> tuple[AgentCore, tuple, dict]:
    """An agent's core and the inputs of its step at ``at_s`` of a closed-loop run in
    process (the first step the run makes at or after it)."""
    original = AgentCore.step
    captured: dict[str, object] = {}

    def hook(self, *args, **kwargs):
        if "core" not in captured and args[0] >= at_s:
            captured.update(core=self, args=args, kwargs=kwargs)
        return original(self, *args, **kwargs)

    AgentCore.step = hook  # type: ignore[method-assign]
    try:
        run_in_process(sc, "model", at_s + 0.01)
    finally:
        AgentCore.step = original  # type: ignore[method-assign]
    return captured["core"], captured["args"], captured["kwargs"]  # type: ignore[return-value]


def cold_step_pieces_us(sc: Scenario, calls: int) -> dict[str, dict[str, float]]:
    """The CPU time (µs, medians over ``calls``) of the essential pieces of one realtime
    agent step, in this process, as the datagram path runs them (its connections are
    authenticated at their hello: no tag a frame, deploy/runtime/transport.py): the
    inputs of the most-connected robot received (its sample and its neighbours'
    shares, unix datagrams), decoded with validation, the paper law's step
    (AgentCore.step), the reply encoded and sent to as many receivers; and the bare
    wake of a 1 ms wait. Apart (``law kernel hot`` / ``cold``): the compiled law's own step
    (Law.step on prepared inputs, AgentCore.kernel_call) after the same wait: what a step
    compiled whole could not go below.

    ``hot``: the pieces back to back, as a loop that never sleeps runs them; ``cold``:
    each round after a 1 ms wait, as a realtime process at 1 kHz runs them (the caches
    and the branch predictors hold whatever ran meanwhile). The difference is what a
    process pays for sleeping between its steps; the sum of ``cold`` is the floor under
    any realtime agent step written in this runtime's Python, before its look-ahead,
    guards, tables and telemetry (docs/bench.md, "The realtime budget")."""
    import select
    import socket

    core, args, kwargs = _captured_core(sc, 0.5)
    kernel = core.kernel_call(*args[:7], **{k: v for k, v in kwargs.items()
                                            if k in ("obstacles", "robots")})
    msgs, codec = sample_messages(sc), Codec(sc.robot_ids)
    sample_msg, reply_msg = msgs["Sample"], msgs["Reply"]
    i = max(range(sc.n), key=lambda i: len(sc.agent_config(i).neighbours))
    frames = [encode(sample_msg)] + [encode(reply_msg)] * len(sc.agent_config(i).neighbours)
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    tick = time.thread_time_ns

    def arrive() -> None:  # the inputs sent by their senders (not this step's cost)
        for data in frames:
            a.send(data)

    def pieces(times: dict[str, list[int]]) -> None:
        t = tick()
        heard = [b.recv(65536) for _ in frames]
        t1 = tick()
        codec.decode(Sample, heard[0], sample_msg.robot)
        for body in heard[1:]:
            codec.decode(Reply, body, reply_msg.robot)
        t2 = tick()
        out = core.step(*args, **kwargs)
        t3 = tick()
        data = encode(reply_msg)
        t4 = tick()
        for _ in frames:  # to the plant and the listening agents (paper: three)
            b.send(data)
        t5 = tick()
        for _ in frames:  # their receiving ends (not this step's cost)
            a.recv(65536)
        if out.nonfinite:
            raise RuntimeError("the law diverged on its repeated step: the figure would time "
                               "its recovery")
        for name, ns in (("receive", t1 - t), ("decode", t2 - t1), ("law step", t3 - t2),
                         ("encode", t4 - t3), ("send", t5 - t4)):
            times.setdefault(name, []).append(ns)

    def kernel_alone(times: dict[str, list[int]]) -> None:  # not one of the pieces
        t = tick()
        kernel()
        times.setdefault("kernel", []).append(tick() - t)

    out: dict[str, dict[str, float]] = {}
    try:
        for mode in ("hot", "cold"):
            times: dict[str, list[int]] = {}
            arrive()
            pieces({})  # imports and first-call costs out of the figures
            for _ in range(calls):
                arrive()
                if mode == "cold":
                    t = tick()
                    select.select((), (), (), 0.001)
                    times.setdefault("wake", []).append(tick() - t)
                pieces(times)
            out[mode] = {name: statistics.median(v) / 1e3 for name, v in times.items()}
            alone: dict[str, list[int]] = {}
            kernel()
            for _ in range(calls):  # the same wait, then the compiled law's step alone
                if mode == "cold":
                    select.select((), (), (), 0.001)
                kernel_alone(alone)
            out["law kernel " + mode] = {"kernel": statistics.median(alone["kernel"]) / 1e3}
    finally:
        a.close()
        b.close()
    return out
