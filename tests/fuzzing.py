"""Shared machinery of the fuzz tests (tests/test_fuzz_*.py): budget, counting, strategies.

Every decoder is fuzzed through :func:`fuzz_decoder`, which calls it on one input,
lets only the decoder's documented rejection through (``None`` or one of
``rejects``), checks what it accepted, and counts the input in :data:`TALLY`; the
counts are printed at the end of the pytest run (tests/conftest.py). Adding a
decoder (the fault-plan file, say) is a strategy and a test of a few lines::

    @fuzz_settings(300)
    @given(text=st.text())
    def test_fault_plan_decoder(text: str) -> None:
        fuzz_decoder("fault plan", lambda t: parse_fault_plan(t), text,
                     rejects=(FaultPlanError,), check=assert_finite_plan)

Budget: each test gives its own suite default (so the whole fuzz suite stays well
under a minute on two cores); ``OMNIFLEET_FUZZ_EXAMPLES=N`` replaces every default
by N for a big run by hand. Examples are derandomized (the same inputs on every
run: CI is reproducible; a bigger budget explores further from the same start).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import msgspec
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

T = TypeVar("T")
R = TypeVar("R")

ENV_EXAMPLES = "OMNIFLEET_FUZZ_EXAMPLES"


def budget(default: int) -> int:
    """Inputs per test: ``default``, or ``$OMNIFLEET_FUZZ_EXAMPLES`` when set."""
    raw = os.environ.get(ENV_EXAMPLES, "").strip()
    return int(raw) if raw else default


def fuzz_settings(default_examples: int) -> settings:
    """Bounded, reproducible hypothesis settings for one fuzz test."""
    return settings(
        max_examples=budget(default_examples),
        derandomize=True,
        database=None,
        deadline=None,
        print_blob=True,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                               HealthCheck.filter_too_much, HealthCheck.large_base_example],
    )


@dataclass
class DecoderTally:
    tried: int = 0
    accepted: int = 0
    rejected: int = 0


@dataclass
class Tally:
    """Inputs tried per decoder in this pytest process (and its workers', added at their end)."""

    by_decoder: dict[str, DecoderTally] = field(default_factory=dict)

    def record(self, decoder: str, accepted: bool) -> None:
        t = self.by_decoder.setdefault(decoder, DecoderTally())
        t.tried += 1
        if accepted:
            t.accepted += 1
        else:
            t.rejected += 1

    def add(self, decoder: str, tried: int, accepted: int, rejected: int) -> None:
        """Counts from another process (a pytest-xdist worker)."""
        t = self.by_decoder.setdefault(decoder, DecoderTally())
        t.tried += tried
        t.accepted += accepted
        t.rejected += rejected

    def lines(self) -> list[str]:
        width = max((len(k) for k in self.by_decoder), default=0)
        return [f"{name:<{width}}  tried {t.tried:>8}  accepted {t.accepted:>8}  "
                f"rejected {t.rejected:>8}"
                for name, t in sorted(self.by_decoder.items())]


TALLY = Tally()


def fuzz_decoder(
    name: str,
    decode: Callable[[T], R | None],
    value: T,
    rejects: tuple[type[BaseException], ...] = (),
    check: Callable[[R], None] | None = None,
) -> R | None:
    """``decode(value)``: a result (checked by ``check``), ``None`` or one of
    ``rejects`` (counted rejected). Any other exception fails the test."""
    try:
        out = decode(value)
    except rejects:
        TALLY.record(name, accepted=False)
        return None
    TALLY.record(name, accepted=out is not None)
    if out is not None and check is not None:
        check(out)
    return out


# --- properties ------------------------------------------------------------------------
def non_finite_floats(value: Any, where: str = "") -> list[str]:
    """Paths of every NaN/Inf float inside ``value`` (structs, tuples, lists, dicts)."""
    if isinstance(value, float):
        return [] if math.isfinite(value) else [where or "."]
    if isinstance(value, msgspec.Struct):
        return [p for f in value.__struct_fields__
                for p in non_finite_floats(getattr(value, f), f"{where}.{f}")]
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in non_finite_floats(v, f"{where}[{k!r}]")]
    if isinstance(value, list | tuple):
        return [p for i, v in enumerate(value) for p in non_finite_floats(v, f"{where}[{i}]")]
    return []


def assert_all_finite(values: Iterable[float], what: str) -> None:
    bad = [v for v in values if not math.isfinite(v)]
    assert not bad, f"{what}: non-finite {bad}"


# --- strategies ------------------------------------------------------------------------
INT64 = (-(2**63), 2**63 - 1)

nasty_floats = st.sampled_from([
    math.nan, -math.nan, math.inf, -math.inf, 0.0, -0.0, 5e-324, 1e-308, 1e308, -1e308,
    1.7976931348623157e308, 3.4028234663852886e38, 3.5e38, 1e39, 1e3, 1e3 + 1e-9, 2.0, 2.0000001,
])
"""Floats at the edges: non-finite, signed zero, subnormal, float32 overflow, limits."""

any_float = st.one_of(st.floats(allow_nan=True, allow_infinity=True), nasty_floats)

nasty_ints = st.sampled_from([0, -1, 1, 2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**63 - 1, -(2**63),
                              2**64 - 1])
any_int = st.one_of(st.integers(min_value=INT64[0], max_value=2**64 - 1), nasty_ints)

msgpack_scalars = st.one_of(st.none(), st.booleans(), any_int, any_float,
                            st.text(max_size=40), st.binary(max_size=40))
any_msgpack = st.recursive(
    msgpack_scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=6),
                            st.dictionaries(st.text(max_size=8), inner, max_size=4)),
    max_leaves=20,
)
"""Any value msgpack can encode (bounded size)."""


@st.composite
def mutated_bytes(draw: st.DrawFn, data: bytes) -> bytes:
    """``data`` with a few edits: bit flips, byte overwrites, truncation, extension,
    insertion or deletion of a slice."""
    out = bytearray(data)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "set", "truncate", "extend", "insert", "delete"]))
        if op == "truncate":
            out = out[:draw(st.integers(0, len(out)))]
        elif op == "extend":
            out += draw(st.binary(min_size=1, max_size=16))
        elif op == "insert":
            at = draw(st.integers(0, len(out)))
            out[at:at] = draw(st.binary(min_size=1, max_size=8))
        elif not out:
            continue
        elif op == "flip":
            bit = draw(st.integers(0, 8 * len(out) - 1))
            out[bit // 8] ^= 1 << (bit % 8)
        elif op == "set":
            out[draw(st.integers(0, len(out) - 1))] = draw(st.integers(0, 255))
        else:  # delete
            a = draw(st.integers(0, len(out) - 1))
            del out[a:a + draw(st.integers(1, 8))]
    return bytes(out)
