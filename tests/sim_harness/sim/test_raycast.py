"""The ray-cast renderer draws what pybullet draws: pinned views, pixel counts, own body hidden."""

import math

import numpy as np
import pytest

from companion.camera.layout import FACE_NAMES, FOV_DEG, split
from companion.errors import ConfigError
from companion.frames import quat_from_euler_zyx, quat_to_rotmat
from sim_harness.sim.drone_solid import drone_solid
from sim_harness.sim.quad_body import QuadGeometry, quad_mesh
from sim_harness.sim.raycast import RaycastRenderer
from sim_harness.sim.render import PyBulletRenderer, camera_poses
from sim_harness.sim.world import World

OBSERVER = np.array([0.0, 0.0, 5.0])
FAR_AWAY = np.array([5000.0, 5000.0, 5.0])
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])

# (offset of the other drone from the observer (m), observer roll, pitch, yaw, other's yaw (rad))
PINNED_VIEWS = [
    ((0.6, 0.1, 0.05), 0.0, 0.0, 0.0, 0.3),
    ((1.2, -0.4, 0.3), 0.2, -0.1, 0.5, 1.0),
    ((-0.5, 1.5, -0.8), -0.3, 0.2, 2.0, -0.7),
    ((0.2, -0.3, -2.5), 0.1, 0.4, -1.2, 0.1),
    ((3.0, 2.0, 1.0), 0.0, 0.0, 3.0, 2.5),
    ((-4.0, 1.0, 0.5), 0.4, -0.3, 0.2, 0.0),
]


@pytest.fixture(scope="module")
def world():
    with World(2) as w:
        yield w


def render_pair(world, renderer, offset, rpy, other_yaw):
    q = np.stack(
        [quat_from_euler_zyx(*rpy), quat_from_euler_zyx(0.0, 0.0, other_yaw)]
    )  # roll, pitch, yaw
    here = renderer.render(world, np.stack([OBSERVER, OBSERVER + offset]), q, [0])[0]
    gone = renderer.render(world, np.stack([OBSERVER, FAR_AWAY]), q, [0])[0]
    return here, here != gone


@pytest.mark.parametrize(("offset", "roll", "pitch", "yaw", "other_yaw"), PINNED_VIEWS)
def test_pinned_views_match_pybullet(world, offset, roll, pitch, yaw, other_yaw) -> None:
    args = (np.array(offset), (roll, pitch, yaw), other_yaw)
    ours, our_mask = render_pair(world, RaycastRenderer(), *args)
    theirs, their_mask = render_pair(world, PyBulletRenderer(), *args)
    assert their_mask.sum() >= 3
    iou = (our_mask & their_mask).sum() / (our_mask | their_mask).sum()
    assert iou >= 0.97
    assert abs(int(our_mask.sum()) - int(their_mask.sum())) <= 2
    assert np.abs(ours.astype(int) - theirs.astype(int)).mean() <= 0.05


@pytest.mark.parametrize("below_m", [1.0, 1.5])
def test_drone_below_covers_its_top_view_area(world, below_m) -> None:
    # Level drone below a level observer: the down camera (0.15 m below the observer's centre)
    # sees its top near the image centre. Expected pixels: top-view area over one
    # pixel's footprint. Top view: body square, four rotor decagons, the bits of arm in between.
    g = QuadGeometry()
    decagon = 5 * g.rotor_radius_m**2 * math.sin(2 * math.pi / 10)
    body = 4 * g.body_half_extents_m[0] * g.body_half_extents_m[1]
    arm_between = g.arm_length_m - g.rotor_radius_m - g.body_half_extents_m[0] * math.sqrt(2)
    area = body + 4 * decagon + 4 * arm_between * 2 * g.arm_half_width_m
    distance = below_m - 0.15 - g.rotor_height_m
    pixel_side = distance * 2 * math.tan(math.radians(FOV_DEG) / 2) / 64
    _, mask = render_pair(world, RaycastRenderer(), np.array([0, 0, -below_m]), (0, 0, 0), 0.0)
    faces = split(mask)
    assert faces.reshape(6, -1).sum(axis=1).argmax() == FACE_NAMES.index("down")
    assert int(mask.sum()) == pytest.approx(area / pixel_side**2, rel=0.2)


@pytest.mark.parametrize("compiled", [False, True])
def test_own_body_is_hidden_and_an_empty_sky_is_the_environment(world, compiled) -> None:
    if compiled:
        pytest.importorskip("numba")
    renderer = RaycastRenderer(compiled=compiled)
    q = np.stack([quat_from_euler_zyx(0.3, -0.2, 1.0), LEVEL])
    pos = np.stack([OBSERVER, FAR_AWAY])
    image = split(renderer.render(world, pos, q, [0])[0]).astype(int)
    eyes, _, _ = camera_poses(pos[:1], q[:1])
    env = np.rint(renderer.environment.shade(eyes, quat_to_rotmat(q[:1])))[0]
    # The compiled environment rounds a few pixels in a thousand to the next gray level.
    assert np.abs(image - env).max() <= (1 if compiled else 0)
    assert (image != env).mean() < 0.01


