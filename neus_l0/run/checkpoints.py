"""Checkpoints: atomic writes, the newest valid one on resume, refusal of NaN states.

A checkpoint (``RUN/checkpoints/ckpt_NNNNNNN.pt``) is a dict with ``iteration``, ``model``
(state dict), ``optimizer`` (state dict), ``rng`` (the ray/sample generator's state and
torch's global CPU/CUDA states), ``config`` (the resolved config as a dict), ``scale_mat``
(4x4 list, normalised -> world), ``has_background`` and ``scene_fingerprint``: plain data
only (`neus_l0.run.checkpoint_schema`), read with ``torch.load(weights_only=True)``, so that
loading a checkpoint never runs code from it.

Unsafe files. A checkpoint whose pickle names any Python global (a function, a class: an
older neus-l0's numpy arrays, or a planted ``os.system``) is not loaded: one line names the
file and the command that converts it, ``neus-l0 checkpoint upgrade FILE --trust-pickle``
(`upgrade_checkpoint`), which unpickles it in full only on that explicit request. Such a
file stops the search for a checkpoint (it is not set aside as damaged).

Damaged checkpoints. `load_newest_checkpoint` (used by `load_trained_model`, hence by
``mesh``, ``demo`` and ``figures``, and by a resumed training) tries the checkpoints newest
first. A file whose *content* is bad -- it does not unpickle (truncated, overwritten), lacks
a checkpoint key or has one of the wrong kind (`schema_problem`: ``iteration: "abc"``, no
``rng``), or holds NaN/inf in the model or optimiser state (which `save_checkpoint` never
writes, so the file was damaged afterwards) -- is renamed to
``<name>.corrupt`` (kept for inspection, no longer listed) as soon as an older checkpoint
loads, and one line on stderr names both. Failures that say nothing about the content (the
file is missing or not readable, memory ran out, a module needed by the pickle is missing)
stop the search with the error instead. When every checkpoint is bad nothing is renamed:
the error names the newest one and why.
"""

from __future__ import annotations

import pickle
import re
import sys
from pathlib import Path
from typing import Any

import torch

from neus_l0.atomic import atomic_torch_save
from neus_l0.config.load import config_from_dict
from neus_l0.config.schema import Config
from neus_l0.errors import NeusL0Error
from neus_l0.fields.model import NeuSModel, make_model
from neus_l0.run.checkpoint_schema import schema_problem, to_plain

CKPT_RE = re.compile(r"^ckpt_(\d+)\.pt$")


class CorruptCheckpointError(NeusL0Error):
    """A checkpoint file whose content is unusable (truncated, not a checkpoint, NaN/inf)."""


class UnsafeCheckpointError(NeusL0Error):
    """A checkpoint that only a full unpickling could load (it names Python globals)."""


def _needs_pickle(exc: BaseException) -> bool:
    """Whether `torch.load(weights_only=True)` refused a file for naming a global (as
    opposed to failing on damaged bytes)."""
    return isinstance(exc, pickle.UnpicklingError) and "GLOBAL" in str(exc)


def unsafe_line(path: Path) -> str:
    """The one line about a checkpoint that needs pickle: why, and how to convert it."""
    return (f"{path}: not loaded: it holds Python objects that only a full unpickling could "
            "build, which runs any code the file carries (a checkpoint from an older neus-l0, "
            "or a planted one); if you trust where it came from, convert it with: neus-l0 "
            f"checkpoint upgrade {path} --trust-pickle")


def _first_line(exc: BaseException, limit: int = 160) -> str:
    """`Type: message` of an exception, cut to its first line and `limit` characters."""
    text = f"{type(exc).__name__}: {exc}".strip().splitlines()[0]
    return text if len(text) <= limit else text[:limit - 3] + "..."


def checkpoint_path(run_dir: str | Path, iteration: int) -> Path:
    """`RUN/checkpoints/ckpt_NNNNNNN.pt`."""
    return Path(run_dir) / "checkpoints" / f"ckpt_{iteration:07d}.pt"


