"""Checks on the output paths that commands are given, before any work starts.

A command that writes a folder (`train --out RUN`, `demo --out DIR`, `synth ... OUT`,
`colmap ... OUT`) or a file (`mesh --out FILE`) checks its destination first, so a file where
a folder belongs (or the reverse) is a one-line `NeusL0Error` instead of a `FileExistsError`
or `NotADirectoryError` traceback minutes into the run.
"""

from __future__ import annotations

from pathlib import Path

from neus_l0.errors import NeusL0Error


def _file_in_the_way(path: Path) -> Path | None:
    """The first existing ancestor of `path` (itself excluded) that is not a folder, or None."""
    for parent in reversed(path.parents):
        if parent.exists() and not parent.is_dir():
            return parent
    return None


def check_output_dir(path: str | Path, flag: str) -> Path:
    """Refuse a folder destination that is (or lies under) an existing non-folder.

    Args:
        path: the folder the command will create or fill.
        flag: how the user gave it (``--out``, ``OUT``), named in the error.

    Returns:
        `path` as a `Path`.

    Raises:
        NeusL0Error: `path` exists and is not a folder, or one of its parents is a file.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise NeusL0Error(f"{flag} {path}: exists and is not a folder (give a new or existing "
                          "folder)")
    blocker = _file_in_the_way(path)
    if blocker is not None:
        raise NeusL0Error(f"{flag} {path}: {blocker} is a file, not a folder")
    return path


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
