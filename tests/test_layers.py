"""The package's import graph is layered as the pipeline runs (a stage imports only stages before it and the
utilities), it has no cycle, and no module is over 600 lines.

Every ``import``/``from ... import`` of every module under src/spinecohort is read with ``ast`` (imports inside
functions and under ``TYPE_CHECKING`` included: a deferred import is still a dependency).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "spinecohort"

#: the layers, lowest first: a module may import its own layer and the layers below it, never one above.
#: A name is a subpackage or a top-level module of spinecohort; "<root>" is spinecohort/__init__.py (the version).
LAYERS: list[set[str]] = [
    {"<root>", "atomic", "logs", "config", "layout"},  # utilities: no pipeline stage
    {"geometry"},  # point-set registration and surface distances (modules of mesh/, see MODULE_LAYERS)
    {"landmarks"},  # the landmark structure every stage reads (cohort/landmarks.py)
    {"store"},  # the Zarr store's format, grid of model IDs, reading and writing, the shard tables' columns
    {"anatomy"},  # the labeled reference spine (real bone surfaces) and its morphometry
    {"cohort"},  # patients' meshes and landmarks
    {"ssm"},  # alignment and the statistical shape model
    {"measure"},  # spinopelvic parameters (of patients, of virtual models, the cohort sheet)
    {"mesh"},  # hex template, morph, hex SSM, quality, repair, contact
    {"virtual"},  # the per-shard job of the virtual cohort (sample, check, repair, measure, store)
    {"fe"},  # FE models and decks
    {"rom"},  # range-of-motion analyses in CalculiX
    {"personalize"},  # patient-personalized models
    {"figures"},
    {"release"},
    {"web"},  # the browser platform
    {"cli", "__main__", "testing"},  # the entry points; testing builds known cases from any stage for the tests
]
#: modules whose layer is not their package's: generic geometry that the cohort stage (registering the reference
#: onto patients) and the mesh stage (morphing the hex template) both use, and the landmark structure that the
#: reference anatomy, the cohort and every later stage read
MODULE_LAYERS = {
    **{f"spinecohort.mesh.{m}": "geometry" for m in ("pointsets", "distance", "bcpd", "registration", "vtk_mesh")},
    "spinecohort.cohort.landmarks": "landmarks",
}
LAYER_OF = {name: i for i, layer in enumerate(LAYERS) for name in layer}

#: (importing module, imported module) pairs allowed against the layer order, each with its reason.  The test
#: also fails when a pair listed here no longer occurs, so that the list only holds what is true.
EXCEPTIONS: dict[tuple[str, str], str] = {}

MAX_MODULE_LINES = 600


def module_name(path: Path) -> str:
    parts = path.relative_to(SRC).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def imported_modules(name: str, path: Path) -> set[str]:
    """The spinecohort modules that module ``name`` imports (``from pkg import mod`` resolves to pkg.mod when
    that is a module, else to pkg)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            targets = [f"{module}.{a.name}" if f"{module}.{a.name}" in MODULES else module for a in node.names]
        else:
            continue
        out.update(t for t in targets if t == "spinecohort" or t.startswith("spinecohort."))
    out.discard(name)
    return out


GRAPH = {name: imported_modules(name, path) for name, path in MODULES.items()}


def layer_name(module: str) -> str:
    if module in MODULE_LAYERS:
        return MODULE_LAYERS[module]
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "<root>"


def test_every_package_has_a_layer():
    missing = sorted({layer_name(m) for m in MODULES} - set(LAYER_OF))
    assert not missing, f"spinecohort.{missing[0]} is in no layer: add it to LAYERS in tests/test_layers.py"


def test_imports_follow_the_layers():
    backward = [
        f"{m} (layer {layer_name(m)}) imports {t} (layer {layer_name(t)}, above it)"
        for m, targets in GRAPH.items()
        for t in sorted(targets)
        if LAYER_OF.get(layer_name(t), -1) > LAYER_OF.get(layer_name(m), len(LAYERS)) and (m, t) not in EXCEPTIONS
    ]
    assert not backward, "\n".join(backward)


def test_every_exception_still_occurs():
    stale = [f"{m} -> {t}" for m, t in EXCEPTIONS if t not in GRAPH.get(m, set())]
    assert not stale, f"no longer imported, delete from EXCEPTIONS: {stale}"


def test_the_import_graph_has_no_cycle():
    """Depth-first search over the module graph; a back edge closes a cycle, which the message spells out."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        path.append(m)
        for t in sorted(GRAPH.get(m, ())):
            if state.get(t) == 1:
                return path[path.index(t) :] + [t]
            if t not in state and (cycle := visit(t)):
                return cycle
        state[m] = 2
        path.pop()
        return None

    for m in sorted(GRAPH):
        if m not in state and (cycle := visit(m)):
            pytest.fail("import cycle: " + " -> ".join(cycle))


def test_the_reader_finds_deferred_and_relative_imports(tmp_path):
    """The graph reader on a module written for the purpose: ``from spinecohort.rom import deck`` inside a
    function of an fe module is found (an fe -> rom arrow, a layer up), and so is a relative import."""
    fe = tmp_path / "spinecohort" / "fe"
    fe.mkdir(parents=True)
    (fe / "x.py").write_text("def f():\n    from spinecohort.rom import deck\n    from . import abaqus\n")
    found = imported_modules("spinecohort.fe.x", fe / "x.py")
    assert found == {"spinecohort.rom.deck", "spinecohort.fe.abaqus"}
    assert LAYER_OF["rom"] > LAYER_OF["fe"]


def test_no_module_over_600_lines():
    sizes = {str(p.relative_to(PACKAGE)): len(p.read_text().splitlines()) for p in MODULES.values()}
    over = sorted(f"{k} ({n} lines)" for k, n in sizes.items() if n > MAX_MODULE_LINES)
    assert not over, f"modules over {MAX_MODULE_LINES} lines, split them by concern: {over}"
