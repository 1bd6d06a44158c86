"""Measure what mutual TLS + ACL costs on state-to-command latency, against plain
TCP, in one sitting: the lab scenario in realtime (200 Hz, model plant) with the
deploy plan's commands, leader/plant/recorder in one namespace and each agent in
its own (tests/netns.py), runs alternating TCP, TLS, TCP, TLS, ...

    sudo .venv/bin/python tests/measure_tls.py [--seconds 20] [--pairs 2]

Prints the plant's latency p50/p99 per run (root only).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent / "e2e"))
sys.path.insert(0, str(Path(__file__).resolve().parent / "e2e"))

from netns import machines, netns_problem, stop  # noqa: E402
from test_netns import MACHINES, _logs, _run_fleet, _wait_all  # noqa: E402

from deploy.fleet.deploy_plan import RunOptions  # noqa: E402


def one_run(ms, tmp: Path, tls: bool, seconds: float, i: int) -> dict:
    out = tmp / f"run{i}-{'tls' if tls else 'tcp'}"
    run = RunOptions("lab", clock="realtime", duration_s=seconds, plant_kind="model",
                     record_out=str(out))
    (tmp / f"w{i}").mkdir()
    procs, logs = _run_fleet(ms, tmp / f"w{i}", f"lat{i}x{int(time.time()) % 10000}", run,
                             tls=tls)
    try:
        codes = _wait_all(procs, seconds + 120)
    finally:
        stop(list(procs.values()))
    if not all(c == 0 for c in codes.values()):
        raise RuntimeError(f"{codes}\n{_logs(logs)}")
    return json.loads((out / "metrics.json").read_text())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--pairs", type=int, default=2)
    args = ap.parse_args()
    problem = netns_problem()
    if problem:
        print(problem, file=sys.stderr)
        return 2
    rows = []
    with tempfile.TemporaryDirectory() as d, machines(MACHINES) as ms:
        for p in range(args.pairs):
            for tls in (False, True):
                m = one_run(ms, Path(d), tls, args.seconds, 2 * p + int(tls))
                rows.append((tls, m))
                lat = m["latency_ms"]
                print(f"{'tls' if tls else 'tcp'}: latency p50 {lat['p50']:.3f} ms, p99 "
                      f"{lat['p99']:.3f} ms; deadline misses {m['deadline_misses']}; "
                      f"steps {m['steps']}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
