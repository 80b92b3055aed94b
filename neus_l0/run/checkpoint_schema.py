"""What a checkpoint may hold, so that it loads with ``torch.load(weights_only=True)``.

A checkpoint is plain data: tensors, dicts, lists, tuples, str, int, float, bool and None.
Nothing in it needs Python's pickle to build an object, so loading one runs no code from the
file. `to_plain` turns what training hands over (numpy arrays and scalars, paths) into those
types before a save; `schema_problem` says what is wrong with a loaded dict, or None.

The keys (see `neus_l0.run.checkpoints`):

* ``iteration``: int >= 0; ``batch_size``: int >= 0 (optional);
* ``model``: the state dict, str -> tensor;
* ``optimizer``: a torch optimiser state dict (``state``, ``param_groups``);
* ``rng``: ``generator`` and ``torch`` (uint8 tensors: the loop generator's and torch's
  global CPU state), ``cuda`` (optional, a list of uint8 tensors);
* ``config``: the resolved config as a nested dict;
* ``scale_mat``: 4x4 nested list of finite numbers (normalised -> world);
* optional: ``has_background`` (bool), ``scene_fingerprint`` (str), ``occupancy``, ``scaler``
  (dicts).
"""

from __future__ import annotations

import math
from pathlib import PurePath
from typing import Any

import numpy as np
import torch

#: The types a checkpoint is built of (containers checked element by element).
PLAIN_LEAVES = (torch.Tensor, str, int, float, bool, type(None))


def to_plain(tree: Any) -> Any:
    """`tree` with numpy arrays as lists, numpy scalars as Python numbers and paths as str.

    Tensors and plain values are kept, and so is every container whose contents need no
    change (the same object: a state dict keeps its type and metadata).

    Raises:
        TypeError: a value of another type (a checkpoint must not need pickle to load).
    """
    if isinstance(tree, PLAIN_LEAVES):
        return tree
    if isinstance(tree, dict):
        new = {k: to_plain(v) for k, v in tree.items()}
        return tree if all(new[k] is v for k, v in tree.items()) else new
    if isinstance(tree, (list, tuple)):
        items = [to_plain(v) for v in tree]
        if all(a is b for a, b in zip(items, tree, strict=True)) and type(tree) in (list, tuple):
            return tree
        return items if isinstance(tree, list) else tuple(items)
    if isinstance(tree, np.ndarray):
        return tree.tolist()
    if isinstance(tree, np.generic):
        return tree.item()
    if isinstance(tree, PurePath):
        return str(tree)
    raise TypeError(f"a {type(tree).__name__} cannot go into a checkpoint (plain data only)")


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _matrix_problem(m: Any) -> str | None:
    """Why `m` is not a 4x4 matrix of finite numbers, or None."""
    if isinstance(m, torch.Tensor):
        m = m.tolist()
    rows = m if isinstance(m, (list, tuple)) else None
    if rows is None or len(rows) != 4 or any(
            not isinstance(r, (list, tuple)) or len(r) != 4 for r in rows):
        return "is not a 4x4 matrix"
    values = [v for r in rows for v in r]
    if any(not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v)
           for v in values):
        return "holds a value that is not a finite number"
    return None


def _rng_problem(rng: Any) -> str | None:
    """Why `rng` is not the generator states `rng_state` writes, or None."""
    if not isinstance(rng, dict):
        return f"is a {type(rng).__name__}, not a dict"
    for key in ("generator", "torch"):
        t = rng.get(key)
        if not isinstance(t, torch.Tensor) or t.dtype != torch.uint8:
            return f"has no uint8 tensor '{key}'"
    cuda = rng.get("cuda", [])
    if not isinstance(cuda, (list, tuple)) or any(
            not isinstance(t, torch.Tensor) or t.dtype != torch.uint8 for t in cuda):
        return "has a 'cuda' that is not a list of uint8 tensors"
    return None


def schema_problem(state: Any) -> str | None:
    """What makes `state` not a neus-l0 checkpoint (one phrase), or None when it is one."""
    if not isinstance(state, dict):
        return f"not a neus-l0 checkpoint (a {type(state).__name__}, not a dict)"
    missing = [k for k in ("iteration", "model", "optimizer", "rng", "config", "scale_mat")
               if k not in state]
    if missing:
        return f"not a neus-l0 checkpoint (missing {', '.join(missing)})"
    checks = [
        ("iteration", _is_int(state["iteration"]) and state["iteration"] >= 0,
         "is not a whole number >= 0"),
        ("batch_size", _is_int(state.get("batch_size", 0)) and state.get("batch_size", 0) >= 0,
         "is not a whole number >= 0"),
        ("model", isinstance(state["model"], dict) and all(
            isinstance(k, str) and isinstance(v, torch.Tensor)
            for k, v in state["model"].items()), "is not a dict of tensors"),
        ("optimizer", isinstance(state["optimizer"], dict)
         and isinstance(state["optimizer"].get("state"), dict)
         and isinstance(state["optimizer"].get("param_groups"), list),
         "is not an optimiser state (state, param_groups)"),
        ("config", isinstance(state["config"], dict), "is not a dict"),
        ("has_background", isinstance(state.get("has_background", False), bool),
         "is not true or false"),
        ("scene_fingerprint", isinstance(state.get("scene_fingerprint", ""), str),
         "is not a string"),
    ]
    for key, ok, why in checks:
        if not ok:
            return f"'{key}' {why} ({_shown(state.get(key))})"
    for key in ("occupancy", "scaler", "error_map"):
        if key in state and not isinstance(state[key], dict):
            return f"'{key}' is not a dict"
    for key, problem in (("rng", _rng_problem(state["rng"])),
                         ("scale_mat", _matrix_problem(state["scale_mat"]))):
        if problem:
            return f"'{key}' {problem}"
    return None


def _shown(value: Any, limit: int = 40) -> str:
    """A short description of a bad value: its repr for plain ones, else its type."""
    if isinstance(value, (str, int, float, bool, type(None))):
        text = repr(value)
        return text if len(text) <= limit else text[:limit - 3] + "..."
    return f"a {type(value).__name__}"