def test_compiled_and_numpy_paths_draw_the_same_drones() -> None:
    pytest.importorskip("numba")
    rng = np.random.default_rng(7)
    with World(12) as w12:
        pos = OBSERVER + rng.uniform(-3, 3, (12, 3))
        q = np.stack([quat_from_euler_zyx(*rng.uniform(-0.5, 0.5, 3)) for _ in range(12)])
        rot = quat_to_rotmat(q)
        chosen = np.arange(12)
        solid = drone_solid(w12.geometry)
        fast = RaycastRenderer(compiled=True).drone_pixels(pos, rot, chosen, solid)
        slow = RaycastRenderer(compiled=False).drone_pixels(pos, rot, chosen, solid)
        order = np.argsort(slow[0])
        np.testing.assert_array_equal(np.sort(fast[0]), slow[0][order])
        np.testing.assert_allclose(fast[1][np.argsort(fast[0])], slow[1][order], atol=1e-9)
        assert len(fast[0]) > 500


def test_deterministic_and_batched_equals_one_by_one(world) -> None:
    rng = np.random.default_rng(4)
    with World(5) as w5:
        pos = OBSERVER + rng.uniform(-2, 2, (5, 3))
        q = np.stack([quat_from_euler_zyx(*rng.uniform(-0.4, 0.4, 3)) for _ in range(5)])
        renderer = RaycastRenderer()
        all_at_once = renderer.render(w5, pos, q)
        np.testing.assert_array_equal(all_at_once, renderer.render(w5, pos, q))
        for agent in range(5):
            np.testing.assert_array_equal(
                renderer.render(w5, pos, q, [agent])[0], all_at_once[agent]
            )


def test_area_averaging_keeps_a_far_drone_that_single_rays_lose(world) -> None:
    # A drone 6 m behind, thinner than a pixel: one ray per pixel misses it in some frames,
    # the 4 x 4 average never; and what it adds to the image (its summed gray change) is on
    # average the same, it is only spread over the pixels it partly covers instead of dropped.
    rng = np.random.default_rng(3)
    offsets = [np.array([-6.0, *rng.uniform(-1.5, 1.5, 2)]) for _ in range(24)]
    single, averaged = RaycastRenderer(), RaycastRenderer(supersample=4)
    q = np.stack([LEVEL, LEVEL])
    mass = {}
    for name, renderer in (("single", single), ("averaged", averaged)):
        gone = renderer.render(world, np.stack([OBSERVER, FAR_AWAY]), q, [0])[0].astype(int)
        mass[name] = np.array(
            [
                np.abs(
                    renderer.render(world, np.stack([OBSERVER, OBSERVER + o]), q, [0])[0] - gone
                ).sum()
                for o in offsets
            ]
        )
    assert (mass["single"] == 0).sum() >= 4
    assert (mass["averaged"] > 0).all()
    assert mass["averaged"].mean() == pytest.approx(mass["single"].mean(), rel=0.35)


def test_area_averaging_leaves_the_sky_alone_and_a_near_drone_as_it_was(world) -> None:
    # No drone in view: the same image as one ray per pixel. A drone 0.7 m below covers ~200
    # pixels: averaging moves only its rim, so what it adds to the image barely changes.
    single, averaged = RaycastRenderer(), RaycastRenderer(supersample=4)
    q = np.stack([LEVEL, LEVEL])
    empty = single.render(world, np.stack([OBSERVER, FAR_AWAY]), q, [0])[0]
    np.testing.assert_array_equal(
        averaged.render(world, np.stack([OBSERVER, FAR_AWAY]), q, [0])[0], empty
    )
    near = np.stack([OBSERVER, OBSERVER + np.array([0.0, 0.0, -0.7])])
    a = single.render(world, near, q, [0])[0].astype(int) - empty
    b = averaged.render(world, near, q, [0])[0].astype(int) - empty
    assert (a != 0).sum() >= 150
    assert np.abs(b).sum() == pytest.approx(np.abs(a).sum(), rel=0.1)
    assert ((a != 0) != (b != 0)).sum() <= 0.5 * (a != 0).sum()  # the rim, not the body


def test_supersample_out_of_range_names_the_field() -> None:
    with pytest.raises(ConfigError, match="supersample"):
        RaycastRenderer(supersample=0)


def test_every_mesh_vertex_lies_on_a_convex_part() -> None:
    """The solid the renderer intersects is the mesh pybullet draws (quad_body.quad_mesh)."""
    g = QuadGeometry()
    solid = drone_solid(g)
    assert len(solid.offset) == 9  # body, four arms, four rotors
    vertices = np.asarray(quad_mesh(g).vertices)
    # Signed distance of each vertex outside each part: max over the part's planes.
    outside = (np.einsum("pki,vi->vpk", solid.normal, vertices) - solid.offset[None]).max(axis=2)
    assert np.all(np.abs(outside).min(axis=1) < 1e-9)
