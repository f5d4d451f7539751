"""The package's structure: imports point one way, no cycles, modules small enough to read.

Every module under ``src/uimm_jax`` is parsed with :mod:`ast` (nothing is imported) and
every import it makes of the package is collected: at module level and inside functions,
``import x``, ``from x import y``, the relative forms (``from . import y``,
``from ..x import y``) and string imports (``importlib.import_module("uimm_jax.x")``,
``__import__``). Then:

* no import cycle between modules (a cycle held together by an import inside a function
  is a cycle too);
* the layers ``engine < plants < scenario < studies < cli``: a module never imports one
  of a higher layer. ``errors``, ``xla_flags`` and ``_checks`` are top-level leaves that
  anything may import and that import nothing of the package but each other;
  ``uimm_jax/__init__.py`` (the public surface) and ``__main__.py`` may import anything,
  and only ``cli`` may import the public surface;
* every module lies in a layer or is a leaf, and every import of the package names a
  module that exists;
* no module has more than 600 lines.

Each test's failure message lists every violation, not only the first.
"""

from __future__ import annotations

import ast
import re
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = "uimm_jax"
LAYERS = ("engine", "plants", "scenario", "studies", "cli")
LEAVES = frozenset({"errors", "xla_flags", "_checks"})
SURFACE = PACKAGE  # uimm_jax/__init__.py
MAIN = f"{PACKAGE}.__main__"
MAX_LINES = 600

# Ranks: a module may import modules of its own rank or below. The leaves sit below
# everything; the public surface above studies (it re-exports them) and below cli.
_RANK = {"leaf": 0, **{layer: i + 1 for i, layer in enumerate(LAYERS)}}
_RANK["surface"] = _RANK["studies"] + 0.5
_RANK["main"] = _RANK["cli"] + 1


class Import(NamedTuple):
    """One import of a package module: who imports what, and where."""

    importer: str
    target: str | None  # None: names a module of the package that does not exist
    spelled: str  # the import as written (the dotted name it resolves from)
    line: int


# --------------------------------------------------------------------------- scanning


def discover(root: Path, package: str = PACKAGE) -> dict[str, Path]:
    """Map each module's dotted name to its file (a package's name maps to __init__.py)."""
    modules = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        modules[".".join(parts)] = path
    return modules


def _package_of(name: str, path: Path) -> str:
    return name if path.name == "__init__.py" else name.rpartition(".")[0]


def _resolve(dotted: str, known: dict[str, Path]) -> str | None:
    """The known module ``dotted`` names, or None."""
    return dotted if dotted in known else None


def _from_targets(base: str, names: list[str], known) -> Iterator[tuple[str | None, str]]:
    """``from base import names``: each name that is a submodule, else ``base`` itself."""
    rest = []
    for n in names:
        if n != "*" and f"{base}.{n}" in known:
            yield f"{base}.{n}", f"{base}.{n}"
        else:
            rest.append(n)
    if rest:
        yield _resolve(base, known), base


def _enclosing_scope(node: ast.AST, parents: dict[ast.AST, ast.AST]) -> ast.AST:
    while node in parents:
        node = parents[node]
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            return node
    return node


def _is_import_call(call: ast.Call) -> bool:
    f = call.func
    name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
    return name in ("import_module", "__import__")


def scan(name: str, path: Path, known: dict[str, Path], package: str = PACKAGE) -> list[Import]:
    """Every import of ``package`` that module ``name`` (file ``path``) makes."""
    tree = ast.parse(path.read_text(), filename=str(path))
    here = _package_of(name, path)
    parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    found: list[Import] = []

    def add(targets, line):
        for target, spelled in targets:
            if spelled == package or spelled.startswith(package + "."):
                found.append(Import(name, target, spelled, line))

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            add(((_resolve(a.name, known), a.name) for a in node.names), node.lineno)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = here.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                base = f"{base}.{node.module}" if node.module else base
            else:
                base = node.module or ""
            add(_from_targets(base, [a.name for a in node.names], known), node.lineno)
        elif isinstance(node, ast.Call) and _is_import_call(node) and node.args:
            arg = node.args[0]
            if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                dotted = arg.value
                pkg = next(
                    (getattr(k.value, "value", None) for k in node.keywords if k.arg == "package"),
                    here,
                )
                if dotted.startswith(".") and isinstance(pkg, str):
                    level = len(dotted) - len(dotted.lstrip("."))
                    parts = pkg.split(".")
                    dotted = ".".join(parts[: len(parts) - level + 1]) + "." + dotted[level:]
                add([(_resolve(dotted, known), dotted)], node.lineno)
            else:  # a computed name: the package modules named by strings in scope
                scope = _enclosing_scope(node, parents)
                add(
                    (
                        (s.value, s.value)
                        for s in ast.walk(scope)
                        if isinstance(s, ast.Constant) and s.value in known
                    ),
                    node.lineno,
                )
    return found


