"""Atomic file writes: write to a temporary file in the same folder, then rename.

A reader (or a resumed run) therefore sees either the previous complete file or the new
complete file, never a truncated one, even if the process is killed mid-write. The file gets
the mode a plain ``open`` would give it (0644 under umask 022), not the temporary file's
private 0600. A writer killed mid-write leaves its temporary file (``.NAME.XXXX.tmp.SUFFIX``)
behind; `remove_orphans` clears them where one writer owns the folder (a locked run folder).
A write that fails (no permission, a file in the way, a full disk, also inside torch's own
writer: `atomic_torch_save`) raises `neus_l0.errors.OutputError`, one line naming the file.

Writes into a folder this tool owns (a run folder) pass ``within=FOLDER``: `inside` then
refuses a path that, once symlinks are followed, leaves that folder (a ``metrics.jsonl`` or
a ``checkpoints/`` linked elsewhere), so that nothing is written outside the run through a
link someone planted. Appends (`append_text`) follow the same rule and never follow a link.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from neus_l0.errors import OutputError

#: Parts of the RuntimeError `torch.save` raises when it cannot write its file (a full disk
#: gives "unexpected pos ... vs ..." or "PytorchStreamWriter failed writing file").
TORCH_WRITE_FAILURES = ("PytorchStreamWriter failed", "unexpected pos", "file write failed")


def inside(folder: str | os.PathLike, path: str | os.PathLike) -> Path:
    """`path`, checked to stay inside `folder` once every symlink on the way is followed.

    `folder` itself may be a link (it is resolved too); what is refused is a link *in* it
    (``RUN/metrics.jsonl -> ~/.bashrc``, ``RUN/checkpoints -> /elsewhere``) whose target
    lies outside. A path that does not exist yet is judged by its existing parents.

    Raises:
        OutputError: naming `path`, where it leads and the folder.
    """
    folder, path = Path(folder), Path(path)
    real = Path(os.path.realpath(path))
    home = Path(os.path.realpath(folder))
    if real != home and home not in real.parents:
        raise OutputError(f"{path}: a symlink leads out of {folder} (to {real}); not written "
                          "through it (remove the link)")
    return path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike,
                within: str | os.PathLike | None = None) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success, rename it onto `path`.

    The caller writes the complete file to the yielded path. On an exception the temporary
    file is removed and `path` is left untouched. `within`: a folder `path` must stay in
    (`inside`).

    Raises:
        OutputError: an `OSError` while making the folder or the temporary file, writing,
            or renaming (naming `path` and why); a path leaving `within`.
    """
    path = Path(path)
    if within is not None:
        inside(within, path)
    tmp_path = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix,
                                   dir=path.parent)
        os.close(fd)
        tmp_path = Path(tmp)
        yield tmp_path
        with open(tmp_path, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, path)
    except OutputError:
        raise
    except OSError as exc:
        raise OutputError(f"{path}: cannot write ({exc.strerror or exc})") from None
    finally:
        if tmp_path is not None and tmp_path.exists():
            tmp_path.unlink()


def _umask() -> int:
    """The process's file-creation mask (read by setting it and putting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def orphan_temporaries(folder: str | os.PathLike) -> list[Path]:
    """The temporary files `atomic_path` left in `folder` (not its subfolders)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.name.startswith(".") and ".tmp" in p.name)


def remove_orphans(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporary files a killed writer left in `folder`; only where no other
    writer can be at work (a run folder under its lock). Returns what was removed."""
    removed = orphan_temporaries(folder)
    for p in removed:
        p.unlink(missing_ok=True)
    return removed


def atomic_write(path: str | os.PathLike, writer: Callable[[Path], Any],
                 within: str | os.PathLike | None = None) -> Path:
    """Call `writer(tmp_path)` to write the file, then move it atomically onto `path`
    (`within`: see `atomic_path`)."""
    with atomic_path(path, within) as tmp:
        writer(tmp)
    return Path(path)


def append_text(path: str | os.PathLike, text: str, within: str | os.PathLike) -> None:
    """Append `text` (UTF-8, one write: keep it small) to `path` inside `within`.

    The file is opened without following a final symlink (``O_NOFOLLOW``), after `inside`
    checked the folders on the way.

    Raises:
        OutputError: the path leaves `within`, is a link, or cannot be written.
    """
    path = Path(path)
    inside(within, path)
    flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(path, flags, 0o666)
        with os.fdopen(fd, "a", encoding="utf-8") as f:
            f.write(text)
    except OSError as exc:
        raise OutputError(f"{path}: cannot append ({exc.strerror or exc})") from None


def atomic_torch_save(path: str | os.PathLike, obj: Any,
                      within: str | os.PathLike | None = None) -> Path:
    """`torch.save(obj)` into `path` atomically; torch's own write failures
    (`TORCH_WRITE_FAILURES`) raise `OutputError` like any other write's."""
    import torch

    def write(tmp: Path) -> None:
        try:
            torch.save(obj, tmp)
        except RuntimeError as exc:
            if not any(s in str(exc) for s in TORCH_WRITE_FAILURES):
                raise
            raise OSError(f"torch: {str(exc).splitlines()[0]}; is the disk full?") from None

    return atomic_write(path, write, within)


def atomic_write_text(path: str | os.PathLike, text: str,
                      within: str | os.PathLike | None = None) -> Path:
    """Write `text` to `path` atomically (UTF-8; `within`: see `atomic_path`)."""
    return atomic_write(path, lambda p: p.write_text(text, encoding="utf-8"), within)


def atomic_write_json(path: str | os.PathLike, obj: Any,
                      within: str | os.PathLike | None = None) -> Path:
    """Write `obj` as indented JSON to `path` atomically (`within`: see `atomic_path`)."""
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True) + "\n", within)


def atomic_write_png(path: str | os.PathLike, bgr: Any,
                     within: str | os.PathLike | None = None) -> Path:
    """Encode an (H, W[, 3]) uint8 image (OpenCV's BGR order) as PNG and write it atomically.

    Raises:
        OSError: when OpenCV cannot encode it.
    """
    import cv2

    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    data = buf.tobytes()
    return atomic_write(path, lambda p: p.write_bytes(data), within)
