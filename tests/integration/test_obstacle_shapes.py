"""Walls and convex polygons as obstacles (docs/scenarios.md): the geometry against hand-worked
distances, the loader (loads, refuses bad shapes and overlapping starts with the key),
perception (the nearest point, in range only; pybullet's the same), pybullet contacts
with the real shapes, the metrics' gaps, the Foxglove scene and perturbed()."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scenario_edits import WALL_GAP, refused

from deploy.cli import main
from deploy.contract.scenario import SCENARIO_DIR, load_scenario, parse_scenario
from deploy.contract.scenario_variants import perturbed
from deploy.report.metrics import compute_metrics
from deploy.run.runner import run_in_process
from plant.perception import sense
from plant.shapes import Polygon, convex_ccw, offset_outline, signed_distances, wall_vertices

SQUARE = Polygon(-1, convex_ccw([[0, 0], [1, 0], [1, 1], [0, 1]]), "polygons[0]")


# -- geometry -----------------------------------------------------------------------------
@pytest.mark.parametrize("point, nearest, dist", [
    ((0.5, -2.0), (0.5, 0.0), 2.0),  # beside an edge
    ((2.0, 2.0), (1.0, 1.0), math.sqrt(2.0)),  # beyond a corner: the vertex
    ((0.5, 0.2), (0.5, 0.0), -0.2),  # inside: negative, nearest edge
    ((1.0, 0.5), (1.0, 0.5), 0.0),  # on the boundary
])
def test_nearest_point_and_signed_distance_of_a_square(point, nearest, dist):
    px, py, d = SQUARE.nearest(*point)
    assert (px, py) == pytest.approx(nearest) and d == pytest.approx(dist)
    assert signed_distances(np.array([point]), SQUARE)[0] == pytest.approx(dist)


def test_vectorised_distances_equal_the_scalar_query_on_random_points():
    poly = Polygon(-2, convex_ccw([[0, 0], [2, -1], [3, 1], [1, 2.5], [-0.5, 1]]))
    pts = np.random.default_rng(3).uniform(-3, 5, (400, 2))
    assert np.allclose(signed_distances(pts, poly), [poly.nearest(*p)[2] for p in pts], atol=1e-12)


def test_a_wall_is_the_rectangle_of_its_thickness():
    wall = Polygon(-1, wall_vertices((0.0, 0.0), (0.0, 2.0), 0.2))
    assert convex_ccw(wall.vertices) == wall.vertices  # already counter-clockwise
    assert wall.nearest(1.0, 1.0)[2] == pytest.approx(0.9)  # the face, 0.1 m from the line
    assert wall.nearest(0.0, 3.0)[2] == pytest.approx(1.0)  # beyond its end cap
    ring = offset_outline(wall, 0.5)
    assert np.allclose(signed_distances(ring, wall), 0.5)


@pytest.mark.parametrize("vertices", [
    [[0, 0], [1, 0]],  # two points
    [[0, 0], [1, 0], [2, 0]],  # on a line: no area
    [[0, 0], [2, 0], [1, 0.5], [2, 2], [0, 2]],  # concave
    [[0, 0], [1, 1], [1, 0], [0, 1]],  # crosses itself
    [[math.cos(a), math.sin(a)] for a in np.arange(5) * 4 * math.pi / 5],  # a star: winds twice
])
def test_not_a_convex_polygon(vertices):
    assert convex_ccw(vertices) is None


def test_either_winding_is_accepted_and_made_counter_clockwise():
    cw = [[0, 0], [0, 1], [1, 1], [1, 0]]
    assert convex_ccw(cw) == ((1.0, 0.0), (1.0, 1.0), (0.0, 1.0), (0.0, 0.0))


# -- the loader ------------------------------------------------------------------------------
def test_wall_gap_loads_walls_and_polygons_with_idents_after_the_discs():
    sc = load_scenario("wall-gap")
    shapes = sc.obstacle_shapes()
    assert [(p.ident, p.name) for p in shapes] == [(-1, "walls[0]"), (-2, "polygons[0]")]
    assert shapes[0].vertices == ((2.55, 0.5), (2.55, 2.5), (2.45, 2.5), (2.45, 0.5))
    assert sc.obstacle_names() == {-1: "walls[0]", -2: "polygons[0]"}
    with_disc = parse_scenario(WALL_GAP.replace("[[walls]]", "[[obstacles]]\nposition = [0, 3]\n"
                                                "radius_m = 0.1\n\n[[walls]]"), "x.toml")
    assert [p.ident for p in with_disc.obstacle_shapes()] == [-2, -3]
    assert with_disc.obstacle_names()[-1] == "obstacles[0]"


@pytest.mark.parametrize("old, new, key, words", [
    ("end = [2.5, 2.5]", "end = [2.5, 0.5]", "walls[0]", "same point"),
    ("thickness_m = 0.1", "thickness_m = 0.0", "walls[0].thickness_m", "(> 0)"),
    ("thickness_m = 0.1", "thickness_m = 1e-300", "walls[0].thickness_m", "at least 0.001 m"),
    ("thickness_m = 0.1", "thickness_m = -1", "walls[0].thickness_m", "(> 0)"),
    ("end = [2.5, 2.5]", "end = [2.5, 2.5, 0]", "walls[0].end", "expected 2 numbers"),
    ("end = [2.5, 2.5]", "end = [2.5, nan]", "walls[0].end[1]", "finite"),
    ("thickness_m = 0.1", "thicknes_m = 0.1", "walls[0]", "did you mean `thickness_m`"),
    ("vertices = [[2.3, -0.4], [2.7, -0.4], [2.9, -1.6], [2.1, -1.6]]",
     "vertices = [[2.3, -0.4], [2.7, -0.4]]", "polygons[0].vertices", "at least 3 vertices"),
    ("vertices = [[2.3, -0.4], [2.7, -0.4], [2.9, -1.6], [2.1, -1.6]]",
     "vertices = [[2.3, -0.4], [2.7, -0.4], [2.5, -1.0], [2.9, -1.6], [2.1, -1.6]]",
     "polygons[0].vertices", "convex"),
    ("vertices = [[2.3, -0.4], [2.7, -0.4], [2.9, -1.6], [2.1, -1.6]]",
     "vertices = [[2.3, -0.4], [2.7], [2.9, -1.6]]", "polygons[0].vertices[1]",
     "expected 2 numbers"),
    ("vertices = [[2.3", "verts = [[2.3", "polygons[0]", "did you mean `vertices`"),
    ("[2.7, -0.4], [2.9", "[2.3, -0.4000001], [2.9", "polygons[0].vertices",
     "vertices 0 and 1 are closer than 0.001 m"),
])
def test_a_bad_wall_or_polygon_is_refused_naming_the_key(old, new, key, words):
    msg = refused(old, new)
    assert "mine.toml" in msg and f"`{key}`" in msg and words in msg, msg


def test_a_start_just_clear_of_a_wall_loads():
    sc = parse_scenario(WALL_GAP.replace("position = [-0.2, 0.0]", "position = [2.2, 1.0]"), "x")
    gaps = sc.obstacle_gaps(sc.initial_state()[0][:, :2])
    assert gaps[2, 0] == pytest.approx(2.45 - 2.2 - 0.2)  # 5 cm from the wall's face


@pytest.mark.parametrize("position, name, gap, inside", [
    ("[2.3, 1.0]", "walls[0]", 0.15 - 0.2, False),  # 0.15 m from the face: 5 cm overlap
    ("[2.5, 1.0]", "walls[0]", -0.05 - 0.2, True),  # centre inside the wall
    ("[2.5, -0.25]", "polygons[0]", 0.15 - 0.2, False),  # 0.15 m above its top edge
    ("[2.5, -1.0]", "polygons[0]", None, True),  # inside the polygon
])
def test_a_start_on_a_wall_or_polygon_is_refused_with_both_names_and_the_gap(
        position, name, gap, inside):
    msg = refused("position = [-0.2, 0.0]", f"position = {position}")
    assert "`robots.position`" in msg and f"robot 3 starts on {name}" in msg, msg
    assert ("(inside)" in msg) == inside
    if gap is not None:
        assert f"gap {gap:.3f} m" in msg


def test_scenario_check_refuses_a_concave_polygon_with_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(WALL_GAP.replace("[2.9, -1.6], [2.1", "[2.5, -0.6], [2.1", 1))
    assert main(["scenario", "check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "polygons[0].vertices" in err and "convex" in err and "Traceback" not in err
    assert main(["scenario", "check", "wall-gap"]) == 0
    out = capsys.readouterr().out
    assert "1 walls, 1 polygons" in out and "leader path waypoints" in out


# -- perception -------------------------------------------------------------------------------
def test_a_wall_is_perceived_as_its_nearest_point_within_range_only():
    sc = load_scenario("wall-gap")
    shapes = sc.obstacle_shapes()
    pos = np.array([[1.0, 1.0], [1.0, -1.0], [-0.6, 1.0]])
    _, seen = sense(0, pos, np.zeros((3, 2)), [0.2] * 3, [1, 2, 3], [], 3.0, shapes)
    wall, poly = seen
    assert wall.ident == -1 and wall.radius == 0.0 and not wall.velocity.any()
    assert wall.position == pytest.approx([2.45, 1.0])  # the face, straight across
    assert poly.ident == -2 and poly.position == pytest.approx([2.3, -0.4])  # its corner
    _, seen = sense(2, pos, np.zeros((3, 2)), [0.2] * 3, [1, 2, 3], [], 3.06, shapes)
    assert [b.ident for b in seen] == [-1]  # the wall's face 3.05 m away; the polygon farther
    _, seen = sense(2, pos, np.zeros((3, 2)), [0.2] * 3, [1, 2, 3], [], 3.04, shapes)
    assert seen == []  # the wall's face is 3.05 m away


def test_pybullet_perceives_walls_and_polygons_as_sense_does():
    from deploy.run.runner import make_plant

    sc = load_scenario("wall-gap")
    plant = make_plant(sc, "pybullet")
    try:
        for i in range(sc.n):
            _, seen = plant.perceive(i, sc.spec.behaviors.detection_range_m)
            _, ref = sense(i, plant.q[:, :2], plant.q_dot[:, :2], [0.2] * 3, sc.robot_ids,
                           [], sc.spec.behaviors.detection_range_m, sc.obstacle_shapes())
            assert [(b.ident, b.position.tolist()) for b in seen] == \
                [(b.ident, b.position.tolist()) for b in ref]
    finally:
        plant.close()


# -- contacts: real shapes in pybullet ------------------------------------------------------
@pytest.mark.parametrize("target, wall, face_x", [
    ("walls", True, 2.45),  # driven east into the wall's west face
    ("polygons", False, None),
])
def test_a_robot_driven_into_a_wall_or_polygon_touches_it_and_stops_at_its_surface(
        target, wall, face_x):
    from plant.pybullet_plant import PybulletPlant

    sc = load_scenario("wall-gap")
    r, dt = sc.spec.robot.body_radius_m, sc.dt
    poly = sc.obstacle_shapes()[0 if wall else 1]
    # start 0.5 m from the shape, heading straight at it: east at y = 1.5 for the wall,
    # north at x = 2.5 under the polygon's bottom edge (y = -1.6)
    start, push_dir = ((1.75, 1.5), (1.0, 0.0)) if wall else ((2.5, -2.3), (0.0, 1.0))
    q = np.array([[*start, 0.0]])
    body_push = np.array([1.0, 1.0, 1.0, 1.0]) if wall else np.array([-1.0, 1.0, 1.0, -1.0])
    with PybulletPlant([sc.model()], q, np.zeros((1, 3)), lambda t: np.zeros(4), [r], [5], [],
                       sc.spec.plant.substeps, shapes=[poly]) as plant:
        closest = np.inf
        for k in range(int(round(2.0 / dt))):
            plant.step(k * dt, dt, 0.5 * body_push[None], None)
            closest = min(closest, poly.nearest(*plant.q[0, :2])[2])
        assert [(e.body_a, e.body_b) for e in plant.contacts] == [(5, poly.ident)], plant.contacts
        assert 0.0 <= plant.contacts[0].max_depth_m <= 1e-3
        assert r - 1e-3 <= closest <= r + 1e-6  # at the surface, not through it
        moved = plant.q[0, :2] - np.array(start)
        assert float(moved @ np.array(push_dir)) == pytest.approx(0.5, abs=2e-3)  # the gap
        if face_x is not None:
            assert plant.q[0, 0] + r == pytest.approx(face_x, abs=1e-3)


# -- metrics, scene, variants ------------------------------------------------------------------
def test_obstacle_gaps_are_surface_to_surface_for_every_kind():
    sc = parse_scenario(WALL_GAP.replace("[[walls]]", "[[obstacles]]\nposition = [0, 3]\n"
                                         "radius_m = 0.1\n\n[[walls]]"), "x.toml")
    pos = np.array([[[0.0, 2.0], [1.0, 1.0], [2.5, -2.6]]])  # (k=1, n=3, 2)
    gaps = sc.obstacle_gaps(pos)[0]
    assert gaps.shape == (3, 3)
    assert gaps[0, 0] == pytest.approx(1.0 - 0.1 - 0.2)  # disc
    assert gaps[1, 1] == pytest.approx(2.45 - 1.0 - 0.2)  # the wall's face
    assert gaps[2, 2] == pytest.approx(1.0 - 0.2)  # the polygon's bottom edge at y = -1.6


def test_the_foxglove_scene_draws_each_wall_and_polygon():
    from foxglove_decode import decode

    from deploy.report.foxglove_scene import FleetScene
    from deploy.report.foxglove_topics import SCENE_OBSTACLES
    from deploy.report.timeseries import TimeSeries

    sc = load_scenario("wall-gap")
    ts = TimeSeries.allocate(1, sc.n)
    q, qd = sc.initial_state()
    q0, v0 = sc.initial_estimates(0)
    ts.record_world(0, 0.0, q0, v0, q, qd, q[:, :2])
    msg = FleetScene(sc).scene_messages(ts, 0)[SCENE_OBSTACLES]
    schema = msg.get_schema()  # decoded as Foxglove decodes it (tests/foxglove_decode.py)
    ents = decode(schema.name, schema.encoding, schema.data, "protobuf", msg.encode()).entities
    assert [e.id for e in ents] == ["obstacle-1", "obstacle-2"]
    for e, poly in zip(ents, sc.obstacle_shapes(), strict=True):
        tri = e.triangles[0].points
        n = len(poly.vertices)
        assert len(tri) == 3 * ((n - 2) + 2 * n)  # top fan + two per side
        assert {(p.x, p.y) for p in tri} == set(poly.vertices)  # float64 on the wire
        outline, band = e.lines
        assert len(outline.points) == n
        band_xy = np.array([[p.x, p.y] for p in band.points])
        assert np.allclose(signed_distances(band_xy, poly), sc.spec.behaviors.obstacle_safe_distance_m)


def test_perturbed_moves_walls_and_polygons_rigidly_and_reproducibly():
    sc = load_scenario("wall-gap")
    a, b, c = (perturbed(sc, seed, obstacle_jitter_m=0.3, start_jitter_m=0.0) for seed in (1, 1, 2))
    assert a.spec.walls == b.spec.walls and a.spec.polygons == b.spec.polygons
    assert a.spec.polygons != c.spec.polygons
    for before, after in zip(sc.obstacle_shapes(), a.obstacle_shapes(), strict=True):
        shift = after.array - before.array
        assert np.allclose(shift, shift[0], atol=1e-12)  # every vertex moved the same way
        assert 0.0 < np.hypot(*shift[0]) <= 0.3 + 1e-12


def test_the_starters_commented_wall_polygon_and_waypoints_load_when_uncommented():
    import re

    from deploy.cli.scenario import STARTER

    # the waypoints replace the harmonic path's lines, as the starter says
    text = re.sub(r'^(path = "harmonic"|[xy] = \{.*|theta_rate = .*)\n', "", STARTER.read_text(),
                  flags=re.M)
    text = re.sub(r"^#   (?=\[\[|\w+ = )", "", text, flags=re.M)
    sc = parse_scenario(text, "starter-uncommented.toml")
    assert sc.spec.leader.path == "waypoints"
    assert [p.name for p in sc.obstacle_shapes()] == ["walls[0]", "polygons[0]"]


def test_one_robot_sent_at_a_wall_stops_short_of_it():
    """The leader drives straight through a wall; the robot, perceiving the wall's
    nearest point, keeps the safety margin off its face (model plant, in process)."""
    text = (SCENARIO_DIR / "wall-gap.toml").read_text()
    robots = text[text.index("[[robots]]"):text.index("[graph]")]
    graph = text[text.index("[graph]"):text.index("[leader]")]
    one = text.replace(robots, "[[robots]]\nid = 1\nposition = [1.4, 1.5]\noffset = [0.0, 0.0]\n\n")
    one = one.replace(graph, "[graph]\nadjacency = [[0]]\nleader = [1]\n\n")
    one = one.replace("waypoints = [[1.4, 0.0], [2.5, 0.0], [3.6, 0.0], [5.0, 0.6], [6.0, 2.0]]",
                      "waypoints = [[1.4, 1.5], [4.0, 1.5]]")
    sc = parse_scenario(one.replace('kind = "pybullet"', 'kind = "model"'), "one.toml")
    res = run_in_process(sc, duration_s=3.0)
    m = compute_metrics(sc, res.series, res.plant, "lockstep", res.wall_time_s)
    wall = sc.obstacle_shapes()[0]
    gaps = np.array([wall.nearest(*p)[2] for p in res.series.q[:, 0, :2]]) - 0.2
    assert m["contacts"] == 0 and gaps.min() == pytest.approx(m["min_obstacle_gap_m"])
    assert gaps.min() >= sc.spec.safety.margin_m - 5e-3  # the margin, to a few mm (0.0503 m)
    assert res.series.leader_q[-1, 0] > 3.0  # while the leader went through the wall
    assert res.series.q[-1, 0, 0] < 2.45 - 0.2  # the robot stayed on its side
