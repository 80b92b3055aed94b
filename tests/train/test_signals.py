"""`neus_l0.train.signals.StopOnSignal`: signals become a flag inside, handlers come back after."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from neus_l0.train.signals import StopOnSignal


def _wait_for(flag, seconds=5.0):
    """Python runs a signal's handler at its next bytecode check; give it a moment."""
    deadline = time.monotonic() + seconds
    while not flag() and time.monotonic() < deadline:
        time.sleep(0.01)


def _marker(signum, frame):  # a previous handler to restore
    pass


@pytest.fixture
def own_handlers():
    """Known handlers before each test, and pytest's own restored after it."""
    saved = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    for s in saved:
        signal.signal(s, _marker)
    yield
    for s, h in saved.items():
        signal.signal(s, h if h is not None else signal.SIG_DFL)


def test_sigterm_sets_the_flag_and_does_not_kill(own_handlers):
    with StopOnSignal() as stop:
        assert stop.active and not stop.requested and stop.exit_code == 0
        os.kill(os.getpid(), signal.SIGTERM)
        _wait_for(lambda: stop.requested)
        assert stop.requested
        assert stop.signal_name == "SIGTERM" and stop.signum == signal.SIGTERM
        assert stop.exit_code == 143
        os.kill(os.getpid(), signal.SIGTERM)  # a second SIGTERM only keeps the flag
        time.sleep(0.05)
    assert signal.getsignal(signal.SIGTERM) is _marker
    assert signal.getsignal(signal.SIGINT) is _marker
    assert not stop.active


def test_sigint_then_a_second_sigint_raises(own_handlers):
    with pytest.raises(KeyboardInterrupt):
        with StopOnSignal() as stop:
            os.kill(os.getpid(), signal.SIGINT)
            _wait_for(lambda: stop.requested)
            assert stop.signal_name == "SIGINT" and stop.exit_code == 130
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)  # interrupted by the KeyboardInterrupt
    assert signal.getsignal(signal.SIGINT) is _marker  # restored on the way out


def test_the_first_signal_is_the_one_recorded(own_handlers):
    with StopOnSignal() as stop:
        os.kill(os.getpid(), signal.SIGINT)
        _wait_for(lambda: stop.requested)
        os.kill(os.getpid(), signal.SIGTERM)  # a SIGTERM after a SIGINT raises nothing
        time.sleep(0.05)
    assert stop.signal_name == "SIGINT" and stop.exit_code == 130


def test_nested_contexts_restore_each_other(own_handlers):
    with StopOnSignal() as outer:
        with StopOnSignal() as inner:
            os.kill(os.getpid(), signal.SIGTERM)
            _wait_for(lambda: inner.requested)
        assert inner.requested and not outer.requested
        os.kill(os.getpid(), signal.SIGTERM)
        _wait_for(lambda: outer.requested)
        assert outer.requested
    assert signal.getsignal(signal.SIGTERM) is _marker


def test_off_the_main_thread_it_does_nothing(own_handlers):
    seen = {}

    def body():
        with StopOnSignal() as stop:
            seen["active"] = stop.active
            seen["handler"] = signal.getsignal(signal.SIGTERM)

    t = threading.Thread(target=body)
    t.start()
    t.join()
    assert seen == {"active": False, "handler": _marker}
    assert signal.getsignal(signal.SIGTERM) is _marker


def test_default_handling_returns_after_the_context():
    """End to end in a child process: survives SIGTERM inside, dies of it outside."""
    code = textwrap.dedent("""
        import os, signal, time
        from neus_l0.train.signals import StopOnSignal
        with StopOnSignal() as stop:
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(500):
                if stop.requested:
                    break
                time.sleep(0.01)
            print(stop.signal_name, stop.exit_code, flush=True)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)
        print("survived", flush=True)
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60, cwd=Path(__file__).resolve().parents[2])
    assert proc.stdout.split() == ["SIGTERM", "143"]
    assert proc.returncode == -signal.SIGTERM
