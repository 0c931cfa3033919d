#!/usr/bin/env bash
# The lint gate (.ci/run runs it before the tests): ruff's rules and formatter (pyproject.toml [tool.ruff],
# 120 columns) on the Python, snakefmt on the Snakefile and the rule files, and two checks of the text:
#   - no history markers: a numbered work session or an issue number in a tracked *.py, *.md, *.yaml,
#     *.smk, *.sh, *.toml or the Snakefile fails the gate, naming file:line (history lives in git and in
#     CHANGELOG.md, which may name versions and link issues, never sessions);
#   - module size: a module under src/ over 600 lines fails the gate.
# Fix the style with
#   .venv/bin/ruff check --fix src tests benchmarks workflow/scripts && .venv/bin/ruff format src tests benchmarks workflow/scripts && .venv/bin/snakefmt Snakefile workflow/rules
set -euo pipefail
cd "$(dirname "$0")/.."
bin=${VENV:-.venv}/bin
"$bin/ruff" check src tests benchmarks workflow/scripts scripts
"$bin/ruff" format --check src tests benchmarks workflow/scripts scripts
"$bin/snakefmt" --check Snakefile workflow/rules

session_re='[Ss]ession [0-9]+'
issue_re='(^|[^[:alnum:]_])[Ii]ssue #?[0-9]+'
# Only tracked files: results/, .venv/ and .snakemake/ are ignored by git and never scanned.
mapfile -t text_files < <(git ls-files -- '*.py' '*.md' '*.yaml' '*.smk' '*.sh' '*.toml' 'Snakefile')
history_failed=0
for f in "${text_files[@]}"; do
    [[ -f $f ]] || continue
    hits=$(grep -nE "$session_re" "$f" || true)
    if [[ $f != CHANGELOG.md ]]; then
        hits+=$'\n'$(grep -nE "$issue_re" "$f" || true)
    fi
    hits=$(sed '/^$/d' <<<"$hits" | sort -t: -k1,1n -u)
    [[ -z $hits ]] && continue
    while IFS= read -r line; do
        echo "error: history marker (session or issue number) at $f:${line%%:*}: ${line#*:}" >&2
    done <<<"$hits"
    history_failed=1
done
if ((history_failed)); then
    echo "lint: history markers found (say what the code is, not when it changed; history goes in CHANGELOG.md)" >&2
    exit 1
fi

max_module_lines=600
size_failed=0
while IFS= read -r f; do
    [[ -f $f ]] || continue
    n=$(wc -l <"$f")
    if ((n > max_module_lines)); then
        echo "error: $f has $n lines (> $max_module_lines): split it by concern" >&2
        size_failed=1
    fi
done < <(git ls-files -- 'src/*.py')
if ((size_failed)); then
    exit 1
fi
echo "lint: clean"
