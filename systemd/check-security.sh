#!/usr/bin/env bash
# The companion unit's sandbox, scored by systemd itself (no install, no running systemd needed):
#
#   systemd/check-security.sh [UNIT_FILE] [MAX_EXPOSURE]
#
# UNIT_FILE defaults to the shipped unit, MAX_EXPOSURE to 2.0 (systemd-analyze's 0-10 scale,
# lower is safer). Fails (exit 1) when the score is above the maximum, when systemd ignores a
# line of the unit (unknown key, bad value: a silently lost directive) or when the unit sets
# MemoryDenyWriteExecute=yes (oneDNN's JIT, used by the model's graph fusion, then fails).
# Exit 2: systemd-analyze is missing or the arguments are wrong.
set -euo pipefail

UNIT=${1:-$(dirname "$0")/vision-swarm-companion.service}
MAX=${2:-2.0}

if ! command -v systemd-analyze >/dev/null; then
    echo "check-security: systemd-analyze not found (Debian: apt-get install systemd)" >&2
    exit 2
fi
if [[ ! -f $UNIT ]]; then
    echo "check-security: $UNIT: no such unit file" >&2
    exit 2
fi
if ! [[ $MAX =~ ^[0-9]+(\.[0-9]+)?$ ]]; then
    echo "check-security: MAX_EXPOSURE: '$MAX' is not a number in [0, 10]" >&2
    exit 2
fi

errors=$(mktemp)
trap 'rm -f "$errors"' EXIT
report=$(systemd-analyze security --offline=true --no-pager "$UNIT" 2>"$errors") || true
score=$(sed -n 's/.*Overall exposure level for .*: \([0-9.]*\) .*/\1/p' <<<"$report")
if [[ -z $score ]]; then
    echo "check-security: systemd-analyze gave no score for $UNIT:" >&2
    cat "$errors" >&2
    exit 1
fi

status=0
if [[ -s $errors ]]; then
    echo "FAIL: systemd ignores lines of $UNIT:"
    cat "$errors"
    status=1
fi
if grep -Eiq '^[[:space:]]*MemoryDenyWriteExecute[[:space:]]*=[[:space:]]*(yes|true|1|on)' "$UNIT"; then
    echo "FAIL: MemoryDenyWriteExecute=yes breaks oneDNN's JIT (the model's graph fusion)"
    status=1
fi
if awk -v s="$score" -v m="$MAX" 'BEGIN { exit !(s + 0 > m + 0) }'; then
    echo "FAIL: $UNIT: exposure $score is above $MAX; what is still open:"
    grep '✗' <<<"$report" || true
    status=1
else
    echo "ok: $UNIT: exposure $score (at most $MAX)"
fi
exit $status