def checkpoint_iteration(path: Path) -> int:
    """The iteration of a checkpoint file, from its name (``ckpt_0001200.pt`` -> 1200)."""
    m = CKPT_RE.match(Path(path).name)
    if m is None:
        raise NeusL0Error(f"{path}: not a checkpoint name (ckpt_NNNNNNN.pt)")
    return int(m.group(1))


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
    """Write `state` atomically to `path` inside its run; refuse NaN/inf; keep only the
    newest `keep`.

    The state is made plain first (`to_plain`: numpy values as lists and numbers), so that
    it loads with ``weights_only=True``; the run folder is ``path.parent.parent``, and a
    ``checkpoints/`` linked out of it is refused (`neus_l0.atomic.inside`).

    Raises:
        NeusL0Error: when the model or optimiser state is not finite (nothing is written).
        OutputError: when it cannot be written (a full disk, a link out of the run, ...;
            nothing is written).
    """
    path = Path(path)
    bad = _non_finite_key({"model": state.get("model"), "optimizer": state.get("optimizer")})
    if bad:
        raise NeusL0Error(f"{path}: not saved: the training state has NaN/inf in '{bad}' "
                          "(training diverged; try a lower train.lr)")
    atomic_torch_save(path, to_plain(state), within=path.parent.parent)
    if keep > 0:
        for old in list_checkpoints(path.parent.parent)[:-keep]:
            if old != path:
                old.unlink(missing_ok=True)
    return path


def _read(path: Path, map_location: str | torch.device) -> Any:
    """`torch.load` with ``weights_only=True``, its failures sorted into our errors."""
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except (FileNotFoundError, PermissionError, IsADirectoryError, MemoryError, ImportError,
            torch.OutOfMemoryError) as exc:
        raise NeusL0Error(f"{path}: cannot read checkpoint ({_first_line(exc)})") from None
    except Exception as exc:  # noqa: BLE001 - truncated zip, unpickling errors, EOF, ...
        if _needs_pickle(exc):
            raise UnsafeCheckpointError(unsafe_line(path)) from None
        raise CorruptCheckpointError(f"{path}: cannot read checkpoint "
                                     f"({_first_line(exc)})") from None


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """Read a checkpoint (``weights_only=True``: no code from the file runs) and check it.

    Raises:
        CorruptCheckpointError: the content is bad (does not unpickle, a missing key or
            one of the wrong kind: `schema_problem`, NaN/inf in the model or optimiser).
        UnsafeCheckpointError: it needs a full unpickling (`unsafe_line`).
        NeusL0Error: the file cannot be read for another reason (missing, no permission, a
            folder, out of memory).
    """
    path = Path(path)
    state = _read(path, map_location)
    problem = schema_problem(state)
    if problem:
        raise CorruptCheckpointError(f"{path}: {problem}")
    bad = _non_finite_key({"model": state["model"], "optimizer": state["optimizer"]})
    if bad:
        raise CorruptCheckpointError(f"{path}: refusing checkpoint with NaN/inf in '{bad}'; "
                                     "resume from an earlier checkpoint (delete this one)")
    return state


