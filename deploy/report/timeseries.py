"""The run's full time series: preallocated columns, saved as one ``.npz``.

Every column is a numpy array with time along axis 0 (robot along axis 1 where
there is one). ``numpy.load`` reads it; ``pandas.DataFrame`` takes any 1-D or
flattened column. Column names and units are listed in ``COLUMNS``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

BEHAVIOR_BITS = {"FDB": 1, "FOCB": 2, "FRCB": 4}

COLUMNS = {
    "t": "s, time of step k",
    "leader_q": "(k,3) leader pose [x, y, psi], m, m, rad",
    "leader_v": "(k,3) leader velocity",
    "q": "(k,n,3) robot pose at t_k",
    "q_dot": "(k,n,3) robot velocity at t_k",
    "q_d": "(k,n,3) CLIK reference q_d",
    "e": "(k,n,3) behavioral tracking error q - q_d",
    "s": "(k,n,3) sliding variable",
    "v_cmd": "(k,n,3) fused velocity command v_d",
    "torque": "(k,n,4) wheel torques sent, N m",
    "q0_hat": "(k,n,3) each agent's leader estimate (after its step)",
    "q_fd": "(k,n,3) desired formation pose from eq. (16)",
    "target": "(k,n,2) x_0 + rho_i with the true leader",
    "fdb_error": "(k,n) FDB task error |x - x_fd|, m",
    "active": "(k,n) active behaviors bitmask FDB=1 FOCB=2 FRCB=4",
    "order": "(k,n) active behaviors, highest priority first, as text",
    "nonfinite": "(k,n) 1 where the law gave NaN/Inf and torques were zeroed",
    "input_age": "(k,n) age of the agent's freshest leader information (or its state), s",
    "speed_factor": "(k,n) degradation speed factor: 1 full speed, 0 degraded speed",
    "safety_active": "(k,n) 1 where the safety filter changed the command (agents/safety_filter.py)",
    "safety_dv": "(k,n) |v_d after the filter - v_d before it|, m/s (0 where it did not act)",
    "safety_infeasible": "(k,n) 1 where no command met every barrier within the limits",
}
# An agent's float columns of one step, in this order, are views of one block
# (steps, n, AGENT_ROW_WIDTH) in an allocated series: a step's row is written in one
# assignment (TimeSeries.record_agent_row) instead of one per column
AGENT_FLOAT_COLUMNS = (("q_d", 3), ("e", 3), ("s", 3), ("v_cmd", 3), ("torque", 4),
                       ("q0_hat", 3), ("q_fd", 3), ("fdb_error", 1), ("input_age", 1),
                       ("speed_factor", 1), ("safety_dv", 1))
AGENT_ROW_WIDTH = sum(w for _, w in AGENT_FLOAT_COLUMNS)
# one row of the block as bytes (native order, no padding): packed in place by one C call
# (a numpy assignment of the tuple first discovers its shape and type, ~2x the cost)
_AGENT_ROW = struct.Struct(f"={AGENT_ROW_WIDTH}d")
# an active set (highest priority first) -> its bitmask and its text, built once each
_ORDERS: dict[tuple[str, ...], tuple[int, str]] = {}
# columns a series written before them lacks: loaded as "never happened"
_ADDED_LATER = ("safety_active", "safety_dv", "safety_infeasible")


@dataclass
class TimeSeries:
    t: np.ndarray
    leader_q: np.ndarray
    leader_v: np.ndarray
    q: np.ndarray
    q_dot: np.ndarray
    q_d: np.ndarray
    e: np.ndarray
    s: np.ndarray
    v_cmd: np.ndarray
    torque: np.ndarray
    q0_hat: np.ndarray
    q_fd: np.ndarray
    target: np.ndarray
    fdb_error: np.ndarray
    active: np.ndarray
    order: np.ndarray
    nonfinite: np.ndarray
    input_age: np.ndarray
    speed_factor: np.ndarray
    safety_active: np.ndarray
    safety_dv: np.ndarray
    safety_infeasible: np.ndarray
    # (steps, n): robot i's state of step k was heard (a distributed realtime run may miss
    # some: deploy/run/collector.py fills them forward); None: every one was (not a column)
    state_heard: np.ndarray | None = None

    @classmethod
    def allocate(cls, steps: int, n: int) -> TimeSeries:
        z = np.zeros
        block = z((steps, n, AGENT_ROW_WIDTH))
        views, j = {}, 0
        for name, width in AGENT_FLOAT_COLUMNS:
            views[name] = block[:, :, j] if width == 1 else block[:, :, j:j + width]
            j += width
        views["speed_factor"][:] = 1.0
        series = cls(
            t=z(steps), leader_q=z((steps, 3)), leader_v=z((steps, 3)),
            q=z((steps, n, 3)), q_dot=z((steps, n, 3)), target=z((steps, n, 2)),
            active=z((steps, n), dtype=np.int8), order=np.full((steps, n), "", dtype="<U16"),
            nonfinite=z((steps, n), dtype=np.int8), safety_active=z((steps, n), dtype=np.int8),
            safety_infeasible=z((steps, n), dtype=np.int8), **views,
        )
        series._agent_rows = block
        return series

    @property
    def steps(self) -> int:
        return len(self.t)

    def record_agent(self, k: int, i: int, out, agent) -> None:
        """Robot i's columns of step k from its agent's output (agents/core.py)."""
        f = out.safety
        acted = f is not None and f.active
        self.record_agent_row(
            k, i, (*out.q_d, *out.tracking_error, *out.sliding, *out.v_cmd, *out.torques,
                   *out.share.q0_hat, *out.q_fd, out.task_errors.get("FDB", np.nan),
                   out.input_age_s, out.speed_factor, f.dv if acted else 0.0),
            out.order, out.nonfinite, acted, acted and f.infeasible)

    def record_agent_row(self, k: int, i: int, floats: tuple, order: tuple[str, ...] | list[str],
                         nonfinite: bool, safety_active: bool, safety_infeasible: bool) -> None:
        """Robot i's columns of step k: ``floats`` the float columns in the order of
        ``AGENT_FLOAT_COLUMNS`` (AGENT_ROW_WIDTH values), ``order`` the active behaviors,
        highest priority first."""
        rows = getattr(self, "_agent_rows", None)
        if rows is not None:
            steps, n = rows.shape[:2]
            if not (0 <= k < steps and 0 <= i < n):
                raise IndexError(f"row ({k}, {i}) of a series of {steps} steps, {n} robots")
            _AGENT_ROW.pack_into(rows, (k * n + i) * _AGENT_ROW.size, *floats)
        else:  # a series built from its columns (loaded, or cut short)
            j = 0
            for name, width in AGENT_FLOAT_COLUMNS:
                getattr(self, name)[k, i] = floats[j] if width == 1 else floats[j:j + width]
                j += width
        key = tuple(order)
        bits_text = _ORDERS.get(key)
        if bits_text is None:
            bits_text = (sum(BEHAVIOR_BITS.get(b, 0) for b in key), ">".join(key))
            if len(_ORDERS) < 64:  # the behaviors' orders are few; anything else not kept
                _ORDERS[key] = bits_text
        self.active[k, i], self.order[k, i] = bits_text
        self.nonfinite[k, i] = nonfinite
        self.safety_active[k, i] = safety_active
        self.safety_infeasible[k, i] = safety_infeasible

    def record_world(self, k, t, q0, v0, q, q_dot, target=None) -> None:
        """Step k's world; the formation targets (deploy/report/targets.py) are filled in
        for the whole run after it, unless given here."""
        self.t[k] = t
        self.leader_q[k], self.leader_v[k] = q0, v0
        self.q[k], self.q_dot[k] = q, q_dot
        if target is not None:
            self.target[k] = target

    def save(self, path: Path) -> None:
        """Every column, uncompressed: deflate saved 30 % of the paper run's 26 MB and cost
        0.8 s, a third of the whole in-process run (docs/bench-history.md)."""
        np.savez(path, **{name: getattr(self, name) for name in COLUMNS})

    @classmethod
    def load(cls, path: Path) -> TimeSeries:
        with np.load(path) as data:
            cols = {name: data[name] for name in COLUMNS if name in data.files}
        missing = [name for name in COLUMNS if name not in cols]
        if missing and not set(missing) <= set(_ADDED_LATER):
            raise KeyError(f"{path}: no column {missing[0]!r}")
        shape = cols["nonfinite"].shape
        for name in missing:
            cols[name] = np.zeros(shape, np.int8 if name != "safety_dv" else float)
        return cls(**cols)
