"""The pybullet world: independent clients, realistic drones, contact detection, rate checks."""

import numpy as np
import pybullet as pb
import pytest

from companion.errors import ConfigError
from sim_harness.sim.quad_body import QuadGeometry, quad_mesh
from sim_harness.sim.world import SimRates, World

IDENTITY = [1.0, 0.0, 0.0, 0.0]


def test_two_worlds_run_side_by_side() -> None:
    with World(2) as a, World(3) as b:
        assert a.client_id != b.client_id
        a.set_poses([[0, 0, 2], [5, 0, 2]], [IDENTITY] * 2)
        b.set_poses([[0, 0, 7], [1, 0, 7], [2, 0, 7]], [IDENTITY] * 3)
        pos_a, _ = pb.getBasePositionAndOrientation(a.body_ids[1], physicsClientId=a.client_id)
        pos_b, _ = pb.getBasePositionAndOrientation(b.body_ids[1], physicsClientId=b.client_id)
        assert pos_a == pytest.approx((5, 0, 2))
        assert pos_b == pytest.approx((1, 0, 7))
        assert pb.getNumBodies(physicsClientId=a.client_id) == 2  # one body per drone
        assert pb.getNumBodies(physicsClientId=b.client_id) == 3


def test_drone_has_realistic_size_mass_and_parts() -> None:
    geometry = QuadGeometry()
    assert 0.4 <= geometry.span_m <= 0.6
    assert 1.0 <= geometry.mass_kg <= 2.0
    with World(1) as world:
        body = world.body_ids[0]
        cid = world.client_id
        # Collision geometry: body box + 4 arms + 4 rotors in one compound shape.
        assert len(pb.getCollisionShapeData(body, -1, physicsClientId=cid)) == 9
        world.set_poses([[0, 0, 3]], [IDENTITY])
        low, high = pb.getAABB(body, -1, physicsClientId=cid)
        extent = np.subtract(high, low)
        assert extent[0] == pytest.approx(extent[1], abs=1e-3)
        # X frame: rotors on the diagonals, so the axis-aligned box is 2 (l cos 45 + r) wide
        # (pybullet pads AABBs by a small collision margin).
        reach = geometry.arm_length_m * np.sqrt(0.5) + geometry.rotor_radius_m
        assert extent[0] == pytest.approx(2 * reach, abs=0.03)
        assert pb.getDynamicsInfo(body, -1, physicsClientId=cid)[0] == pytest.approx(
            geometry.mass_kg
        )


def test_drone_mesh_shows_every_part_in_its_own_dark_colour() -> None:
    geometry = QuadGeometry()
    mesh = quad_mesh(geometry)
    vertices = np.array(mesh.vertices)
    # Same footprint as the collision geometry: rotor tips at the arm ends on the diagonals.
    reach = geometry.arm_length_m * np.sqrt(0.5) + geometry.rotor_radius_m
    assert np.abs(vertices[:, 0]).max() == pytest.approx(reach, abs=0.01)
    assert len(mesh.indices) % 3 == 0 and max(mesh.indices) < len(vertices)
    palette = geometry.palette_rgb_u8()
    columns = sorted({int(u * palette.shape[1]) for u, _ in mesh.uvs})
    gray = palette[0, columns] @ np.array([0.299, 0.587, 0.114])
    assert len(columns) == 3  # body, arms, rotors
    assert gray.max() < 90  # darker than the ground (>= 100) and the sky (>= 200)


def test_contacts_are_detected_and_reported_as_agent_pairs() -> None:
    with World(3) as world:
        q = [IDENTITY] * 3
        assert world.contacts([[0, 0, 3], [2, 0, 3], [4, 0, 3]], q) == []
        # Rotor tips overlap at 0.3 m between centres (span 0.49 m); agent 2 stays away.
        assert world.contacts([[0, 0, 3], [0.3, 0, 3], [4, 0, 3]], q) == [(0, 1)]
        assert world.contacts([[4, 0, 3], [0, 0, 3], [0.0, 0.1, 3]], q) == [(1, 2)]


def test_ground_contact_is_not_a_drone_contact() -> None:
    with World(1) as world:
        assert world.contacts([[0, 0, 0.0]], [IDENTITY]) == []


def test_rates_must_divide_evenly() -> None:
    rates = SimRates(physics_hz=240, control_hz=10)
    assert rates.substeps == 24
    with pytest.raises(ConfigError, match="physics_hz"):
        SimRates(physics_hz=100, control_hz=30)
    with pytest.raises(ConfigError, match="control_hz"):
        SimRates(physics_hz=100, control_hz=0)
