"""`neus_l0.run.lock.RunLock`: one holder per run folder, stale locks taken over."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from neus_l0.errors import NeusL0Error
from neus_l0.run.lock import LOCK_NAME, RunLock, pid_alive

ROOT = Path(__file__).resolve().parents[2]


def test_lock_file_names_the_holder_and_goes_on_exit(tmp_path):
    run = tmp_path / "run"
    with RunLock(run) as lock:
        assert lock.held
        record = json.loads((run / LOCK_NAME).read_text())
        assert record["pid"] == os.getpid() and record["host"] == socket.gethostname()
        assert record["started"]
    assert not (run / LOCK_NAME).exists()
    assert not lock.held
    with RunLock(run):  # free again
        pass


def test_second_lock_in_the_same_process_is_refused_naming_the_pid(tmp_path):
    with RunLock(tmp_path):
        with pytest.raises(NeusL0Error) as err:
            RunLock(tmp_path).acquire()
    msg = str(err.value)
    assert f"in use by PID {os.getpid()}" in msg and "started" in msg
    assert str(tmp_path / LOCK_NAME) in msg and "\n" not in msg
    assert not (tmp_path / LOCK_NAME).exists()  # the refused one did not remove it


def test_lock_is_released_when_the_body_raises(tmp_path):
    with pytest.raises(RuntimeError):
        with RunLock(tmp_path):
            raise RuntimeError("boom")
    assert not (tmp_path / LOCK_NAME).exists()


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    assert not pid_alive(proc.pid)
    return proc.pid


def test_stale_lock_of_a_dead_process_is_taken_over(tmp_path):
    pid = _dead_pid()
    (tmp_path / LOCK_NAME).write_text(json.dumps(
        {"pid": pid, "host": socket.gethostname(), "started": "yesterday"}))
    notices = []
    with RunLock(tmp_path, log=notices.append):
        assert json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == os.getpid()
    assert len(notices) == 1 and f"stale lock of PID {pid}" in notices[0]
    assert "\n" not in notices[0]
    assert not (tmp_path / LOCK_NAME).exists()


def test_a_reused_pid_is_not_mistaken_for_the_holder(tmp_path):
    """Our own (live) PID, but a process start time that is not ours: stale."""
    (tmp_path / LOCK_NAME).write_text(json.dumps(
        {"pid": os.getpid(), "host": socket.gethostname(), "started": "long ago",
         "proc_start": 1}))
    if not Path(f"/proc/{os.getpid()}/stat").exists():
        pytest.skip("no /proc")
    notices = []
    with RunLock(tmp_path, log=notices.append):
        pass
    assert len(notices) == 1


def test_a_lock_on_another_host_is_refused(tmp_path):
    (tmp_path / LOCK_NAME).write_text(json.dumps(
        {"pid": _dead_pid(), "host": "elsewhere.invalid", "started": "now"}))
    with pytest.raises(NeusL0Error, match="on elsewhere.invalid"):
        RunLock(tmp_path).acquire()
    assert (tmp_path / LOCK_NAME).exists()


def test_unreadable_lock_is_stale_only_once_old(tmp_path):
    path = tmp_path / LOCK_NAME
    path.write_text("")
    with pytest.raises(NeusL0Error, match="being written or unreadable"):
        RunLock(tmp_path).acquire()
    old = time.time() - 60
    os.utime(path, (old, old))
    with RunLock(tmp_path, log=lambda m: None):
        pass


def test_a_live_holder_in_another_process_refuses_until_it_dies(tmp_path):
    code = textwrap.dedent(f"""
        import time
        from neus_l0.run.lock import RunLock
        with RunLock({str(tmp_path)!r}):
            print("locked", flush=True)
            time.sleep(120)
    """)
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                             cwd=ROOT)
    try:
        assert child.stdout.readline().strip() == "locked"
        with pytest.raises(NeusL0Error, match=f"in use by PID {child.pid} "):
            RunLock(tmp_path).acquire()
    finally:
        child.kill()  # killed: no release, the lock file stays behind
        child.wait()
    assert (tmp_path / LOCK_NAME).exists()
    notices = []
    with RunLock(tmp_path, log=notices.append):
        pass
    assert f"PID {child.pid}" in notices[0]


def test_racing_takeovers_of_one_stale_lock_leave_one_holder(tmp_path):
    (tmp_path / LOCK_NAME).write_text(json.dumps(
        {"pid": _dead_pid(), "host": socket.gethostname(), "started": "then"}))
    code = textwrap.dedent(f"""
        import time
        from neus_l0.errors import NeusL0Error
        from neus_l0.run.lock import RunLock
        time.sleep(max(0.0, {time.time() + 1.5!r} - time.time()))  # start together
        try:
            with RunLock({str(tmp_path)!r}, log=lambda m: None):
                print("won", flush=True)
                time.sleep(3)
        except NeusL0Error:
            print("refused", flush=True)
    """)
    procs = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                              cwd=ROOT) for _ in range(4)]
    outs = sorted(p.communicate(timeout=60)[0].strip() for p in procs)
    assert outs == ["refused", "refused", "refused", "won"]
