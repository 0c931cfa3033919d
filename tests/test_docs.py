"""The manual stays whole: every relative link in README.md and docs/ reaches a file, and the generated
reference pages equal what their scripts write from the schema and the CLI today."""

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Markdown links and images: [text](target) / ![alt](target), target up to a space, ) or "title".
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def markdown_files():
    return [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").rglob("*.md"))]


def relative_links(path: Path):
    """(line number, target without its #anchor) of every link that is not a URL or a pure anchor."""
    in_code = False
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if line.lstrip().startswith("```"):
            in_code = not in_code
        if in_code:
            continue
        for target in LINK.findall(re.sub(r"`[^`]*`", "", line)):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
                continue
            yield number, target.split("#", 1)[0]


def test_the_link_pattern_finds_links_and_skips_urls_and_code(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(
        'See [a](a.md#x), ![img](img/p.png "t") and [web](https://example.org).\n'
        "`[not](code.md)` and [anchor](#here)\n```\n[in](fence.md)\n```\n"
    )
    assert list(relative_links(page)) == [(1, "a.md"), (1, "img/p.png")]


def test_every_relative_link_resolves():
    broken = []
    for page in markdown_files():
        if not page.exists():
            continue
        for number, target in relative_links(page):
            resolved = (page.parent / target).resolve()
            if resolved.exists():
                continue
            broken.append(f"{page.relative_to(ROOT)}:{number}: {target}")
    assert not broken, "links to missing files:\n" + "\n".join(broken)


def test_the_docs_tree_has_each_purpose():
    # the layout the README and docs/index.md promise: a tutorial, how-tos, reference and explanations
    for page in (
        "README.md",
        "CHANGELOG.md",
        "docs/index.md",
        "docs/tutorial.md",
        "docs/howto/index.md",
        "docs/reference/config.md",
        "docs/reference/cli.md",
        "docs/reference/outputs.md",
        "docs/reference/store-format.md",
        "docs/reference/deck.md",
        "docs/explanation/performance.md",
    ):
        assert (ROOT / page).is_file(), page


def _script(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(
    "script, page",
    [("render_config_reference", "docs/reference/config.md"), ("render_cli_reference", "docs/reference/cli.md")],
)
def test_the_generated_reference_is_up_to_date(script, page):
    # the committed page must be exactly what the script writes from the schema / the parser today; after a
    # change to either, run `.venv/bin/python scripts/<script>.py` and commit the page
    module = _script(script)
    assert module.OUT == ROOT / page
    expected = module.main(["--check"])
    assert expected == 0, f"{page} is out of date: run .venv/bin/python scripts/{script}.py"


def test_the_config_reference_lists_every_key_of_the_default_config():
    # every leaf of config/config.yaml has its own row, or is an entry of a documented map (e.g. the facet
    # angles per level), so a key added to config and schema shows up on the page
    import yaml

    rows = {}
    for line in (ROOT / "docs/reference/config.md").read_text().splitlines():
        match = re.match(r"^\| `([^`]+)`[^|]*\| ([^|]*)\|", line)
        if match:
            rows[match.group(1)] = match.group(2)

    def leaves(node, prefix=""):
        for key, value in node.items():
            name = f"{prefix}{key}"
            if isinstance(value, dict):
                yield from leaves(value, f"{name}.")
            else:
                yield name

    def documented(key):
        parent = key.rsplit(".", 1)[0]
        return key in rows or rows.get(parent, "").startswith("map of")

    config = yaml.safe_load((ROOT / "config/config.yaml").read_text())
    missing = [k for k in leaves(config) if not documented(k)]
    assert not missing, missing
    assert len(rows) > 200  # the default config has ~210 documented keys
