"""Machines for tests: Linux network namespaces joined by veth pairs on a bridge.

Root only (``ip netns``); :func:`netns_problem` says why not when a test must
skip. Every namespace, veth and bridge made here is deleted on the way out of
:func:`machines`, whatever happened; every process started in a namespace is
ended by pid (its process group).
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def netns_problem() -> str | None:
    """Why namespace tests cannot run here, or None."""
    if os.geteuid() != 0:
        return "network namespaces need root (CI runs as root)"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    probe = f"omf-probe-{secrets.token_hex(3)}"
    r = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if r.returncode != 0:
        return f"`ip netns add` fails here: {r.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


@dataclass(frozen=True)
class Machine:
    name: str
    netns: str
    address: str
    host_veth: str  # the bridge side: ``ip link set ... down`` cuts the machine off

    def cut(self) -> None:
        _ip("link", "set", self.host_veth, "down")

    def restore(self) -> None:
        _ip("link", "set", self.host_veth, "up")

    def start(self, argv: list[str], log: Path) -> subprocess.Popen:
        """``argv`` inside this machine's namespace, output to ``log``, own session."""
        with open(log, "wb") as f:
            return subprocess.Popen(["ip", "netns", "exec", self.netns, *argv], cwd=REPO,
                                    stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    start_new_session=True,
                                    env=dict(os.environ, PYTHONUNBUFFERED="1"))


def omnifleet() -> list[str]:
    return [sys.executable, "-m", "deploy.cli"]


@contextlib.contextmanager
def machines(names: list[str]):
    """One namespace per name on a private /24, all on one bridge; yields
    {name: Machine}. Everything is deleted on exit."""
    sfx = secrets.token_hex(3)
    bridge = f"omfbr{sfx}"
    subnet = f"10.{secrets.randbelow(200) + 20}.{secrets.randbelow(250) + 1}"
    made_ns: list[str] = []
    made_links: list[str] = [bridge]
    try:
        _ip("link", "add", bridge, "type", "bridge")
        _ip("link", "set", bridge, "up")
        out = {}
        for i, name in enumerate(names):
            ns = f"omf-{sfx}-{name}"
            _ip("netns", "add", ns)
            made_ns.append(ns)
            host, inner = f"omf{sfx}h{i}", f"omf{sfx}n{i}"
            _ip("link", "add", host, "type", "veth", "peer", "name", inner)
            made_links.append(host)
            _ip("link", "set", host, "master", bridge)
            _ip("link", "set", host, "up")
            _ip("link", "set", inner, "netns", ns)
            address = f"{subnet}.{i + 1}"
            _ip("-n", ns, "addr", "add", f"{address}/24", "dev", inner)
            _ip("-n", ns, "link", "set", inner, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
            out[name] = Machine(name, ns, address, host)
        yield out
    finally:
        for ns in made_ns:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        for link in made_links:
            subprocess.run(["ip", "link", "del", link], capture_output=True)


def stop(procs: list[subprocess.Popen]) -> None:
    """End every process by pid (its whole group): SIGTERM, then SIGKILL."""
    for p in procs:
        if p.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=5)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()
