"""Every config key with its value and its one-line meaning (`neus-l0 config show`).

The meanings are the schema's own field docstrings (`neus_l0.config.schema`), read from its
source, so the listing cannot drift from the documentation.
"""

from __future__ import annotations

import ast
import dataclasses
import typing
from functools import cache
from pathlib import Path
from typing import Any

from neus_l0.config import schema
from neus_l0.config.schema import Config


@cache
def field_docs() -> dict[tuple[str, str], str]:
    """(dataclass name, field name) -> the field's docstring, whitespace folded."""
    tree = ast.parse(Path(schema.__file__).read_text(encoding="utf-8"))
    docs = {}
    for node in tree.body:
        if not isinstance(node, ast.ClassDef):
            continue
        body = node.body
        for a, b in zip(body, body[1:]):
            if (isinstance(a, ast.AnnAssign) and isinstance(a.target, ast.Name)
                    and isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant)
                    and isinstance(b.value.value, str)):
                docs[(node.name, a.target.id)] = " ".join(b.value.value.split())
    return docs


def first_sentence(text: str, limit: int = 110) -> str:
    """The text up to its first full stop (a dot, then a space and a capital letter or a
    backtick, or the end; not "e.g." or "i.e."), cut to `limit` characters."""
    end = len(text)
    for i, ch in enumerate(text):
        if ch != "." or text[max(0, i - 3):i + 1] in ("e.g.", "i.e.") or text[i - 1:i] == ".":
            continue
        nxt = text[i + 2:i + 3]
        if i + 1 == len(text) or (text[i + 1] == " " and (nxt.isupper() or nxt == "`")):
            end = i + 1
            break
    out = text[:end]
    return out if len(out) <= limit else out[:limit - 3].rstrip() + "..."


def describe(cfg: Any, prefix: str = "", full: bool = False) -> list[tuple[str, Any, str]]:
    """(dotted key, value, meaning) of every leaf of a config dataclass, in the schema's
    order; the meaning is the docstring's first sentence, cut to one line, or (`full`) the
    whole docstring."""
    rows = []
    hints = typing.get_type_hints(type(cfg))
    docs = field_docs()
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        key = prefix + f.name
        if dataclasses.is_dataclass(hints[f.name]) and dataclasses.is_dataclass(value):
            rows += describe(value, key + ".", full)
        else:
            doc = docs.get((type(cfg).__name__, f.name), "")
            rows.append((key, value, doc if full else first_sentence(doc)))
    return rows


def format_listing(cfg: Config, full: bool = False) -> str:
    """The resolved config as ``key: value  # meaning`` lines, values in YAML flow style;
    `full`: each key's whole description, wrapped under it, instead of one cut line."""
    import textwrap

    import yaml

    rows = describe(cfg, full=full)
    if full:
        return "\n".join(f"{k}: {yaml.safe_dump(v, default_flow_style=True).strip()}"
                         .removesuffix("\n...").removesuffix(" ...")
                         + "".join(f"\n    # {line}" for line in textwrap.wrap(d, 92))
                         for k, v, d in rows)
    shown = [(k, yaml.safe_dump(v, default_flow_style=True).strip().removesuffix("\n...")
              .removesuffix(" ..."), d) for k, v, d in rows]
    width = max(len(f"{k}: {v}") for k, v, _ in shown)
    return "\n".join(f"{k}: {v}".ljust(width) + (f"  # {d}" if d else "")
                     for k, v, d in shown)
