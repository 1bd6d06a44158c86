"""Zenoh configurations for a fleet across machines: peers and an optional router.

A configuration is a plain dict (JSON is JSON5), written to a file that a node
reads with ``--zenoh-config FILE``. What every one of them says:

- ``mode``: ``peer`` for nodes, ``router`` for ``omnifleet router``;
- explicit ``listen``/``connect`` endpoints (``tcp/host:port`` or, with
  certificates, ``tls/host:port``);
- multicast scouting **off** (on a shared network nobody is found by
  broadcast); gossip scouting on, so peers that connect to one common endpoint
  (the base station, or a router) learn each other's listen endpoints and link
  directly (one hop for every message);
- with certificates: mutual TLS (``enable_mtls``: both ends show a certificate of
  the fleet's CA, names verified on connect), only TLS links accepted
  (``transport/link/protocols``), and the fleet's access control
  (:mod:`deploy.fleet.acl`);
- optionally a shorter link lease, so that a lost link is noticed sooner (the
  default is 10 s; a cut link is declared dead after one lease).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

from deploy.fleet.certs import RoleFiles


def tls_section(files: RoleFiles, verify_names: bool = True) -> dict:
    """``transport/link/tls``: this role's certificate for both directions, mTLS."""
    return {
        "root_ca_certificate": str(files.ca),
        "listen_private_key": str(files.key),
        "listen_certificate": str(files.cert),
        "connect_private_key": str(files.key),
        "connect_certificate": str(files.cert),
        "enable_mtls": True,
        "verify_name_on_connect": verify_names,
    }


def node_config(
    listen: Iterable[str] = (),
    connect: Iterable[str] = (),
    tls: RoleFiles | None = None,
    acl: dict | None = None,
    mode: str = "peer",
    lease_ms: int | None = None,
    verify_names: bool = True,
) -> dict:
    """A peer (or router) configuration as a dict; see the module's docstring."""
    if mode not in ("peer", "router"):
        raise ValueError(f"mode must be peer or router, not {mode!r}")
    cfg: dict = {
        "mode": mode,
        "listen": {"endpoints": list(listen)},
        "connect": {"endpoints": list(connect)},
        "scouting": {"multicast": {"enabled": False},
                     "gossip": {"enabled": True}},
        "transport": {"link": {}},
    }
    link = cfg["transport"]["link"]
    if tls is not None:
        link["tls"] = tls_section(tls, verify_names)
        link["protocols"] = ["tls"]  # nothing but mutual TLS, not even by mistake
    if lease_ms is not None:
        link["tx"] = {"lease": int(lease_ms), "keep_alive": 4}
    if acl is not None:
        cfg["access_control"] = acl
    return cfg


def write_config(path: str | Path, cfg: dict) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(cfg, indent=2) + "\n")
    return path
