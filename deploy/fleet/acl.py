"""Access control generated from the scenario's graph (zenoh 1.x ``access_control``).

Identity is the common name of a peer's TLS certificate (:mod:`deploy.fleet.certs`:
the CN is the role). For every role the scenario can have we list

- what it may **publish** (``put``): agent i only ``robot/i/cmd`` (its reply:
  command and share), its telemetry and its own report; the plant the samples,
  its state log and control; the leader ``leader/state``; bridge i robot i's
  sample and its state log;
- what it may **receive**: agent i its robot's sample, the replies of its
  neighbours j (a_ij != 0: it reads their shares in them), ``leader/state`` iff
  b_i != 0, and control; the launcher (recorder) and a router everything.

A neighbour reads agent j's wheel command along with j's share (wire v2 puts both
in one message, one put a step): a command says nothing a neighbour could not
compute from j's share and state, and a key of its own for the share would cost
every agent a second message per step.

Every node's configuration holds the same table, as zenoh enforces it per
session on each link, by the remote's certificate: an ``ingress`` rule for
subject S says what S may put to this node, an ``egress`` rule what this node
may put to S. So a publication is checked twice, by the sender's egress (it is
never sent to a peer not allowed to receive it: a non-neighbour that subscribes
with a wildcard gets nothing) and by every receiver's ingress (an agent that
publishes another robot's command, with its own configuration changed, is
refused by the plant). A router holds the same table and enforces both on the
links it forwards between. Anything not allowed is denied (``default_permission:
deny``), so a link whose remote matches no subject (no fleet certificate, plain
TCP) carries nothing.

Declarations (subscribers, liveliness subscribers and queries) are allowed for
every fleet role on the fleet's keys: a declaration carries no data, and
allowing them keeps subscriptions and liveliness working. A liveliness token is
allowed only on the role's own ``alive/<role>`` and ``ready/<role>`` keys.
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
DECLARATIONS = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]


def fleet_roles(sc: Scenario, bridges: bool = True, router: bool = True) -> list[str]:
    """Every role a deployment of this scenario can have (one certificate each)."""
    roles = [LEADER_ROLE, PLANT_ROLE, LAUNCHER_ROLE]
    roles += [agent_role(r) for r in sc.robot_ids]
    if bridges:
        roles += [bridge_role(r) for r in sc.robot_ids]
    if router:
        roles.append(ROUTER_ROLE)
    return roles


def _robot_of(role: str, prefix: str) -> int | None:
    if role.startswith(prefix) and role[len(prefix):].lstrip("-").isdigit():
        return int(role[len(prefix):])
    return None


def all_keys(sc: Scenario, keys: Keys, roles: Iterable[str]) -> set[str]:
    """Every key expression the fleet's wire contract uses (concrete, no wildcards:
    then what a node may send to a peer is a plain set intersection)."""
    out = {keys.leader_state, *(keys.ctl(c) for c in CONTROL_COMMANDS),
           *(keys.report(r) for r in roles)}
    for r in sc.robot_ids:
        out |= {keys.sample(r), keys.cmd(r), keys.telemetry(r)}
    out |= {keys.state_log(r) for r in roles}
    return out


def publishes(role: str, sc: Scenario, keys: Keys, roles: Iterable[str]) -> set[str]:
    """Keys ``role`` may put."""
    ctl = {keys.ctl(c) for c in CONTROL_COMMANDS}
    if role in (LAUNCHER_ROLE, ROUTER_ROLE):
        return all_keys(sc, keys, roles)  # the launcher sends ctl; a router forwards all
    if role == PLANT_ROLE:
        return ({keys.sample(r) for r in sc.robot_ids} | ctl | {keys.report(role),
                                                                  keys.state_log(role)})
    if role == LEADER_ROLE:
        return {keys.leader_state, keys.report(role)}
    if (r := _robot_of(role, "agent-")) is not None:
        return {keys.telemetry(r), keys.cmd(r), keys.report(role)}
    if (r := _robot_of(role, "bridge-")) is not None:
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
        return ctl
    if (r := _robot_of(role, "agent-")) is not None:
        cfg = sc.agent_config(sc.index_of(r))
        out = {keys.sample(r)} | ctl
        out |= {keys.cmd(j) for j, _w in cfg.neighbours}
        if cfg.leader_weight != 0.0:
            out.add(keys.leader_state)
        return out
    if (r := _robot_of(role, "bridge-")) is not None:
        # the other robots' samples: the bridge builds its robot's perception from them
        return {keys.cmd(r)} | {keys.sample(j) for j in sc.robot_ids if j != r} | ctl
    raise ValueError(f"no access rules for role {role!r}")


def _tokens(role: str, keys: Keys) -> list[str]:
    """Liveliness tokens ``role`` may declare: its own (a router forwards everybody's)."""
    if role == ROUTER_ROLE:
        return [f"{keys.root}/alive/*", f"{keys.root}/ready/*"]
    return [keys.alive(role), keys.ready(role)]


def access_control(sc: Scenario, fleet: str, me: str, roles: Iterable[str] | None = None) -> dict:
    """The ``access_control`` section of role ``me``'s zenoh configuration: for every
    fleet role S, what S may put to me (``ingress``: S may publish it and I may
    receive it) and what I may put to S (``egress``: I may publish it and S may
    receive it). Everything else is denied."""
    keys = Keys(fleet)
    roles = list(roles) if roles is not None else fleet_roles(sc)
    if me not in roles:
        roles.append(me)
    mine_pub, mine_recv = publishes(me, sc, keys, roles), receives(me, sc, keys, roles)
    rules: list[dict] = [
        {"id": "declarations", "permission": "allow", "flows": ["ingress", "egress"],
         "messages": DECLARATIONS, "key_exprs": [keys.everything]},
        {"id": "my-tokens", "permission": "allow", "flows": ["egress"],
         "messages": ["liveliness_token"], "key_exprs": _tokens(me, keys)},
    ]
    subjects, policies = [], []
    for role in roles:
        if role == me:
            continue
        subjects.append({"id": role, "cert_common_names": [role]})
        ids = ["declarations", "my-tokens", f"tokens:{role}"]
        rules.append({"id": ids[-1], "permission": "allow", "flows": ["ingress"],
                      "messages": ["liveliness_token"], "key_exprs": _tokens(role, keys)})
        inbound = sorted(publishes(role, sc, keys, roles) & mine_recv)
        outbound = sorted(mine_pub & receives(role, sc, keys, roles))
        if inbound:
            rules.append({"id": f"from:{role}", "permission": "allow", "flows": ["ingress"],
                          "messages": ["put"], "key_exprs": inbound})
            ids.append(f"from:{role}")
        if outbound:
            rules.append({"id": f"to:{role}", "permission": "allow", "flows": ["egress"],
                          "messages": ["put"], "key_exprs": outbound})
            ids.append(f"to:{role}")
        policies.append({"id": f"policy:{role}", "rules": ids,
                         "subjects": [role]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}
