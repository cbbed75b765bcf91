#!/usr/bin/env bash
# Make sure PostgreSQL server binaries (initdb, pg_ctl) are installed, for the API tests that
# start a throwaway server (tests/postgres.py). Quick and silent when they already are.
#
#   as root:        installs Debian's `postgresql` package with apt-get when missing;
#   not root:       prints how to install it; fails when CI=true, warns (exit 0) otherwise.
set -euo pipefail

have_server_binaries() {
    local dir
    for dir in /usr/lib/postgresql/*/bin; do
        if [[ -x "$dir/initdb" && -x "$dir/pg_ctl" ]]; then
            return 0
        fi
    done
    command -v initdb >/dev/null 2>&1 && command -v pg_ctl >/dev/null 2>&1
}

is_ci() {
    case "${CI:-}" in
        [Tt][Rr][Uu][Ee] | 1 | [Yy][Ee][Ss]) return 0 ;;
        *) return 1 ;;
    esac
}

if have_server_binaries; then
    exit 0
fi

if [[ "$(id -u)" -eq 0 ]]; then
    if ! command -v apt-get >/dev/null 2>&1; then
        echo "ensure-postgres: PostgreSQL server binaries (initdb, pg_ctl) not found and apt-get is" \
            "not available; install PostgreSQL with this system's package manager." >&2
        exit 1
    fi
    echo "ensure-postgres: installing PostgreSQL server (apt-get install postgresql) ..." >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends postgresql >/dev/null
    if ! have_server_binaries; then
        echo "ensure-postgres: 'apt-get install postgresql' finished but initdb/pg_ctl are still" \
            "missing under /usr/lib/postgresql/*/bin." >&2
        exit 1
    fi
    echo "ensure-postgres: installed $(ls -d /usr/lib/postgresql/*/bin | sort -V | tail -n 1)" >&2
    exit 0
fi

message="PostgreSQL server binaries (initdb, pg_ctl) are not installed; the PostgreSQL API tests
need them. Install them with:  sudo apt-get install --no-install-recommends postgresql
(or run 'sudo bash scripts/ensure-postgres.sh')."
if is_ci; then
    echo "ensure-postgres: error: $message" >&2
    exit 1
fi
echo "ensure-postgres: warning: $message The PostgreSQL tests will be skipped." >&2
exit 0
