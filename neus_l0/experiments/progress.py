"""A benchmark run's current step, passed from the run's process to the sweep's progress bar.

Every run executes in its own process with its output in ``log.txt``
(`neus_l0.experiments.runner`), so the sweep cannot show that process's bars. Instead the run
writes its current step to ``RUN_DIR/progress.json`` (`StepReporter`): the step's name,
how far it is (``n`` of ``total``, ``total`` None for a step of unknown length such as
marching cubes) and its unit. The sweep polls that file while it waits (`StepDisplay`) and
shows it as a second tqdm bar under the bar of runs, so every step that takes more than a
moment (training, marching cubes, scoring, rendering the held-out views) is visible with
its elapsed time.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from neus_l0.atomic import atomic_write_json

#: Name of the step file in a run folder.
PROGRESS_FILE = "progress.json"

#: tqdm's format for a step of unknown length (marching cubes, scoring).
UNKNOWN_LENGTH = "{desc}: {elapsed}{postfix}"


class StepReporter:
    """Writes a run's current step to ``RUN_DIR/progress.json`` (atomically, throttled).

    Args:
        path: the step file (``RUN_DIR/progress.json``); None: report nothing.
        min_interval: seconds between two writes for the same step (a new step, or a
            step's last unit, is always written).
    """

    def __init__(self, path: str | Path | None, min_interval: float = 0.5):
        self.path = None if path is None else Path(path)
        self.min_interval = min_interval
        self._last: tuple[str, float] | None = None  # (step, monotonic time of the write)

    def __call__(self, step: str, n: float = 0, total: float | None = None,
                 unit: str = "it", note: str = "") -> None:
        """Report that `step` is at `n` of `total` `unit`s (`note`: shown after the bar)."""
        if self.path is None:
            return
        now = time.monotonic()
        same = self._last is not None and self._last[0] == step
        if same and now - self._last[1] < self.min_interval and n != total:
            return
        self._last = (step, now)
        atomic_write_json(self.path, {"step": step, "n": n, "total": total, "unit": unit,
                                       "note": note})


def read_step(path: str | Path) -> dict | None:
    """The step in a progress file, or None when there is none (yet) or it is unreadable."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and isinstance(data.get("step"), str) else None


class StepDisplay:
    """A tqdm bar that follows a run's step file.

    Args:
        bar: the tqdm bar to drive (e.g. ``tqdm(position=1, leave=False)``).
    """

    def __init__(self, bar):
        self.bar = bar
        self._step: str | None = None

    def start(self, run_name: str) -> None:
        """A new run begins: clear the bar."""
        self._step = None
        self.bar.reset()
        self.bar.total = None
        self.bar.bar_format = UNKNOWN_LENGTH
        self.bar.set_description_str(f"{run_name}: starting")

    def poll(self, path: str | Path) -> None:
        """Show the step in `path` (called every half second or so while the run runs)."""
        data = read_step(path)
        if data is None:
            self.bar.refresh()
            return
        step, total = data["step"], data.get("total")
        if step != self._step:
            self._step = step
            self.bar.reset()
            self.bar.total = total  # reset(total=None) would keep the old total
            self.bar.unit = str(data.get("unit") or "it")
            # a step of unknown length shows its elapsed time only, not a count of 0
            self.bar.bar_format = UNKNOWN_LENGTH if total is None else None
            self.bar.set_description_str(step)
        self.bar.n = data.get("n") or 0
        self.bar.set_postfix_str(str(data.get("note") or ""), refresh=False)
        self.bar.refresh()
