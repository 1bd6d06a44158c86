"""A compromised agent, as a process of its own: it holds one agent's real keyring (and,
across hosts, its certificate), joins the fleet with a zenoh configuration of its own
(its access control thrown away), and tries to command another robot: replies on
that robot's key for every step of the run, tagged with its own keys as itself, and
claiming to be that robot's agent with every key it shares with the plant and with
the victim's agent. With ``--stop``, it tags a ``ctl/stop`` as the plant with the
keys it holds instead.

    python tests/rogue_agent.py --scenario S --fleet F --keys agent-3.keys --role agent-3
        --victim 2 --connect ENDPOINT [--zenoh-config FILE] --steps N --seconds S

Prints ``peers N`` once it is linked with N nodes, and ``sent N`` at the end. Used by
tests/e2e/test_compromised.py and tests/e2e/test_netns.py.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from deploy.contract import mac  # noqa: E402
from deploy.contract.keyring import Keyring, read_file  # noqa: E402
from deploy.contract.scenario import load_scenario  # noqa: E402
from deploy.contract.wire import (  # noqa: E402
    WIRE_VERSION,
    Control,
    Keys,
    Reply,
    Share,
    agent_role,
    encode,
)
from deploy.runtime.transport import zenoh_config  # noqa: E402

Z = (0.0, 0.0, 0.0)


def forgeries(ring: Keyring, keys: Keys, victim: int, k: int) -> list[bytes]:
    """Replies of robot ``victim`` for step ``k``: as the rogue itself, and as the victim's
    agent tagged for the plant with each key the rogue holds."""
    key = keys.cmd(victim)
    body = encode(Reply(WIRE_VERSION, victim, k, 0, robot=victim, k=k, t=0.0,
                        torques=(-2.0,) * 4, v_cmd=Z, state_seq=k, state_stamp_ns=0,
                        share=Share((50.0, 50.0, 0.0), Z, Z, Z, Z, Z)))
    claimed = agent_role(victim)
    tags = [(mac.hint(receiver), mac.prefixed(ring._pair[held], key, claimed, receiver))
            for receiver in ("plant", f"bridge-{victim}") for held in ring._pair]
    return [ring.seal(body, key), mac.seal(body, tags, mac.trailer(mac.hint(claimed), len(tags)))]


def main() -> int:
    p = argparse.ArgumentParser()
    for name in ("--scenario", "--fleet", "--keys", "--role"):
        p.add_argument(name, required=True)
    p.add_argument("--victim", type=int, default=2)
    p.add_argument("--connect", action="append", default=[])
    p.add_argument("--zenoh-config")
    p.add_argument("--steps", type=int, required=True)
    p.add_argument("--seconds", type=float, required=True)
    p.add_argument("--stop", action="store_true")
    args = p.parse_args()
    import zenoh

    sc, keys = load_scenario(args.scenario), Keys(args.fleet)
    ring = Keyring.from_text(read_file(args.keys), args.keys, args.role, sc, keys)
    session = zenoh.open(zenoh_config(args.zenoh_config, connect=args.connect))
    block = zenoh.CongestionControl.BLOCK
    sent = linked = 0
    until = time.monotonic() + args.seconds
    try:
        # said once it is in the fleet, before the flood (a flood of blocking puts can
        # outlast the run, and a test may end the rogue any time)
        while not linked and time.monotonic() < until:
            linked = len(session.info.peers_zid())
            if not linked:
                time.sleep(0.01)  # polling the session's links, with the deadline above
        if linked:
            print(f"peers {linked}", flush=True)
        while time.monotonic() < until:
            if args.stop:
                stop = encode(Control(WIRE_VERSION, 0, sent, 0, command="stop"))
                # for every receiver but itself (stopping its own process proves nothing)
                tags = [(mac.hint(r), mac.prefixed(ring._pair[held], keys.ctl("stop"), "plant", r))
                        for r in ring._pair if r != args.role for held in ring._pair]
                session.put(keys.ctl("stop"), mac.seal(stop, tags, mac.trailer(mac.hint("plant"), len(tags))),
                            congestion_control=block)
                sent += 1
            else:
                for k in range(args.steps):
                    for data in forgeries(ring, keys, args.victim, k):
                        session.put(keys.cmd(args.victim), data, congestion_control=block)
                        sent += 1
            time.sleep(0.05)  # a pace, not a synchronisation: the rogue floods for its time
    finally:
        session.close()
    print(f"sent {sent}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
