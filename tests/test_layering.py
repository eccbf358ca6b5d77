"""The package layering of docs/architecture.md holds: no cycle, no upward import, no private
name taken from another package.

Every module of ``sss2bathy`` is parsed with :mod:`ast` (imports inside functions, under
``TYPE_CHECKING`` and ``importlib.import_module("sss2bathy...")`` with a literal name
included; nothing is imported). Each import of another first-level package (``data``,
``eval``, ...; a top-level module such as ``config_validation`` counts as one) is an edge of
the package graph. The rules:

1. the graph has no cycle;
2. an edge goes strictly downward in :data:`LAYERS` (a package imports only from lower
   layers; packages of one layer do not import each other);
3. no module imports a ``_private`` name or module of another package (public seams only);
4. inside a package, the modules' import graph has no cycle either (an import inside a
   function hides a cycle; it does not remove it);
5. the top-level ``studies/`` and ``benchmarks/`` sit above everything: they import the
   library's public names only, no ``sss2bathy`` module imports them, and the package build
   (``[tool.setuptools.packages.find]`` of pyproject.toml) leaves them out.

:data:`KNOWN_VIOLATIONS` names the violations that are being fixed; each must still exist,
so the list can only shrink. :data:`LAYERS` must match the layer block of
docs/architecture.md.
"""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "sss2bathy"
DOC = ROOT / "docs" / "architecture.md"
#: Top-level folders of scripts on the library's public API, outside the package.
OUTSIDE = ("studies", "benchmarks")

#: Bottom to top; ``sss2bathy`` is the root ``__init__`` (the version string only).
LAYERS: tuple[tuple[str, ...], ...] = (
    ("sss2bathy",),
    ("utils",),
    ("geometry",),
    ("survey",),
    ("io",),
    ("sim",),
    ("draping",),
    ("losses", "metrics"),
    ("models",),
    ("data",),
    ("eval",),
    ("callbacks",),
    ("modules",),
    ("config_validation",),
    ("cli", "pretrained"),
)

#: ``(rule, importing file relative to sss2bathy/, imported module + name)``: known violations
#: being fixed in parallel (issue #17). Empty it as they go; an entry that no longer occurs
#: fails.
KNOWN_VIOLATIONS: frozenset[tuple[str, str, str]] = frozenset()


#: ``(importing module, imported module)`` edges of known cycles between the modules of one
#: package, left out of rule 4 until fixed; an entry that no longer occurs fails.
KNOWN_MODULE_CYCLE_EDGES: frozenset[tuple[str, str]] = frozenset()


@dataclass(frozen=True)
class Import:
    """One import of another first-level package."""

    source: str  # importing package
    target: str  # imported package
    file: str  # importing file, relative to sss2bathy/
    line: int
    module: str  # imported module (``.name`` appended for a ``from`` import)


def _package_of(module: str) -> str:
    """First-level package of a dotted module name inside ``sss2bathy``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _first_level(path: Path) -> str:
    rel = path.relative_to(PACKAGE).parts
    if len(rel) == 1:
        return "sss2bathy" if rel[0] == "__init__.py" else rel[0].removesuffix(".py")
    return rel[0]


def _imported(node: ast.AST, module: str, is_package: bool) -> list[str]:
    """Fully qualified modules (``from`` imports: module + name) an AST node imports."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if isinstance(node, ast.ImportFrom):
        base = node.module or ""
        if node.level:
            here = module.split(".") if is_package else module.split(".")[:-1]
            here = here[: len(here) - (node.level - 1)]
            base = ".".join(here + ([node.module] if node.module else []))
        return [f"{base}.{a.name}" for a in node.names]
    if (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute | ast.Name)
        and (getattr(node.func, "attr", None) or getattr(node.func, "id", None)) == "import_module"
        and node.args
        and isinstance(node.args[0], ast.Constant)
        and isinstance(node.args[0].value, str)
    ):
        return [node.args[0].value]
    return []


