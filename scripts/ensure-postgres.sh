#!/usr/bin/env bash
# Make sure PostgreSQL server binaries (initdb, pg_ctl) are installed, for the API tests that
# start a throwaway server (harness/postgres.py). Quick and silent when they already are.
set -euo pipefail
source "$(dirname "$0")/lib/ensure.sh"

have_server_binaries() {
    local dir
    for dir in /usr/lib/postgresql/*/bin; do
        if [[ -x "$dir/initdb" && -x "$dir/pg_ctl" ]]; then
            return 0
        fi
    done
    command -v initdb >/dev/null 2>&1 && command -v pg_ctl >/dev/null 2>&1
}

ensure_package postgres postgresql have_server_binaries \
    "the PostgreSQL API tests need its server binaries (initdb, pg_ctl)."
