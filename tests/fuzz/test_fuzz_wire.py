"""Fuzzing the wire decoder (``Codec.decode``, deploy/contract/wire.py) for every message type.

Properties: decode returns a valid message or ``None`` and never raises; what it
returns has the wire version, a robot id of the scenario, and no NaN/Inf anywhere;
a valid message survives encode -> decode unchanged. Inputs: random bytes, valid
messages with mutated bytes, field lists with wrong types, non-finite, huge or
out-of-range values, cut short or extended (tests/fuzz_wire_inputs.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import msgspec
import pytest
from fuzz_wire_inputs import ROBOT_IDS, message_bytes
from fuzzing import fuzz_decoder, fuzz_settings, mutated_bytes, non_finite_floats
from hypothesis import given
from hypothesis import strategies as st

from deploy.contract.wire import (
    FLOAT_LIMIT,
    MAX_BODIES,
    MESSAGE_TYPES,
    WIRE_VERSION,
    Codec,
    Message,
    Reply,
    Sample,
    SensedBody,
    encode,
    within_wire_bound,
)

CODEC = Codec(list(ROBOT_IDS))
KINDS = pytest.mark.parametrize("kind", MESSAGE_TYPES, ids=lambda k: k.__name__)


def check_message(kind: type[Message], robot: int | None) -> Callable[[Message], None]:
    def check(msg: Message) -> None:
        assert type(msg) is kind
        assert msg.v == WIRE_VERSION and msg.seq >= 0
        assert not non_finite_floats(msg), non_finite_floats(msg)
        if kind.ROBOT_FIELD is not None:
            rid = getattr(msg, kind.ROBOT_FIELD)
            assert rid in ROBOT_IDS and (robot is None or rid == robot)
        if isinstance(msg, Sample):
            assert len(msg.robots) <= MAX_BODIES and len(msg.obstacles) <= MAX_BODIES
            assert all(b.ident < 0 or b.ident in ROBOT_IDS for b in msg.robots)
        if isinstance(msg, Reply):
            assert len(msg.torques) == 4 and all(math.isfinite(x) for x in msg.torques)
    return check


def decode_fuzzed(kind: type[Message], data: bytes, robot: int | None = None) -> Message | None:
    return fuzz_decoder(f"wire {kind.__name__}", lambda d: CODEC.decode(kind, d, robot), data,
                        check=check_message(kind, robot))


@KINDS
@fuzz_settings(100)
@given(data=st.binary(max_size=300))
def test_random_bytes(kind: type[Message], data: bytes) -> None:
    decode_fuzzed(kind, data)


@KINDS
@fuzz_settings(120)
@given(st.data())
def test_wrong_fields(kind: type[Message], data: st.DataObject) -> None:
    """Field lists with wrong types, NaN/Inf, huge ints, bad version or robot id, any length."""
    raw = data.draw(message_bytes(kind, sane=False))
    robot = data.draw(st.sampled_from([None, *ROBOT_IDS]))
    decode_fuzzed(kind, raw, robot)


@KINDS
@fuzz_settings(100)
@given(st.data())
def test_mutated_valid_messages(kind: type[Message], data: st.DataObject) -> None:
    raw = data.draw(message_bytes(kind, sane=True))
    decode_fuzzed(kind, data.draw(mutated_bytes(raw)))


@KINDS
@fuzz_settings(40)
@given(st.data())
def test_valid_messages_round_trip(kind: type[Message], data: st.DataObject) -> None:
    """The decoder does not refuse what it should accept: a valid message comes back equal."""
    raw = data.draw(message_bytes(kind, sane=True))
    msg = decode_fuzzed(kind, raw)
    assert msg is not None, msgspec.msgpack.decode(raw)
    assert encode(msg) == raw


@pytest.mark.parametrize("n", [MAX_BODIES, MAX_BODIES + 1, 10 * MAX_BODIES])
def test_perception_body_count_is_bounded(n: int) -> None:
    body = SensedBody(-1, (0.0, 0.0), (0.0, 0.0), 0.5)
    raw = encode(Sample(WIRE_VERSION, 0, 0, 0, robot=1, k=0, t=0.0, q=(0.0, 0.0, 0.0),
                        q_dot=(0.0, 0.0, 0.0), robots=[],
                        obstacles=[body] * min(n, MAX_BODIES)))
    if n > MAX_BODIES:  # built as a list: the Struct would refuse it at construction
        fields = msgspec.msgpack.decode(raw)
        fields[-2] = fields[-2] * (n // MAX_BODIES + 1)
        raw = msgspec.msgpack.encode(fields)
    assert (CODEC.decode(Sample, raw) is None) == (n > MAX_BODIES)


def test_a_message_of_another_wire_version_is_refused_and_counted_apart() -> None:
    """Old and new installs told apart: a version-1 state (its old layout) and a
    current message relabelled version 1 are both refused, and counted as such."""
    codec = Codec(list(ROBOT_IDS))
    old_state = msgspec.msgpack.encode([1, 0, 0, 5, 1, 0, 0.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    fields = msgspec.msgpack.decode(encode(Sample(
        WIRE_VERSION, 0, 0, 0, robot=1, k=0, t=0.0, q=(0.0, 0.0, 0.0), q_dot=(0.0, 0.0, 0.0),
        robots=[], obstacles=[])))
    fields[0] = 1
    for raw in (old_state, msgspec.msgpack.encode(fields)):
        assert codec.decode(Sample, raw, 1) is None
    assert codec.wrong_version == 2 and codec.versions_seen == {1}
    assert codec.decode(Sample, b"\xc1garbage", 1) is None
    assert codec.wrong_version == 2  # garbage is invalid, not another version


STATE_FLOATS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([FLOAT_LIMIT, -FLOAT_LIMIT, math.nextafter(FLOAT_LIMIT, math.inf),
                     -math.nextafter(FLOAT_LIMIT, math.inf), 1e308, math.nan, -math.inf]))


@fuzz_settings(200)
@given(st.lists(STATE_FLOATS, min_size=6, max_size=6))
def test_the_plants_one_check_of_a_state_says_what_the_receivers_schema_takes(
        values: list[float]) -> None:
    """The plant sends its samples unchecked when ``within_wire_bound`` passed its state:
    so it must pass exactly the states whose sample the receivers' decoder accepts."""
    q, q_dot = tuple(values[:3]), tuple(values[3:])
    raw = encode(Sample(WIRE_VERSION, 0, 0, 0, robot=ROBOT_IDS[0], k=0, t=0.0, q=q,
                        q_dot=q_dot, robots=[], obstacles=[]))
    taken = CODEC.decode(Sample, raw, ROBOT_IDS[0]) is not None
    assert within_wire_bound([list(q)], [list(q_dot)]) == taken
