"""spinecohort.layout: the one place results paths are spelled."""

import re
from pathlib import Path

from spinecohort.layout import FIGURE_NAMES, Layout

ROOT = Path(__file__).resolve().parents[1]


def _properties(layout):
    return {n: getattr(layout, n) for n, v in vars(Layout).items() if isinstance(v, property)}


def test_every_path_lies_under_the_root_and_no_two_names_spell_the_same_path():
    L = Layout("out/")  # a trailing slash is not doubled
    paths = _properties(L)
    singles = {n: p for n, p in paths.items() if isinstance(p, str)}
    assert all(p.startswith("out/") and "//" not in p for p in singles.values()), singles
    assert len(set(singles.values())) == len(singles)  # one name per path
    assert L.figures == [f"out/{n}" for n in FIGURE_NAMES] and len(set(FIGURE_NAMES)) == len(FIGURE_NAMES)
    assert L.shard_file("{shard}", "sample.json") == "out/shards/{shard}.sample.json"  # a wildcard pattern
    assert L.benchmark("sample_shard", "{shard}") == "out/benchmarks/sample_shard/{shard}.tsv"


def test_no_rule_file_spells_a_results_path():
    # every results path of the rules comes from L (common.smk); a literal "results/..." or an f"{R}/..."
    # would be a second spelling
    for smk in (ROOT / "workflow" / "rules").glob("*.smk"):
        text = smk.read_text()
        assert not re.search(r'f"\{R\}/|"results/', text), smk.name
