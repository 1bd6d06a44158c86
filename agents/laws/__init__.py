"""The laws that come with omnifleet, by name, and how a law is named where one is chosen
(a scenario's ``[law] use``, ``--law``; docs/laws.md).

A name is one of:

- ``paper``: the paper's law, compiled (agents/law_kernel.pyx), the default;
- a bundled law's name (:data:`BUNDLED`);
- ``module:Class``: a class of an importable module (``mylab.laws:Swarm``);
- ``path/to/file.py:Class``: a class of a Python file (a path relative to the working
  directory, or absolute).

The class must be a :class:`agents.law_api.BehaviorLaw` or :class:`agents.law_api.TorqueLaw`
whose ``Params`` is a dataclass; :func:`load` says what is wrong otherwise (a file that does
not import: its exception), before any process starts.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
import importlib.util
import math
import sys
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from agents.law_api import LEVELS, BehaviorLaw, ControlLaw, TorqueLaw

PAPER = "paper"
BUNDLED: dict[str, str] = {
    "consensus": "agents.laws.consensus:ConsensusLaw",
    "consensus-pd": "agents.laws.consensus_pd:ConsensusPdLaw",
}
NAMES = (PAPER, *BUNDLED)


class LawError(ValueError):
    """A law that cannot be used, as named (exit 2 at the command line)."""


def load(spec: str) -> type[ControlLaw] | None:
    """The class a law's name names (None: the paper's compiled law)."""
    spec = spec.strip()
    if spec == PAPER:
        return None
    target = BUNDLED.get(spec, spec)
    where, sep, cls_name = target.rpartition(":")
    if not sep or not where or not cls_name.isidentifier():
        raise LawError(f"law {spec!r}: expected {', '.join(NAMES)}, module:Class or "
                       "path/to/file.py:Class" + _near(spec))
    try:
        module = _file_module(where) if where.endswith(".py") else importlib.import_module(where)
    except LawError:
        raise
    except Exception as exc:  # noqa: BLE001 - a lab's module may fail any way
        raise LawError(f"law {spec!r}: {where} does not import: {type(exc).__name__}: {exc}") from exc
    cls = getattr(module, cls_name, None)
    if cls is None:
        found = [n for n, v in vars(module).items()
                 if isinstance(v, type) and issubclass(v, ControlLaw)
                 and v not in (ControlLaw, BehaviorLaw, TorqueLaw)]
        raise LawError(f"law {spec!r}: {where} has no {cls_name}"
                       + (f" (its laws: {', '.join(found)})" if found else ""))
    check_class(cls, spec)
    return cls


def _file_module(path: str) -> Any:
    file = Path(path).expanduser()
    if not file.is_file():
        raise LawError(f"law file {path}: not a file")
    name = f"omnifleet_law_{abs(hash(str(file.resolve())))}"
    if name in sys.modules:  # one import per process (every robot's agent shares it)
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, file)
    if spec is None or spec.loader is None:
        raise LawError(f"law file {path}: not a Python module")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module


def check_class(cls: Any, spec: str) -> None:
    """That ``cls`` is a law the runtime can step (LawError naming what is not)."""
    if not (isinstance(cls, type) and issubclass(cls, ControlLaw)):
        raise LawError(f"law {spec!r}: {getattr(cls, '__name__', cls)!r} is not a "
                       "BehaviorLaw or a TorqueLaw (agents/law_api.py)")
    if cls.level not in LEVELS:
        raise LawError(f"law {spec!r}: {cls.__name__} says no level: subclass BehaviorLaw "
                       "or TorqueLaw")
    if cls.step in (ControlLaw.step, BehaviorLaw.step, TorqueLaw.step):
        raise LawError(f"law {spec!r}: {cls.__name__} does not define step(self, inputs)")
    if not dataclasses.is_dataclass(cls.Params):
        raise LawError(f"law {spec!r}: {cls.__name__}.Params must be a dataclass of its "
                       "parameters with their defaults")


def params_of(cls: type[ControlLaw] | None, given: Mapping[str, Any], spec: str) -> Any:
    """The law's ``Params`` from ``given`` (a scenario's ``[law] params``): each name must be
    one of its fields (the nearest one is suggested), each value of its field's type,
    numbers finite; the rest keep their defaults. The paper's law takes none here (its
    gains are the scenario's own tables)."""
    if cls is None:
        if given:
            raise LawError(f"law {spec!r} takes no [law] params: its gains are the "
                           "scenario's own tables ([controller], [eso], [estimator], ...)")
        return None
    try:
        kinds = typing.get_type_hints(cls.Params)
    except Exception as exc:  # noqa: BLE001 - an annotation that does not resolve
        raise LawError(f"law {spec!r}: {cls.__name__}.Params: {exc}") from exc
    fields = [f.name for f in dataclasses.fields(cls.Params)]
    values: dict[str, Any] = {}
    for name, value in given.items():
        if name not in fields:
            raise LawError(f"law {spec!r}: no parameter {name!r}" + _near(name, fields)
                           + (f" (its parameters: {', '.join(fields)})" if fields else
                              " (it takes none)"))
        want = kinds.get(name)
        if want is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)  # TOML's 2 for 2.0
        if want in (float, int, bool, str) and type(value) is not want:
            raise LawError(f"law {spec!r}: parameter {name!r} must be a {want.__name__}, "
                           f"got {value!r}")
        if isinstance(value, float) and not math.isfinite(value):
            raise LawError(f"law {spec!r}: parameter {name!r} must be finite, got {value!r}")
        values[name] = value
    try:
        return cls.Params(**values)
    except (TypeError, ValueError) as exc:  # a parameter without a default, its own check
        raise LawError(f"law {spec!r}: {exc}") from exc


def _near(word: str, known: Any = NAMES) -> str:
    near = difflib.get_close_matches(word, list(known), n=1, cutoff=0.6)
    return f"; did you mean {near[0]!r}?" if near else ""
