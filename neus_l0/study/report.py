"""Writing the sampling study: CSV, a summary table against `hvs`, and heat-map plots."""

from __future__ import annotations

import csv
import io
from pathlib import Path

from neus_l0.atomic import atomic_write, atomic_write_text

#: The headline metric: fraction of fine samples within this distance of the first hit.
HEADLINE = "within_0.01"


def write_csv(path: Path, rows: list[dict]) -> Path:
    """All rows, one per case x regime x budget x sampler."""
    buf = io.StringIO()
    names = [k for k in rows[0] if not k.startswith("_")]
    writer = csv.DictWriter(buf, fieldnames=names)
    writer.writeheader()
    for r in rows:
        writer.writerow({k: (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k])
                         for k in names})
    return atomic_write_text(path, buf.getvalue())


def _key(r: dict) -> tuple:
    return r["case"], r["regime"], r["budget"]


def relative_to_hvs(rows: list[dict], metric: str = HEADLINE) -> dict[tuple, dict[str, float]]:
    """(case, regime, budget) -> {sampler: metric / hvs's metric} (inf where hvs has 0)."""
    hvs = {_key(r): r[metric] for r in rows if r["sampler"] == "hvs"}
    out: dict[tuple, dict[str, float]] = {}
    for r in rows:
        base = hvs[_key(r)]
        out.setdefault(_key(r), {})[r["sampler"]] = (r[metric] / base if base > 0
                                                     else float("inf") if r[metric] > 0
                                                     else 1.0)
    return out


def paired(rows: list[dict], metric: str = HEADLINE) -> dict[tuple, tuple[float, float]]:
    """(case, regime, budget, sampler) -> (mean, standard error) of the per-ray difference of
    `metric` to hvs on the same rays (needs the rows' ``_per_ray``)."""
    hvs = {_key(r): r["_per_ray"][metric] for r in rows if r["sampler"] == "hvs"}
    out = {}
    for r in rows:
        diff = (r["_per_ray"][metric] - hvs[_key(r)]).double()  # (B,)
        se = float(diff.std() / diff.numel() ** 0.5) if diff.numel() > 1 else 0.0
        out[(*_key(r), r["sampler"])] = (float(diff.mean()), se)
    return out


def summary(rows: list[dict], metric: str = HEADLINE) -> str:
    """Markdown: per sampler and budget, the geometric-mean ratio to hvs over the cases and
    regimes, the worst (smallest) ratio with its case, and in how many cases the sampler is
    worse / better than hvs by more than two standard errors of the paired per-ray
    difference."""
    import math

    rel = relative_to_hvs(rows, metric)
    pair = paired(rows, metric) if all("_per_ray" in r for r in rows) else {}
    samplers = list(dict.fromkeys(r["sampler"] for r in rows))
    budgets = list(dict.fromkeys(r["budget"] for r in rows))
    lines = [f"`{metric}` relative to `hvs`: geometric mean over cases and regimes; worst "
             "case; cases worse / better than hvs by > 2 standard errors (paired per ray)", "",
             "| sampler | " + " | ".join(budgets) + " |",
             "|---|" + "---|" * len(budgets)]
    for s in samplers:
        cells = []
        for b in budgets:
            vals = [(v[s], k) for k, v in rel.items() if k[2] == b and math.isfinite(v[s])
                    and v[s] > 0]
            gm = math.exp(sum(math.log(x) for x, _ in vals) / max(1, len(vals)))
            worst, wk = min(vals)
            stats = [v for k, v in pair.items() if k[2] == b and k[3] == s]
            worse = sum(m + 2 * se < 0 for m, se in stats)
            better = sum(m - 2 * se > 0 for m, se in stats)
            cells.append(f"{gm:.2f} ({worst:.2f} {wk[0]}, {wk[1]}) -{worse}/+{better}")
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(path: Path, rows: list[dict], metric: str = HEADLINE) -> Path:
    """Heat maps of metric / hvs: one panel per regime x budget, cases x samplers."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    import numpy as np

    rel = relative_to_hvs(rows, metric)
    samplers = list(dict.fromkeys(r["sampler"] for r in rows))
    cases = list(dict.fromkeys(r["case"] for r in rows))
    panels = list(dict.fromkeys((r["regime"], r["budget"]) for r in rows))
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels) + 2, 0.32 * len(cases)
                                                      + 2.5), squeeze=False)
    for ax, (regime, budget) in zip(axes[0], panels):
        m = np.array([[rel[(c, regime, budget)][s] for s in samplers] for c in cases])
        im = ax.imshow(np.log2(np.clip(m, 1 / 4, 4)), cmap="RdBu", vmin=-2, vmax=2)
        ax.set_title(f"{regime}, {budget}", fontsize=9)
        ax.set_xticks(range(len(samplers)), samplers, rotation=90, fontsize=7)
        ax.set_yticks(range(len(cases)), cases if ax is axes[0][0] else [], fontsize=7)
    fig.colorbar(im, ax=axes[0].tolist(), label=f"log2({metric} / hvs)", shrink=0.8)
    atomic_write(path, lambda p: fig.savefig(p, dpi=110, format="png"))
    plt.close(fig)
    return path