def import_graph(root: Path = SRC, package: str = PACKAGE) -> tuple[dict, list[Import]]:
    """``(modules, imports)`` of the package under ``root``."""
    known = discover(root, package)
    imports = [imp for name, path in known.items() for imp in scan(name, path, known, package)]
    return known, imports


# --------------------------------------------------------------------------- checks


def find_cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """One shortest cycle per strongly connected component (Tarjan), as a closed path."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    nodes = sorted(set(edges) | {t for ts in edges.values() for t in ts})

    def strongconnect(v):  # recursive: the package has a few dozen modules
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                strongconnect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in edges.get(v, ()):
                components.append(sorted(comp))

    for v in nodes:
        if v not in index:
            strongconnect(v)

    cycles = []
    for comp in sorted(components):
        start, members = comp[0], set(comp)
        prev: dict[str, str] = {}
        frontier = [start]
        while frontier and start not in prev:  # breadth first, back to start
            nxt = []
            for v in frontier:
                for w in sorted(edges.get(v, ())):
                    if w in members and w not in prev:
                        prev[w] = v
                        nxt.append(w)
            frontier = nxt
        path = [start]
        v = prev[start]
        while v != start:
            path.append(v)
            v = prev[v]
        cycles.append([start, *reversed(path[1:]), start])
    return cycles


def layer_of(module: str, package: str = PACKAGE) -> str | None:
    """``"leaf"``, a layer's name, ``"surface"``, ``"main"``, or None (outside the layers)."""
    if module == package:
        return "surface"
    if module == f"{package}.__main__":
        return "main"
    top = module.split(".")[1]
    if top in LEAVES and module.count(".") == 1:
        return "leaf"
    return top if top in LAYERS else None


def _where(imp: Import, modules: dict[str, Path]) -> str:
    return f"{modules[imp.importer].relative_to(SRC)}:{imp.line}"


def cycle_violations(modules, imports) -> list[str]:
    edges: dict[str, set[str]] = {}
    line: dict[tuple[str, str], Import] = {}
    for imp in imports:
        if imp.target is not None and imp.target != imp.importer:
            edges.setdefault(imp.importer, set()).add(imp.target)
            line.setdefault((imp.importer, imp.target), imp)
    out = []
    for cycle in find_cycles(edges):
        steps = [
            f"{a} ({_where(line[a, b], modules)})" for a, b in zip(cycle, cycle[1:], strict=False)
        ]
        out.append("cycle: " + " -> ".join([*steps, cycle[-1]]))
    return out


def layer_violations(modules, imports) -> list[str]:
    out = [
        f"{m} ({p.relative_to(SRC)}) lies outside the layers {'/'.join(LAYERS)} and is not "
        f"a leaf ({', '.join(sorted(LEAVES))})"
        for m, p in modules.items()
        if layer_of(m) is None
    ]
    for imp in imports:
        if imp.target is None:
            continue
        src, dst = layer_of(imp.importer), layer_of(imp.target)
        if src in (None, "surface", "main") or dst is None:
            continue
        if _RANK[dst] > _RANK[src]:
            out.append(
                f"{imp.importer} ({src}) imports {imp.target} ({dst}) at {_where(imp, modules)}"
            )
    return out


def missing_imports(modules, imports) -> list[str]:
    return [
        f"{imp.importer} imports {imp.spelled!r}, which is no module of the package, at "
        f"{_where(imp, modules)}"
        for imp in imports
        if imp.target is None
    ]


def size_violations(modules) -> list[str]:
    out = []
    for p in modules.values():
        n = len(p.read_text().splitlines())
        if n > MAX_LINES:
            out.append(f"{p.relative_to(SRC)}: {n} lines (> {MAX_LINES})")
    return out


def _check(what: str, violations: list[str]) -> None:
    """Fail with every violation, one a line."""
    if violations:
        pytest.fail(f"{len(violations)} {what}:\n  " + "\n  ".join(violations), pytrace=False)


@pytest.fixture(scope="module")
def graph():
    return import_graph()


# --------------------------------------------------------------------------- the package


def test_no_import_cycles(graph):
    violations = cycle_violations(*graph)
    _check("import cycles (each module imports the next at the line given)", violations)


def test_imports_follow_the_layers(graph):
    violations = layer_violations(*graph)
    _check("layer violations", violations)


