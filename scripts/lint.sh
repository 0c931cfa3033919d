#!/usr/bin/env bash
# The lint gate (.ci/run runs it before the tests): ruff's rules and formatter (pyproject.toml [tool.ruff],
# 120 columns) on the Python, snakefmt on the Snakefile and the rule files. Fix with
#   .venv/bin/ruff check --fix src tests benchmarks workflow/scripts && .venv/bin/ruff format src tests benchmarks workflow/scripts && .venv/bin/snakefmt Snakefile workflow/rules
set -euo pipefail
cd "$(dirname "$0")/.."
bin=${VENV:-.venv}/bin
"$bin/ruff" check src tests benchmarks workflow/scripts
"$bin/ruff" format --check src tests benchmarks workflow/scripts
"$bin/snakefmt" --check Snakefile workflow/rules
echo "lint: clean"
