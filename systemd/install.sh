#!/usr/bin/env bash
# Install or update the companion daemon on a drone (Debian 12 arm64, as root, from a checkout).
#
#   sudo OPERATOR=odroid systemd/install.sh                  # online: torch from PyTorch's CPU index
#   sudo OPERATOR=odroid systemd/install.sh --wheelhouse W   # offline: every package from folder W
#   systemd/install.sh --dry-run                             # print what would be done
#   systemd/install.sh --root DIR [--files-only]             # stage everything under DIR (tests,
#                                                            # images): no user, no systemctl/udevadm
#
# Creates the `companion` system user (in dialout), a venv in $PREFIX with the package (companion
# only: no pybullet) and the CPU build of torch, the state directory /var/lib/vision-swarm, the
# config /etc/vision-swarm/companion.toml, the udev rules for the cameras, the systemd unit
# (enabled, not started), and a sudoers rule that lets $OPERATOR run `systemctl
# start|stop|restart|status|is-active` on this one unit without a password (what `companion
# ground launch` uses over SSH).
#
# Safe to re-run: a file under /etc that was edited since this script installed it is kept, and
# the new version is written beside it as FILE.new (compare them and merge by hand). The package
# is built in a temporary copy of the sources, never in the checkout. --files-only skips the venv.
set -euo pipefail

PREFIX=${PREFIX:-/opt/vision-swarm}
PYTHON=${PYTHON:-python3.11}
OPERATOR=${OPERATOR:-}
TORCH_INDEX_URL=${TORCH_INDEX_URL:-https://download.pytorch.org/whl/cpu}
UNIT=vision-swarm-companion.service
REPO=$(cd "$(dirname "$0")/.." && pwd)
DRY_RUN=0
ROOT=""
WHEELHOUSE=""
FILES_ONLY=0

usage() {
    sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'
    exit "${1:-0}"
}
while [[ $# -gt 0 ]]; do
    case $1 in
    --dry-run) DRY_RUN=1 ;;
    --root) ROOT=$(realpath -m "${2:?--root needs a directory}") && shift ;;
    --wheelhouse) WHEELHOUSE=$(realpath "${2:?--wheelhouse needs a directory}") && shift ;;
    --files-only) FILES_ONLY=1 ;;
    -h | --help) usage 0 ;;
    *) echo "install.sh: unknown option '$1' (see --help)" >&2 && exit 2 ;;
    esac
    shift
done
if [[ -n $WHEELHOUSE && ! -d $WHEELHOUSE ]]; then
    echo "install.sh: --wheelhouse $WHEELHOUSE: no such directory" >&2
    exit 2
fi
if [[ $DRY_RUN == 0 && -z $ROOT && $(id -u) != 0 ]]; then
    echo "install.sh: run as root (or with --dry-run, or --root DIR)" >&2
    exit 2
fi

VENV=$ROOT$PREFIX/venv
CONFIG_DIR=$ROOT/etc/vision-swarm
STATE_DIR=$ROOT/var/lib/vision-swarm
MANIFEST=$ROOT$PREFIX/installed-etc.sha256 # what this script last wrote to each /etc file

run() {
    echo "+ $*"
    if [[ $DRY_RUN == 0 ]]; then "$@"; fi
}

system() { # a command that changes the running system: not when staging under --root
    if [[ -n $ROOT ]]; then
        echo "  (--root: skipped) $*"
    else
        run "$@"
    fi
}

# The manifest names files as on the drone (without --root's DIR).
recorded_sha() {
    [[ -f $MANIFEST ]] && awk -v f="${1#"$ROOT"}" '$2 == f { s = $1 } END { print s }' "$MANIFEST"
}

record_sha() {
    local sha
    sha=$(sha256sum "$1" | cut -d' ' -f1)
    mkdir -p "$(dirname "$MANIFEST")"
    { [[ -f $MANIFEST ]] && awk -v f="${1#"$ROOT"}" '$2 != f' "$MANIFEST"; } >"$MANIFEST.tmp" || true
    echo "$sha  ${1#"$ROOT"}" >>"$MANIFEST.tmp"
    mv "$MANIFEST.tmp" "$MANIFEST"
}

# install_etc SRC DEST MODE: install a configuration file, never over the operator's edits.
install_etc() {
    local src=$1 dest=$2 mode=$3 current
    if [[ -e $dest ]]; then
        current=$(sha256sum "$dest" | cut -d' ' -f1)
        if cmp -s "$src" "$dest"; then
            echo "  $dest: up to date"
            [[ $DRY_RUN == 1 ]] || record_sha "$dest"
            return
        fi
        if [[ $current != "$(recorded_sha "$dest")" ]]; then
            echo "  $dest: edited here: kept; the new version is $dest.new (merge by hand)"
            run install -m "$mode" "$src" "$dest.new"
            return
        fi
    fi
    run install -D -m "$mode" "$src" "$dest"
    [[ $DRY_RUN == 1 ]] || record_sha "$dest"
}