def upgrade_checkpoint(path: str | Path, out: str | Path | None = None,
                       trust_pickle: bool = False) -> tuple[Path, bool]:
    """Rewrite a checkpoint that needs pickle as plain data (`to_plain`), checked.

    Args:
        path: the checkpoint.
        out: where the plain checkpoint goes (default: over `path`, atomically).
        trust_pickle: the user's explicit consent to unpickle `path` in full, which runs any
            code it carries; without it nothing is read beyond what ``weights_only`` allows.

    Returns:
        (the file written or `path`, whether anything was converted).

    Raises:
        NeusL0Error: no consent, or the file is not a checkpoint even once unpickled.
    """
    path = Path(path)
    try:
        load_checkpoint(path)
        return path, False  # already plain: nothing to do
    except UnsafeCheckpointError:
        if not trust_pickle:
            raise NeusL0Error(f"{path}: converting it unpickles it in full, which runs any "
                              "code the file carries; add --trust-pickle if you trust where "
                              "it came from") from None
    try:  # the one full unpickling, on the user's explicit request (--trust-pickle)
        state = torch.load(path, map_location="cpu", weights_only=not trust_pickle)
        state = to_plain(state)
    except Exception as exc:  # noqa: BLE001 - whatever the pickle raises
        raise NeusL0Error(f"{path}: cannot convert ({_first_line(exc)})") from None
    problem = schema_problem(state)
    if problem:
        raise NeusL0Error(f"{path}: not converted: {problem}")
    target = Path(out) if out is not None else path
    atomic_torch_save(target, state)
    load_checkpoint(target)
    return target, True


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
    """Put a checkpoint's training state back (the resume of `neus_l0.train.loop.train`).

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
    load_weights(path, model, state["model"], "resume with the run's config.yaml")
    try:
        optimizer.load_state_dict(state["optimizer"])
    except (RuntimeError, ValueError, KeyError) as exc:
        raise NeusL0Error(f"{path}: does not fit the config's networks (resume with the "
                          f"run's config.yaml): {_fit_line(exc)}") from None
    try:
        restore_rng(generator, state["rng"])
    except (RuntimeError, ValueError, TypeError) as exc:
        raise NeusL0Error(f"{path}: its random generator states do not load "
                          f"({_fit_line(exc)}); resume from an earlier checkpoint") from None
    if occupancy is not None and "occupancy" in state:
        occupancy.load_state_dict(state["occupancy"])
    elif occupancy is not None:
        occupancy.update(model.sdf.sdf, model.variance.inv_s())
    if "scaler" in state:
        scaler.load_state_dict(state["scaler"])
    return int(state["iteration"]), int(state.get("batch_size", 0))


def _fit_line(exc: BaseException) -> str:
    """The informative line of a torch loading error (its first line is often only a
    header such as "Error(s) in loading state_dict for NeuSModel:")."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    if len(lines) > 1 and lines[0].endswith(":"):
        lines = lines[1:]
    text = lines[0] if lines else type(exc).__name__
    return text if len(text) <= 160 else text[:157] + "..."


def load_weights(path: Path, model: torch.nn.Module, weights: dict, hint: str) -> None:
    """`model.load_state_dict(weights)`, refusing a tensor of another shape or kind (an
    integer tensor where the model holds floats) in one line naming `path`.

    Raises:
        NeusL0Error: the checkpoint's networks do not fit `model` (`hint` says what to do).
    """
    own = model.state_dict()
    for key, value in weights.items():
        mine = own.get(key)
        if mine is not None and mine.is_floating_point() != value.is_floating_point():
            raise NeusL0Error(f"{path}: does not fit the config's networks ({hint}): "
                              f"'{key}' is {value.dtype}, the model's is {mine.dtype}")
    try:
        model.load_state_dict(weights)
    except (RuntimeError, ValueError, KeyError) as exc:
        raise NeusL0Error(f"{path}: does not fit the config's networks ({hint}): "
                          f"{_fit_line(exc)}") from None


def prune_checkpoints(run_dir: Path, keep: int, protected: set[Path]) -> None:
    """Delete all but the newest `keep` checkpoints that are not in `protected`."""
    if keep <= 0:
        return
    others = [p for p in list_checkpoints(run_dir) if p not in protected]
    for old in others[:-keep]:
        old.unlink(missing_ok=True)
def _set_aside(path: Path) -> Path:
    """Rename a damaged checkpoint to `<name>.corrupt` (`.corrupt.1`, ... if taken)."""
    target = path.with_name(path.name + ".corrupt")
    n = 0
    while target.exists():
        n += 1
        target = path.with_name(f"{path.name}.corrupt.{n}")
    path.rename(target)
    return target


