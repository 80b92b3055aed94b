"""What a resume may change, and the record of what resumes changed (``RUN/resumes.jsonl``).

A run's ``config.yaml`` is its original record and is never rewritten by a resume. A resume
that changes settings appends one line here (the iteration, the ``key=value`` overrides and
the keys they changed); the run's config is then ``config.yaml`` with every recorded
override applied in order (`recorded_overrides`), so that a later plain ``--resume``
continues with what the run last used.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from neus_l0.atomic import append_text
from neus_l0.config.load import to_dict
from neus_l0.config.schema import Config
from neus_l0.run.metrics import text_lines

#: The file a run keeps its resumes' overrides in.
RESUMES_FILE = "resumes.jsonl"

#: Keys a resume may change freely: how long to train and what to log, not what is learnt.
FREE_ON_RESUME = frozenset({
    "train.iters", "train.max_seconds", "train.log_every", "train.val_every",
    "train.val_downscale", "train.save_every", "train.keep_checkpoints", "train.tensorboard",
    "train.compile", "train.threads", "train.budget_up_to_iters", "render.chunk",
})


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(d, dict):
        return {prefix[:-1]: d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}."))
    return out


def changed_keys(old: Config, new: Config) -> list[str]:
    """The dotted keys whose values differ between two configs."""
    a, b = _flat(to_dict(old)), _flat(to_dict(new))
    return sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))


def guarded_keys(changed: list[str]) -> list[str]:
    """The changed keys a resume may change only when asked to (`FREE_ON_RESUME`)."""
    return [k for k in changed if k not in FREE_ON_RESUME]


def recorded_overrides(run_dir: str | Path) -> list[str]:
    """Every override the run's resumes recorded, in order (none without the file)."""
    path = Path(run_dir) / RESUMES_FILE
    if not path.is_file():
        return []
    out: list[str] = []
    for line in text_lines(path):
        if line is None:
            continue
        try:
            out += list(json.loads(line).get("overrides", []))
        except (ValueError, AttributeError):
            continue
    return out


@dataclasses.dataclass
class ResumeRecord:
    """One resume that changed the config: at `iteration`, `overrides` changed `changed`."""

    iteration: int
    overrides: list[str]
    changed: list[str]


def as_overrides(cfg: Config, keys: list[str]) -> list[str]:
    """``key=value`` overrides that set `keys` to their values in `cfg` (values as YAML)."""
    import yaml

    flat = _flat(to_dict(cfg))
    out = []
    for k in keys:
        value = yaml.safe_dump(flat[k], default_flow_style=True).strip()
        out.append(f"{k}={value.removesuffix(chr(10) + '...').removesuffix(' ...')}")
    return out


def record_resume(run_dir: str | Path, record: ResumeRecord) -> None:
    """Append one resume's record (one small line: a single write), never through a link
    out of the run (`neus_l0.atomic.append_text`)."""
    append_text(Path(run_dir) / RESUMES_FILE, json.dumps(dataclasses.asdict(record)) + "\n",
                within=run_dir)
