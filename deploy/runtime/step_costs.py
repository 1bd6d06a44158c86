"""Where a node's run loop spends its time, part by part (docs/bench-history.md, "The realtime
budget"): the figures behind each process's CPU per step.

A node adds the wall time of each part of its steps as it goes (``time.perf_counter_ns``,
~65 ns a reading in this VM; a part's handful of readings a step cost ~1 µs in all), and
reports the totals with its loop's CPU time (``NodeReport.step_costs_ns``, ``cpu_s``). On a
node that is not put off its core in the middle of a step, a part's wall time is its CPU
time; what the parts do not cover (the kernel's wake-up, the context switches, the cold
caches of a process that slept, the loop's own bookkeeping) is the process's CPU time less
their sum, reported as ``wake and the rest``.

The parts:

- ``receive``: reading frames off the sockets and finding their handler (system calls,
  the datagram path's dispatch), less what follows;
- ``mac``: checking the envelope of what is heard and sealing what is sent
  (deploy/contract/mac.py);
- ``decode``: decoding and validating what is heard (deploy/contract/wire.py);
- ``handle``: what the node does with a message it heard (step guards, tables);
- ``law``: the agent's step and look-ahead (the compiled kernel and its Python face), the
  plant's integration and perception, a bridge's odometry and command gate;
- ``encode``: building and encoding what is sent (and checking its numbers);
- ``send``: handing it to the sockets (system calls), zenoh's put for what goes there;
- ``telemetry``: telemetry rows and state logs for observers;
- ``can``: a bridge's CAN frames: encoding, sending, receiving and decoding them.
"""

from __future__ import annotations

from time import perf_counter_ns

PARTS = ("receive", "mac", "decode", "handle", "law", "encode", "send", "telemetry", "can")
RECEIVE, MAC, DECODE, HANDLE, LAW, ENCODE, SEND, TELEMETRY, CAN = range(len(PARTS))
REST = "wake and the rest"  # the process's CPU time less the parts (see above)

now_ns = perf_counter_ns  # the clock every part is read on


class StepCosts:
    """Running totals of each part's time, ns (indexed by the constants above)."""

    __slots__ = ("ns",)

    def __init__(self) -> None:
        self.ns = [0] * len(PARTS)

    def add(self, part: int, since_ns: int) -> int:
        """Add the time since ``since_ns`` to ``part``; returns now (the next part's start)."""
        t = perf_counter_ns()
        self.ns[part] += t - since_ns
        return t

    def take_from(self, part: int, ns: int) -> None:
        """Move ``ns`` out of ``part`` (a part measured inside another's span)."""
        self.ns[part] -= ns

    def mark(self) -> tuple[int, int, int]:
        """What publishing has cost so far (encode, MAC, send): see :meth:`charge`."""
        ns = self.ns
        return ns[ENCODE], ns[MAC], ns[SEND]

    def charge(self, part: int, since_ns: int, mark: tuple[int, int, int]) -> None:
        """Count all the time since ``since_ns`` as ``part``, what publishing cost meanwhile
        (since ``mark``) included: telemetry and a bridge's state log are sent off the
        control path, and counted as what they are for."""
        ns = self.ns
        ns[ENCODE], ns[MAC], ns[SEND] = mark
        ns[part] += perf_counter_ns() - since_ns

    def totals(self) -> dict[str, int]:
        """Each part's total, ns, by name (the report's ``step_costs_ns``)."""
        return {name: max(0, v) for name, v in zip(PARTS, self.ns, strict=True)}


def per_step_us(totals_ns: dict[str, int], cpu_s: float, steps: int) -> dict[str, float]:
    """Each part's µs per step, and ``REST``: the loop's CPU time per step less the parts
    (clamped at 0: a part measured while the process was off its core counts wall time)."""
    n = max(1, steps)
    parts = {k: v / n / 1e3 for k, v in totals_ns.items()}
    parts[REST] = max(0.0, cpu_s / n * 1e6 - sum(parts.values()))
    return parts
