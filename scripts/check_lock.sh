#!/usr/bin/env bash
# Fail when the installed Python packages differ from requirements.lock (a dependency added to
# pyproject.toml without `bash scripts/lock.sh`, or a version the lock does not pin).
set -euo pipefail
cd "$(dirname "$0")/.."
py=${1:-.venv/bin/python}
if ! diff <(grep -v '^#' requirements.lock | LC_ALL=C sort -f) <("$py" -m pip freeze --exclude-editable | LC_ALL=C sort -f); then
    echo "check_lock: the environment differs from requirements.lock ('<' lock, '>' installed); run bash scripts/lock.sh" >&2
    exit 1
fi
echo "check_lock: environment matches requirements.lock ($(grep -vc '^#' requirements.lock) packages)"
