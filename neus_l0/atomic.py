"""Atomic file writes: write to a temporary file in the same folder, then rename.

A reader (or a resumed run) therefore sees either the previous complete file or the new
complete file, never a truncated one, even if the process is killed mid-write. The file gets
the mode a plain ``open`` would give it (0644 under umask 022), not the temporary file's
private 0600. A writer killed mid-write leaves its temporary file (``.NAME.XXXX.tmp.SUFFIX``)
behind; `remove_orphans` clears them where one writer owns the folder (a locked run folder).
A write that fails (no permission, a file in the way, a full disk, also inside torch's own
writer: `atomic_torch_save`) raises `neus_l0.errors.OutputError`, one line naming the file.
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


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success, rename it onto `path`.

    The caller writes the complete file to the yielded path. On an exception the temporary
    file is removed and `path` is left untouched.

    Raises:
        OutputError: an `OSError` while making the folder or the temporary file, writing,
            or renaming (naming `path` and why).
    """
    path = Path(path)
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


def atomic_write(path: str | os.PathLike, writer: Callable[[Path], Any]) -> Path:
    """Call `writer(tmp_path)` to write the file, then move it atomically onto `path`."""
    with atomic_path(path) as tmp:
        writer(tmp)
    return Path(path)


def atomic_torch_save(path: str | os.PathLike, obj: Any) -> Path:
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

    return atomic_write(path, write)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write `text` to `path` atomically (UTF-8)."""
    return atomic_write(path, lambda p: p.write_text(text, encoding="utf-8"))


def atomic_write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write `obj` as indented JSON to `path` atomically."""
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


def atomic_write_png(path: str | os.PathLike, bgr: Any) -> Path:
    """Encode an (H, W[, 3]) uint8 image (OpenCV's BGR order) as PNG and write it atomically.

    Raises:
        OSError: when OpenCV cannot encode it.
    """
    import cv2

    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    data = buf.tobytes()
    return atomic_write(path, lambda p: p.write_bytes(data))
