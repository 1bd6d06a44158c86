"""Fault plans: the schema of ``--faults PLAN.toml`` and its validation (docs/faults.md).

A plan says what goes wrong in a run, per directed edge of the run's graph and
per process, reproducibly from one seed::

    seed = 7
    [defaults]                       # every edge (optional)
    drop = 0.1
    [[link]]                         # the edges it names (``*`` matches any role)
    from = "leader"
    to = "agent-1"
    partitions = [[8.0, 10.0]]       # [start_s, end_s): nothing passes
    burst = { p_enter = 0.02, p_exit = 0.3 }   # Gilbert-Elliott losses
    delay_s = 0.01
    [[kill]]
    process = "agent-2"
    at_s = 10.0
    restart_after_s = 4.0            # optional
    [[kill]]
    process = "agent-3"
    at_s = 5.0
    pause_s = 2.0                    # SIGSTOP, SIGCONT 2 s later (not with restart_after_s)
    [can]                            # --plant can-emulated: the buses' frames
    frame_loss = 0.01
    corrupt = 0.001

The edges of a run: ``leader -> agent-i`` (b_i != 0), ``plant -> agent-i``
(state and perception), ``agent-i -> plant`` (wheel command) and ``agent-j ->
agent-i`` (a_ij != 0). A ``[[link]]`` that matches none of them is an error,
so a typo cannot silently test nothing. An edge takes the fields of
``[defaults]``, then of every matching ``[[link]]`` in file order (later
entries override field by field).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fnmatch import fnmatchcase
from pathlib import Path

import msgspec

from deploy.contract.scenario import Scenario
from deploy.contract.schema_hints import readable
from deploy.contract.wire import LEADER_ROLE, PLANT_ROLE, agent_role


class FaultPlanError(ValueError):
    """A fault plan that cannot be used (exit code 2 at the CLI); names file and key."""


class _S(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    pass


class Burst(_S, kw_only=True):
    """Gilbert-Elliott: a good and a bad state; per message, move good -> bad
    with ``p_enter``, bad -> good with ``p_exit``; lose with ``loss_bad`` in the
    bad state and ``loss_good`` in the good one."""

    p_enter: float
    p_exit: float
    loss_bad: float = 1.0
    loss_good: float = 0.0


class LinkFields(_S, kw_only=True):
    drop: float | None = None
    burst: Burst | None = None
    delay_s: float | None = None
    partitions: list[list[float]] | None = None


class LinkEntry(LinkFields, kw_only=True):
    from_: str = msgspec.field(name="from", default="*")
    to: str = "*"


class Kill(_S, kw_only=True):
    process: str
    at_s: float
    restart_after_s: float | None = None
    pause_s: float | None = None  # SIGSTOP instead of SIGKILL, SIGCONT after this long


class CanFaults(_S, kw_only=True):
    frame_loss: float = 0.0
    corrupt: float = 0.0


class FaultPlanFile(_S, kw_only=True):
    seed: int = 0
    description: str = ""
    defaults: LinkFields = msgspec.field(default_factory=LinkFields)
    link: list[LinkEntry] = msgspec.field(default_factory=list)
    kill: list[Kill] = msgspec.field(default_factory=list)
    can: CanFaults = msgspec.field(default_factory=CanFaults)


@dataclass(frozen=True)
class LinkFaults:
    """What happens on one directed edge (all fields resolved)."""

    drop: float = 0.0
    burst: Burst | None = None
    delay_s: float = 0.0
    partitions: tuple[tuple[float, float], ...] = ()

    @property
    def perfect(self) -> bool:
        return self.drop == 0.0 and self.burst is None and self.delay_s == 0.0 \
            and not self.partitions


@dataclass(frozen=True)
class FaultPlan:
    """A validated plan for one scenario: the faults of every edge that has any."""

    path: str
    seed: int
    links: dict[tuple[str, str], LinkFaults]  # (from role, to role) -> faults
    kills: tuple[Kill, ...]
    can: CanFaults

    def link(self, src: str, dst: str) -> LinkFaults | None:
        return self.links.get((src, dst))

    @property
    def empty(self) -> bool:
        return not self.links and not self.kills and self.can.frame_loss == 0.0 \
            and self.can.corrupt == 0.0


def run_edges(sc: Scenario) -> list[tuple[str, str]]:
    """Every directed edge a run's messages travel, as (sender role, receiver role)."""
    edges: list[tuple[str, str]] = []
    ids = sc.robot_ids
    for i, rid in enumerate(ids):
        me = agent_role(rid)
        if sc.leader_weights[i] != 0.0:
            edges.append((LEADER_ROLE, me))
        edges.append((PLANT_ROLE, me))
        edges.append((me, PLANT_ROLE))
        edges += [(agent_role(ids[j]), me) for j in range(sc.n)
                  if j != i and sc.adjacency[i, j] != 0.0]
    return edges


def edge_name(src: str, dst: str) -> str:
    return f"{src}->{dst}"


def _fail(path: str, key: str, msg: str) -> FaultPlanError:
    return FaultPlanError(f"{path}: `{key}`: {msg}")


def _probability(path: str, key: str, p: float) -> None:
    if not (0.0 <= p <= 1.0):  # also false for NaN
        raise _fail(path, key, f"must be a probability in [0, 1], got {p}")


