"""What a run folder holds, how to tell one, and the check that its entries stay inside it.

A run folder is this tool's once it holds a record of a run (`RUN_RECORDS`: ``run.json`` or
a checkpoint); a folder without one may hold only what a started run leaves before its
record is written (`RUN_LEFTOVERS`), so that a user's folder of their own ``config.yaml``
and ``metrics.jsonl`` is never taken for a run (`neus_l0.commands._paths.check_output_dir`).

Every file a run writes stays inside the run folder: the writers pass ``within=RUN``
(`neus_l0.atomic.inside`), and `check_run_entries` refuses, before training, an entry of the
run (``checkpoints/``, ``hull.pt``, ...) that is a symlink leading out of it.
"""

from __future__ import annotations

from pathlib import Path

from neus_l0.atomic import inside
from neus_l0.errors import OutputError

#: Globs (relative to the folder) whose presence makes a folder a run of this tool.
RUN_RECORDS = ("run.json", "checkpoints/ckpt_*.pt")
#: What a run writes before its record (a start refused after the lock or the hull).
RUN_LEFTOVERS = ("hull.pt", "checkpoints", "validation", "events.out.tfevents.*", ".lock")
#: Every entry training writes at the top of a run folder.
RUN_ENTRIES = ("config.yaml", "run.json", "metrics.jsonl", "resumes.jsonl", "hull.pt",
               "checkpoints", "validation")


def check_run_entries(run_dir: str | Path) -> None:
    """Refuse a run folder one of whose entries (`RUN_ENTRIES`) leads out of it, or is
    neither a file nor a folder (a FIFO ``metrics.jsonl`` would block the run for good).

    Raises:
        OutputError: naming the entry and where it leads, or what it is.
    """
    for name in RUN_ENTRIES:
        path = inside(run_dir, Path(run_dir) / name)
        if path.exists() and not (path.is_file() or path.is_dir()):
            raise OutputError(f"{path}: not a file or a folder (a pipe, socket or device); "
                              "a run's entries must be files (remove it)")
