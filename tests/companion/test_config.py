"""The composed TOML config: real files parsed with tomllib, defaults, paths, clear errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.config import CompanionConfig, DaemonConfig, config_from_dict, load_config
from companion.errors import ConfigError, ConfigErrors
from sim_harness.experiments.suites import SHIPPED_LOW_PASS_HZ

REPO = Path(__file__).resolve().parents[2]
FACES = ("front", "right", "back", "left", "up", "down")


def faces_toml(prefix: str = "/dev/openmv-") -> str:
    return "\n".join(
        f'[cameras.faces.{face}]\ndevice = "{prefix}{face}"\ncamera_id = "{index + 1:024x}"\n'
        for index, face in enumerate(FACES)
    )


MINIMAL = f"""
[policy]
model_path = "models/policy.pt"

[cameras]
{faces_toml()}
"""


def write(tmp_path: Path, text: str, name: str = "companion.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_the_shipped_example_config_loads() -> None:
    config = load_config(REPO / "systemd" / "companion.toml")
    assert config.drone.id == "drone1"
    assert config.autopilot.url == "serial:///dev/ttyS1:921600"
    assert config.cameras.faces["down"].device == "/dev/openmv-down"
    assert config.recorder.directory == Path("/var/lib/vision-swarm/flights")
    assert config.telemetry.listen_endpoints == ("tcp/127.0.0.1:7447",)
    assert not config.telemetry.multicast_scouting
    # What the shipped model is flown with in simulation (unset: off; models/README.md).
    assert config.control.low_pass_cutoff_hz == SHIPPED_LOW_PASS_HZ
    # The example spells out the defaults: it must not drift from the code.
    assert config.daemon == DaemonConfig()


def test_minimal_config_takes_the_defaults_and_resolves_paths_from_its_folder(
    tmp_path: Path,
) -> None:
    path = write(tmp_path, MINIMAL + '\n[recorder]\ndirectory = "logs"\n')
    config = load_config(path)
    assert isinstance(config, CompanionConfig) and config.source == path
    assert config.policy.model_path == tmp_path.resolve() / "models" / "policy.pt"
    assert config.recorder.directory == tmp_path.resolve() / "logs"
    assert config.daemon.rate_hz == 10.0 and config.daemon.period_s == pytest.approx(0.1)
    assert config.daemon.stale_hover_after_s == 0.3
    assert config.control.v_max_mps == 2.0 and config.control.k_mig == 1.0  # the paper's
    assert config.cameras.baud == 115200
    assert config.autopilot.failsafe_action == "hold"
    assert config.telemetry.drone_id == config.drone.id == "drone0"


def test_drone_id_and_rate_flow_into_the_sections_that_use_them(tmp_path: Path) -> None:
    text = MINIMAL + '\n[drone]\nid = "d7"\n\n[daemon]\nrate_hz = 20.0\n'
    config = load_config(write(tmp_path, text))
    assert config.telemetry.drone_id == "d7"
    assert config.telemetry.key("state") == "swarm/d7/state"
    assert config.autopilot.setpoint_rate_hz == 20.0
    assert config.daemon.budget_s == pytest.approx(0.025)  # half the period by default


def test_absolute_paths_stay_as_written(tmp_path: Path) -> None:
    text = MINIMAL.replace('"models/policy.pt"', '"/opt/m/p.pt"')
    assert load_config(write(tmp_path, text)).policy.model_path == Path("/opt/m/p.pt")


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (
            "[daemon]\nrate_hz = 5.0\n",
            r"daemon\.rate_hz: 5 is outside the allowed range \[10, 100\]",
        ),
        ("[daemon]\nstale_hover_after_s = 0\n", r"daemon\.stale_hover_after_s: 0 is outside"),
        ("[daemon]\ninference_budget_s = 0.1\n", r"daemon\.inference_budget_s: 0\.1 is outside"),
        ("[daemon]\nrate_hz = 20.0\ninference_budget_s = 0.05\n", r"\[0, 0\.05\)"),
        ('[daemon]\nengage = "maybe"\n', r"daemon\.engage: 'maybe' must be one of operator, gr"),
        ("[daemon]\nfailsafe_after = 3\n", r"daemon: unknown key\(s\) 'failsafe_after'"),
        ("[daemon]\nengage_requires_airborne = 1\n", r"daemon\.engage_requires_airborne"),
        ('[drone]\nid = "a b"\n', r"drone\.id: 'a b' must be"),
        ("[wings]\nspan = 1\n", r"config: unknown key\(s\) 'wings'"),
        ("[cameras.extra]\n", r"cameras: unknown key\(s\) 'extra'"),
        ('[telemetry]\ndrone_id = "other"\n', r"telemetry\.drone_id: 'other' differs from"),
        ("[autopilot]\nsetpoint_rate_hz = 20.0\n", r"autopilot\.setpoint_rate_hz: 20\.0 differs"),
        ('[autopilot]\nfailsafe_action = "rtl"\n', r"autopilot\.failsafe_action"),
        ("[control]\nv_max_mps = -1\n", r"control\.v_max_mps"),
        ("[recorder]\nmax_file_mb = 0\n", r"recorder\.max_file_mb"),
        ('[telemetry]\nlisten_endpoints = ["127.0.0.1"]\n', r"telemetry\.listen_endpoints"),
    ],
)
def test_errors_name_the_file_the_field_and_the_range(
    tmp_path: Path, extra: str, message: str
) -> None:
    path = write(tmp_path, MINIMAL + "\n" + extra)
    with pytest.raises(ConfigError, match=message) as info:
        load_config(path)
    assert str(info.value).startswith(str(path))


def test_camera_errors_come_from_the_camera_section(tmp_path: Path) -> None:
    text = MINIMAL.replace("[cameras]\n", "[cameras]\nbaud = 921600\n")
    with pytest.raises(ConfigError, match=r"cameras\.baud: 921600 is reserved"):
        load_config(write(tmp_path, text))
    no_down = MINIMAL.split("[cameras.faces.down]")[0]
    with pytest.raises(ConfigError, match=r"cameras\.faces: missing face\(s\) down"):
        load_config(write(tmp_path, no_down))


@pytest.mark.parametrize("section", ["policy", "cameras"])
def test_required_sections(tmp_path: Path, section: str) -> None:
    document = {"policy": {"model_path": "m.pt"}, "cameras": {"faces": {}}}
    del document[section]
    with pytest.raises(ConfigError, match=rf"{section}: missing section \[{section}\]"):
        config_from_dict(document)


def test_required_key_inside_a_section(tmp_path: Path) -> None:
    text = MINIMAL.replace('model_path = "models/policy.pt"', "threads = 2")
    with pytest.raises(ConfigError, match=r"policy\.model_path: missing \(required\)"):
        load_config(write(tmp_path, text))


def test_a_section_that_is_not_a_table(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="daemon: expected a table, got int"):
        load_config(write(tmp_path, "daemon = 3\n" + MINIMAL))


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read config file .*nope.toml"):
        load_config(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match=r"bad\.toml: not valid TOML"):
        load_config(write(tmp_path, "[daemon\nrate_hz = 10", "bad.toml"))


def test_every_problem_of_a_file_is_reported_at_once(tmp_path: Path) -> None:
    # Three problems in three places: two fields of one section and a field of another.
    text = MINIMAL + (
        "\n[daemon]\nrate_hz = 5.0\nfailsafe_after_s = -1.0\n[control]\nv_max_mps = 0\n"
    )
    path = write(tmp_path, text)
    with pytest.raises(ConfigErrors) as info:
        load_config(path)
    problems = info.value.problems
    assert len(problems) == 3
    assert all(p.startswith(f"{path}: ") for p in problems)
    assert any("daemon.rate_hz: 5 is outside the allowed range [10, 100]" in p for p in problems)
    assert any("daemon.failsafe_after_s: -1 is outside the allowed range (0, 600]" in p
               for p in problems)  # fmt: skip
    assert any("control.v_max_mps: 0 is outside the allowed range (0, 20]" in p for p in problems)
    assert str(info.value).startswith(f"{path}: 3 problems: daemon.rate_hz")
    assert isinstance(info.value, ConfigError)  # callers that catch ConfigError still do


def test_a_bad_face_and_a_bad_option_of_the_camera_section_are_both_reported(
    tmp_path: Path,
) -> None:
    text = MINIMAL.replace("[cameras]\n", "[cameras]\nmax_age_s = 0\n").replace(
        '"/dev/openmv-up"', '""'
    )
    with pytest.raises(ConfigErrors) as info:
        load_config(write(tmp_path, text))
    assert len(info.value.problems) == 2
    assert "cameras.faces.up.device" in info.value.problems[0]
    assert "cameras.max_age_s: 0 is outside" in info.value.problems[1]


def test_a_cross_section_rule_is_not_reported_against_a_refused_section(tmp_path: Path) -> None:
    # daemon.rate_hz is refused; autopilot's rate is not then compared with it.
    text = MINIMAL + "\n[daemon]\nrate_hz = 5.0\n[autopilot]\nsetpoint_rate_hz = 5.0\n"
    with pytest.raises(ConfigError, match=r"daemon\.rate_hz") as info:
        load_config(write(tmp_path, text))
    assert not isinstance(info.value, ConfigErrors)