def _check_fields(path: str, key: str, f: LinkFields, duration_s: float) -> None:
    if f.drop is not None:
        _probability(path, f"{key}.drop", f.drop)
    if f.burst is not None:
        for name in ("p_enter", "p_exit", "loss_bad", "loss_good"):
            _probability(path, f"{key}.burst.{name}", getattr(f.burst, name))
        if f.burst.p_exit == 0.0:
            raise _fail(path, f"{key}.burst.p_exit", "0 would never leave the bad state; "
                        "use partitions for a link that stays down")
    if f.delay_s is not None and not (0.0 <= f.delay_s <= 10.0):
        raise _fail(path, f"{key}.delay_s", f"must be in [0, 10] s, got {f.delay_s}")
    for k, w in enumerate(f.partitions or ()):
        if len(w) != 2 or not all(math.isfinite(x) for x in w) or not (0.0 <= w[0] < w[1]):
            raise _fail(path, f"{key}.partitions[{k}]",
                        f"must be [start_s, end_s] with 0 <= start < end, got {w}")
        if w[0] >= duration_s:
            raise _fail(path, f"{key}.partitions[{k}]",
                        f"starts at {w[0]} s, after the run ends ({duration_s} s)")


def _merge(base: LinkFaults, f: LinkFields) -> LinkFaults:
    return LinkFaults(
        drop=base.drop if f.drop is None else f.drop,
        burst=base.burst if f.burst is None else f.burst,
        delay_s=base.delay_s if f.delay_s is None else f.delay_s,
        partitions=base.partitions if f.partitions is None
        else tuple((float(a), float(b)) for a, b in f.partitions),
    )


def validate_plan(path: str, raw: FaultPlanFile, sc: Scenario) -> FaultPlan:
    """Check a decoded plan against the scenario it will run with."""
    duration = sc.spec.duration_s
    _check_fields(path, "defaults", raw.defaults, duration)
    edges = run_edges(sc)
    links = {e: _merge(LinkFaults(), raw.defaults) for e in edges}
    for k, entry in enumerate(raw.link):
        key = f"link[{k}]"
        _check_fields(path, key, entry, duration)
        hit = [e for e in edges if fnmatchcase(e[0], entry.from_) and fnmatchcase(e[1], entry.to)]
        if not hit:
            known = ", ".join(edge_name(*e) for e in edges)
            raise _fail(path, key, f"{entry.from_} -> {entry.to} matches no edge of scenario "
                        f"{sc.name!r}; its edges are {known}")
        for e in hit:
            links[e] = _merge(links[e], entry)
    roles = {LEADER_ROLE, PLANT_ROLE, *(agent_role(r) for r in sc.robot_ids)}
    for k, kill in enumerate(raw.kill):
        key = f"kill[{k}]"
        if kill.process not in roles:
            raise _fail(path, f"{key}.process", f"no process {kill.process!r} in this run; "
                        f"choose one of {', '.join(sorted(roles))}")
        if not (0.0 <= kill.at_s < duration):
            raise _fail(path, f"{key}.at_s", f"must be within the run [0, {duration}) s")
        if kill.restart_after_s is not None and not (0.0 < kill.restart_after_s <= 3600.0):
            raise _fail(path, f"{key}.restart_after_s", "must be in (0, 3600] s")
        if kill.pause_s is not None:
            if not (0.0 < kill.pause_s <= 3600.0):
                raise _fail(path, f"{key}.pause_s", "must be in (0, 3600] s")
            if kill.restart_after_s is not None:
                raise _fail(path, f"{key}.pause_s", "a paused process resumes by itself; "
                            "give pause_s or restart_after_s, not both")
    if len({k.process for k in raw.kill}) != len(raw.kill):
        raise _fail(path, "kill", "one kill per process")
    _probability(path, "can.frame_loss", raw.can.frame_loss)
    _probability(path, "can.corrupt", raw.can.corrupt)
    return FaultPlan(path, raw.seed, {e: f for e, f in links.items() if not f.perfect},
                     tuple(raw.kill), raw.can)


def decode_plan(text: bytes | str, sc: Scenario, path: str = "<fault plan>") -> FaultPlan:
    try:
        raw = msgspec.toml.decode(text, type=FaultPlanFile)
    except msgspec.ValidationError as exc:
        raise FaultPlanError(f"{path}: {readable(str(exc), FaultPlanFile)}") from exc
    except (msgspec.DecodeError, UnicodeDecodeError) as exc:
        raise FaultPlanError(f"{path}: not valid TOML: {exc}") from exc
    if not (0 <= raw.seed < 2**63):
        raise _fail(path, "seed", "must be in [0, 2^63)")
    return validate_plan(path, raw, sc)


def load_plan(path: str | Path, sc: Scenario) -> FaultPlan:
    """Read and validate a fault plan for ``sc``; raises :class:`FaultPlanError`."""
    p = Path(path)
    try:
        text = p.read_bytes()
    except OSError as exc:
        raise FaultPlanError(f"{p}: cannot read: {exc}") from exc
    return decode_plan(text, sc, str(p))


def uniform_drop_plan(sc: Scenario, drop: float, seed: int) -> FaultPlan:
    """Independent loss ``drop`` on every edge of the run (what the sweep runs)."""
    return validate_plan(f"<drop {drop}, seed {seed}>",
                         FaultPlanFile(seed=seed, defaults=LinkFields(drop=drop)), sc)
