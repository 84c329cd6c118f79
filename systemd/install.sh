#!/usr/bin/env bash
# Install the companion daemon on a drone (Debian/Ubuntu-like, as root, from the repository root).
#
#   sudo OPERATOR=odroid systemd/install.sh            # install
#   systemd/install.sh --dry-run                       # print what would be done
#
# Creates the `companion` system user (in dialout), a venv in $PREFIX with the package (companion
# only: no pybullet), the config /etc/vision-swarm/companion.toml (kept if present), the udev rules
# for the cameras, the systemd unit (enabled, not started), and a sudoers rule that lets $OPERATOR
# run `systemctl start|stop|restart|status` on this one unit without a password (what
# `companion ground launch` uses over SSH).
set -euo pipefail

PREFIX=${PREFIX:-/opt/vision-swarm}
PYTHON=${PYTHON:-python3.11}
OPERATOR=${OPERATOR:-}
UNIT=vision-swarm-companion.service
CONFIG_DIR=/etc/vision-swarm
REPO=$(cd "$(dirname "$0")/.." && pwd)
DRY_RUN=0
[[ ${1:-} == "--dry-run" ]] && DRY_RUN=1

run() {
    echo "+ $*"
    if [[ $DRY_RUN == 0 ]]; then "$@"; fi
}

if [[ $DRY_RUN == 0 && $(id -u) != 0 ]]; then
    echo "install.sh: run as root (or with --dry-run)" >&2
    exit 2
fi

id -u companion >/dev/null 2>&1 || run useradd --system --home-dir /var/lib/vision-swarm \
    --shell /usr/sbin/nologin --groups dialout companion

run "$PYTHON" -m venv "$PREFIX/venv"
run "$PREFIX/venv/bin/pip" install --upgrade pip
run "$PREFIX/venv/bin/pip" install "$REPO"
run install -d -m 0755 "$PREFIX/models" "$PREFIX/docs" "$CONFIG_DIR"
run install -m 0644 "$REPO/docs/operator-guide.md" "$PREFIX/docs/"

if [[ -e $CONFIG_DIR/companion.toml ]]; then
    echo "keeping the existing $CONFIG_DIR/companion.toml"
else
    run install -m 0644 "$REPO/systemd/companion.toml" "$CONFIG_DIR/companion.toml"
fi

run install -m 0644 "$REPO/firmware_cfg/udev/99-openmv.rules" /etc/udev/rules.d/99-openmv.rules
run udevadm control --reload-rules
run udevadm trigger --subsystem-match=tty

run install -m 0644 "$REPO/systemd/$UNIT" "/etc/systemd/system/$UNIT"
run systemctl daemon-reload
run systemctl enable "$UNIT"

if [[ -n $OPERATOR ]]; then
    rule="$OPERATOR ALL=(root) NOPASSWD:"
    for action in start stop restart status is-active; do
        rule+=" /usr/bin/systemctl $action $UNIT,"
    done
    rule=${rule%,}
    if [[ $DRY_RUN == 1 ]]; then
        echo "+ write /etc/sudoers.d/vision-swarm: $rule"
    else
        tmp=$(mktemp)
        echo "$rule" >"$tmp"
        visudo -cf "$tmp"
        install -m 0440 "$tmp" /etc/sudoers.d/vision-swarm
        rm -f "$tmp"
    fi
fi

echo "done: edit $CONFIG_DIR/companion.toml, copy the model to $PREFIX/models/, then"
echo "      $PREFIX/venv/bin/companion check --config $CONFIG_DIR/companion.toml"
