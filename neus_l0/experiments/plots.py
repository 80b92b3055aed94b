"""Figures and the table of a sweep folder, written into ``DIR/plots/``.

* ``chamfer_vs_time.png``: overall Chamfer distance against the measured training time, a
  panel per scene, a line per sampler through one point per budget (mean over seeds of the
  time and of the Chamfer; vertical band = min..max Chamfer over seeds, horizontal bar =
  min..max time: a run that finishes `train.iters` early stops before its budget);
* ``psnr_vs_time.png``: held-out PSNR against the measured training time, drawn the same way;
* ``pits_vs_time.png`` and ``thin_vs_time.png``: the Chamfer distance over the scene's pit and
  thin features against the training time, drawn the same way (only when some run has them:
  a synthetic scene with ``features.json``);
* ``chamfer_vs_iterations.png``: overall Chamfer against the iterations each run reached, a
  point per run: the iteration-matched view, which machine load does not move;
* ``sample_distance.png``: mean distance of the fine samples to the true surface against
  the iteration (``sample_dist`` of metrics.jsonl), a panel per scene, one line per seed of
  each sampler's longest run;
* ``table.md``: the final numbers per (scene, sampler, budget), mean ± std over seeds, the
  failed runs, the paired differences (`paired_differences`) and the iteration-matched
  offset (`iteration_matched_effect`) of each sampler against ``hvs``.
"""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from neus_l0.atomic import atomic_path, atomic_write_text
from neus_l0.experiments.results import read_results
from neus_l0.run.metrics import read_lines

#: Line colours per sampler (others cycle through matplotlib's defaults).
COLORS = {"hvs": "tab:blue", "l0": "tab:red", "l0-inverse": "tab:green",
          "l0-linear": "tab:purple"}


def _color(sampler: str, i: int) -> str:
    return COLORS.get(sampler, f"C{i % 10}")


def _done(rows: list[dict]) -> list[dict]:
    return [r for r in rows if r["status"] == "done"]


def _groups(rows: list[dict]) -> dict:
    """{scene: {sampler: {budget: [rows]}}} of done rows."""
    out: dict = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    for r in _done(rows):
        out[r["scene"]][r["sampler"]][r["budget_s"]].append(r)
    return out


