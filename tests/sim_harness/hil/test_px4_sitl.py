"""The PX4 SITL fixture's parts that need no PX4: what it says when it cannot run, and each
instance's ports, system id and start-up variables (tests/px4 runs the real thing)."""

from __future__ import annotations

from pathlib import Path

import pytest

from sim_harness.hil.px4_sitl import SITL_ENV, Px4Instance, Px4SitlError, unavailable_reason


def test_without_a_tarball_the_reason_says_how_to_get_one(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.delenv(SITL_ENV, raising=False)
    reason = unavailable_reason()
    assert reason is not None and "PX4_SITL_TARBALL is not set" in reason
    assert "make px4_sitl_default" in reason
    monkeypatch.setenv(SITL_ENV, str(tmp_path / "nope.tar.xz"))
    assert "no such file" in (unavailable_reason() or "")


def test_an_instance_has_its_own_ports_system_id_and_start_position() -> None:
    spec = Px4Instance(2, home_lat_deg=47.5, home_lon_deg=8.5, home_alt_m=400.0, params={"X": 5})
    assert (spec.system_id, spec.offboard_port, spec.gcs_port) == (3, 14542, 18572)
    env = spec.environment()
    assert env["PX4_HOME_LAT"] == "47.5000000" and env["PX4_HOME_ALT"] == "400.00"
    assert env["PX4_PARAM_X"] == "5" and env["PX4_SIM_MODEL"] == "sihsim_quadx"
    with pytest.raises(Px4SitlError, match="0..9"):
        Px4Instance(10)  # PX4's start script reuses port 14549 from instance 10 on
