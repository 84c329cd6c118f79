"""The pybullet world: independent clients, realistic drones, contact detection, rate checks."""

import numpy as np
import pybullet as pb
import pytest

from companion.errors import ConfigError
from sim_harness.quad_body import QuadGeometry
from sim_harness.world import SimRates, World

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
        assert pb.getNumBodies(physicsClientId=a.client_id) == 3  # ground + 2 drones
        assert pb.getNumBodies(physicsClientId=b.client_id) == 4


def test_drone_has_realistic_size_mass_and_parts() -> None:
    geometry = QuadGeometry()
    assert 0.4 <= geometry.span_m <= 0.6
    assert 1.0 <= geometry.mass_kg <= 2.0
    with World(1) as world:
        body = world.body_ids[0]
        assert pb.getNumJoints(body, physicsClientId=world.client_id) == 8  # 4 arms + 4 rotors
        world.set_poses([[0, 0, 3]], [IDENTITY])
        low, high = pb.getAABB(body, -1, physicsClientId=world.client_id)
        lows, highs = [low], [high]
        for link in range(8):
            lo, hi = pb.getAABB(body, link, physicsClientId=world.client_id)
            lows.append(lo)
            highs.append(hi)
        extent = np.max(highs, axis=0) - np.min(lows, axis=0)
        assert extent[0] == pytest.approx(extent[1])
        # X frame: rotors on the diagonals, so the axis-aligned box is 2 (l cos 45 + r) wide.
        reach = geometry.arm_length_m * np.sqrt(0.5) + geometry.rotor_radius_m
        assert extent[0] == pytest.approx(2 * reach, abs=1e-3)
        total = sum(
            pb.getDynamicsInfo(body, k, physicsClientId=world.client_id)[0] for k in range(-1, 8)
        )
        assert total == pytest.approx(geometry.mass_kg)


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
