"""The house's rules (docs/ARCHITECTURE.md), read from the code's imports.

Every import counts: module level, inside functions and under ``TYPE_CHECKING``.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "neus_l0"


def _module(path: Path) -> str:
    name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
    return name.removesuffix(".__init__")


MODULES = {_module(p): p for p in PACKAGE.rglob("*.py")}


def _imports(path: Path) -> set[str]:
    """The package modules `path` imports (a name imported from a package is the package,
    unless the name is one of its modules)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:
                full = f"{node.module}.{a.name}"
                out.add(full if full in MODULES else node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return {m for m in out if m in MODULES}


GRAPH = {m: _imports(p) - {m} for m, p in MODULES.items()}


def _room(module: str) -> str:
    """The top-level room of a module: ``neus_l0.bounds.hull`` -> ``bounds``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycle_between_modules():
    assert _cycles(GRAPH) == []


def test_no_import_cycle_between_rooms():
    rooms: dict[str, set[str]] = {}
    for m, targets in GRAPH.items():
        for t in targets:
            a, b = _room(m), _room(t)
            if a != b and b:
                rooms.setdefault(a, set()).add(b)
    assert _cycles(rooms) == []


def test_at_most_eight_modules_at_the_package_root():
    root = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert len(root) <= 8, root


def test_package_faces_define_nothing():
    """Every ``__init__.py`` is a docstring (and the root's version): no re-exports."""
    for path in PACKAGE.rglob("__init__.py"):
        body = ast.parse(path.read_text(encoding="utf-8")).body
        rest = [n for n in body
                if not (isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant))]
        if path.parent == PACKAGE:
            rest = [n for n in rest if not (isinstance(n, ast.Assign)
                                            and n.targets[0].id == "__version__")]
        assert not rest, f"{path.relative_to(ROOT)} does more than document its room"


def test_config_imports_only_errors():
    for m, targets in GRAPH.items():
        if _room(m) == "config":
            assert {t for t in targets if _room(t) != "config"} <= {"neus_l0.errors"}, m


def test_sampling_kernels_import_nothing_of_the_package():
    assert GRAPH["neus_l0.sampling.kernels"] == set()


def test_mesh_never_imports_train():
    for m, targets in GRAPH.items():
        if _room(m) == "mesh":
            assert not any(_room(t) == "train" for t in targets), m


def test_lower_rooms_never_import_the_rooms_above_them():
    """Data flows one way: nothing below training imports training, the bench, figures or
    the commands."""
    above = {"train", "bench", "figures", "study", "commands", "cli"}
    below = {"config", "data", "fields", "sampling", "bounds", "render", "run", "mesh",
             "evaluation", "photos", "formats"}
    for m, targets in GRAPH.items():
        if _room(m) in below:
            assert not {_room(t) for t in targets} & above, m


def test_no_test_module_imports_another():
    names = {p.stem for p in (ROOT / "tests").glob("test_*.py")}
    for path in (ROOT / "tests").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            mods = ([node.module] if isinstance(node, ast.ImportFrom) and node.module else
                    [a.name for a in node.names] if isinstance(node, ast.Import) else [])
            assert not set(mods) & names, f"{path.name} imports {set(mods) & names}"


def test_tools_and_tests_do_not_reach_into_each_other_through_sys_path():
    """Shared test fixtures live in tests/conftest.py, shared tool code in tools/_common.py;
    neither folder puts the other on ``sys.path``."""
    for folder in ("tools", "tests"):
        for path in (ROOT / folder).glob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                assert not (isinstance(node, ast.Attribute) and node.attr == "path"
                            and isinstance(node.value, ast.Name) and node.value.id == "sys"), \
                    f"{path.name}:{node.lineno} uses sys.path"


def _defined(path: Path) -> set[str]:
    names = set()
    for n in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(n.name)
        elif isinstance(n, ast.Assign):
            names.update(t.id for t in n.targets if isinstance(t, ast.Name))
        elif isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name):
            names.add(n.target.id)
    return names


def test_every_name_is_imported_from_the_module_that_defines_it():
    """No re-exports: a module that moved, or a name one module imports from another, is
    imported from where it is defined (in the package, its tests and tools)."""
    defined = {m: _defined(p) for m, p in MODULES.items()}
    files = [*MODULES.values(), *(ROOT / "tests").glob("*.py"), *(ROOT / "tools").glob("*.py")]
    wrong = []
    for path in files:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module in defined:
                for a in node.names:
                    if (a.name not in defined[node.module]
                            and f"{node.module}.{a.name}" not in MODULES):
                        wrong.append(f"{path.relative_to(ROOT)}: {node.module}.{a.name}")
    assert not wrong, wrong


def test_the_current_benchmarks_page_stays_a_page():
    """docs/BENCHMARKS.md holds the current numbers (at most 500 lines); the dated history
    lives in docs/benchmarks/."""
    lines = (ROOT / "docs" / "BENCHMARKS.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 500, len(lines)
    assert (ROOT / "docs" / "benchmarks" / "README.md").is_file()
