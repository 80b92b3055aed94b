"""Every name `tools/` (and code strings the tools and tests run in subprocesses) imports from
`neus_l0` exists: a module that moves leaves no re-export behind, so a tool that was not
moved with it breaks only when somebody runs it (bench_mesh did, on a lent GPU)."""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_FROM_LINE = re.compile(r"^\s*from (neus_l0[\w.]*) import ([\w, ]+)$", re.M)


def _imports(path: Path) -> list[tuple[str, str]]:
    """``(module, name)`` pairs that `path` imports from neus_l0, in code or in code strings."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("neus_l0"):
            found += [(node.module, a.name) for a in node.names]
        elif isinstance(node, ast.Import):
            found += [(a.name, "") for a in node.names if a.name.startswith("neus_l0")]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            for module, names in _FROM_LINE.findall(node.value):
                found += [(module, n.strip()) for n in names.split(",") if n.strip()]
    return found


FILES = [p for p in sorted(ROOT.glob("tools/*.py")) + sorted(ROOT.glob("tests/**/*.py"))
         if p.name != Path(__file__).name]  # its own example string is not an import


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_neus_l0_import_resolves(path):
    missing = []
    for module, name in _imports(path):
        try:
            mod = importlib.import_module(module)
        except ImportError as exc:
            missing.append(f"{module} ({exc})")
            continue
        if name and not hasattr(mod, name):
            try:
                importlib.import_module(f"{module}.{name}")
            except ImportError:
                missing.append(f"{module}.{name}")
    assert not missing, f"{path.relative_to(ROOT)} imports what neus_l0 no longer has: {missing}"


def test_the_check_sees_code_strings(tmp_path):
    p = tmp_path / "t.py"
    p.write_text('CASE = """\nimport torch\nfrom neus_l0.mesh import sdf_grid\n"""\n')
    assert _imports(p) == [("neus_l0.mesh", "sdf_grid")]
