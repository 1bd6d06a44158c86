"""``omnifleet router``: a zenoh router through the zenoh Python API (no separate
``zenohd`` binary assumed), for sites that want one (peers on different subnets,
or one place that enforces the fleet's access control on every link).

It opens a session in ``router`` mode with the given configuration (usually the
``router.json5`` that ``omnifleet deploy plan --write`` made: TLS and the ACL)
and stays until SIGINT/SIGTERM.
"""

from __future__ import annotations

from deploy.runtime.transport import TransportError, zenoh_config


def router_config(config_file: str | None, listen: list[str], connect: list[str]):
    cfg = zenoh_config(config_file, listen, connect)
    try:
        cfg.insert_json5("mode", '"router"')
    except Exception as exc:
        raise TransportError(f"zenoh configuration: {exc}") from exc
    return cfg




