"""What the drive emulator's ground-truth files say of a CAN run: how far its physics
lagged the wall clock, and the frames its faults dropped or corrupted."""

from __future__ import annotations

from pathlib import Path


def emulator_lag_ms(truth_files: dict[int, Path]) -> dict[str, float | None]:
    """How far the driver emulator's physics was behind the wall clock during the
    run (sampled every 10 ms; every robot's truth file carries the same log)."""
    import numpy as np

    for path in truth_files.values():
        try:
            with np.load(path) as d:
                lag = np.asarray(d["lag_s"], float) * 1e3
        except (OSError, KeyError, ValueError):
            continue
        if len(lag):
            return {"p50": float(np.median(lag)), "p99": float(np.percentile(lag, 99)),
                    "max": float(lag.max())}
    return {"p50": None, "p99": None, "max": None}


def can_fault_counts(truth_files: dict[int, Path]) -> dict[str, dict[str, int]]:
    """Frames each robot's driver emulator lost or corrupted (the plan's [can])."""
    import numpy as np

    out = {}
    for robot, path in truth_files.items():
        try:
            with np.load(path) as d:
                out[f"robot-{robot}"] = {"dropped": int(d["dropped_by_fault"]),
                                         "corrupted": int(d["corrupted_by_fault"])}
        except (OSError, KeyError, ValueError):
            out[f"robot-{robot}"] = {"dropped": -1, "corrupted": -1}  # no truth file: unknown
    return out
