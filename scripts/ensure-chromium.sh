#!/usr/bin/env bash
# Make sure Debian's Chromium is installed, for the dashboard's browser tests
# (tests/test_dashboard_browser.py drive it with Playwright). Quick and silent when it is.
set -euo pipefail
source "$(dirname "$0")/lib/ensure.sh"

have_chromium() {
    [[ -x /usr/bin/chromium ]]
}

ensure_package chromium chromium have_chromium "the dashboard's browser tests drive /usr/bin/chromium."