def _scene_panels(groups: dict) -> tuple:
    """A figure with one panel per scene: (figure, [(axes, scene), ...])."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = sorted(groups) or ["(no finished runs)"]
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.6 * len(scenes), 3.6), squeeze=False)
    return fig, list(zip(axes[0], scenes))


def _finish_panels(fig, panels: list, path: Path) -> Path:
    """Legends where there are lines, then write the figure atomically and close it."""
    import matplotlib.pyplot as plt

    for ax, _ in panels:
        if ax.get_legend_handles_labels()[0]:
            ax.legend()
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return path


def _save(fig, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    return path


def _finite(values) -> np.ndarray:
    a = np.array([v for v in values if v is not None], dtype=float)
    return a[np.isfinite(a)]


def plot_metric_vs_time(rows: list[dict], metric: str, ylabel: str, path: Path) -> Path:
    """`metric` against the measured training time: a panel per scene, a line per sampler.

    One point per budget: x = mean ``train_seconds`` over seeds (bar: min..max), y = mean
    `metric` (band: min..max). Rows without a measured time fall back to their budget.
    """
    groups = _groups(rows)
    fig, panels = _scene_panels(groups)
    for ax, scene in panels:
        for i, sampler in enumerate(sorted(groups.get(scene, {}))):
            pts = []  # (x mean, x min, x max, y mean, y min, y max)
            for budget in sorted(groups[scene][sampler]):
                rs = [r for r in groups[scene][sampler][budget]
                      if r[metric] is not None and math.isfinite(r[metric])]
                if not rs:
                    continue
                t = np.array([r["train_seconds"] if r.get("train_seconds") is not None
                              else budget for r in rs], dtype=float)
                v = np.array([r[metric] for r in rs], dtype=float)
                pts.append((t.mean(), t.min(), t.max(), v.mean(), v.min(), v.max()))
            if not pts:
                continue
            p = np.array(pts)
            c = _color(sampler, i)
            n = max(len(b) for b in groups[scene][sampler].values())
            ax.errorbar(p[:, 0], p[:, 3], xerr=[p[:, 0] - p[:, 1], p[:, 2] - p[:, 0]],
                        fmt="o-", color=c, capsize=2,
                        label=f"{sampler} ({n} seed{'s' * (n > 1)})")
            ax.fill_between(p[:, 0], p[:, 4], p[:, 5], color=c, alpha=0.2, linewidth=0)
        ax.set_title(scene)
        ax.set_xlabel("training time (s, wall-clock, measured)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    return _finish_panels(fig, panels, path)


def plot_metric_vs_iterations(rows: list[dict], metric: str, ylabel: str, path: Path) -> Path:
    """`metric` against the iterations each run reached: a point per run, a colour per sampler.

    The iteration-matched comparison: two samplers at the same iteration count have had the
    same schedule, whatever the machine load did to their wall-clock.
    """
    groups = _groups(rows)
    fig, panels = _scene_panels(groups)
    for ax, scene in panels:
        for i, sampler in enumerate(sorted(groups.get(scene, {}))):
            rs = [r for b in groups[scene][sampler].values() for r in b
                  if r[metric] is not None and math.isfinite(r[metric])
                  and r.get("iterations") is not None]
            if not rs:
                continue
            rs.sort(key=lambda r: r["iterations"])
            c = _color(sampler, i)
            ax.plot([r["iterations"] for r in rs], [r[metric] for r in rs], "o", color=c,
                    alpha=0.8, label=f"{sampler} ({len(rs)} run{'s' * (len(rs) > 1)})")
        ax.set_title(scene)
        ax.set_xlabel("iterations reached")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    return _finish_panels(fig, panels, path)


def read_sample_distance(run_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """(iterations, sample_dist) logged in ``run_dir/metrics.jsonl`` (empty if none)."""
    its, vals = [], []
    for m in read_lines(run_dir):
        v = m.get("sample_dist")
        if isinstance(v, (int, float)) and math.isfinite(v) and "iter" in m:
            its.append(m["iter"])
            vals.append(v)
    return np.array(its), np.array(vals)


def plot_sample_distance(out_dir: Path, rows: list[dict], path: Path) -> Path:
    """Fine-sample distance to the surface against iterations (each sampler's longest runs)."""
    groups = _groups(rows)
    fig, panels = _scene_panels(groups)
    for ax, scene in panels:
        for i, sampler in enumerate(sorted(groups.get(scene, {}))):
            longest = max(groups[scene][sampler])
            for j, r in enumerate(sorted(groups[scene][sampler][longest],
                                         key=lambda r: r["seed"])):
                its, vals = read_sample_distance(out_dir / r["run_dir"])
                if len(its):
                    ax.plot(its, vals, color=_color(sampler, i), alpha=0.9 if j == 0 else 0.5,
                            label=f"{sampler} ({longest:g} s)" if j == 0 else None)
        ax.set_title(scene)
        ax.set_xlabel("iteration")
        ax.set_ylabel("mean distance of fine samples\nto the surface (world units)")
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
    return _finish_panels(fig, panels, path)


def _fmt(values, digits: int = 3) -> str:
    v = _finite(values)
    if not len(v):
        return "–"
    if len(v) == 1:
        return f"{v[0]:.{digits}g}"
    return f"{v.mean():.{digits}g} ± {v.std(ddof=1):.2g}"


def results_table(rows: list[dict]) -> str:
    """Markdown table of the final numbers (mean ± std over seeds) and the failed runs."""
    cols = [("iterations", "iterations", 4), ("its_per_s", "it/s", 3),
            ("accuracy", "accuracy", 3), ("completeness", "completeness", 3),
            ("overall", "Chamfer overall", 3), ("pits", "pits", 3), ("thin", "thin parts", 3),
            ("psnr_heldout", "PSNR held-out (dB)", 3),
            ("peak_mem_mb", "peak mem (MB)", 4), ("sample_dist_final", "sample dist", 3)]
    lines = ["| scene | sampler | budget (s) | seeds | " + " | ".join(c[1] for c in cols) + " |",
             "|---" * (4 + len(cols)) + "|"]
    groups = _groups(rows)
    for scene in sorted(groups):
        for sampler in sorted(groups[scene]):
            for budget in sorted(groups[scene][sampler]):
                rs = groups[scene][sampler][budget]
                cells = [_fmt((r[k] for r in rs), d) for k, _, d in cols]
                lines.append(f"| {scene} | {sampler} | {budget:g} | {len(rs)} | "
                             + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    text += ("\nChamfer distances and sample distances in world units (mean ± sample std over "
             "seeds; pits and thin parts: over the scene's features of that kind); PSNR over "
             "the foreground of the held-out views.\n")
    text += paired_differences(rows)
    text += iteration_matched_effect(rows)
    failed = [r for r in rows if r["status"] != "done"]
    if failed:
        text += "\nFailed runs:\n\n"
        text += "".join(f"- `{r['run_dir']}`: {r['error']}\n" for r in failed)
    return text


def paired_differences(rows: list[dict], reference: str = "hvs") -> str:
    """Markdown: each sampler against `reference` in runs that differ only in the sampler.

    A pair is two done runs with the same scene, budget and seed. Per sampler: the number of
    pairs, in how many the sampler's Chamfer is lower, the mean and range of the Chamfer
    difference (sampler - reference; negative favours the sampler), the mean ratio of
    iterations reached (load and per-step cost move it under a wall-clock budget), and the
    two-sided sign-test p-value of "lower as often as higher". Empty when there are no pairs.
    """
    from neus_l0.evaluation.paired import sign_test_p

    done = {(r["scene"], r["sampler"], r["budget_s"], r["seed"]): r for r in _done(rows)}
    samplers = sorted({k[1] for k in done} - {reference})
    lines = []
    for sampler in samplers:
        diffs, ratios = [], []
        for (scene, s, budget, seed), r in done.items():
            ref = done.get((scene, reference, budget, seed))
            if s != sampler or ref is None or r["overall"] is None or ref["overall"] is None:
                continue
            diffs.append(r["overall"] - ref["overall"])
            if r.get("iterations") and ref.get("iterations"):
                ratios.append(r["iterations"] / ref["iterations"])
        if not diffs:
            continue
        n, wins = len(diffs), sum(d < 0 for d in diffs)
        p = sign_test_p(wins, n)
        d = np.array(diffs)
        ratio = f"{np.mean(ratios):.2f}" if ratios else "–"
        lines.append(f"| {sampler} | {n} | {wins} | {d.mean():+.3f} | {d.min():+.3f} .. "
                     f"{d.max():+.3f} | {ratio} | {p:.3g} |")
    if not lines:
        return ""
    head = (f"\nPaired runs (same scene, budget and seed), each sampler against `{reference}`"
            " (Chamfer difference = sampler - reference; negative favours the sampler):\n\n"
            "| sampler | pairs | lower Chamfer in | mean difference | range | iterations ratio"
            " | sign-test p |\n|---|---|---|---|---|---|---|\n")
    return head + "\n".join(lines) + "\n"


def iteration_matched_effect(rows: list[dict], reference: str = "hvs") -> str:
    """Markdown: each sampler's Chamfer offset against `reference` at equal iterations.

    Wall-clock budgets mix the sampler's effect with the iterations each run got (machine
    load, per-step cost). This fits, over every done run of `reference` and the sampler,

        overall = a_scene + b_scene * log(iterations) + g * [sampler],

    by least squares (a line in log-iterations per scene, shared by both samplers) and
    reports g (negative: the sampler's Chamfer is lower at the same iteration count) with
    its standard error and the residual degrees of freedom. Empty when the fit has no
    degrees of freedom left.
    """
    lines = []
    samplers = sorted({r["sampler"] for r in _done(rows)} - {reference})
    for sampler in samplers:
        rs = [r for r in _done(rows) if r["sampler"] in (reference, sampler)
              and r.get("overall") is not None and r.get("iterations")
              and math.isfinite(r["overall"])]
        scenes = sorted({r["scene"] for r in rs})
        if not rs or len({r["sampler"] for r in rs}) < 2:
            continue
        X = np.zeros((len(rs), 2 * len(scenes) + 1))
        y = np.array([r["overall"] for r in rs], dtype=float)
        for i, r in enumerate(rs):
            j = scenes.index(r["scene"])
            X[i, 2 * j] = 1.0
            X[i, 2 * j + 1] = math.log(r["iterations"])
            X[i, -1] = float(r["sampler"] == sampler)
        dof = len(rs) - np.linalg.matrix_rank(X)
        if dof <= 0:
            continue
        coef, *_ = np.linalg.lstsq(X, y, rcond=None)
        resid = y - X @ coef
        sigma2 = float(resid @ resid) / dof
        cov = sigma2 * np.linalg.pinv(X.T @ X)
        se = math.sqrt(max(cov[-1, -1], 0.0))
        lines.append(f"| {sampler} | {len(rs)} | {len(scenes)} | {coef[-1]:+.3f} | {se:.3f} "
                     f"| {dof} |")
    if not lines:
        return ""
    head = (f"\nIteration-matched offset against `{reference}` (least squares over all runs: "
            "Chamfer = scene intercept + scene slope x log(iterations) + offset x [sampler]; "
            "negative favours the sampler):\n\n"
            "| sampler | runs | scenes | offset | std. error | residual dof |\n"
            "|---|---|---|---|---|---|\n")
    return head + "\n".join(lines) + "\n"


def write_plots(out_dir: str | Path, rows: list[dict] | None = None) -> list[Path]:
    """Write every figure and table.md into ``out_dir/plots/``; return their paths."""
    out_dir = Path(out_dir)
    rows = read_results(out_dir) if rows is None else rows
    plots = out_dir / "plots"
    plots.mkdir(parents=True, exist_ok=True)
    written = [
        plot_metric_vs_time(rows, "overall", "Chamfer overall (world units)",
                            plots / "chamfer_vs_time.png"),
        plot_metric_vs_time(rows, "psnr_heldout", "held-out PSNR (dB)",
                            plots / "psnr_vs_time.png"),
        plot_metric_vs_iterations(rows, "overall", "Chamfer overall (world units)",
                                  plots / "chamfer_vs_iterations.png"),
        plot_sample_distance(out_dir, rows, plots / "sample_distance.png"),
        atomic_write_text(plots / "table.md", results_table(rows)),
    ]
    for metric, label in (("pits", "pits"), ("thin", "thin parts")):
        if len(_finite(r.get(metric) for r in _done(rows))):
            written.append(plot_metric_vs_time(rows, metric, f"Chamfer over the {label} "
                                               "(world units)", plots / f"{metric}_vs_time.png"))
    return written
