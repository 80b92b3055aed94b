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


#: The floors of the house, lowest first: a room imports only rooms on its own floor or below
#: (docs/ARCHITECTURE.md draws them). "" is the package root (``__version__``).
FLOORS: tuple[tuple[str, ...], ...] = (
    ("", "errors", "atomic", "device"),
    ("config",),
    ("data", "sampling", "fields", "synthetic"),
    ("bounds",),
    ("render", "run", "formats", "evaluation"),
    ("train", "mesh", "photos"),
    ("figures", "experiments", "viewer"),
    ("pipelines",),
    ("commands", "cli", "__main__"),
)
FLOOR = {room: i for i, rooms in enumerate(FLOORS) for room in rooms}


def _room_graph() -> dict[str, set[str]]:
    """Room -> the other rooms its modules import (root modules are rooms of their own)."""
    rooms: dict[str, set[str]] = {}
    for m, targets in GRAPH.items():
        for t in targets:
            a, b = _room(m), _room(t)
            if a != b:
                rooms.setdefault(a, set()).add(b)
    return rooms


def test_every_room_has_a_floor():
    rooms = {_room(m) for m in MODULES}
    assert rooms <= set(FLOOR), sorted(rooms - set(FLOOR))


def test_no_arrow_runs_back_up():
    """Data flows one way: no module imports a room on a higher floor."""
    up = [f"{m} -> {t}" for m, targets in GRAPH.items() for t in targets
          if FLOOR[_room(t)] > FLOOR[_room(m)]]
    assert not up, up


def test_mesh_never_imports_train():
    for m, targets in GRAPH.items():
        if _room(m) == "mesh":
            assert not any(_room(t) == "train" for t in targets), m


def test_nothing_below_training_reads_the_run_folder():
    """The rooms training stands on (everything `train/` imports, but `run/` itself) never
    import `run/`: geometry, rendering and scenes do not depend on the run folder."""
    rooms = _room_graph()
    below, todo = set(), ["train"]
    while todo:
        for r in rooms.get(todo.pop(), ()):
            if r not in below:
                below.add(r)
                todo.append(r)
    below -= {"run"}
    bad = sorted(r for r in below if "run" in rooms.get(r, ()))
    assert not bad, bad


def test_render_is_volume_rendering_only():
    """`render/` imports neither the run folder nor the scene formats."""
    bad = [m for m, targets in GRAPH.items() if _room(m) == "render"
           and {_room(t) for t in targets} & {"run", "formats"}]
    assert not bad, bad


def test_commands_are_thin():
    long = [f"{p.name} ({n} lines)" for p in (PACKAGE / "commands").glob("*.py")
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > 150]
    assert not long, long


def _defs(pattern: str) -> list[str]:
    """Modules defining a top-level function or class whose name matches `pattern`."""
    import re

    rx = re.compile(pattern)
    return sorted(f"{m}.{n.name}" for m, p in MODULES.items()
                  for n in ast.parse(p.read_text(encoding="utf-8")).body
                  if isinstance(n, (ast.FunctionDef, ast.ClassDef)) and rx.fullmatch(n.name))


def test_each_concept_lives_in_one_place():
    """The view split, the sphere fit, the mesh rasteriser and the metric names: one module
    each."""
    assert _defs(r".*split_views|subset_scene") == ["neus_l0.data.split.split_views",
                                                    "neus_l0.data.split.subset_scene"]
    holdout_rule = [m for m, p in MODULES.items() if m != "neus_l0.data.split"
                    for n in ast.walk(ast.parse(p.read_text(encoding="utf-8")))
                    if isinstance(n, ast.BinOp) and isinstance(n.op, ast.Mod)
                    and "holdout" in ast.unparse(n.right)]
    assert not holdout_rule, holdout_rule
    fits = {d.rsplit(".", 1)[0] for d in _defs(r"\w*(choose|find|fit|hull|camera|given|user)"
                                                r"_sphere|Sphere(Fit|Choice)")}
    assert fits == {"neus_l0.formats.sphere"}, fits
    assert _defs(r"\w*(raster|splat)_render\w*") == ["neus_l0.figures.raster.raster_render"]
    lists = sorted({m for m, p in MODULES.items()
                    for n in ast.walk(ast.parse(p.read_text(encoding="utf-8")))
                    if isinstance(n, (ast.Tuple, ast.List))
                    and any(isinstance(e, ast.Constant) and e.value == "color_loss"
                            for e in n.elts)})
    assert lists == ["neus_l0.train.losses"], lists