if [[ -z $ROOT ]] && ! id -u companion >/dev/null 2>&1; then
    run useradd --system --home-dir /var/lib/vision-swarm --shell /usr/sbin/nologin \
        --groups dialout companion
fi

if [[ $FILES_ONLY == 0 ]]; then
    # Build from a temporary copy: pip's in-tree build would leave build/ and *.egg-info, owned
    # by root, in the checkout.
    src=$(mktemp -d)
    trap 'rm -rf "$src"' EXIT
    tar -C "$REPO" --exclude=__pycache__ -cf - pyproject.toml README.md companion sim_harness |
        tar -C "$src" -xf -
    # The installed package says which commit it was built from (`companion --version`).
    (cd "$src" && "$PYTHON" -m companion.version --record --repo "$REPO") ||
        echo "  (not a git checkout: companion --version will say commit unknown)"
    run "$PYTHON" -m venv "$VENV"
    if [[ -n $WHEELHOUSE ]]; then
        run "$VENV/bin/pip" install --no-index --find-links "$WHEELHOUSE" "$src"
    else
        torch_pin=$(grep -o '"torch==[^"]*"' "$REPO/pyproject.toml" | tr -d '"')
        run "$VENV/bin/pip" install --upgrade pip
        # PyPI's torch for aarch64 is a CUDA build (GBs of NVIDIA libraries): take the CPU one.
        run "$VENV/bin/pip" install --index-url "$TORCH_INDEX_URL" "$torch_pin"
        run "$VENV/bin/pip" install "$src"
    fi
    if [[ $DRY_RUN == 0 ]]; then
        read -r torch_version cuda < <("$VENV/bin/python" -c \
            "import torch; print(torch.__version__, torch.version.cuda)")
        echo "torch $torch_version, CUDA $cuda"
        if [[ $cuda != None ]]; then
            echo "WARNING: torch is a CUDA build; the drone needs the CPU one ($TORCH_INDEX_URL)"
        fi
    fi
fi

run install -d -m 0755 "$ROOT$PREFIX/models" "$ROOT$PREFIX/docs" "$CONFIG_DIR"
run install -m 0644 "$REPO/docs/operator-guide.md" "$ROOT$PREFIX/docs/"
# The state directory exists before the first start, so that `companion check` can see it.
if [[ -z $ROOT ]]; then
    run install -d -o companion -g companion -m 0750 "$STATE_DIR"
else
    run install -d -m 0750 "$STATE_DIR"
fi

install_etc "$REPO/systemd/companion.toml" "$CONFIG_DIR/companion.toml" 0644
# PX4's parameters (drone 1's; `companion params file --sysid N` renders each drone's), the
# default of `companion check --autopilot`.
install_etc "$REPO/firmware_cfg/px4/companion.params" "$CONFIG_DIR/companion.params" 0644
install_etc "$REPO/firmware_cfg/udev/99-openmv.rules" "$ROOT/etc/udev/rules.d/99-openmv.rules" 0644
install_etc "$REPO/systemd/$UNIT" "$ROOT/etc/systemd/system/$UNIT" 0644
system udevadm control --reload-rules
system udevadm trigger --subsystem-match=tty
system systemctl daemon-reload
system systemctl enable "$UNIT"

if [[ -n $OPERATOR ]]; then
    rule="$OPERATOR ALL=(root) NOPASSWD:"
    for action in start stop restart status is-active; do
        rule+=" /usr/bin/systemctl $action $UNIT,"
    done
    # A failed launch shows the unit's last lines; the control socket's commands (engagement).
    rule+=" /usr/bin/journalctl -u $UNIT -n 20 --no-pager -o cat,"
    for action in engage disengage status; do
        rule+=" $PREFIX/venv/bin/companion $action,"
    done
    sudoers=$(mktemp)
    echo "${rule%,}" >"$sudoers"
    if [[ -z $ROOT ]]; then run visudo -cf "$sudoers"; fi
    install_etc "$sudoers" "$ROOT/etc/sudoers.d/vision-swarm" 0440
    rm -f "$sudoers"
fi

echo "done: edit /etc/vision-swarm/companion.toml, copy the model to $PREFIX/models/, then"
echo "      $PREFIX/venv/bin/companion check --config /etc/vision-swarm/companion.toml"
