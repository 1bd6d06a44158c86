"""The live view serves clients that offer only ``foxglove.websocket.v1`` (Lichtblick before
lichtblick-suite/lichtblick#819, Foxglove before the SDK) as well as those that offer
``foxglove.sdk.v1`` (deploy/report/ws_front.py); a client that offers neither is refused
with HTTP 400 naming both, said once however often it retries.

Seen: a ``foxglove.websocket.v1`` client got HTTP 400 "Missing expected
sec-websocket-protocol header", and the run printed 129 lines of "Dropping client ...:
handshake failed" with no reason."""

from __future__ import annotations

import asyncio
import threading

import pytest
import websockets
import websockets.exceptions  # a submodule: not there until someone imports it
from conftest import cached_run
from foxglove_ws import watch

from deploy.contract.scenario import load_scenario
from deploy.report.foxglove_topics import SCENE_ROBOTS
from deploy.report.live_view import LiveView
from deploy.report.ws_front import LEGACY_PROTOCOL, SDK_PROTOCOL


@pytest.fixture
def view():
    """A live view of a run that goes on: a row more every 10 ms (0.5 s of lab = 100 rows,
    then again from the start), as `omnifleet run --live` feeds it."""
    sc = load_scenario("lab")
    said: list[str] = []
    live = LiveView(sc, "127.0.0.1", 0)
    live.server.front.say = said.append
    series = cached_run("lab", 0.5, "model").series
    live.follow(series)
    stop = threading.Event()

    def feed() -> None:
        k = 0
        while not stop.wait(0.01):
            live.publish(k)
            k = (k + 1) % series.steps
            if k == 0:
                live._sent = -1  # the run's rows again from the start (a test feeder only)

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        yield live, sc, said
    finally:
        stop.set()
        feeder.join()
        live.close()


def _every_robot(sc):
    def done(s) -> bool:
        want = {f"robot-{r}" for r in sc.robot_ids}
        return any(want <= {e.id for e in m.entities} for _t, m in s.received.get(SCENE_ROBOTS, []))
    return done


@pytest.mark.parametrize("offer", [[LEGACY_PROTOCOL], [SDK_PROTOCOL]],
                         ids=["foxglove.websocket.v1 only", "foxglove.sdk.v1 only"])
def test_a_client_offering_one_name_is_served_the_scene_under_it(view, offer):
    live, sc, _ = view
    before = dict(live.server.front.served)
    s = watch(f"ws://127.0.0.1:{live.port}", {SCENE_ROBOTS}, _every_robot(sc), timeout_s=30,
              subprotocols=offer)
    assert s.subprotocol == offer[0]  # answered with the name it asked for
    assert s.server_info is not None and s.server_info["op"] == "serverInfo"
    assert _every_robot(sc)(s), s.topics()
    assert live.server.front.served[offer[0]] == before[offer[0]] + 1


def test_a_client_offering_neither_is_refused_once_with_the_reason(view):
    live, _, said = view

    async def attempt() -> str:
        with pytest.raises(websockets.exceptions.InvalidStatus) as refused:
            async with websockets.connect(f"ws://127.0.0.1:{live.port}",
                                          subprotocols=["something.else.v2"]):
                pass
        return refused.value.response.body.decode()

    bodies = [asyncio.run(attempt()) for _ in range(5)]  # a client that keeps retrying
    assert all(SDK_PROTOCOL in b and LEGACY_PROTOCOL in b and "something.else.v2" in b
               for b in bodies)
    assert live.server.front.refused == 5
    assert len(said) == 1 and "refused a client" in said[0] and LEGACY_PROTOCOL in said[0]