def load_newest_checkpoint(run_dir: str | Path,
                           map_location: str | torch.device = "cpu") -> tuple[Path, dict] | None:
    """The newest checkpoint of a run that loads, setting damaged newer ones aside.

    Checkpoints are tried newest first. One that raises `CorruptCheckpointError` is renamed
    to ``<name>.corrupt`` once an older one has loaded, and one line on stderr names the
    damaged file(s) and the checkpoint used instead.

    Args:
        run_dir: the run folder (``RUN/checkpoints/ckpt_*.pt``).
        map_location: passed to `torch.load`.

    Returns:
        (path, state) of the checkpoint used, or None when the run has no checkpoint.

    Raises:
        NeusL0Error: checkpoints exist but none loads (nothing is renamed then), or one
            cannot be read for a reason that is not its content.
    """
    ckpts = list_checkpoints(run_dir)
    if not ckpts:
        return None
    damaged: list[tuple[Path, str]] = []
    for path in reversed(ckpts):
        try:
            state = load_checkpoint(path, map_location)
        except CorruptCheckpointError as exc:
            damaged.append((path, str(exc).removeprefix(f"{path}: ")))
            continue
        if damaged:
            notes = "; ".join(f"{p.name} ({why}) kept as {_set_aside(p).name}"
                              for p, why in damaged)
            print(f"neus-l0: {Path(run_dir) / 'checkpoints'}: damaged {notes}; using "
                  f"{path.name} (iteration {state['iteration']})", file=sys.stderr, flush=True)
        return path, state
    newest, why = damaged[0]
    raise NeusL0Error(f"{newest}: none of the {len(ckpts)} checkpoints of {run_dir} loads "
                      f"(the newest: {why}); delete or replace them")


def _restore_view_scale(path: Path, model: torch.nn.Module, value: Any) -> None:
    """Set the colour network's view-encoding weight a run trained with
    (`model.color.view_warmup`: a run stopped during the ramp renders with the weight it
    had, not the full view encoding); absent: left at 1."""
    if value is None:
        return
    if not isinstance(value, (int, float)) or not 0.0 <= float(value) <= 1.0:
        raise NeusL0Error(f"{path}: view_scale must be a number in [0, 1], not {value!r}")
    model.color.view_scale.fill_(float(value))


def load_trained_model(run_dir: str | Path, device: str | torch.device = "cpu",
                       checkpoint: str | Path | None = None
                       ) -> tuple[NeuSModel, Config, dict]:
    """The networks of a finished (or interrupted) run.

    Args:
        run_dir: the run folder.
        device: where the model goes (and the checkpoint's `map_location`).
        checkpoint: a specific checkpoint file (loaded as is, no fallback); default the
            newest that loads (`load_newest_checkpoint`).

    Returns:
        model (eval mode, built from the checkpoint's config with `cfg.train.seed`, as
        training builds it), config, and the checkpoint dict without the heavy states
        (``iteration``, ``scale_mat``, ..., and ``path``).

    Raises:
        NeusL0Error: no checkpoint, or none usable.
    """
    if checkpoint:
        path = Path(checkpoint)
        state = load_checkpoint(path, map_location=device)
    else:
        found = load_newest_checkpoint(run_dir, map_location=device)
        if found is None:
            raise NeusL0Error(f"{run_dir}: no checkpoints/ckpt_*.pt (train first)")
        path, state = found
    try:
        cfg = config_from_dict(state["config"])
    except NeusL0Error as exc:
        raise NeusL0Error(f"{path}: its config is not valid: {exc}") from None
    model = make_model(cfg, device)
    load_weights(path, model, state["model"], "a damaged or foreign file")
    _restore_view_scale(path, model, state.get("view_scale"))
    model.eval()
    info = {k: v for k, v in state.items() if k not in ("model", "optimizer", "rng")}
    info["path"] = path
    return model, cfg, info
