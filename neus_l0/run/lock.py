"""A lock on a run folder, so that two trainings cannot write into one run at once.

`RunLock(run_dir)` creates ``run_dir/.lock`` atomically (``O_CREAT | O_EXCL``: of two
processes only one can create it) holding the holder's PID, host name, start time and, on
Linux, the process's start time in clock ticks (so that a PID reused by another process is
not mistaken for the holder). The file is removed when the lock is released.

A lock whose holder is gone is stale: its host is this host and ``os.kill(pid, 0)`` says
no such process (or the PID now belongs to a process that started at another time). A
stale lock is taken over with a one-line notice. A lock held on another host cannot be
checked and is refused like a live one; the message says which file to remove.

Take-overs are serialised by an advisory ``flock`` on the run folder, held only while a
stale lock is re-read, removed and re-created, so two processes that find the same stale
lock cannot both take it.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path

from neus_l0.errors import NeusL0Error

#: Name of the lock file in a run folder.
LOCK_NAME = ".lock"

#: An unreadable lock file younger than this (seconds) is being written, not stale.
_WRITE_GRACE_S = 5.0


def _process_start(pid: int) -> int | None:
    """Start time of `pid` in clock ticks since boot (Linux ``/proc``), or None."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    try:  # field 22; the command name (field 2) may hold spaces, so split after its ')'
        return int(stat.rsplit(")", 1)[1].split()[19])
    except (IndexError, ValueError):
        return None


def pid_alive(pid: int) -> bool:
    """Whether a process with this PID exists on this host (``os.kill(pid, 0)``)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's process
    return True


def _notice(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


class RunLock:
    """The lock on one run folder, as a context manager.

    Args:
        run_dir: the run folder (created if missing).
        log: where the one-line take-over notice goes (default: stderr).

    Raises (on entry / `acquire`):
        NeusL0Error: the folder is in use: ``RUN: in use by PID N on HOST (started ...);
            ...`` in one line.
    """

    def __init__(self, run_dir: str | Path, log: Callable[[str], None] = _notice):
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / LOCK_NAME
        self.log = log
        self._token: str | None = None

    @property
    def held(self) -> bool:
        """Whether this object holds the lock."""
        return self._token is not None

    def _record(self) -> dict:
        now = time.time()
        return {"pid": os.getpid(), "host": socket.gethostname(),
                "started": datetime.datetime.fromtimestamp(now).astimezone()
                .isoformat(timespec="seconds"),
                "proc_start": _process_start(os.getpid()),
                "token": f"{os.getpid()}-{time.monotonic_ns()}-{id(self)}"}

    def _create(self) -> bool:
        """Create the lock file with our record; False if it exists."""
        record = self._record()
        try:
            fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            return False
        except OSError as exc:  # a read-only mount, no permission
            raise self._unwritable(exc) from None
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(json.dumps(record) + "\n")
            f.flush()
            os.fsync(f.fileno())
        self._token = record["token"]
        return True

    def read(self) -> dict | None:
        """The current lock file's record; ``{}`` if unreadable; None if there is none."""
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return None
        except OSError:
            return {}
        try:
            data = json.loads(text)
        except ValueError:
            return {}
        return data if isinstance(data, dict) else {}

    def is_stale(self, record: dict) -> bool:
        """Whether the holder of `record` is certainly gone (checked on this host only)."""
        if not record:  # unreadable: stale once it is too old to be still being written
            try:
                return time.time() - self.path.stat().st_mtime > _WRITE_GRACE_S
            except FileNotFoundError:
                return True
        if record.get("host") != socket.gethostname():
            return False
        pid = record.get("pid")
        if not isinstance(pid, int) or not pid_alive(pid):
            return True
        start = record.get("proc_start")
        now_start = _process_start(pid)
        return start is not None and now_start is not None and start != now_start

    def _refusal(self, record: dict) -> NeusL0Error:
        if not record:
            return NeusL0Error(f"{self.run_dir}: in use (its lock {self.path} is being "
                               "written or unreadable); remove that file if no run is active")
        where = record.get("host", "?")
        return NeusL0Error(
            f"{self.run_dir}: in use by PID {record.get('pid')} on {where} (started "
            f"{record.get('started', '?')}); wait for that run to end or stop it, or remove "
            f"{self.path} if no run is active")

    def _unwritable(self, exc: OSError) -> NeusL0Error:
        return NeusL0Error(f"{self.run_dir}: cannot write there ({exc.strerror or exc}); "
                           "choose another --out")

    def acquire(self) -> None:
        """Take the lock, or take over a stale one (see the module docstring).

        Raises:
            NeusL0Error: held by a live process (or one on another host); the folder cannot
                be written (a read-only mount, no permission).
        """
        if self.held:
            raise NeusL0Error(f"{self.run_dir}: this lock is already held by this object")
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise self._unwritable(exc) from None
        for _ in range(5):
            if self._create():
                return
            record = self.read()
            if record is None:
                continue  # released meanwhile: try again
            if not self.is_stale(record):
                raise self._refusal(record)
            with _folder_flock(self.run_dir):
                again = self.read()
                if again != record:
                    continue  # someone else took it over or released it: look again
                with contextlib.suppress(FileNotFoundError):
                    self.path.unlink()
                if self._create():
                    self.log(f"{self.run_dir}: took over a stale lock of PID "
                             f"{record.get('pid', '?')} (started {record.get('started', '?')}), "
                             "which is no longer running")
                    return
        raise NeusL0Error(f"{self.run_dir}: could not take the lock {self.path} (it keeps "
                          "changing hands)")

    def release(self) -> None:
        """Remove the lock file if it is still ours (idempotent)."""
        if self._token is None:
            return
        record = self.read()
        if record and record.get("token") == self._token:
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()
        self._token = None

    def __enter__(self) -> RunLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()


@contextlib.contextmanager
def _folder_flock(folder: Path):
    """An exclusive advisory lock on `folder` for the duration (a no-op without fcntl)."""
    try:
        import fcntl
    except ImportError:  # not POSIX: take-overs are not serialised
        yield
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # retried by Python when a signal interrupts it
        yield
    finally:
        os.close(fd)  # closing releases the flock
