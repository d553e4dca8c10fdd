"""The simulated world: scenario files validate, geometry and ground truth agree with each other."""

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import ConfigError
from drivers.sim.world import SCENARIO_DIR, World


@pytest.fixture(scope="module")
def world() -> World:
    return World.load("default")


def small_world(**extra) -> World:
    data = {
        "name": "test",
        "boxes": [{"name": "b", "center_ne_m": [10.0, 20.0], "size_m": [8.0, 4.0], "height_m": 6.0, "yaw_deg": 30.0,
                   "textured_height_m": 4.0}],
        "ridges": [{"name": "r", "start_ne_m": [50.0, 0.0], "end_ne_m": [50.0, 30.0], "width_m": 10.0, "height_m": 3.0,
                    "facets": 4}],
        "tree_lines": [{"name": "t", "start_ne_m": [-20.0, -10.0], "end_ne_m": [-20.0, 10.0], "depth_m": 4.0, "height_m": 7.0}],
    }
    data.update(extra)
    return World.from_dict(data, "test.yaml")


# ---- the default scenario reproduces the seed's experiment -------------------------------------


def test_default_scenario_is_the_papers_circuit(world):
    c = world.circuit
    assert c.altitude_agl_m == pytest.approx(15.0)  # ~50 ft
    assert c.speed_mps == pytest.approx(6.0)  # ~20 ft/s
    assert world.clearance_m == pytest.approx(15.0)  # 50 ft
    building = world.obstacle("building")
    assert building.height_m == pytest.approx(12.0)  # ~40 ft
    assert building.textured_height_m == pytest.approx(9.0)  # texture to ~30 ft
    # The circuit passes over the building: some leg crosses its footprint.
    wps = np.vstack([world.waypoints_ne_m, world.waypoints_ne_m[:1]])
    samples = np.concatenate([np.linspace(a, b, 400) for a, b in zip(wps[:-1], wps[1:])])
    heights = world.terrain_height(samples[:, 0], samples[:, 1])
    assert heights.max() == pytest.approx(12.0)
    # Everything else on the circuit is low enough to fly with the law (well under the nominal height).
    others = [o for o in world.obstacles if o.name != "building"]
    assert {o.kind for o in others} == {"trees", "ridge"}
    assert all(o.height_m < c.altitude_agl_m / 2 for o in others)
    assert {"lat_deg", "lon_deg", "alt_m"} <= set(dir(world.home))


def test_window_corners_stop_below_the_textured_height(world):
    corners = world.window_corners_ned("building")
    assert len(corners) >= 4 * 4 * 3  # four walls, several bays, three floors
    alt = -corners[:, 2]
    assert alt.max() <= 9.0 + 1e-9
    assert alt.max() > 8.0  # the top row of windows reaches close to the textured height
    assert alt.min() > 0.0
    # Every corner lies on a wall of the 20 m x 20 m building centred at (100, 0).
    on_wall = np.isclose(np.abs(corners[:, 0] - 100.0), 10.0) | np.isclose(np.abs(corners[:, 1]), 10.0)
    assert np.all(on_wall)


def test_flat_scenario_is_ground_only():
    flat = World.load("flat")
    assert flat.faces == () and flat.obstacles == ()
    n, e = np.meshgrid(np.linspace(-100, 300, 50), np.linspace(-100, 200, 40))
    assert np.all(flat.terrain_height(n, e) == 0.0)