def import_table() -> str:
    """The Markdown table of which room imports which, generated from the code (what
    docs/ARCHITECTURE.md shows between its ``imports`` markers)."""
    rooms = _room_graph()
    lines = ["| floor | room | imports |", "|---|---|---|"]
    for i, floor in enumerate(FLOORS):
        for room in floor:
            if room == "" or room not in {_room(m) for m in MODULES}:
                continue
            deps = sorted(r for r in rooms.get(room, ()) if r)
            lines.append(f"| {i} | `{room}` | {', '.join(f'`{d}`' for d in deps) or '-'} |")
    return "\n".join(lines)


BEGIN, END = "<!-- imports: generated by tests/test_architecture.py -->", "<!-- imports: end -->"


def test_the_architecture_page_shows_the_imports_as_they_are():
    """docs/ARCHITECTURE.md's import table is the code's (`import_table`); to refresh it,
    run ``python tests/test_architecture.py``."""
    doc = (ROOT / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    assert BEGIN in doc and END in doc
    shown = doc.split(BEGIN, 1)[1].split(END, 1)[0].strip()
    assert shown == import_table(), "run: python tests/test_architecture.py"


def test_no_test_module_imports_another():
    names = {p.stem for p in (ROOT / "tests").rglob("test_*.py")}
    for path in (ROOT / "tests").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            mods = ([node.module] if isinstance(node, ast.ImportFrom) and node.module else
                    [a.name for a in node.names] if isinstance(node, ast.Import) else [])
            assert not set(mods) & names, f"{path.name} imports {set(mods) & names}"


def test_tools_and_tests_do_not_reach_into_each_other_through_sys_path():
    """Shared test fixtures live in tests/conftest.py, shared tool code in tools/_common.py;
    neither folder puts the other on ``sys.path``."""
    for folder in ("tools", "tests"):
        for path in (ROOT / folder).rglob("*.py"):
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
    files = [*MODULES.values(), *(ROOT / "tests").rglob("*.py"), *(ROOT / "tools").glob("*.py")]
    wrong = []
    for path in files:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module in defined:
                for a in node.names:
                    if (a.name not in defined[node.module]
                            and f"{node.module}.{a.name}" not in MODULES):
                        wrong.append(f"{path.relative_to(ROOT)}: {node.module}.{a.name}")
    assert not wrong, wrong


def test_tests_mirror_the_package():
    """At least 90 % of the test files sit in a folder named for a room (or ``cli/``), and no
    test file is over 800 lines."""
    rooms = {_room(m) for m in MODULES} | {"cli"}
    files = sorted((ROOT / "tests").rglob("test_*.py"))
    placed = [f for f in files if f.parent.name in rooms]
    assert len(placed) >= 0.9 * len(files), sorted(str(f) for f in set(files) - set(placed))
    long = [f"{f.relative_to(ROOT)} ({n} lines)" for f in files
            if (n := len(f.read_text(encoding="utf-8").splitlines())) > 800]
    assert not long, long


def test_the_current_benchmarks_page_stays_a_page():
    """docs/BENCHMARKS.md holds the current numbers (at most 500 lines); the dated history
    lives in docs/benchmarks/."""
    lines = (ROOT / "docs" / "BENCHMARKS.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 500, len(lines)
    assert (ROOT / "docs" / "benchmarks" / "README.md").is_file()


if __name__ == "__main__":  # refresh docs/ARCHITECTURE.md's import table
    page = ROOT / "docs" / "ARCHITECTURE.md"
    doc = page.read_text(encoding="utf-8")
    head, rest = doc.split(BEGIN, 1)
    page.write_text(f"{head}{BEGIN}\n{import_table()}\n{END}{rest.split(END, 1)[1]}",
                    encoding="utf-8")
