"""`companion check --config FILE`: is this drone ready to run? One line per check, no flying.

Checks, in order: the config file (parse + validation), the model (SHA-256 against the config and
the sidecar, metadata contract), the six camera devices (exist, are character devices), the
autopilot link (serial device exists; UDP/TCP are not contacted), the recorder directory
(one the installed unit's sandbox lets the service write, writable by its user, free space), the
telemetry endpoints and the daemon's safety settings. Nothing is opened that the running daemon
would hold (no serial port, no MAVLink, no Zenoh session).
"""

from __future__ import annotations

import grp
import os
import pwd
import shutil
import stat
from dataclasses import dataclass
from pathlib import Path

from companion.errors import CompanionError, ConfigError, problems_of
from companion.policy import PolicyConfig
from companion.service_unit import INSTALLED_UNIT, ServiceSandbox, sandbox_of

OK, WARN, FAIL = "ok", "warn", "FAIL"


@dataclass(frozen=True)
class CheckItem:
    """One line of the report: what was checked, the verdict (ok, warn, FAIL) and the detail."""

    name: str
    verdict: str
    detail: str


def _device(path: str) -> tuple[str, str]:
    """(verdict, detail) for a serial device path."""
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        return FAIL, f"{path}: {exc.strerror or exc}"
    target = os.path.realpath(path)
    shown = path if target == path else f"{path} -> {target}"
    if not stat.S_ISCHR(mode):
        return FAIL, f"{shown}: not a character device"
    return OK, shown


def _nearest_existing(path: Path) -> Path | None:
    """`path` or its closest existing parent; None when this user cannot look (EACCES)."""
    existing = path
    try:
        while not existing.exists() and existing != existing.parent:
            existing = existing.parent
    except PermissionError:
        return None
    return existing


def _free(existing: Path) -> tuple[str, str]:
    free_gb = shutil.disk_usage(existing).free / 1e9
    return (WARN if free_gb < 1.0 else OK), f"{free_gb:.1f} GB free"


def _directory(path: Path) -> tuple[str, str]:
    """Writable by the user running the check (no installed unit to say who the service is)."""
    existing = _nearest_existing(path)
    if existing is None:
        return WARN, f"{path}: cannot look inside as {_me()}: run the check as root"
    if not os.access(existing, os.W_OK | os.X_OK):
        return FAIL, f"{path}: {existing} is not writable"
    created = "" if path.exists() else " (will be created)"
    verdict, free = _free(existing)
    return verdict, f"{path}{created}, {free}"


def _me() -> str:
    return pwd.getpwuid(os.geteuid()).pw_name


def _writable_by(st: os.stat_result, user: str, groups: tuple[str, ...]) -> bool | None:
    """Whether `user` (with `groups`) may create files in a directory; None: no such user here."""
    try:
        uid = pwd.getpwnam(user).pw_uid
        gids = {grp.getgrnam(g).gr_gid for g in groups}
    except KeyError:
        return None
    if uid == 0:
        return True
    if st.st_uid == uid:
        return bool(st.st_mode & stat.S_IWUSR)
    if st.st_gid in gids:
        return bool(st.st_mode & stat.S_IWGRP)
    return bool(st.st_mode & stat.S_IWOTH)


def _service_directory(path: Path, sandbox: ServiceSandbox) -> tuple[str, str]:
    """The recorder directory as the installed service will see it: inside the unit's writable
    directories (ProtectSystem=strict makes the rest read-only) and writable by its User=."""
    if sandbox.writable is None:  # no read-only file system: the user's permissions decide
        return _directory(path)
    root = sandbox.writable_root(path)
    if root is None:
        allowed = ", ".join(str(p) for p in sandbox.writable) or "none"
        return FAIL, (
            f"{path}: the service cannot write there ({sandbox.source} makes the file system "
            f"read-only but for: {allowed}); put [recorder] directory under one of them"
        )
    existing = _nearest_existing(path)
    if existing is None:  # e.g. the state directory is 0750 companion: the operator cannot look
        return OK, f"{path} (inside the service's {root}; cannot look inside as {_me()})"
    created = "" if path.exists() else " (will be created)"
    user = sandbox.user or "root"
    managed = root in sandbox.managed
    root_path = Path(root)
    if existing != root_path and root_path not in existing.parents:  # the root is missing
        if not managed:
            return FAIL, f"{path}: {root} does not exist (the service cannot start without it)"
        created = f" (systemd creates {root} for {user} at the first start)"
    elif (existing != root_path or not managed) and (  # systemd hands a managed root to user
        _writable_by(existing.stat(), user, sandbox.groups) is False
    ):
        return FAIL, f"{path}: {existing} is not writable by the service's user {user}"
    verdict, free = _free(existing)
    return verdict, f"{path}{created}, {free}"


