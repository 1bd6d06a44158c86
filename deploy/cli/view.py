"""``omnifleet view RUN_DIR``: serve a finished run's recording over Foxglove's WebSocket
protocol, as ``--live`` serves a running one (the player: deploy/report/recording_player.py,
imported only when the command runs)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from deploy.contract.options import EXIT_BAD_INPUT, add_option
from deploy.report.run_folder import RECORDING
from deploy.report.ws_address import DEFAULT_PORT, LiveAddressError, parse_address, url


def _cmd_view(args: argparse.Namespace) -> int:
    path = Path(args.run_dir)
    if path.is_dir():
        path = path / RECORDING
    if not path.is_file():
        print(f"omnifleet view: no recording at {path} (was the run made with --no-record?)",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        host, port = parse_address(args.listen)
    except LiveAddressError as exc:
        print(f"omnifleet view: --listen: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT

    from deploy.report.recording_player import serve_recording

    def ready(p: int) -> None:
        print(f"serving {path} on {url(host, p)} (Foxglove: Open connection -> Foxglove "
              "WebSocket; layout docs/foxglove-layout.json); Ctrl-C stops", file=sys.stderr,
              flush=True)

    try:
        serve_recording(path, host, port, args.speed, args.play, args.loop, on_ready=ready)
    except (ValueError, RuntimeError, OSError) as exc:
        print(f"omnifleet view: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    return 0


def add_view_command(sub) -> None:
    p = sub.add_parser(
        "view", help="serve a finished run's recording to Foxglove or Lichtblick over WebSocket",
        description="Serve RUN_DIR/recording.mcap to Foxglove or Lichtblick over Foxglove's "
        "WebSocket protocol (the same scene and plots as --live, with playback control). "
        "docs/foxglove.md.")
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run's folder (or an .mcap file)")
    p.add_argument("--listen", metavar="[HOST:]PORT", default=str(DEFAULT_PORT),
                   help=f"where to serve (default 127.0.0.1:{DEFAULT_PORT}; loopback unless HOST "
                   "is given; port 0: any free one)")
    add_option(p, "--speed")
    p.add_argument("--play", action="store_true",
                   help="start playing at once (default: when the first client subscribes)")
    p.add_argument("--loop", action="store_true", help="start again at the end")
    p.set_defaults(func=_cmd_view)
