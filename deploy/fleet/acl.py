"""Access control generated from the scenario's graph (zenoh 1.x ``access_control``).

Identity is the common name of a peer's TLS certificate (:mod:`deploy.fleet.certs`:
the CN is the role). What each role may publish and receive is the table of
:mod:`deploy.contract.audience` (the same table decides which receivers a
message's authentication tags are for: deploy/contract/keyring.py).

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

from deploy.contract.audience import (  # noqa: F401 - fleet_roles: the roles a deployment has
    ROUTER_ROLE,
    fleet_roles,
    publishes,
    receives,
)
from deploy.contract.scenario import Scenario
from deploy.contract.wire import Keys

DECLARATIONS = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]


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
