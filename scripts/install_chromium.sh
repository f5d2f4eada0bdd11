#!/usr/bin/env bash
# Install Debian's chromium for the browser tests (tests/app/test_viewer_browser.py), unless it is
# already there. Never downloads a browser through playwright: the tests drive this one with
# executable_path=/usr/bin/chromium.
#
#   bash scripts/install_chromium.sh            # installs only when /usr/bin/chromium is missing
#   CHROMIUM=/path/to/chromium bash scripts/... # checks another path instead
set -euo pipefail

CHROMIUM="${CHROMIUM:-/usr/bin/chromium}"

if [ -x "$CHROMIUM" ]; then
    echo "chromium present: $CHROMIUM"
else
    SUDO=""
    if [ "$(id -u)" -ne 0 ]; then
        if command -v sudo >/dev/null 2>&1; then
            SUDO="sudo"
        else
            echo "install_chromium.sh: need root or sudo to apt-get install chromium" >&2
            exit 1
        fi
    fi
    if ! command -v apt-get >/dev/null 2>&1; then
        echo "install_chromium.sh: no apt-get; install chromium yourself (expected at $CHROMIUM)" >&2
        exit 1
    fi
    echo "install_chromium.sh: installing Debian's chromium with apt-get for the browser test" \
         "of the viewer (tests/app/test_viewer_browser.py); this may take a minute"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get update -q
    $SUDO apt-get install -y -q --no-install-recommends chromium fonts-liberation
    if [ ! -x "$CHROMIUM" ]; then
        echo "install_chromium.sh: apt-get finished but $CHROMIUM is missing" >&2
        exit 1
    fi
fi
# Print the version (Debian's wrapper script may print a harmless shell warning first).
"$CHROMIUM" --version 2>/dev/null || true
