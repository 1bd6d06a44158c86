"""The CAN bus and driver options every CAN command shares (bridge, emulate,
can-check), opening the bus they name and making the driver they name, each with a
clear error."""

from __future__ import annotations

import argparse
import math
import threading
import time
from pathlib import Path
from typing import Any

from bridges import drivers
from bridges.driver import DriverSettings, WheelDriver
from bridges.drivers import DEFAULT_DRIVER, DRIVERS, node_ids_for
from deploy.contract.options import (  # noqa: F401 (can_check reads MAX_SPIN_TORQUE_NM here)
    MAX_CAN_NODE_ID,
    MAX_SPIN_TORQUE_NM,
    add_option,
)


class CanBusError(RuntimeError):
    """The bus the options name cannot be opened (exit code 2 at the CLI)."""


def parse_node_ids(text: str) -> tuple[int, ...]:
    """4 distinct node ids; the protocol's own range is checked by the driver
    (:func:`bridges.drivers.node_ids_for`)."""
    try:
        ids = tuple(int(x) for x in text.split(","))
    except ValueError:
        ids = ()
    if len(ids) != 4 or len(set(ids)) != 4 or not all(0 <= i <= MAX_CAN_NODE_ID for i in ids):
        raise argparse.ArgumentTypeError(f"expected 4 distinct node ids in 0..{MAX_CAN_NODE_ID} (the wheel "
                                         f"order of eq. 1), got {text!r}")
    return ids


def parse_can_arg(text: str) -> tuple[str, int | str]:
    key, sep, value = text.partition("=")
    if not sep or not key.isidentifier():
        raise argparse.ArgumentTypeError(f"{text!r}: expected KEY=VALUE, e.g. port=43114")
    return key, int(value) if value.lstrip("-").isdigit() else value


class _Collect(argparse.Action):
    def __call__(self, parser, namespace, value, option_string=None):
        got = dict(getattr(namespace, self.dest, None) or {})
        got.update([value])
        setattr(namespace, self.dest, got)


class _Append(argparse.Action):
    def __call__(self, parser, namespace, value, option_string=None):
        setattr(namespace, self.dest, [*(getattr(namespace, self.dest, None) or []), value])


