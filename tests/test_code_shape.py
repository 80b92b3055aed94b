"""The code base's shape limits (issues #14, #32): small functions with few parameters."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "neus_l0"


def _functions():
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                params = [*a.posonlyargs, *a.args, *a.kwonlyargs]
                n = len([p for p in params if p.arg not in ("self", "cls")])
                n += bool(a.vararg) + bool(a.kwarg)
                yield path.relative_to(PACKAGE.parent), node, node.end_lineno - node.lineno + 1, n


def test_no_function_is_over_80_lines_or_10_parameters():
    long = [f"{p}:{f.lineno} {f.name} ({n} lines)" for p, f, n, _ in _functions() if n > 80]
    wide = [f"{p}:{f.lineno} {f.name} ({k} parameters)" for p, f, _, k in _functions()
            if k > 10]
    assert not long, long
    assert not wide, wide


def test_the_training_loop_reads_in_short_functions():
    long = [f"{f.name} ({n} lines)" for p, f, n, _ in _functions()
            if p.parts[1] == "train" and n > 80]
    assert not long, long
