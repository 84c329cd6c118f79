"""Camera geometry: other drones land in the right face and place; the horizon follows the body."""

import math

import numpy as np
import pytest

from companion.camera.layout import FACE_NAMES, IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX, split, stitch
from companion.frames import quat_from_euler_zyx
from sim_harness.sim.quad_body import QuadGeometry
from sim_harness.sim.render import PyBulletRenderer, camera_poses
from sim_harness.sim.world import World

OBSERVER = np.array([0.0, 0.0, 5.0])
FAR_AWAY = np.array([500.0, 500.0, 5.0])


@pytest.fixture(scope="module")
def world():
    with World(2) as w:
        yield w


def where_is_the_other_drone(world, other_pos, q_observer):
    """(face name, row, col) of the centroid of what the other drone changes in the image."""
    renderer = PyBulletRenderer()
    q = np.stack([q_observer, [1.0, 0.0, 0.0, 0.0]])
    with_drone = renderer.render(world, np.stack([OBSERVER, other_pos]), q, [0])[0]
    without = renderer.render(world, np.stack([OBSERVER, FAR_AWAY]), q, [0])[0]
    changed = split(np.abs(with_drone.astype(int) - without.astype(int)) > 20)
    per_face = changed.reshape(6, -1).sum(axis=1)
    face = int(np.argmax(per_face))
    assert per_face[face] >= 2, "the other drone is not visible"
    rows, cols = np.nonzero(changed[face])
    return FACE_NAMES[face], rows.mean(), cols.mean()


def test_drone_straight_ahead_is_in_the_front_face_centre(world) -> None:
    face, row, col = where_is_the_other_drone(world, OBSERVER + [3.0, 0.0, 0.0], [1, 0, 0, 0])
    assert face == "front"
    assert abs(row - 31.5) < 3 and abs(col - 31.5) < 3


def test_drone_above_is_in_the_up_face(world) -> None:
    face, row, col = where_is_the_other_drone(world, OBSERVER + [0.0, 0.0, 3.0], [1, 0, 0, 0])
    assert face == "up"
    assert abs(row - 31.5) < 3 and abs(col - 31.5) < 3


def test_drone_ahead_and_left_is_left_of_centre(world) -> None:
    _, _, col = where_is_the_other_drone(world, OBSERVER + [3.0, 1.5, 0.0], [1, 0, 0, 0])
    assert col < 25


@pytest.mark.parametrize(("yaw_deg", "face"), [(90, "right"), (180, "back"), (-90, "left")])
def test_turning_the_observer_moves_the_drone_to_the_matching_face(world, yaw_deg, face) -> None:
    # The other drone stays 3 m east; the observer turns, so east is on its right / back / left.
    q = quat_from_euler_zyx(0.0, 0.0, math.radians(yaw_deg))
    seen_in, _, col = where_is_the_other_drone(world, OBSERVER + [3.0, 0.0, 0.0], q)
    assert seen_in == face
    assert abs(col - 31.5) < 3


def horizon_row(tile: np.ndarray) -> float:
    """First row (from the top) that is mostly ground: the sky is brighter than 200 everywhere."""
    ground = np.median(tile, axis=1) < 195
    return float(np.argmax(ground))


def test_pitching_moves_the_horizon_the_right_way(world) -> None:
    renderer = PyBulletRenderer()
    pos = np.stack([OBSERVER, FAR_AWAY])
    level = np.array([[1.0, 0, 0, 0]] * 2)
    nose_down = level.copy()
    nose_down[0] = quat_from_euler_zyx(0.0, math.radians(20), 0.0)  # FLU: +pitch = nose down
    front_level = split(renderer.render(world, pos, level, [0]))[0, 0]
    front_down = split(renderer.render(world, pos, nose_down, [0]))[0, 0]
    back_down = split(renderer.render(world, pos, nose_down, [0]))[0, 2]
    # Level: horizon near the middle. Nose down: the front camera sees more ground (horizon up),
    # the back camera looks up (horizon down).
    assert abs(horizon_row(front_level) - 32) <= 2
    assert horizon_row(front_down) < horizon_row(front_level) - 5
    assert horizon_row(back_down) > horizon_row(front_level) + 5


def test_shapes_dtypes_and_layout_round_trip(world) -> None:
    image = PyBulletRenderer().render(
        world, np.stack([OBSERVER, FAR_AWAY]), np.array([[1.0, 0, 0, 0]] * 2)
    )
    assert image.shape == (2, IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX) and image.dtype == np.uint8
    np.testing.assert_array_equal(stitch(split(image)), image)
    tiles = np.arange(6 * 64 * 64, dtype=np.int64).reshape(6, 64, 64).astype(np.uint8)
    strip = stitch(tiles)
    for k in range(6):  # face k occupies columns 64k .. 64k+63
        np.testing.assert_array_equal(strip[:, 64 * k : 64 * (k + 1)], tiles[k])


def test_own_body_is_not_in_its_own_views() -> None:
    # A large frame (1 m arms) reaches into the cameras' fields of view: without hiding it, the
    # drone would see its own rotors. (The default 0.49 m frame stays out of view on its own.)
    big = QuadGeometry(arm_length_m=1.0, rotor_radius_m=0.3)
    renderer = PyBulletRenderer()
    pos, q = OBSERVER[None, :], np.array([[1.0, 0, 0, 0]])
    eyes, axes, ups = camera_poses(pos, q)
    with World(1, big) as world:
        seen = renderer.render(world, pos, q)[0]
        world.set_poses(pos, q)

        def drone_pixels():
            return sum(
                int(renderer._render_face(world, eyes[0, f], axes[0, f], ups[0, f])[1].sum())
                for f in range(6)
            )

        assert drone_pixels() > 50  # the body would be visible
        world.set_poses(FAR_AWAY[None, :], q)
        assert drone_pixels() == 0
    # What the drone sees is the bare environment.
    empty = renderer.environment.shade(eyes, np.eye(3)[None])
    np.testing.assert_array_equal(seen, stitch(np.rint(empty).astype(np.uint8))[0])


def test_drone_below_stands_out_against_the_ground(world) -> None:
    # Seen from above, the drone is against the textured ground: it must still be found, and be
    # clearly darker than the ground around it.
    face, row, col = where_is_the_other_drone(world, OBSERVER + [0.0, 0.0, -3.0], [1, 0, 0, 0])
    assert face == "down"
    assert abs(row - 31.5) < 3 and abs(col - 31.5) < 3
    renderer = PyBulletRenderer()
    q = np.array([[1.0, 0, 0, 0]] * 2)
    down = split(renderer.render(world, np.stack([OBSERVER, OBSERVER + [0, 0, -3.0]]), q, [0]))
    tile = down[0, 5].astype(float)
    assert tile[28:36, 28:36].min() < tile.mean() - 50


def test_sky_is_brighter_than_the_ground(world) -> None:
    image = PyBulletRenderer().render(
        world, np.stack([OBSERVER, FAR_AWAY]), np.array([[1.0, 0, 0, 0]] * 2), [0]
    )
    tiles = split(image)[0]
    assert tiles[4].min() >= 195  # up: sky only
    assert 100 <= tiles[5].mean() <= 210  # down: ground only
    assert tiles[4].mean() > tiles[5].mean() + 30
