"""Variants of a scenario, made in memory and validated like a file (docs/safety.md):

- :func:`perturbed`: obstacles (discs, walls, polygons: each moved rigidly) and starts
  jittered, seeded (the same seed gives the same
  scenario); a start that would overlap an obstacle or another robot (gap below
  ``min_start_gap_m``) is drawn again, so a variant never starts in contact;
- :func:`with_obstacle_pair`: the scenario's obstacles replaced by two discs leaving a
  gap of ``ratio`` times the robot's width, centred ``offset_m`` beside the leader's path;
- :func:`scenario_toml`: any scenario as TOML text (every key written), to save a variant.

``omnifleet scenario perturb`` writes :func:`perturbed` files; ``omnifleet safety sweep``
runs many of them (deploy/run/safety_sweep.py).
"""

from __future__ import annotations

import math
import random
from typing import Any

import msgspec

from deploy.contract.scenario import Obstacle, Scenario, obstacle_shapes, parse_scenario

MAX_DRAWS = 200  # per start: a field that leaves no room is an error, not a hang


def _reloaded(sc: Scenario, spec: Any, name: str) -> Scenario:
    """The changed spec through the same validation as a file."""
    spec = msgspec.structs.replace(spec, name=name)
    return parse_scenario(scenario_toml_of(spec), f"{sc.path} ({name})")


def perturbed(sc: Scenario, seed: int, obstacle_jitter_m: float | None = None,
              start_jitter_m: float | None = None, min_start_gap_m: float = 0.05) -> Scenario:
    """``sc`` with every obstacle moved uniformly within ``obstacle_jitter_m`` (default:
    two robot radii) and every start within ``start_jitter_m`` (default: one robot
    radius), seeded by ``seed``."""
    s = sc.spec
    r = s.robot.body_radius_m
    oj = 2.0 * r if obstacle_jitter_m is None else obstacle_jitter_m
    sj = r if start_jitter_m is None else start_jitter_m
    for name, value in (("obstacle jitter", oj), ("start jitter", sj)):
        if not math.isfinite(value) or value < 0:
            raise ValueError(f"{name} must be a finite number >= 0, not {value!r}")
    rng = random.Random(seed)

    def jitter(x: float, y: float, by: float) -> list[float]:
        a, d = rng.uniform(0.0, 2.0 * math.pi), by * math.sqrt(rng.uniform(0.0, 1.0))
        return [x + d * math.cos(a), y + d * math.sin(a)]

    obstacles = [msgspec.structs.replace(o, position=jitter(*o.position, oj)) for o in s.obstacles]

    def shift(points: list[list[float]]) -> list[list[float]]:  # one rigid move for a body
        dx, dy = jitter(0.0, 0.0, oj)
        return [[x + dx, y + dy] for x, y in points]

    walls = []
    for w in s.walls:
        start, end = shift([w.start, w.end])
        walls.append(msgspec.structs.replace(w, start=start, end=end))
    polygons = [msgspec.structs.replace(p, vertices=shift(p.vertices)) for p in s.polygons]
    shapes = obstacle_shapes(msgspec.structs.replace(s, obstacles=obstacles, walls=walls,
                                                     polygons=polygons))
    placed: list[tuple[float, float]] = []
    robots = []
    for k, robot in enumerate(s.robots):
        for _ in range(MAX_DRAWS):
            x, y = jitter(*robot.position, sj)
            if all(math.hypot(x - o.position[0], y - o.position[1]) - o.radius_m - r >= min_start_gap_m
                   for o in obstacles) and all(
                    p.nearest(x, y)[2] - r >= min_start_gap_m for p in shapes) and all(
                    math.hypot(x - px, y - py) - 2 * r >= min_start_gap_m for px, py in placed):
                break
        else:
            raise ValueError(f"seed {seed}: no start for robot #{k + 1} clear of the others "
                             f"within {MAX_DRAWS} draws; use a smaller jitter")
        placed.append((x, y))
        robots.append(msgspec.structs.replace(robot, position=[x, y]))
    spec = msgspec.structs.replace(s, obstacles=obstacles, walls=walls, polygons=polygons,
                                   robots=robots)
    return _reloaded(sc, spec, f"{s.name}-perturbed-{seed}")


def with_obstacle_pair(sc: Scenario, ratio: float, offset_m: float = 0.0, at_x: float = 3.0,
                       obstacle_radius_m: float = 0.15) -> Scenario:
    """``sc`` with two disc obstacles at x = ``at_x`` leaving a gap of ``ratio`` robot
    widths (surface to surface), its middle ``offset_m`` to the side of y = 0."""
    r = sc.spec.robot.body_radius_m
    half = ratio * r  # half the gap: ratio * width / 2
    pair = [Obstacle(position=[at_x, offset_m + s * (half + obstacle_radius_m)],
                     radius_m=obstacle_radius_m) for s in (1.0, -1.0)]
    spec = msgspec.structs.replace(sc.spec, obstacles=pair)
    return _reloaded(sc, spec, f"{sc.spec.name}-gap-{ratio:g}x-off-{offset_m:g}")


def _no_none(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _no_none(v) for k, v in x.items() if v is not None}
    if isinstance(x, list):
        return [_no_none(v) for v in x]
    return x


def scenario_toml_of(spec: Any) -> str:
    """A scenario spec as TOML (optional keys left unset are left out)."""
    import tomli_w  # the TOML writer of the tomli author (the standard library only reads)

    return tomli_w.dumps(_no_none(msgspec.to_builtins(spec)))


def scenario_toml(sc: Scenario) -> str:
    return scenario_toml_of(sc.spec)
