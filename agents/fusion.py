"""Null-space priority fusion (26) and the behavior supervisor (erratum 8).

    v_d = v_1 + N_1 (v_2 + N_2 v_3),   N_k = I - J_k^+ J_k

The supervisor orders the behaviors by the configured priority (default
FOCB > FRCB > FDB). An inactive behavior contributes zero velocity and an
identity projector, which is the same as leaving it out of the chain.

When an avoidance behavior (FOCB, FRCB) takes part is the scenario's choice:
* ``inside``: whenever the body is inside its safety threshold (as printed, and
  as the authors' code does for FOCB);
* ``approaching`` (set-based, after Moe et al., "Set-based tasks within the
  singularity-robust multiple task-priority inverse kinematics framework"):
  inside the threshold AND the velocity fused without it would bring the body
  closer (J_1 v < 0). ``inside`` removes every radial motion, moving away
  included; two robots sent to one spot (the paper's narrow passage S =
  diag(1, 0) does exactly that to robots 2 and 3) then block each other in a
  column while the formation moves on. ``approaching`` lets the front robot go.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from agents.behaviors import BehaviorOutput, Task, pinv_task_jacobian
from agents.law_kernel import fuse_of, supervise_of
from agents.signals import Vec3

DEFAULT_PRIORITY = ("FOCB", "FRCB", "FDB")


def null_space_projector(J: np.ndarray) -> np.ndarray:
    return np.eye(J.shape[1]) - pinv_task_jacobian(J) @ J


def fuse(ordered: Sequence[BehaviorOutput]) -> np.ndarray:
    """Eq. (26) for any number of behaviors, highest priority first."""
    v = np.zeros(3)
    for b in reversed([b for b in ordered if b.active]):
        v = b.velocity + null_space_projector(b.jacobian) @ v
    return v


AVOIDANCE = ("FOCB", "FRCB")


def supervise(ordered: Sequence[BehaviorOutput], engage: str,
              limit: Callable[[np.ndarray], np.ndarray] | None = None) -> list[BehaviorOutput]:
    """The behaviors that take part in (26), highest priority first. ``limit``: what
    the agent does to the fused velocity before commanding it; "approaching" judges
    J v < 0 on the limited velocity (see :func:`supervise_tasks`)."""
    lim = limit or (lambda v: v)
    active = [b for b in ordered if b.active]
    if engage == "inside":
        return active
    if engage != "approaching":
        raise ValueError(f"unknown avoidance engage mode {engage!r}")
    engaged: set[tuple[str, int]] = set()
    while True:  # `engaged` only grows, at most once per avoidance behavior and body
        chain = [b for b in active if b.name not in AVOIDANCE or (b.name, b.body) in engaged]
        fused = fuse(chain)
        v = lim(fused)
        now = engaged | {
            (b.name, b.body) for b in active
            if b.name in AVOIDANCE and min(float(b.jacobian[0] @ fused), float(b.jacobian[0] @ v)) < 0.0
        }
        if now == engaged:
            return chain
        engaged = now


def order_by_priority(
    outputs: Sequence[BehaviorOutput], priority: Sequence[str]
) -> list[BehaviorOutput]:
    rank = {name: k for k, name in enumerate(priority)}
    return sorted(outputs, key=lambda b: rank[b.name])


def saturate_velocity(v: np.ndarray, max_speed: float, max_yaw_rate: float) -> np.ndarray:
    """Explicit scenario limit on the fused command: |v_xy| <= max_speed, |w| <= max_yaw_rate."""
    out = v.copy()
    speed = float(np.hypot(v[0], v[1]))
    if speed > max_speed:
        out[:2] *= max_speed / speed
    out[2] = float(np.clip(v[2], -max_yaw_rate, max_yaw_rate))
    return out


# --- the compiled law's fusion on reduced tasks (agents/law_kernel.pyx;
# tests/unit/test_hot_path.py checks it against supervise and fuse above) ----------------


def fuse_tasks(ordered: Sequence[Task]) -> Vec3:
    """:func:`fuse` for active tasks, highest priority first: eq. (26)."""
    return fuse_of(list(ordered))


def supervise_tasks(ordered: Sequence[Task], engage: str) -> tuple[list[Task], Vec3]:
    """:func:`supervise` for active tasks (no limits), and the velocity of the chain it
    returns. "approaching" engages a task when the fused velocity closes on its body,
    J v < 0; each avoidance task guards one body (``Task.body``)."""
    tasks = list(ordered)
    chain, v = supervise_of(tasks, engage)
    return [tasks[i] for i in chain], v
