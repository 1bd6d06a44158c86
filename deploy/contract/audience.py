"""Who may publish each key of a fleet, and who receives it: one table, from the
scenario's graph, for everything that decides by it.

- the access control across hosts (deploy/fleet/acl.py: zenoh's rules per
  certificate name),
- the message authentication on every host (deploy/contract/keyring.py): a message
  on a key carries a tag for each receiver of that key, and a receiver accepts it
  only when its tag checks under the key it shares with one of the key's senders.

Per role:

- **publishes**: agent i only ``robot/i/cmd`` (its reply: command and share), its
  telemetry and its own report; the plant the samples, its state log, its report
  and control; the leader ``leader/state`` and its report; bridge i robot i's
  sample, its state log and its report; the launcher control (it starts and
  ends a run on CAN) and ``leader/steer`` (the recorder across hosts publishes nothing); a router
  forwards everything.
- **receives**: agent i its robot's sample, the replies of its neighbours j
  (a_ij != 0: it reads their shares in them), ``leader/state`` iff b_i != 0, and
  control; the plant every robot's reply and control; bridge i robot i's reply,
  the other robots' samples (its robot's perception) and control; the leader
  control; the launcher (the run's observer) and a router everything.

A neighbour reads agent j's wheel command along with j's share (one message a
step): a command says nothing a neighbour could not compute from j's share and
state, and a key of its own for the share would cost every agent a second
message a step.
"""

from __future__ import annotations

from collections.abc import Iterable

from deploy.contract.scenario import Scenario
from deploy.contract.wire import (
    CONTROL_COMMANDS,
    LAUNCHER_ROLE,
    LEADER_ROLE,
    PLANT_ROLE,
    Keys,
    agent_role,
    bridge_role,
)

ROUTER_ROLE = "router"


def fleet_roles(sc: Scenario, bridges: bool = True, router: bool = True) -> list[str]:
    """Every role a deployment of this scenario can have (one certificate each)."""
    roles = [LEADER_ROLE, PLANT_ROLE, LAUNCHER_ROLE]
    roles += [agent_role(r) for r in sc.robot_ids]
    if bridges:
        roles += [bridge_role(r) for r in sc.robot_ids]
    if router:
        roles.append(ROUTER_ROLE)
    return roles


def robot_of(role: str, prefix: str) -> int | None:
    """The robot id of ``agent-<id>`` (prefix ``agent-``) or ``bridge-<id>``, else None."""
    if role.startswith(prefix) and role[len(prefix):].lstrip("-").isdigit():
        return int(role[len(prefix):])
    return None


def all_keys(sc: Scenario, keys: Keys, roles: Iterable[str]) -> set[str]:
    """Every key expression the fleet's wire contract uses (concrete, no wildcards:
    then what a node may send to a peer is a plain set intersection)."""
    out = {keys.leader_state, keys.leader_steer, *(keys.ctl(c) for c in CONTROL_COMMANDS),
           *(keys.report(r) for r in roles)}
    for r in sc.robot_ids:
        out |= {keys.sample(r), keys.cmd(r), keys.telemetry(r)}
    out |= {keys.state_log(r) for r in roles}
    return out


def publishes(role: str, sc: Scenario, keys: Keys, roles: Iterable[str]) -> set[str]:
    """Keys ``role`` may put."""
    ctl = {keys.ctl(c) for c in CONTROL_COMMANDS}
    if role == ROUTER_ROLE:
        return all_keys(sc, keys, roles)  # a router forwards all
    if role == LAUNCHER_ROLE:
        # start and end when it keeps the run's time (CAN); stop, estop; a steered leader's
        # commands
        return ctl | {keys.leader_steer}
    if role == PLANT_ROLE:
        return ({keys.sample(r) for r in sc.robot_ids} | ctl | {keys.report(role),
                                                                  keys.state_log(role)})
    if role == LEADER_ROLE:
        return {keys.leader_state, keys.report(role)}
    if (r := robot_of(role, "agent-")) is not None:
        return {keys.telemetry(r), keys.cmd(r), keys.report(role)}
    if (r := robot_of(role, "bridge-")) is not None:
        return {keys.sample(r), keys.report(role), keys.state_log(role)}
    raise ValueError(f"no access rules for role {role!r}")


def receives(role: str, sc: Scenario, keys: Keys, roles: Iterable[str]) -> set[str]:
    """Keys that may be put to ``role``."""
    ctl = {keys.ctl(c) for c in CONTROL_COMMANDS}
    if role in (LAUNCHER_ROLE, ROUTER_ROLE):
        return all_keys(sc, keys, roles)  # the recorder hears the whole fleet
    if role == PLANT_ROLE:
        return {keys.cmd(r) for r in sc.robot_ids} | ctl
    if role == LEADER_ROLE:
        return ctl | {keys.leader_steer}
    if (r := robot_of(role, "agent-")) is not None:
        cfg = sc.agent_config(sc.index_of(r))
        out = {keys.sample(r)} | ctl
        out |= {keys.cmd(j) for j, _w in cfg.neighbours}
        if cfg.leader_weight != 0.0:
            out.add(keys.leader_state)
        return out
    if (r := robot_of(role, "bridge-")) is not None:
        # the other robots' samples: the bridge builds its robot's perception from them
        return {keys.cmd(r)} | {keys.sample(j) for j in sc.robot_ids if j != r} | ctl
    raise ValueError(f"no access rules for role {role!r}")
