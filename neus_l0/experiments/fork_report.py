"""Writing the fork study: fork.csv, fork.json and summary.md (paired against the hvs arm)."""

from __future__ import annotations

import csv
import dataclasses
import io
import math
from pathlib import Path

import numpy as np

from neus_l0.atomic import atomic_write_json, atomic_write_text
from neus_l0.evaluation.paired import compare

#: The reported metrics: key -> (label, lower is better).
METRICS = {
    "overall": ("Chamfer", True),
    "pit": ("pits", True),
    "thin": ("thin parts", True),
    "sample_dist": ("fine-sample distance", True),
    "psnr": ("held-out PSNR", False),
}
#: The arm every other is paired with.
REFERENCE = "hvs"
COLUMNS = ("scene", "seed", "arm", "sampler", "masses", "iteration", "train_s", "overall",
           "accuracy", "completeness", "pit", "thin", "sample_dist", "psnr")


def _num(x) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return ""
    return f"{x:.6g}" if isinstance(x, float) else str(x)


def to_csv(rows: list[dict]) -> str:
    """One line per (scene, seed, arm), the base run's scores included (arm ``base``)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    for r in rows:
        w.writerow([_num(r.get(k)) for k in COLUMNS])
    return buf.getvalue()


def _value(r: dict | None, key: str) -> float | None:
    v = None if r is None else r.get(key)
    return None if v is None or not math.isfinite(v) else float(v)


def paired_rows(rows: list[dict], metric: str,
                scenes: list[str] | None = None) -> dict[str, dict]:
    """arm -> `neus_l0.evaluation.paired.compare` of `metric` against the hvs arm, over the
    (scene, seed) units both have (restricted to `scenes` when given)."""
    by = {(r["scene"], r["seed"], r["arm"]): r for r in rows}
    units = sorted({(r["scene"], r["seed"]) for r in rows
                    if scenes is None or r["scene"] in scenes})
    lower = METRICS[metric][1]
    out = {}
    for arm in sorted({r["arm"] for r in rows} - {REFERENCE}, key=_arm_order):
        ref, other = [], []
        for unit in units:
            a, b = _value(by.get((*unit, REFERENCE)), metric), _value(by.get((*unit, arm)), metric)
            if a is not None and b is not None:
                ref.append(a)
                other.append(b)
        if ref:
            out[arm] = compare(ref, other, lower_is_better=lower)
    return out


def _arm_order(arm: str) -> tuple:
    order = ["base", "hvs", "l0", "l0 interp", "l0-inverse", "neus-exact"]
    return (order.index(arm) if arm in order else len(order), arm)


def means_table(rows: list[dict]) -> str:
    """Markdown: per scene and arm, the mean (and seed count) of every metric."""
    head = ("| scene | arm | seeds | " + " | ".join(m[0] for m in METRICS.values())
            + " |\n|---|---|---|" + "---|" * len(METRICS) + "\n")
    lines = []
    for scene in sorted({r["scene"] for r in rows}):
        for arm in sorted({r["arm"] for r in rows if r["scene"] == scene}, key=_arm_order):
            rs = [r for r in rows if r["scene"] == scene and r["arm"] == arm]
            cells = []
            for key in METRICS:
                vals = [v for v in (_value(r, key) for r in rs) if v is not None]
                cells.append(f"{np.mean(vals):.4g}" if vals else "–")
            lines.append(f"| {scene} | {arm} | {len(rs)} | " + " | ".join(cells) + " |")
    return head + "\n".join(lines) + "\n"


def paired_table(rows: list[dict], scenes: list[str] | None = None) -> str:
    """Markdown: every arm against hvs, per metric: pairs, better in, the mean relative
    difference with its 95 % t interval, and the sign test's p."""
    head = ("| metric | arm | pairs | better in | mean difference (% of hvs) | 95 % CI | "
            "sign-test p |\n|---|---|---|---|---|---|---|\n")
    lines = []
    for key, (label, lower) in METRICS.items():
        for arm, c in paired_rows(rows, key, scenes).items():
            if arm == "base":
                continue
            lines.append(f"| {label} ({'lower' if lower else 'higher'} is better) | {arm} | "
                         f"{c['n']} | {c['better']} | {c['rel']:+.2f} | "
                         f"{c['rel_low']:+.2f} .. {c['rel_high']:+.2f} | {c['p']:.3g} |")
    return head + "\n".join(lines) + "\n"


def summary(rows: list[dict], spec) -> str:
    """The study's summary.md: settings, means per scene and arm, and the paired tables
    (all scenes pooled, then the scenes with pits and thin parts)."""
    s = dataclasses.asdict(spec)
    text = (f"# Fork study\n\nBase: hvs for {s['base_iters']} of {s['base_iters'] + s['arm_iters']}"
            f" iterations (config `{s['conf']}` {' '.join(s['overrides'])}), then each arm "
            f"for {s['arm_iters']} from the same checkpoint; every {s['holdout']}-th view held "
            f"out; meshes at {s['resolution']}^3, Chamfer density {s['eval_density']}. "
            "Units: world (Chamfer, sample distance), dB (PSNR). `base`: the field at the "
            "fork.\n\n## Means over seeds\n\n" + means_table(rows)
            + "\n## Paired against the hvs arm (every scene and seed)\n\n"
            + paired_table(rows))
    featured = sorted({r["scene"] for r in rows if _value(r, "pit") is not None})
    if featured:
        text += (f"\n## Paired, scenes with features only ({', '.join(featured)})\n\n"
                 + paired_table(rows, featured))
    return text


def write_outputs(out: Path, rows: list[dict], spec) -> None:
    """OUT/fork.csv, OUT/fork.json (rows and settings), OUT/summary.md."""
    atomic_write_text(out / "fork.csv", to_csv(rows))
    atomic_write_json(out / "fork.json", {"spec": {k: (str(v) if isinstance(v, Path) else v)
                                                   for k, v in dataclasses.asdict(spec).items()},
                                          "rows": rows})
    atomic_write_text(out / "summary.md", summary(rows, spec))
