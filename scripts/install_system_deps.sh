#!/usr/bin/env bash
# Install the Debian packages spinecohort needs outside Python (idempotent).
#   calculix-ccx : the CalculiX solver `ccx` (2.20 on Debian 12), used by spinecohort.fe.calculix to
#                  check and run the exported .inp decks.
#   chromium, chromium-driver : a headless browser and its WebDriver, for the tests of the web platform
#                  (tests/test_web.py drives `spinecohort serve` in a real Chromium; the platform itself needs
#                  only the user's browser)
#   nginx-light  : a static HTTP server that honours Range requests, for the tests and the benchmark of
#                  reading the release over HTTP (tests/test_remote.py, benchmarks/bench_remote.py start their
#                  own nginx on 127.0.0.1; Python's http.server ignores Range)
# Usage: sudo scripts/install_system_deps.sh   (does nothing but report when not root)
set -euo pipefail

PACKAGES=(calculix-ccx chromium chromium-driver nginx-light)

missing=()
for pkg in "${PACKAGES[@]}"; do
    if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
        missing+=("$pkg")
    fi
done

if [ ${#missing[@]} -eq 0 ]; then
    echo "install_system_deps: all present (${PACKAGES[*]})"
    exit 0
fi

if [ "$(id -u)" -ne 0 ]; then
    echo "install_system_deps: not root; skipping. Missing: ${missing[*]}" >&2
    echo "  run: sudo apt-get update && sudo apt-get install -y ${missing[*]}" >&2
    exit 0
fi

export DEBIAN_FRONTEND=noninteractive
apt-get update
apt-get install -y --no-install-recommends "${missing[@]}"
echo "install_system_deps: installed ${missing[*]}"
