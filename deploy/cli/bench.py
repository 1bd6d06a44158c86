"""``omnifleet bench``'s command line: its options, and a sitting run and written (the groups
and figures: deploy/bench/suite.py)."""

from __future__ import annotations

import argparse
import json
import sys
import time

from deploy.bench.suite import SCALE_SIZES, Bench, Settings, markdown
from deploy.contract.options import EXIT_BAD_INPUT, add_option
from deploy.contract.output_paths import check_folder


def cmd_bench(args: argparse.Namespace) -> int:
    out = check_folder(args.out, "--out")  # OutputPathError: exit 2 (cli.main), before anything
    out.mkdir(parents=True, exist_ok=True)
    settings = Settings.of(args.quick, args.repeats)
    started = time.monotonic()

    def log(msg: str) -> None:
        print(f"[bench {time.monotonic() - started:6.1f} s] {msg}", file=sys.stderr, flush=True)

    bench = Bench(out, settings, log, args.scale_sizes)
    only = None if args.only is None else [g.strip() for g in args.only.split(",") if g.strip()]
    unknown = sorted(set(only or ()) - set(bench.groups()))
    if unknown:
        print(f"omnifleet bench: no group {', '.join(unknown)}; the groups are "
              f"{', '.join(bench.groups())}", file=sys.stderr)
        return EXIT_BAD_INPUT
    interrupted = False
    try:
        bench.run_all(only)
    except KeyboardInterrupt:
        interrupted = True
        log("interrupted: writing what was measured")
    report = bench.report(args.quick, started)
    (out / "bench.json").write_text(json.dumps(report, indent=2) + "\n")
    (out / "bench.md").write_text(markdown(report))
    failed = [n for n, f in report["figures"].items() if f["median"] is None]
    log(f"wrote {out / 'bench.json'} and {out / 'bench.md'}"
        + (f"; no figure for {', '.join(failed)}" if failed else ""))
    if not args.keep_runs:
        import shutil

        shutil.rmtree(bench.work, ignore_errors=True)
    if interrupted:
        return 130
    return 1 if failed else 0


def scale_sizes(text: str) -> tuple[int, ...]:
    """``--scale-sizes``: robot counts, each a whole number from 1 to 100."""
    try:
        sizes = tuple(int(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"not whole numbers separated by commas: {text!r}") from None
    if not sizes or any(not 1 <= n <= 100 for n in sizes):
        raise argparse.ArgumentTypeError(f"each size must be from 1 to 100: {text!r}")
    return tuple(sorted(set(sizes)))


def add_bench_command(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench", help="measure speed and memory against the targets; writes bench.json",
        description="Benchmarks, side by side in one sitting: lockstep overhead vs in-process, "
        "README command 1 with and without recording, the realtime loop (lab at 500 Hz, paper "
        "at 1 kHz), scale to 3/10/20/30 robots, agent memory, and the costs underneath (agent "
        "math, plant step, codec, one zenoh hop by the runtime's path and the old one vs one "
        "UDP hop). Writes bench.json and bench.md to --out. Takes ~30 min; --quick a few "
        "minutes (~30 s with --scale-sizes 3).")
    p.add_argument("--quick", action="store_true",
                   help="short runs, one repeat: a smoke run that still writes every figure")
    p.add_argument("--out", default="runs/bench", help="output folder (default: runs/bench)")
    add_option(p, "--repeats")
    p.add_argument("--only", metavar="GROUP[,GROUP]",
                   help="run only these groups: costs, in-process, lockstep, lockstep-paper, "
                   "data-path, paper-run, rtf500, realtime, realtime-fast, realtime-paper, scale, "
                   "budget (each realtime process's CPU per step and its parts), one-core (the "
                   "realtime fleets pinned to one core) (memory is always judged on the fleet "
                   "runs made)")
    p.add_argument("--scale-sizes", type=scale_sizes, default=SCALE_SIZES, metavar="N[,N]",
                   help="the fleet sizes of the scale group (default: "
                   f"{','.join(map(str, SCALE_SIZES))}; the n30 targets apply to N = 30)")
    p.add_argument("--keep-runs", action="store_true",
                   help="keep the fleet runs' folders (metrics.json, logs) under --out")
    p.set_defaults(func=cmd_bench)
