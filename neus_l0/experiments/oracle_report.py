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


#: Below this value of hvs's metric a ratio to it means nothing (a handful of samples).
FLOOR = 0.01


def relative_to_hvs(rows: list[dict], metric: str = HEADLINE) -> dict[tuple, dict[str, float]]:
    """(case, regime, budget) -> {sampler: metric / hvs's metric}; NaN where hvs's metric
    is below `FLOOR` (e.g. grazing planes at 16+16, where no sampler gets samples within
    0.01)."""
    hvs = {_key(r): r[metric] for r in rows if r["sampler"] == "hvs"}
    out: dict[tuple, dict[str, float]] = {}
    for r in rows:
        base = hvs[_key(r)]
        out.setdefault(_key(r), {})[r["sampler"]] = (r[metric] / base if base >= FLOOR
                                                     else float("nan"))
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
    lines = [f"`{metric}` relative to `hvs`: geometric mean over cases and regimes (those "
             f"where hvs has at least {FLOOR:g}); worst case; number of cases worse / better "
             "than hvs by > 2 standard errors (paired per ray, all cases)", "",
             "| sampler | " + " | ".join(budgets) + " |",
             "|---|" + "---|" * len(budgets)]
    for s in samplers:
        cells = []
        for b in budgets:
            vals = [(v[s], k) for k, v in rel.items() if k[2] == b and math.isfinite(v[s])
                    and v[s] > 0]
            if not vals:
                cells.append("-")
                continue
            gm = math.exp(sum(math.log(x) for x, _ in vals) / max(1, len(vals)))
            worst, wk = min(vals)
            stats = [v for k, v in pair.items() if k[2] == b and k[3] == s]
            worse = sum(m + 2 * se < 0 for m, se in stats)
            better = sum(m - 2 * se > 0 for m, se in stats)
            cells.append(f"{gm:.2f} ({worst:.2f} {wk[0]}, {wk[1]}) -{worse}/+{better}")
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(path: Path, rows: list[dict], metric: str = HEADLINE) -> Path:
    """Heat maps of log2(metric / hvs), clipped to [-1, 1]: one panel per regime x budget,
    cases x samplers; grey where hvs's metric is below `FLOOR`."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    import numpy as np

    rel = relative_to_hvs(rows, metric)
    samplers = list(dict.fromkeys(r["sampler"] for r in rows))
    cases = list(dict.fromkeys(r["case"] for r in rows))
    panels = list(dict.fromkeys((r["regime"], r["budget"]) for r in rows))
    regimes = list(dict.fromkeys(p[0] for p in panels))
    budgets = list(dict.fromkeys(p[1] for p in panels))
    fig, axes = plt.subplots(len(regimes), len(budgets), squeeze=False,
                             figsize=(0.28 * len(samplers) * len(budgets) + 3,
                                      (0.22 * len(cases) + 1.8) * len(regimes) + 0.6))
    cmap = matplotlib.colormaps["RdBu"].copy()
    cmap.set_bad("0.85")
    for (i, regime), (j, budget) in ((a, b) for a in enumerate(regimes)
                                     for b in enumerate(budgets)):
        ax = axes[i][j]
        m = np.array([[rel.get((c, regime, budget), {}).get(s, np.nan) for s in samplers]
                      for c in cases])
        im = ax.imshow(np.log2(np.clip(m, 0.5, 2.0)), cmap=cmap, vmin=-1, vmax=1,
                       aspect="auto")
        ax.set_title(f"{regime}, {budget}", fontsize=9)
        ax.set_xticks(range(len(samplers)), samplers if i == len(regimes) - 1 else [],
                      rotation=90, fontsize=7)
        ax.set_yticks(range(len(cases)), cases if j == 0 else [], fontsize=7)
    fig.colorbar(im, ax=axes.ravel().tolist(), label=f"log2({metric} / hvs); grey: hvs "
                 f"< {FLOOR:g}", shrink=0.8)
    atomic_write(path, lambda p: fig.savefig(p, dpi=110, format="png", bbox_inches="tight"))
    plt.close(fig)
    return path