def test_load_by_path_and_seed_override(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text((SCENARIO_DIR / "default.yaml").read_text())
    a = World.load(path)
    b = World.load(str(path), seed=123)
    assert a.seed == 7 and b.seed == 123
    assert a.faces[0].texture.seed != b.faces[0].texture.seed
    assert World.load("default").faces[0].texture.seed == a.faces[0].texture.seed  # deterministic


# ---- ground truth ------------------------------------------------------------------------------


def test_terrain_height_of_a_rotated_box_and_a_ridge():
    w = small_world()
    yaw = np.radians(30.0)
    u, v = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
    c = np.array([10.0, 20.0])
    inside = c + 3.9 * u + 1.9 * v
    outside_long = c + 4.1 * u
    outside_wide = c + 2.1 * v
    h = w.terrain_height(*np.array([inside, outside_long, outside_wide]).T)
    np.testing.assert_allclose(h, [6.0, 0.0, 0.0])
    # The axis-aligned corner (10+4, 20+2) is outside a box yawed by 30 deg.
    assert w.terrain_height(14.0, 22.0) == 0.0
    # Ridge: crest height on the axis, zero at the base edges, piecewise linear between.
    across = np.array([0.0, 2.5, -5.0, 5.0, 6.0])
    h = w.terrain_height(50.0 + across, np.full(5, 15.0))
    np.testing.assert_allclose(h, [3.0, 3.0 * np.cos(np.pi / 4), 0.0, 0.0, 0.0], atol=1e-12)
    # textured_only caps a building at its textured height; trees and ridges are textured all over.
    assert w.terrain_height(*inside, textured_only=True) == pytest.approx(4.0)
    assert w.terrain_height(-20.0, 0.0, textured_only=True) == pytest.approx(7.0)


def test_terrain_height_is_batched():
    w = small_world()
    n = np.zeros((3, 4, 5)) + 10.0
    assert w.terrain_height(n, 20.0).shape == (3, 4, 5)
    assert np.all(w.terrain_height(n, 20.0) == 6.0)


def test_true_height_grid_samples_cell_centres(world):
    grid = world.true_height_grid(80.0, -20.0, 120.0, 20.0, 0.5)
    assert grid.shape == (80, 80)
    xs = 80.0 + (np.arange(80) + 0.5) * 0.5
    ys = -20.0 + (np.arange(80) + 0.5) * 0.5
    np.testing.assert_array_equal(grid, world.terrain_height(xs[:, None], ys[None, :]))
    assert np.sum(grid == 12.0) == 40 * 40  # 20 m x 20 m building in 0.5 m cells
    capped = world.true_height_grid(80.0, -20.0, 120.0, 20.0, 0.5, textured_only=True)
    assert capped.max() == pytest.approx(9.0)
    with pytest.raises(ValueError):
        world.true_height_grid(0, 0, 10, 10, 0.0)


def test_raycast_known_ranges(world):
    origin = np.array([100.0, 0.0, -30.0])  # 30 m above the building's centre
    rays = np.array([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, 0, 5.0]])
    rng, face = world.raycast(origin, rays, return_face=True)
    assert rng[0] == pytest.approx(18.0)  # roof at 12 m
    assert np.isinf(rng[1]) and np.isinf(rng[2])  # up and horizontal above everything: nothing
    assert rng[3] == pytest.approx(18.0)  # rays need not be unit
    assert world.faces[face[0]].structure == "building" and face[1] == -2
    # Horizontally at the south wall (north = 90) from 30 m south of it, 5 m up.
    r = world.raycast(np.array([60.0, 0.0, -5.0]), np.array([[1.0, 0.0, 0.0]]))
    assert r[0] == pytest.approx(30.0)
    # Down onto open ground from 15 m.
    r, f = world.raycast(np.array([0.0, 0.0, -15.0]), np.array([[0.0, 0.0, 1.0]]), return_face=True)
    assert r[0] == pytest.approx(15.0) and f[0] == -1


def test_raycast_rejects_bad_rays(world):
    with pytest.raises(ValueError):
        world.raycast(np.zeros(3), np.zeros((2, 3)))
    with pytest.raises(ValueError):
        world.raycast(np.zeros(3), np.array([[np.nan, 0, 1]]))
    with pytest.raises(ValueError):
        world.raycast(np.zeros((2, 3)), np.ones((3, 3)))


