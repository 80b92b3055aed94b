"""Checkpoints: atomic writes, the newest valid one on resume, refusal of NaN states.

A checkpoint (``RUN/checkpoints/ckpt_NNNNNNN.pt``) is a dict with ``iteration``, ``model``
(state dict), ``optimizer`` (state dict), ``rng`` (the ray/sample generator's state and
torch's global CPU/CUDA states), ``config`` (the resolved config as a dict), ``scale_mat``
(4x4 list, normalised -> world) and ``has_background``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import torch

from neus_l0.atomic import atomic_write
from neus_l0.errors import NeusL0Error

CKPT_RE = re.compile(r"^ckpt_(\d+)\.pt$")


def checkpoint_path(run_dir: str | Path, iteration: int) -> Path:
    """`RUN/checkpoints/ckpt_NNNNNNN.pt`."""
    return Path(run_dir) / "checkpoints" / f"ckpt_{iteration:07d}.pt"


def list_checkpoints(run_dir: str | Path) -> list[Path]:
    """Checkpoints of a run, oldest first (temporary files of interrupted writes ignored)."""
    folder = Path(run_dir) / "checkpoints"
    if not folder.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in folder.iterdir() if (m := CKPT_RE.match(p.name))]
    return [p for _, p in sorted(found)]


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    """The newest checkpoint of a run, or None."""
    ckpts = list_checkpoints(run_dir)
    return ckpts[-1] if ckpts else None


def _non_finite_key(tree: Any, prefix: str = "") -> str | None:
    """The first key path whose floating-point tensor holds NaN or inf, else None."""
    if isinstance(tree, torch.Tensor):
        if tree.is_floating_point() and not torch.isfinite(tree).all():
            return prefix or "<tensor>"
        return None
    if isinstance(tree, dict):
        items = tree.items()
    elif isinstance(tree, (list, tuple)):
        items = enumerate(tree)
    else:
        return None
    for k, v in items:
        bad = _non_finite_key(v, f"{prefix}.{k}" if prefix else str(k))
        if bad:
            return bad
    return None


def save_checkpoint(path: str | Path, state: dict, keep: int = 0) -> Path:
    """Write `state` atomically to `path`; refuse NaN/inf; keep only the newest `keep`.

    Raises:
        NeusL0Error: when the model or optimiser state is not finite (nothing is written).
    """
    path = Path(path)
    bad = _non_finite_key({"model": state.get("model"), "optimizer": state.get("optimizer")})
    if bad:
        raise NeusL0Error(f"{path}: not saved: the training state has NaN/inf in '{bad}' "
                          "(training diverged; try a lower train.lr)")
    atomic_write(path, lambda tmp: torch.save(state, tmp))
    if keep > 0:
        for old in list_checkpoints(path.parent.parent)[:-keep]:
            if old != path:
                old.unlink(missing_ok=True)
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """Read a checkpoint and check it.

    Raises:
        NeusL0Error: unreadable file, missing keys, or NaN/inf in the model or optimiser.
    """
    path = Path(path)
    try:
        state = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is a user-facing error
        raise NeusL0Error(f"{path}: cannot read checkpoint ({type(exc).__name__}: {exc})") from None
    missing = [k for k in ("iteration", "model", "optimizer", "config") if k not in state]
    if missing:
        raise NeusL0Error(f"{path}: not a neus-l0 checkpoint (missing {', '.join(missing)})")
    bad = _non_finite_key({"model": state["model"], "optimizer": state["optimizer"]})
    if bad:
        raise NeusL0Error(f"{path}: refusing checkpoint with NaN/inf in '{bad}'; "
                          "resume from an earlier checkpoint (delete this one)")
    return state


# ------------------------------------------------------------------------------------------
# Training state: what a checkpoint holds and how a resume restores it.


def rng_state(generator: torch.Generator) -> dict:
    """The loop generator's state and torch's global CPU (and CUDA) states."""
    state = {"generator": generator.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng(generator: torch.Generator, state: dict) -> None:
    """Inverse of `rng_state`."""
    generator.set_state(state["generator"].cpu())
    torch.set_rng_state(state["torch"].cpu())
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])


def restore_training(path: Path, state: dict, model: torch.nn.Module,
                     optimizer: torch.optim.Optimizer, generator: torch.Generator,
                     scaler: torch.amp.GradScaler, occupancy: Any | None = None) -> tuple[int, int]:
    """Put a checkpoint's training state back (the resume of `neus_l0.train.train`).

    Args:
        path: the checkpoint (named in errors); state: its contents (`load_checkpoint`).
        model, optimizer, generator, scaler: restored in place.
        occupancy: the occupancy grid, restored from the checkpoint or, for a checkpoint of
            a run without the grid, rebuilt from the restored SDF.

    Returns:
        the iteration to continue from and the batch size in force then.

    Raises:
        NeusL0Error: the checkpoint's networks do not fit the config's.
    """
    try:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
    except (RuntimeError, ValueError, KeyError) as exc:
        raise NeusL0Error(f"{path}: does not fit the config's networks (resume with the "
                          f"run's config.yaml): {str(exc).splitlines()[0]}") from None
    restore_rng(generator, state["rng"])
    if occupancy is not None and "occupancy" in state:
        occupancy.load_state_dict(state["occupancy"])
    elif occupancy is not None:
        occupancy.update(model.sdf.sdf, model.variance.inv_s())
    if "scaler" in state:
        scaler.load_state_dict(state["scaler"])
    return int(state["iteration"]), int(state.get("batch_size", 0))


def prune_checkpoints(run_dir: Path, keep: int, protected: set[Path]) -> None:
    """Delete all but the newest `keep` checkpoints that are not in `protected`."""
    if keep <= 0:
        return
    others = [p for p in list_checkpoints(run_dir) if p not in protected]
    for old in others[:-keep]:
        old.unlink(missing_ok=True)
