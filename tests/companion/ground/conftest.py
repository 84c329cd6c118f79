"""A real OpenSSH server on 127.0.0.1 for the ground station's tests (`sshd` fixture).

It runs as the test's own user (as root too: tests run as root in CI), on a free port, with its
own host key and a key pair made for the test; nothing of the machine's SSH set-up is used or
changed, except that sshd, started as root, insists on its privilege-separation folder
/run/sshd, which is created (empty, as the openssh-server service would) when missing.

The session's PATH starts with `sshd.bin_dir`, where a test puts stand-ins for the drone's
`systemctl` and `journalctl` (systemd is not under test). The `sudo` there allows exactly the
commands of the sudoers rule that the operator guide and systemd/install.sh set up (`ALLOWED`),
and answers anything else as sudo -n does. The SSH, the quoting, the timeouts, the output and the
tar stream are real.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from companion.groundstation import DEFAULT_UNIT, SshTarget

SSHD_MISSING = "needs OpenSSH's server: apt-get install openssh-server (sshd, ssh, ssh-keygen)"
# The sudoers rule for the operator: these commands, exactly, without a password.
ALLOWED = [
    *(f"systemctl {action} {DEFAULT_UNIT}" for action in ("start", "stop", "restart", "status")),
    f"systemctl is-active {DEFAULT_UNIT}",
    f"journalctl -u {DEFAULT_UNIT} -n 20 --no-pager -o cat",
]
_FAKE_SUDO = """[ "$1" = "-n" ] || {{ echo "sudo: a terminal is required" >&2; exit 1; }}
shift
echo "$*" >> "{calls}"
grep -Fxq -- "$*" "{allowed}" || {{ echo "sudo: a password is required" >&2; exit 1; }}
exec "$@"
"""


def _program(name: str) -> str | None:
    return shutil.which(name) or next(
        (str(p) for p in (Path("/usr/sbin") / name, Path("/usr/bin") / name) if p.is_file()), None
    )


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@dataclass
class Sshd:
    """A running sshd: where to reach it and the test-controlled side of the 'drone'."""

    port: int
    user: str
    key: Path
    bin_dir: Path
    sudo_calls: Path  # one line per command the fake sudo was asked to run
    log: Path

    def options(self) -> tuple[str, ...]:
        """ssh options for this server (the ground station's --ssh-option pass-through)."""
        return (
            "StrictHostKeyChecking=no",
            "UserKnownHostsFile=/dev/null",
            f"IdentityFile={self.key}",
            "IdentitiesOnly=yes",
            "LogLevel=ERROR",
        )

    def target(self) -> SshTarget:
        return SshTarget("127.0.0.1", user=self.user, port=self.port, options=self.options())

    def cli_args(self) -> list[str]:
        args = ["--user", self.user, "--port", str(self.port)]
        for option in self.options():
            args += ["--ssh-option", option]
        return args

    def fake(self, name: str, script: str) -> None:
        """Put an executable `name` (a shell script body) first on the session's PATH."""
        path = self.bin_dir / name
        path.write_text("#!/bin/sh\n" + script)
        path.chmod(0o755)

    def sudo_log(self) -> list[str]:
        return self.sudo_calls.read_text().splitlines() if self.sudo_calls.exists() else []


@pytest.fixture
def sshd(tmp_path: Path) -> Iterator[Sshd]:
    programs = {name: _program(name) for name in ("sshd", "ssh", "ssh-keygen")}
    if not all(programs.values()):
        pytest.skip(SSHD_MISSING)
    sshd_bin, keygen = str(programs["sshd"]), str(programs["ssh-keygen"])
    if os.geteuid() == 0:
        Path("/run/sshd").mkdir(mode=0o755, exist_ok=True)
    root = tmp_path / "sshd"
    bin_dir = root / "bin"
    bin_dir.mkdir(parents=True)
    for key in ("host_key", "user_key"):
        subprocess.run([keygen, "-q", "-t", "ed25519", "-N", "", "-f", str(root / key)], check=True)
    shutil.copy(root / "user_key.pub", root / "authorized_keys")
    (root / "allowed").write_text("\n".join(ALLOWED) + "\n")
    server = Sshd(
        port=_free_port(),
        user=os.environ.get("USER")
        or subprocess.run(["id", "-un"], capture_output=True, text=True, check=True).stdout.strip(),
        key=root / "user_key",
        bin_dir=bin_dir,
        sudo_calls=root / "sudo_calls",
        log=root / "sshd.log",
    )
    server.fake("sudo", _FAKE_SUDO.format(calls=server.sudo_calls, allowed=root / "allowed"))
    config = root / "sshd_config"
    config.write_text(
        f"Port {server.port}\nListenAddress 127.0.0.1\nHostKey {root / 'host_key'}\n"
        f"AuthorizedKeysFile {root / 'authorized_keys'}\nPidFile {root / 'sshd.pid'}\n"
        "StrictModes no\nUsePAM no\nPasswordAuthentication no\nKbdInteractiveAuthentication no\n"
        "PermitRootLogin prohibit-password\nUseDNS no\nMaxStartups 64\n"
        f"SetEnv PATH={bin_dir}:/usr/local/bin:/usr/bin:/bin\n"
    )
    with open(server.log, "wb") as log:
        process = subprocess.Popen(
            [sshd_bin, "-D", "-e", "-f", str(config)], stdout=log, stderr=subprocess.STDOUT
        )
    try:
        deadline = time.monotonic() + 30.0
        while True:
            if process.poll() is not None:
                pytest.fail(f"sshd exited: {server.log.read_text()[-2000:]}")
            with socket.socket() as sock:
                if sock.connect_ex(("127.0.0.1", server.port)) == 0:
                    break
            if time.monotonic() > deadline:
                pytest.fail(f"sshd not listening after 30 s: {server.log.read_text()[-2000:]}")
            time.sleep(0.05)
        yield server
    finally:
        process.terminate()
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
