"""Checks on the output paths that commands are given, before any work starts.

A command that writes a folder (`train --out RUN`, `demo --out DIR`, `synth ... OUT`,
`colmap ... OUT`) or a file (`mesh --out FILE`) checks its destination first, so a file where
a folder belongs (or the reverse) is a one-line `NeusL0Error` instead of a `FileExistsError`
or `NotADirectoryError` traceback minutes into the run.

One rule for what an output folder may already hold (`foreign_entries`): nothing (it may
also be missing), or this tool's own folder of the command's kind: one that holds the
kind's record (``run.json`` or a checkpoint for a run, ``scene.json`` for a synthetic scene,
...), or only entries the command itself writes (its names). Anything else -- a user's
``config.yaml``, ``metrics.jsonl`` and ``notes.txt`` -- is refused in one line, before any
work, so that no file of the user's is replaced, appended to or deleted. And an output is
never one of the command's inputs (`check_not_input`).
"""

from __future__ import annotations

import fnmatch
import os
from collections.abc import Iterable
from pathlib import Path

from neus_l0.errors import NeusL0Error


def _file_in_the_way(path: Path) -> Path | None:
    """The first existing ancestor of `path` (itself excluded) that is not a folder, or None."""
    for parent in reversed(path.parents):
        if parent.exists() and not parent.is_dir():
            return parent
    return None


def _ignored(name: str) -> bool:
    """Entries no rule looks at: the temporaries of killed writers, Finder's litter."""
    return (name.startswith(".") and ".tmp" in name) or name == ".DS_Store"


def foreign_entries(folder: Path, records: Iterable[str] = (),
                    names: Iterable[str] = ()) -> list[str]:
    """The entries of an existing `folder` that make it not this command's to write into.

    Args:
        folder: an existing folder.
        records: globs relative to `folder`; when one matches, the folder is the command's
            own (a run, a scene) whatever else it holds: none is foreign.
        names: globs of the top-level entries the command writes.

    Returns:
        the names of the entries matching no glob of `names`, sorted (empty: the folder may
        be written into).
    """
    if any(next(folder.glob(r), None) is not None for r in records):
        return []
    names = tuple(names)
    return sorted(n for n in os.listdir(folder) if not _ignored(n)
                  and not any(fnmatch.fnmatchcase(n, pat) for pat in names))


def check_output_dir(path: str | Path, flag: str, records: Iterable[str] = (),
                     names: Iterable[str] = (), what: str = "this command's output") -> Path:
    """Refuse a folder destination that is a file, lies under one, or holds what is not
    this command's (`foreign_entries`).

    Args:
        path: the folder the command will create or fill.
        flag: how the user gave it (``--out``, ``OUT``), named in the error.
        records, names: the command's own folder (`foreign_entries`); with neither, only a
            missing or empty folder is accepted.
        what: what the command makes (``a run folder``), named in the error.

    Returns:
        `path` as a `Path`.

    Raises:
        NeusL0Error: `path` exists and is not a folder, one of its parents is a file, or it
            holds entries that are not the command's.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise NeusL0Error(f"{flag} {path}: exists and is not a folder (give a new or existing "
                          "folder)")
    blocker = _file_in_the_way(path)
    if blocker is not None:
        raise NeusL0Error(f"{flag} {path}: {blocker} is a file, not a folder")
    if path.is_dir():
        try:
            strangers = foreign_entries(path, records, names)
        except OSError as exc:
            raise NeusL0Error(f"{flag} {path}: cannot list it ({exc.strerror or exc})") from None
        if strangers:
            more = f" (and {len(strangers) - 1} more)" if len(strangers) > 1 else ""
            raise NeusL0Error(f"{flag} {path}: holds {strangers[0]}{more}: not {what} and not "
                              "empty; give a new or empty folder (nothing was written)")
    return path


def _same(a: Path, b: Path) -> bool:
    """Whether two paths name the same file or folder (links followed)."""
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_not_input(out: str | Path, flag: str, inputs: Iterable[str | Path | None]) -> Path:
    """Refuse an output that is one of the command's inputs (``eval MESH --json MESH``).

    Raises:
        NeusL0Error: naming the output and the input it would overwrite.
    """
    out = Path(out)
    for given in inputs:
        if given is None:
            continue
        given = Path(given)
        if _same(out, given) or Path(os.path.realpath(out)) == Path(os.path.realpath(given)):
            raise NeusL0Error(f"{flag} {out}: is the input {given}; writing it would destroy "
                              "the input (give another path)")
    return out


def check_not_in_input_folder(out: str | Path, flag: str, folders: Iterable) -> Path:
    """Refuse an output file that exists inside an input folder (``eval MESH --scene S
    --json S/scene.json``). Raises `NeusL0Error` naming both."""
    out = Path(out)
    real = Path(os.path.realpath(out))
    for folder in (f for f in folders if f is not None and Path(f).is_dir()):
        if out.exists() and Path(os.path.realpath(folder)) in real.parents:
            raise NeusL0Error(f"{flag} {out}: is a file of the input {folder}; writing it "
                              "would destroy part of the input (give another path)")
    return out


def check_output_file(path: str | Path, flag: str) -> Path:
    """Refuse a file destination that is an existing folder or lies under a file.

    Raises:
        NeusL0Error: `path` is a folder, or one of its parents is a file.
    """
    path = Path(path)
    if path.is_dir():
        raise NeusL0Error(f"{flag} {path}: is a folder (give a file name)")
    blocker = _file_in_the_way(path)
    if blocker is not None:
        raise NeusL0Error(f"{flag} {path}: {blocker} is a file, not a folder")
    return path
