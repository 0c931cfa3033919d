"""Render docs/reference/config.md from the config schema and the default config.

    .venv/bin/python scripts/render_config_reference.py            # rewrite docs/reference/config.md
    .venv/bin/python scripts/render_config_reference.py --check    # exit 1 if the committed file differs

The schema (workflow/schemas/config.schema.yaml) is the config's documentation: every key with its type,
range and description.  This page lays it out as one table per section, with the default value of
config/config.yaml beside each key; tests/test_docs.py fails when the committed page is not this output.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"
CONFIG = ROOT / "config" / "config.yaml"
OUT = ROOT / "docs" / "reference" / "config.md"
MAX_DEFAULT_CHARS = 60
BOUNDS = (("minimum", ">="), ("exclusiveMinimum", ">"), ("maximum", "<="), ("exclusiveMaximum", "<"))


def resolve(node: dict, defs: dict) -> dict:
    """The node with a local ``$ref`` merged in (the node's own keys, e.g. its description, win)."""
    if "$ref" not in node:
        return node
    target = defs[node["$ref"].rsplit("/", 1)[-1]]
    return {**target, **{k: v for k, v in node.items() if k != "$ref"}}


def type_of(node: dict) -> str:
    if "enum" in node:
        return "one of"
    t = node.get("type", "")
    if isinstance(t, list):
        return " or ".join(str(x) for x in t)
    if t == "array" and isinstance(node.get("items"), dict):
        inner = node["items"]
        return f"list of {inner.get('type', 'enum' if 'enum' in inner else 'object')}"
    if t == "object" and isinstance(node.get("additionalProperties"), dict):
        return f"map of {node['additionalProperties'].get('type', 'value')}"
    return str(t)


def allowed(node: dict) -> str:
    """Enum values, numeric bounds, patterns and sizes of a schema node, in one cell."""
    parts = []
    if "enum" in node:
        parts.append(", ".join(f"`{v}`" for v in node["enum"]))
    for src in (node, node.get("items") if isinstance(node.get("items"), dict) else {}, _value_schema(node)):
        for key, sign in BOUNDS:
            if key in src:
                parts.append(f"{sign} {src[key]}")
        if "enum" in src and src is not node:
            parts.append(", ".join(f"`{v}`" for v in src["enum"]))
        if "pattern" in src:
            parts.append(f"pattern `{src['pattern']}`")
    if "propertyNames" in node and "pattern" in node["propertyNames"]:
        parts.append(f"keys `{node['propertyNames']['pattern']}`")
    for key, label in (("minItems", ">= {} items"), ("maxItems", "<= {} items"), ("minLength", "length >= {}")):
        if key in node:
            parts.append(label.format(node[key]))
    return "; ".join(parts)


def _value_schema(node: dict) -> dict:
    extra = node.get("additionalProperties")
    return extra if isinstance(extra, dict) else {}


def default_cell(value, present: bool | None) -> str:
    """The default as inline code; None: a field of a list's items, which has no single default."""
    if present is None:
        return "—"
    if not present:
        return "(absent)"
    text = json.dumps(value, ensure_ascii=False)
    if len(text) > MAX_DEFAULT_CHARS:
        if isinstance(value, (list, dict)):
            text = f"{len(value)} {'entry' if len(value) == 1 else 'entries'}"
        else:
            text = text[: MAX_DEFAULT_CHARS - 1] + "…"
    return f"`{text}`"


def cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def prose(text: str) -> str:
    """A description cell: angle brackets outside code spans escaped, so <disc> is shown, not read as HTML."""
    parts = cell(text).split("`")
    return "`".join(p if i % 2 else p.replace("<", "&lt;").replace(">", "&gt;") for i, p in enumerate(parts))


def rows(node: dict, defs: dict, config, present: bool | None, prefix: str, required: set) -> list[str]:
    """One table row per key below ``node`` (depth first), objects with named properties recursed into."""
    out = []
    for key, child in node.get("properties", {}).items():
        child = resolve(child, defs)
        has = None if present is None else bool(present and isinstance(config, dict) and key in config)
        value = config.get(key) if has else None
        name = f"{prefix}{key}"
        need = "" if key in required else " (optional)"
        out.append(
            f"| `{name}`{need} | {cell(type_of(child))} | {cell(default_cell(value, has))} | "
            f"{cell(allowed(child))} | {prose(child.get('description', ''))} |"
        )
        if "properties" in child:
            out += rows(child, defs, value, has, f"{name}.", set(child.get("required", [])))
        items = child.get("items")
        if isinstance(items, dict) and "properties" in resolve(items, defs):
            out += rows(resolve(items, defs), defs, None, None, f"{name}[].", set(items.get("required", [])))
    return out


def render(schema: dict, config: dict) -> str:
    defs = schema.get("$defs", {})
    lines = [
        "# Configuration reference",
        "",
        "<!-- Generated by scripts/render_config_reference.py from workflow/schemas/config.schema.yaml and",
        "     config/config.yaml; do not edit by hand (tests/test_docs.py checks it is up to date). -->",
        "",
        "Units are millimetres and degrees unless a key's name says otherwise. The pipeline reads",
        "`config/config.yaml` (or `--configfile`) and validates it against `workflow/schemas/config.schema.yaml` before any rule runs: unknown keys, wrong types",
        "and out-of-range values are rejected with the key named. The *default* column is the value in",
        "`config/config.yaml`; `.test/config/config.yaml` has the same keys with a small cohort. Rules receive",
        "their settings as `params`, so changing a value reruns exactly the rules that use it.",
        "",
        "Sections: " + ", ".join(f"[`{k}`](#{k})" for k in schema["properties"]) + ".",
        "",
    ]
    required = set(schema.get("required", []))
    for key, node in schema["properties"].items():
        node = resolve(node, defs)
        lines += [f"## {key}", "", prose(node.get("description", "")), ""]
        lines += ["| key | type | default | allowed | description |", "|---|---|---|---|---|"]
        has = key in config
        need = "" if key in required else " (optional)"
        if "properties" not in node:
            lines.append(
                f"| `{key}`{need} | {cell(type_of(node))} | {cell(default_cell(config.get(key), has))} | "
                f"{cell(allowed(node))} | {prose(node.get('description', ''))} |"
            )
        else:
            lines += rows(node, defs, config.get(key), has, f"{key}.", set(node.get("required", [])))
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="compare with the committed file instead of writing it")
    args = ap.parse_args(argv)
    text = render(yaml.safe_load(SCHEMA.read_text()), yaml.safe_load(CONFIG.read_text()))
    if args.check:
        if not OUT.exists() or OUT.read_text() != text:
            print(f"{OUT.relative_to(ROOT)} is out of date: run scripts/render_config_reference.py", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