def _platform(policy_config: PolicyConfig) -> CheckItem:
    """Load the policy as the daemon does (warm-up, fusion) and run it on its export's reference
    image: a platform that computes it wrongly (a CPU or library fault) is found before flight."""
    from companion.policy import Policy

    try:
        policy = Policy.load(policy_config)
    except CompanionError as exc:
        return CheckItem("platform", FAIL, str(exc))
    try:
        verdict = OK if policy.reference_error_mps is not None else WARN
        return CheckItem("platform", verdict, policy.reference_text)
    finally:
        policy.close(2.0)


def run_checks(config_path: str | Path, unit_path: Path | None = INSTALLED_UNIT) -> list[CheckItem]:
    """Every check's result; stops after the config check if the config is unusable (then one
    FAIL line per problem of the file, all of them). `unit_path`: the service's unit file, whose
    sandbox decides where the recorder may write (skipped when absent or None)."""
    from companion.config import load_config  # torch is imported with the policy section
    from companion.model_file import load_model

    try:
        config = load_config(config_path)
    except ConfigError as exc:  # every problem of the file, one line each
        return [CheckItem("config", FAIL, problem) for problem in problems_of(exc)]
    except CompanionError as exc:
        return [CheckItem("config", FAIL, str(exc))]
    items = [CheckItem("config", OK, f"{config.source} (drone {config.drone.id})")]

    policy = config.policy
    try:
        model = load_model(policy.model_path, expected_sha256=policy.sha256)
    except CompanionError as exc:
        items.append(CheckItem("model", FAIL, str(exc)))
    else:
        output = model.metadata.get("output", {})
        pinned = "pinned in the config" if policy.sha256 else "from the sidecar only (not pinned)"
        items.append(
            CheckItem(
                "model",
                OK if policy.sha256 else WARN,
                f"{model.path}: sha256 {model.sha256} ({pinned}); "
                f"format {model.metadata.get('format')}, "
                f"output {output.get('frame')} {output.get('units')}",
            )
        )
        items.append(_platform(config.policy))

    for face, camera in config.cameras.faces.items():
        verdict, detail = _device(camera.device)
        items.append(CheckItem(f"camera {face}", verdict, f"{detail} (camera {camera.camera_id})"))

    url = config.autopilot.url
    if url.startswith("serial://"):
        device = url.removeprefix("serial://").rsplit(":", 1)[0]
        verdict, detail = _device(device)
        items.append(CheckItem("autopilot", verdict, f"{url}: {detail}"))
    else:
        items.append(CheckItem("autopilot", OK, f"{url} (network link: not contacted here)"))

    if config.recorder.enabled:
        directory = Path(config.recorder.directory)
        if unit_path is not None and unit_path.is_file():
            verdict, detail = _service_directory(directory, sandbox_of(unit_path))
        else:
            verdict, detail = _directory(directory)
            if unit_path is not None:
                detail += f" (no {unit_path}: the service's sandbox is not checked)"
        items.append(CheckItem("recorder", verdict, detail))
    else:
        items.append(CheckItem("recorder", WARN, "disabled: no flight log will be written"))

    telemetry = config.telemetry
    if telemetry.enabled:
        endpoints = list(telemetry.listen_endpoints) + list(telemetry.connect_endpoints)
        scouting = "multicast scouting ON" if telemetry.multicast_scouting else "scouting off"
        items.append(
            CheckItem(
                "telemetry",
                WARN if telemetry.multicast_scouting else OK,
                f"swarm key {telemetry.key('*')}, endpoints {', '.join(endpoints)}, {scouting}",
            )
        )
    else:
        items.append(CheckItem("telemetry", WARN, "disabled"))

    d = config.daemon
    items.append(
        CheckItem(
            "daemon",
            OK if d.engage in ("operator", "ground") else WARN,
            f"{d.rate_hz:g} Hz, hover after {d.stale_hover_after_s:g} s stale, "
            f"{config.autopilot.failsafe_action} after {d.failsafe_after_s:g} s of hover, "
            f"engage {d.engage}" + ENGAGE_NOTES.get(d.engage, ""),
        )
    )
    return items


ENGAGE_NOTES = {
    "operator": " (the pilot's switch to OFFBOARD engages)",
    "ground": " (companion engage engages)",
    "auto": " (engages with no operator action: for simulation only)",
    "never": " (never commands the vehicle)",
}


def format_report(items: list[CheckItem]) -> str:
    """The report text, ending with a one-line verdict."""
    width = max(len(item.name) for item in items)
    lines = [f"[{item.verdict:>4}] {item.name:<{width}}  {item.detail}" for item in items]
    failed = [item.name for item in items if item.verdict == FAIL]
    warned = [item.name for item in items if item.verdict == WARN]
    if failed:
        names = ", ".join(dict.fromkeys(failed))  # each name once, in report order
        lines.append(f"NOT READY: {len(failed)} problem(s): {names}")
    else:
        lines.append("ready" + (f" ({len(warned)} warning(s))" if warned else ""))
    return "\n".join(lines)


def has_failures(items: list[CheckItem]) -> bool:
    return any(item.verdict == FAIL for item in items)
