"""A run's ``metrics.jsonl``: the one reader and writer.

One JSON object a line, appended as training goes:

* a *log line* every ``train.log_every`` iterations: ``iter``, ``loss``, ``psnr``,
  ``inv_s`` (NeuS's sharpness s, the inverse standard deviation of its logistic density),
  ``lr``, ``elapsed``, ... and the numbers that training hooks add (``sample_dist``);
* a *snapshot line* for each checkpoint a snapshot mark took: ``snapshot_s``, ``iter``,
  ``elapsed``.

Reading skips lines that do not parse (a line cut by a crash, bytes that are not UTF-8),
and renames the keys that
older runs wrote (`OLD_KEYS`: their ``s`` held 1 / s, the logistic's standard deviation,
under a name that read as the sharpness), so every run folder reads the same way.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path

from neus_l0.atomic import append_text, atomic_write_text

#: The metrics file's name inside a run folder.
METRICS_FILE = "metrics.jsonl"

#: Keys older runs wrote: old name -> (today's name, today's value from the old one).
OLD_KEYS: dict[str, tuple[str, Callable[[float], float]]] = {
    "s": ("inv_s", lambda v: 1.0 / v if v else float("nan")),
}


def metrics_path(run_dir: str | Path) -> Path:
    """``RUN/metrics.jsonl``."""
    return Path(run_dir) / METRICS_FILE


def _parse(line: str) -> dict | None:
    """One line as a dict with today's keys, or None (empty, cut or not an object)."""
    try:
        m = json.loads(line)
    except json.JSONDecodeError:
        return None
    if not isinstance(m, dict):
        return None
    for old, (new, convert) in OLD_KEYS.items():
        if old in m and new not in m:
            value = m.pop(old)
            m[new] = convert(value) if isinstance(value, (int, float)) else value
    return m


def text_lines(path: Path) -> list[str | None]:
    """The lines of a text file, each decoded as UTF-8 on its own; None for a line that is
    not UTF-8 (so that one damaged line costs only itself)."""
    out: list[str | None] = []
    for raw in path.read_bytes().splitlines():
        try:
            out.append(raw.decode("utf-8"))
        except UnicodeDecodeError:
            out.append(None)
    return out


def read_lines(run_dir: str | Path) -> Iterator[dict]:
    """Every line of the run's metrics file that parses, in order (none if no file)."""
    path = metrics_path(run_dir)
    if not path.is_file():
        return
    for line in text_lines(path):
        m = _parse(line) if line is not None else None
        if m is not None:
            yield m


def log_lines(run_dir: str | Path) -> list[dict]:
    """The log lines (those with a ``loss``), in order."""
    return [m for m in read_lines(run_dir) if "loss" in m]


def last_log_line(run_dir: str | Path) -> dict:
    """The newest log line (empty when none was logged)."""
    lines = log_lines(run_dir)
    return lines[-1] if lines else {}


def snapshot_lines(run_dir: str | Path) -> list[dict]:
    """The snapshot lines (``snapshot_s``, ``iter``, ``elapsed``), in order."""
    return [m for m in read_lines(run_dir) if "snapshot_s" in m and "iter" in m]


def append_line(run_dir: str | Path, line: dict) -> None:
    """Append one line (a line is small, so the append is one write), never through a link
    out of the run (`neus_l0.atomic.append_text`)."""
    append_text(metrics_path(run_dir), json.dumps(line) + "\n", within=run_dir)


def truncate(run_dir: str | Path, iteration: int) -> int:
    """Keep only the lines up to `iteration` (after a resume), dropping lines that do not
    parse; written atomically inside the run. Returns how many lines were dropped as
    unreadable (not UTF-8, not JSON)."""
    path = metrics_path(run_dir)
    if not path.exists():
        return 0
    lines = [ln for ln in text_lines(path) if ln is None or ln.strip()]
    parsed = [_parse(ln) if ln is not None else None for ln in lines]
    keep = [m for m in parsed if m is not None and m.get("iter", 0) <= iteration]
    atomic_write_text(path, "".join(json.dumps(m) + "\n" for m in keep), within=run_dir)
    return sum(m is None for m in parsed)