@given(
    st.floats(40.0, 260.0), st.floats(-40.0, 100.0), st.floats(14.0, 40.0),
    st.floats(-np.pi, np.pi), st.floats(0.05, 1.4),
)
@settings(max_examples=60, deadline=None)
def test_raycast_agrees_with_terrain_height(n, e, alt, azimuth, depression):
    """Along any ray from above the scene, every point before the hit is above the terrain, and
    the hit point is on the terrain surface (top) or against a wall (terrain rises just beyond)."""
    world = _DEFAULT
    origin = np.array([n, e, -alt])
    d = np.array([np.cos(depression) * np.cos(azimuth), np.cos(depression) * np.sin(azimuth), np.sin(depression)])
    r = world.raycast(origin, d[None])[0]
    assert np.isfinite(r)  # going down, it always meets at least the ground
    t = np.linspace(0.0, r * (1 - 1e-6) - 1e-4, 200)
    pts = origin + t[:, None] * d
    assert np.all(-pts[:, 2] >= world.terrain_height(pts[:, 0], pts[:, 1]) - 1e-6)
    hit = origin + r * d
    beyond = origin + (r + 1e-3) * d
    h_hit = world.terrain_height(hit[0], hit[1])
    h_beyond = world.terrain_height(beyond[0], beyond[1])
    assert abs(-hit[2] - h_hit) < 1e-3 or -beyond[2] < h_beyond


_DEFAULT = World.load("default")


# ---- validation ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "data, key",
    [
        ({"boxes": [{"heigth_m": 3}]}, "boxes[0].heigth_m"),
        ({"boxes": [{"height_m": -3}]}, "boxes[0].height_m"),
        ({"boxes": [{"height_m": 5, "textured_height_m": 6}]}, "boxes[0].textured_height_m"),
        ({"boxes": [{"wall_texture": "bricks"}]}, "boxes[0].wall_texture"),
        ({"boxes": [{"center_ne_m": [1, 2, 3]}]}, "boxes[0].center_ne_m"),
        ({"ridges": [{"start_ne_m": [0, 0], "end_ne_m": [0, 0]}]}, "ridges[0].end_ne_m"),
        ({"ridges": [{"facets": 1}]}, "ridges[0].facets"),
        ({"tree_lines": [{"height_m": "tall"}]}, "tree_lines[0].height_m"),
        ({"circuit": {"waypoints_ne_m": [[0, 0]]}}, "circuit.waypoints_ne_m"),
        ({"circuit": {"waypoints_ne_m": [[0, 0], [0, 0]]}}, "circuit.waypoints_ne_m"),
        ({"circuit": {"speed_mps": 0}}, "circuit.speed_mps"),
        ({"ground": {"tile_px": 1000}}, "ground.tile_px"),
        ({"home": {"lat_deg": 91}}, "home.lat_deg"),
        ({"boxes": [{"name": "x"}], "ridges": [{"name": "x"}]}, "unique, repeated: x"),
        ({"colour": "red"}, "colour"),
    ],
)
def test_validation_errors_name_the_key_and_the_file(data, key):
    with pytest.raises(ConfigError) as err:
        World.from_dict(data, "bad_scenario.yaml")
    assert "bad_scenario.yaml" in str(err.value) and key in str(err.value)


def test_load_errors_are_clear(tmp_path):
    with pytest.raises(ConfigError, match="no scenario named 'nowhere'.*default"):
        World.load("nowhere")
    bad = tmp_path / "bad.yaml"
    bad.write_text("boxes: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        World.load(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        World.load(tmp_path / "missing.yaml")
    top = tmp_path / "list.yaml"
    top.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping"):
        World.load(top)
    with pytest.raises(ConfigError, match="seed"):
        World.load("flat", seed=-1)


def test_every_shipped_scenario_loads():
    names = sorted(p.stem for p in Path(SCENARIO_DIR).glob("*.yaml"))
    assert {"default", "flat"} <= set(names)
    for name in names:
        assert World.load(name).name == name