def package_imports() -> list[Import]:
    """Every import from one first-level package of sss2bathy into another."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = _module_name(path)
        source = _first_level(path)
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            for name in _imported(node, module, path.name == "__init__.py"):
                if name != "sss2bathy" and not name.startswith("sss2bathy."):
                    continue
                target = _package_of(name)
                if name.count(".") == 1 and not _is_first_level(target):
                    target = "sss2bathy"  # ``from sss2bathy import __version__``
                if target != source:
                    rel = str(path.relative_to(PACKAGE))
                    found.append(Import(source, target, rel, node.lineno, name))
    return found


def module_edges() -> dict[str, set[str]]:
    """``{module: modules of the same first-level package it imports}`` (a module's own
    parent packages left out: importing them is how a package's modules meet)."""
    paths = sorted(PACKAGE.rglob("*.py"))
    modules = {_module_name(p) for p in paths}
    edges: dict[str, set[str]] = defaultdict(set)
    for path in paths:
        module = _module_name(path)
        package = module.split(".")[:2]
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            for name in _imported(node, module, path.name == "__init__.py"):
                parts = name.split(".")
                while parts and ".".join(parts) not in modules:
                    parts.pop()  # ``from pkg.mod import name``: the module is pkg.mod
                target = ".".join(parts)
                if target and parts[:2] == package and not (module + ".").startswith(target + "."):
                    edges[module].add(target)
    return edges


def _is_first_level(name: str) -> bool:
    return (PACKAGE / name / "__init__.py").is_file() or (PACKAGE / f"{name}.py").is_file()


def first_level_packages() -> set[str]:
    names = {p.parent.name for p in PACKAGE.glob("*/__init__.py")}
    names |= {p.stem for p in PACKAGE.glob("*.py") if p.name != "__init__.py"}
    return names | {"sss2bathy"}


def _rank() -> dict[str, int]:
    return {pkg: i for i, layer in enumerate(LAYERS) for pkg in layer}


def violations(imports: list[Import]) -> dict[tuple[str, str, str], list[Import]]:
    """``{(rule, file, module): [imports]}`` of the rules 2 (upward) and 3 (private)."""
    rank = _rank()
    out: dict[tuple[str, str, str], list[Import]] = defaultdict(list)
    for imp in imports:
        if rank[imp.target] >= rank[imp.source]:
            out[("upward", imp.file, imp.module)].append(imp)
        inside = imp.module.split(".")[1:]
        if any(part.startswith("_") and not part.startswith("__") for part in inside):
            out[("private", imp.file, imp.module)].append(imp)
    return out


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """A cycle ``[a, b, ..., a]`` of the directed graph ``edges``, or None."""
    state: dict[str, int] = {}  # 1: on the stack, 2: done
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(edges):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def _graph(imports: list[Import], skip: set[tuple[str, str, str]]) -> dict[str, set[str]]:
    known = violations(imports)
    skipped = {id(i) for key in skip for i in known.get(key, [])}
    edges: dict[str, set[str]] = defaultdict(set)
    for imp in imports:
        if id(imp) not in skipped:
            edges[imp.source].add(imp.target)
    return edges


def _show(imps: list[Import]) -> str:
    return ", ".join(f"{i.file}:{i.line}" for i in imps)


def outside_imports(path: Path, module: str) -> list[tuple[int, str]]:
    """``(line, module)`` of every import of a module of :data:`OUTSIDE` in one file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    return [
        (node.lineno, name)
        for node in ast.walk(tree)
        for name in _imported(node, module, path.name == "__init__.py")
        if name.split(".")[0] in OUTSIDE
    ]


# ------------------------------------------------------------------------------ tests
@pytest.fixture(scope="module")
def imports() -> list[Import]:
    found = package_imports()
    assert found, "no imports between packages found: is the package path right?"
    return found


def test_every_package_has_a_layer():
    ranked = _rank()
    assert len(ranked) == sum(len(layer) for layer in LAYERS), "a package is in two layers"
    unplaced = sorted(first_level_packages() - set(ranked))
    assert not unplaced, f"LAYERS: expected every first-level package placed, missing {unplaced}"


def test_no_upward_or_private_import(imports):
    found = violations(imports)
    rank = _rank()
    new = []
    for key in sorted(set(found) - KNOWN_VIOLATIONS):
        rule, _, module = key
        imp = found[key][0]
        why = (
            f"layer {rank[imp.source]} {imp.source} imports layer {rank[imp.target]} {imp.target}"
            if rule == "upward"
            else f"{module} is private to {imp.target}"
        )
        new.append(f"{rule}: {module} at {_show(found[key])} ({why})")
    assert not new, "imports against docs/architecture.md's layering:\n" + "\n".join(new)


def test_known_violations_still_exist(imports):
    stale = sorted(KNOWN_VIOLATIONS - set(violations(imports)))
    assert not stale, f"KNOWN_VIOLATIONS: fixed, remove these entries: {stale}"


def test_package_graph_is_acyclic(imports):
    cycle = find_cycle(_graph(imports, set(KNOWN_VIOLATIONS)))
    assert cycle is None, "package import cycle: " + " -> ".join(cycle or [])


def test_modules_of_a_package_import_no_cycle():
    edges = module_edges()
    stale = sorted(e for e in KNOWN_MODULE_CYCLE_EDGES if e[1] not in edges.get(e[0], set()))
    assert not stale, f"KNOWN_MODULE_CYCLE_EDGES: fixed, remove these entries: {stale}"
    for source, target in KNOWN_MODULE_CYCLE_EDGES:
        edges[source].discard(target)
    cycle = find_cycle(edges)
    assert cycle is None, "module import cycle: " + " -> ".join(cycle or [])


def test_layers_match_the_design_doc():
    text = DOC.read_text()
    block = re.search(r"<!-- layers:begin -->\n```\n(.*?)```\n<!-- layers:end -->", text, re.S)
    assert block, f"{DOC}: expected a ```-block between <!-- layers:begin/end --> markers"
    rows = [r.split("#")[0].strip() for r in block.group(1).splitlines()]
    documented = [tuple(p.strip().strip("`/") for p in row.split(",")) for row in rows if row][
        ::-1
    ]  # the doc lists top first
    assert tuple(documented) == LAYERS, (
        f"{DOC}: expected the layers of tests/test_layering.py (bottom first) {LAYERS}, "
        f"found {tuple(documented)}"
    )


def test_the_library_never_imports_studies_or_benchmarks():
    found = [
        f"{path.relative_to(ROOT)}:{line} imports {name}"
        for path in sorted(PACKAGE.rglob("*.py"))
        for line, name in outside_imports(path, _module_name(path))
    ]
    assert not found, f"sss2bathy: expected no import of {OUTSIDE}, found:\n" + "\n".join(found)


def test_studies_and_benchmarks_use_public_names_only():
    found = []
    for folder in OUTSIDE:
        for path in sorted((ROOT / folder).rglob("*.py")):
            module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            tree = ast.parse(path.read_text(), filename=str(path))
            for node in ast.walk(tree):
                for name in _imported(node, module, path.name == "__init__.py"):
                    parts = name.split(".")
                    if parts[0] == "sss2bathy" and any(
                        p.startswith("_") and not p.startswith("__") for p in parts[1:]
                    ):
                        found.append(f"{path.relative_to(ROOT)}:{node.lineno} imports {name}")
    assert not found, "expected the library's public names only, found:\n" + "\n".join(found)


def test_studies_and_benchmarks_are_not_packaged():
    from setuptools import find_packages

    tomllib = pytest.importorskip("tomllib")  # Python 3.11+

    find = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    find = find["packages"]["find"]
    packaged = find_packages(str(ROOT), include=find.get("include", ["*"]))
    assert "sss2bathy" in packaged, f"pyproject.toml: expected sss2bathy packaged, found {packaged}"
    inside = sorted(p for p in packaged if p.split(".")[0] in OUTSIDE)
    assert not inside, f"pyproject.toml packages.find: expected {OUTSIDE} left out, found {inside}"
    assert not any((PACKAGE / name).exists() for name in OUTSIDE), (
        "a study folder inside sss2bathy/"
    )


def test_the_checks_catch_what_they_should(tmp_path):
    """The graph helpers on a hand-made graph: a cycle is found, an upward and a private
    import are reported, downward edges pass."""
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}}) is None
    up = Import("data", "modules", "data/x.py", 3, "sss2bathy.modules.predict.f")
    down = Import("modules", "data", "modules/y.py", 4, "sss2bathy.data.pings.f")
    private = Import("cli", "io", "cli/z.py", 5, "sss2bathy.io.xtf_survey._validate")
    found = violations([up, down, private])
    assert set(found) == {
        ("upward", "data/x.py", "sss2bathy.modules.predict.f"),
        ("private", "cli/z.py", "sss2bathy.io.xtf_survey._validate"),
    }
    tree = ast.parse("def f():\n    from ..eval import maps\n    from . import sibling\n")
    rel = [n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert _imported(rel[0], "sss2bathy.modules.siren", False) == ["sss2bathy.eval.maps"]
    assert _imported(rel[1], "sss2bathy.data", True) == ["sss2bathy.data.sibling"]
    script = tmp_path / "probe.py"
    script.write_text("def f():\n    from studies.tables import to_csv\n    import benchmarks\n")
    assert outside_imports(script, "sss2bathy.eval.probe") == [
        (2, "studies.tables.to_csv"),
        (3, "benchmarks"),
    ]