def driver_name(value: str) -> str:
    """``--driver``'s type: a registered protocol, an installed plug-in's included
    (bridges/drivers.py); another name exits 2 listing them."""
    try:
        drivers.entry(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return value


def add_driver_option(p: argparse.ArgumentParser, default: str | None, about: str) -> None:
    p.add_argument("--driver", type=driver_name, default=default, metavar="DRIVER",
                   help=f"{about} (default {DEFAULT_DRIVER}; or a protocol a package "
                   "registers, docs/extending.md)")


def add_can_options(p: argparse.ArgumentParser, per_robot: bool = False) -> None:
    """The CAN options; ``per_robot``: one bus per ``--robot`` (``--can-channel`` once
    per robot, in order; a ``--can-arg`` key given once applies to every bus, given
    once per robot it is that robot's), opened with :func:`open_buses`."""
    p.add_argument("--can-interface", required=True, metavar="IFACE",
                   help="python-can interface: virtual (this process only), udp_multicast (across "
                   "processes and machines, no kernel module), socketcan, pcan, kvaser, slcan, ...")
    p.add_argument("--can-channel", required=True, metavar="CH",
                   action="append" if per_robot else "store",
                   help="the interface's channel: a name for virtual, a multicast group address "
                   "for udp_multicast (e.g. 239.74.163.2), can0 for socketcan"
                   + ("; once per --robot, in the same order" if per_robot else ""))
    add_option(p, "--bitrate")
    p.add_argument("--can-arg", type=parse_can_arg, action=_Append if per_robot else _Collect,
                   metavar="KEY=VALUE",
                   help="an interface-specific bus option, repeatable (e.g. port=43114 for "
                   "udp_multicast: every group on one port is heard by every bus on that port)"
                   + ("; a key given once applies to every robot's bus, given once per --robot "
                      "each robot gets its own value, in order" if per_robot else ""))
    p.add_argument("--node-ids", type=parse_node_ids, default=None, metavar="A,B,C,D",
                   help="CAN node ids of the wheels' drives, in the wheel order of the model "
                   "(default: the driver's: " + "; ".join(
                       f"{name} {','.join(map(str, e.default_node_ids))}"
                       for name, e in DRIVERS.items()) + ")")
    add_driver_option(p, DEFAULT_DRIVER, "the drives' CAN protocol: " + "; ".join(
        f"{name}: {e.about}" for name, e in DRIVERS.items()))
    p.add_argument("--eds", metavar="FILE",
                   help="cia402: the drives' EDS file (default: the emulated drive's, shipped "
                   "with omnifleet: bridges/cia402_drive.eds)")


class DriverOptionError(ValueError):
    """The driver the options name cannot be made (a bad EDS or node id): exit code 2."""


def driver_settings(args: argparse.Namespace, period_s: float = 0.005,
                    max_wheel_torque_nm: float = math.inf) -> DriverSettings:
    """What the driver options say (DriverOptionError naming a node id the protocol
    cannot address or an EDS that does not exist)."""
    try:
        ids = node_ids_for(args.driver, args.node_ids)
    except ValueError as exc:
        raise DriverOptionError(str(exc)) from None
    if args.eds is not None and not Path(args.eds).is_file():
        raise DriverOptionError(f"--eds {args.eds}: no such file")
    return DriverSettings(ids, period_s, max_wheel_torque_nm, args.eds)


def make_driver(args: argparse.Namespace, period_s: float = 0.005,
                max_wheel_torque_nm: float = math.inf) -> WheelDriver:
    """The host side of the driver the options name (DriverOptionError naming what
    is wrong: a node id, the EDS file, its contents)."""
    settings = driver_settings(args, period_s, max_wheel_torque_nm)
    try:
        return drivers.make_driver(args.driver, settings)
    except ValueError as exc:
        raise DriverOptionError(str(exc)) from None


def open_bus(args: argparse.Namespace) -> Any:
    """The python-can bus the options name; CanBusError with the reason otherwise."""
    return _open(args.can_interface, args.can_channel,
                 dict(getattr(args, "can_arg", None) or {}), args.bitrate)


def per_robot_buses(args: argparse.Namespace, n: int) -> list[tuple[str, dict[str, Any]]]:
    """(channel, bus options) of each of ``n`` robots, from per-robot CAN options;
    CanBusError if the counts do not match."""
    channels = list(args.can_channel)
    if len(channels) != n:
        raise CanBusError(f"give --can-channel once per --robot: {n} robots, "
                          f"{len(channels)} channels")
    by_key: dict[str, list[Any]] = {}
    for key, value in getattr(args, "can_arg", None) or []:
        by_key.setdefault(key, []).append(value)
    opts: list[dict[str, Any]] = [{} for _ in range(n)]
    for key, values in by_key.items():
        if len(values) not in (1, n):
            raise CanBusError(f"--can-arg {key}=...: give it once (every bus) or once per "
                              f"--robot ({n}), not {len(values)} times")
        for i in range(n):
            opts[i][key] = values[0] if len(values) == 1 else values[i]
    return list(zip(channels, opts, strict=True))


def open_buses(args: argparse.Namespace, n: int) -> list[Any]:
    """The bus of each of ``n`` robots (see :func:`per_robot_buses`); on an error the
    ones already open are shut down and CanBusError is raised."""
    buses: list[Any] = []
    try:
        for channel, kwargs in per_robot_buses(args, n):
            buses.append(_open(args.can_interface, channel, kwargs, args.bitrate))
    except CanBusError:
        for bus in buses:
            bus.shutdown()
        raise
    return buses


def _open(interface: str, channel: str, kwargs: dict[str, Any], bitrate: int | None) -> Any:
    import can

    if interface not in can.VALID_INTERFACES:
        raise CanBusError(f"unknown --can-interface {interface!r}; python-can knows "
                          f"{', '.join(sorted(can.VALID_INTERFACES))}")
    if bitrate is not None:
        kwargs = {**kwargs, "bitrate": bitrate}
    try:
        bus = can.Bus(interface=interface, channel=channel, **kwargs)
    except Exception as exc:  # python-can raises many kinds for a bad channel or option
        raise CanBusError(f"cannot open CAN bus {interface}:{channel}: {exc}") from None
    if interface == "udp_multicast":
        _grow_receive_buffer(bus)
        _drop_own_frames(bus)
    return bus


UDP_RECEIVE_BUFFER_BYTES = 4 << 20


def _grow_receive_buffer(bus: Any) -> None:
    """A loaded host can leave a process off the CPU for tens of ms: with the kernel's
    default ~200 kB a busy udp_multicast bus then drops frames. Ask for 4 MB (root may
    exceed net.core.rmem_max; others get what the kernel allows)."""
    import socket

    sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
    if sock is None:
        return
    for opt in (getattr(socket, "SO_RCVBUFFORCE", None), socket.SO_RCVBUF):
        if opt is None:
            continue
        try:
            sock.setsockopt(socket.SOL_SOCKET, opt, UDP_RECEIVE_BUFFER_BYTES)
            return
        except OSError:
            continue


# distinct datagrams sent and not yet heard back that a bus remembers: only loopbacks the
# kernel dropped (a full receive buffer) stay; past this many they are forgotten at once
OWN_FRAMES_PENDING = 4096


def _drop_own_frames(bus: Any) -> None:
    """A udp_multicast bus hears its own frames: the group's loopback, which the other
    processes on the host (the emulator, the bridges) need, also reaches the socket
    that sent them. A CAN controller does not give a node its own frames back
    (python-can's ``receive_own_messages``, off). Here each datagram this bus sends is
    counted, and as many byte-identical datagrams heard later are dropped before they are
    unpacked: what the bus then receives is, as a multiset, exactly what the others sent
    (a CAN identifier has one sender, and even two senders of identical bytes lose only
    copies of our own). Measured on the CAN fleet (``lab --plant can-emulated``, 200 Hz):
    each bridge's receive thread heard its own 4 torque frames a period (about two thirds
    of its frames, by the frame rates), and the emulator its own encoder frames; each
    cost a wake-up, the unpacking and the GIL (docs/bench-history.md)."""
    multicast = getattr(bus, "_multicast", None)
    send, recv = getattr(multicast, "send", None), getattr(multicast, "recv", None)
    if send is None or recv is None:
        return
    pending: dict[bytes, int] = {}  # datagram -> copies sent and not heard back yet
    lock = threading.Lock()  # sent from the node's thread, heard on the reader's

    def forget_one(data: bytes) -> bool:
        n = pending.get(data)
        if not n:
            return False
        if n == 1:
            del pending[data]
        else:
            pending[data] = n - 1
        return True

    def send_counted(data: bytes, timeout: float | None = None) -> None:
        with lock:  # before it goes out: its loopback can be heard before sendto returns
            if len(pending) >= OWN_FRAMES_PENDING:
                pending.clear()
            pending[data] = pending.get(data, 0) + 1
        try:
            send(data, timeout)
        except BaseException:
            with lock:
                forget_one(data)
            raise

    def recv_others(timeout: float | None = None) -> Any:
        # ours are read past within the same timeout: a frame queued behind one of them
        # is returned by this call (recv(timeout=0), the emulator's poll once a tick,
        # would otherwise stop at our own frame and leave a torque frame for later)
        end = None if timeout is None else time.monotonic() + timeout
        while True:
            got = recv(None if end is None else max(end - time.monotonic(), 0.0))
            if not got:
                return got
            with lock:
                if not forget_one(got[0]):
                    return got

    multicast.send, multicast.recv = send_counted, recv_others
