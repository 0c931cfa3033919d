#!/usr/bin/env bash
# Refresh requirements.lock: the exact version of every Python package that `pip install -e ".[test]"`
# resolves today, for this Python (3.11). Run after changing dependencies in pyproject.toml, commit the lock.
# The README's install command and .ci/run install with `-c requirements.lock`, so a release is rebuilt
# with the versions it was built with; .ci/run fails when the installed set drifts from the lock.
set -euo pipefail
cd "$(dirname "$0")/.."
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
python3 -m venv "$tmp/venv"
"$tmp/venv/bin/pip" install --quiet --upgrade pip
"$tmp/venv/bin/pip" install --quiet -e ".[test]"
{
    echo "# Exact versions of every Python dependency (pyproject.toml [project] + [test]); Python $("$tmp/venv/bin/python" -c 'import platform; print(platform.python_version())')."
    echo "# Refresh: bash scripts/lock.sh   Use: pip install -c requirements.lock -e \".[test]\""
    "$tmp/venv/bin/pip" freeze --exclude-editable | LC_ALL=C sort -f
} > requirements.lock
echo "requirements.lock: $(grep -vc '^#' requirements.lock) packages"
