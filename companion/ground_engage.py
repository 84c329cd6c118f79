"""`companion ground engage | disengage | status`: the drones' control sockets, over SSH.

Each host runs `sudo -n /opt/vision-swarm/venv/bin/companion ACTION` (`companion.control_cli`:
the daemon's local control socket, reachable only by root and the service user), all hosts in
parallel. The report gives the daemon's one-line answer per host; the exit status is 1 if any
host failed or refused (e.g. `engage` on a drone whose `[daemon] engage` is not "ground").
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence

from companion.errors import ConfigError
from companion.groundstation import RemoteResult, SshTarget, run_remote

COMPANION_BIN = "/opt/vision-swarm/venv/bin/companion"
CONTROL_ACTIONS = ("engage", "disengage", "status")
DEFAULT_TIMEOUT_S = 15.0  # SSH login plus the daemon's answer (it answers within a tick)


def control_argv(action: str, companion: str = COMPANION_BIN) -> list[str]:
    """`sudo -n COMPANION ACTION` (validated)."""
    if action not in CONTROL_ACTIONS:
        raise ConfigError(f"ground.action: {action!r} must be one of {', '.join(CONTROL_ACTIONS)}")
    if not companion.startswith("/"):
        raise ConfigError(f"ground.companion: {companion!r} must be an absolute path")
    return ["sudo", "-n", companion, action]


async def control_all(
    targets: Sequence[SshTarget],
    action: str,
    *,
    companion: str = COMPANION_BIN,
    timeout_s: float = DEFAULT_TIMEOUT_S,
) -> list[RemoteResult]:
    """Run the action on every drone in parallel; results in the order of `targets`."""
    argv = control_argv(action, companion)
    runs = (run_remote(t.host, t.argv(argv), timeout_s) for t in targets)
    return list(await asyncio.gather(*runs))


def format_control(results: Sequence[RemoteResult], action: str) -> str:
    """One line per host (the daemon's answer, or why none came), then a count."""
    width = max((len(r.host) for r in results), default=4)
    lines = []
    for result in results:
        text = result.output.strip().splitlines()
        last = text[-1] if text else ""
        if result.returncode is None:
            verdict = f"FAILED ({last or 'no answer'})"
        elif result.ok:
            verdict = last or "ok"
        else:
            verdict = f"FAILED (exit {result.returncode}): {last}"
        lines.append(f"{result.host:<{width}}  {action:<9}  {verdict}")
    ok = sum(r.ok for r in results)
    lines.append(f"{ok}/{len(results)} hosts ok")
    return "\n".join(lines)
