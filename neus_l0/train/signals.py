"""Stop a long loop cleanly on SIGTERM or SIGINT instead of dying mid-step.

Cluster schedulers preempt a job with SIGTERM (and kill it some seconds later); a user
presses Ctrl-C (SIGINT). `StopOnSignal` turns either into a flag that the loop checks
between steps, so the loop can finish its step, write a checkpoint and exit::

    with StopOnSignal() as stop:
        for step in range(start, end):
            train_step()
            if stop.requested:
                save_checkpoint()
                print(f"{stop.signal_name}: stopped after step {step}; checkpoint saved")
                sys.exit(stop.exit_code)      # 143 for SIGTERM, 130 for SIGINT

Rules:

* The handlers are installed on entry and the previous ones restored on exit, so a nested
  use, or code that set its own handler, gets its handler back.
* Signal handlers can only be installed from the main thread. Elsewhere the context does
  nothing (``active`` is False and ``requested`` stays False): the signals keep their
  previous handling.
* A second SIGINT while a stop is pending raises `KeyboardInterrupt` at once (a user who
  presses Ctrl-C twice does not want to wait for the checkpoint). A second SIGTERM only
  keeps the flag set.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Sequence

#: The signals `StopOnSignal` handles by default.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


class StopOnSignal:
    """A context manager that records SIGTERM / SIGINT in a flag instead of stopping.

    Args:
        signals: the signals to catch (default SIGTERM and SIGINT).

    Attributes:
        requested: True once one of the signals has arrived inside the context.
        signal_name: the first such signal's name (``"SIGTERM"``), or None.
        signum: its number, or None.
        active: whether the handlers were installed (False off the main thread).
    """

    def __init__(self, signals: Sequence[int] = STOP_SIGNALS):
        self.signals = tuple(signal.Signals(s) for s in signals)
        self.requested = False
        self.signal_name: str | None = None
        self.signum: int | None = None
        self.active = False
        self._previous: dict[signal.Signals, object] = {}

    @property
    def exit_code(self) -> int:
        """The shell's code for death by the signal: 128 + signum (143 SIGTERM, 130 SIGINT);
        0 when no stop was requested."""
        return 128 + int(self.signum) if self.signum is not None else 0

    def _handle(self, signum: int, frame) -> None:
        if self.requested and signum == signal.SIGINT:
            raise KeyboardInterrupt  # the second Ctrl-C: stop now
        if not self.requested:
            self.requested = True
            self.signum = int(signum)
            self.signal_name = signal.Signals(signum).name

    def __enter__(self) -> StopOnSignal:
        if threading.current_thread() is not threading.main_thread():
            return self  # signal.signal would raise ValueError here
        for sig in self.signals:
            self._previous[sig] = signal.getsignal(sig)
            signal.signal(sig, self._handle)
        self.active = True
        return self

    def __exit__(self, *exc) -> None:
        for sig, previous in self._previous.items():
            # None: a handler not installed from Python; the default is the best we can do
            signal.signal(sig, previous if previous is not None else signal.SIG_DFL)
        self._previous.clear()
        self.active = False