def test_every_package_import_names_a_module(graph):
    violations = missing_imports(*graph)
    _check("imports of missing modules", violations)


def test_no_module_over_600_lines(graph):
    violations = size_violations(graph[0])
    _check(f"modules over {MAX_LINES} lines", violations)


def test_architecture_doc_names_existing_modules():
    """docs/architecture.md names modules as ``layer/name.py`` or, in a layer's row, ``name.py``."""
    doc = SRC.parent / "docs" / "architecture.md"
    layers = "|".join(LAYERS)
    named = re.findall(rf"`(?:uimm_jax/)?((?:{layers})/\w+\.py|\w+\.py)`", doc.read_text())
    names = {p.name for p in (SRC / PACKAGE).rglob("*.py")}
    missing = sorted(
        {n for n in named if not (SRC / PACKAGE / n).is_file() and ("/" in n or n not in names)}
    )
    _check("modules named in docs/architecture.md that do not exist", missing)


# --------------------------------------------------------------------------- the scanner


def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        p = root / "pkg" / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(textwrap.dedent(text))


def test_scanner_sees_every_import_form(tmp_path):
    _write(
        tmp_path,
        {
            "__init__.py": "from pkg.a import f\n",
            "a.py": """
                import importlib
                import pkg.b
                from . import c
                from .sub import d as _d

                def f():
                    from pkg.sub.e import g
                    importlib.import_module("pkg.c")
                    for name in ("pkg.b", "pkg.sub.d"):
                        __import__(name, fromlist=["x"])
                    return importlib.import_module(".e", package="pkg.sub")
                """,
            "b.py": "from pkg import f\nfrom .. import nothing_here\n",
            "c.py": "from pkg.gone import x\n",
            "sub/__init__.py": "",
            "sub/d.py": "from ..b import y\n",
            "sub/e.py": "def g(): pass\n",
        },
    )
    modules, imports = import_graph(tmp_path, "pkg")
    assert set(modules) == {"pkg", "pkg.a", "pkg.b", "pkg.c", "pkg.sub", "pkg.sub.d", "pkg.sub.e"}
    found = {(i.importer, i.target, i.line) for i in imports}
    assert found >= {
        ("pkg", "pkg.a", 1),
        ("pkg.a", "pkg.b", 3),  # import pkg.b
        ("pkg.a", "pkg.c", 4),  # from . import c
        ("pkg.a", "pkg.sub.d", 5),  # from .sub import d as _d
        ("pkg.a", "pkg.sub.e", 8),  # inside a function
        ("pkg.a", "pkg.c", 9),  # importlib.import_module("pkg.c")
        ("pkg.a", "pkg.b", 11),  # __import__(name) over names in scope
        ("pkg.a", "pkg.sub.d", 11),
        ("pkg.a", "pkg.sub.e", 12),  # import_module(".e", package="pkg.sub")
        ("pkg.b", "pkg", 1),  # from pkg import f: the package's __init__
        ("pkg.c", None, 1),  # pkg.gone does not exist
        ("pkg.sub.d", "pkg.b", 1),  # from ..b import y
    }
    assert {i.spelled for i in imports if i.target is None} == {"pkg.gone"}
    # `from .. import nothing_here` in pkg/b.py leaves the package: no import of it.
    assert not [i for i in imports if i.importer == "pkg.b" and i.line == 2]


def test_cycle_finder_reports_each_cycle_as_a_closed_path():
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"e"}, "f": {"g"}}
    assert find_cycles(edges) == [["a", "b", "c", "a"], ["e", "e"]]
    assert find_cycles({"x": {"y"}, "y": set()}) == []


@pytest.mark.parametrize(
    ("module", "layer"),
    [
        ("uimm_jax", "surface"),
        ("uimm_jax.__main__", "main"),
        ("uimm_jax.errors", "leaf"),
        ("uimm_jax._checks", "leaf"),
        ("uimm_jax.engine", "engine"),
        ("uimm_jax.engine.kalman", "engine"),
        ("uimm_jax.studies.plots", "studies"),
        ("uimm_jax.cli.run", "cli"),
        ("uimm_jax.runner", None),
        ("uimm_jax.engine.errors", "engine"),
    ],
)
def test_layer_of(module, layer):
    assert layer_of(module) == layer


def test_ranks_put_the_layers_in_order():
    order = ["leaf", *LAYERS]
    assert [_RANK[k] for k in order] == sorted(_RANK[k] for k in order)
    assert _RANK["studies"] < _RANK["surface"] < _RANK["cli"] < _RANK["main"]
