"""The budget frontier: Chamfer against wall-clock time for each sampler at each sample
budget, read from `neus-l0 bench --snapshots N` folders (one folder per sample budget, since
a bench folder shares one config).

A run's curve is eval.json's ``curve``: Chamfer at each snapshot mark (``budget * k / N``)
and at its end. The reference is `hvs` at the largest budget (NeuS's own draw at the
sample count a config ships with); the question is whether another (sampler, samples)
reaches the reference's final Chamfer sooner, i.e. with fewer samples per ray and so
cheaper steps. Runs pair by (scene, seed).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from neus_l0.errors import NeusL0Error


def samples_label(config: dict) -> str:
    """``"n_samples+n_importance"`` of a sweep's resolved config."""
    r = config.get("render", {})
    return f"{r.get('n_samples')}+{r.get('n_importance')}"


def read_bench(folder: str | Path) -> list[dict]:
    """The done runs of a bench folder: scene, seed, sampler, samples, budget_s,
    iterations, curve ([(seconds, iteration, overall)], by time).

    Raises:
        NeusL0Error: not a bench folder.
    """
    folder = Path(folder)
    try:
        sweep = json.loads((folder / "sweep.json").read_text())
        rows = json.loads((folder / "results.json").read_text())
    except (OSError, ValueError) as exc:
        raise NeusL0Error(f"{folder}: not a bench folder with results ({exc})") from None
    label = samples_label(sweep["config"])
    out = []
    for r in rows:
        if r.get("status") != "done":
            continue
        ev = json.loads((folder / r["run_dir"] / "eval.json").read_text())
        curve = sorted((float(p["seconds"]), int(p["iteration"]), p.get("overall"))
                       for p in ev.get("curve", []))
        out.append({"scene": r["scene"], "seed": int(r["seed"]), "sampler": r["sampler"],
                    "samples": label, "budget_s": float(r["budget_s"]),
                    "iterations": r.get("iterations"), "overall": r.get("overall"),
                    "curve": curve, "folder": str(folder)})
    return out


def time_to_reach(curve: Sequence[tuple[float, int, float | None]], target: float) -> float:
    """The first time a curve's Chamfer is at or below `target`, linear between its points
    (inf when it never is; the first point counts from time 0 only if it is already there).

    Args:
        curve: [(seconds, iteration, overall)] by time.
    """
    prev = None
    for t, _, c in curve:
        if c is None or not math.isfinite(c):
            continue
        if c <= target:
            if prev is None or prev[1] == c:
                return t
            t0, c0 = prev
            return t0 + (t - t0) * (c0 - target) / (c0 - c)
        prev = (t, c)
    return math.inf


def _key(r: dict) -> tuple[str, str]:
    return r["sampler"], r["samples"]


def _order(arm: tuple[str, str]) -> tuple:
    n = int(arm[1].split("+")[0]) if arm[1].split("+")[0].isdigit() else 0
    return (-n, arm[0] != "hvs", arm[0])


def reference_arm(runs: list[dict]) -> tuple[str, str]:
    """hvs at its largest sample budget."""
    hvs = [_key(r) for r in runs if r["sampler"] == "hvs"]
    if not hvs:
        raise NeusL0Error("the frontier needs hvs runs (its reference)")
    return min(set(hvs), key=_order)


def frontier_rows(runs: list[dict]) -> list[dict]:
    """Per (sampler, samples) and (scene, seed): the final Chamfer, the reference's, and the
    time to reach the reference's final Chamfer (inf: not within the budget)."""
    ref = reference_arm(runs)
    by = {(r["scene"], r["seed"], *_key(r)): r for r in runs}
    out = []
    for r in runs:
        base = by.get((r["scene"], r["seed"], *ref))
        if base is None or base["overall"] is None:
            continue
        out.append({"scene": r["scene"], "seed": r["seed"], "sampler": r["sampler"],
                    "samples": r["samples"], "iterations": r["iterations"],
                    "overall": r["overall"], "reference": base["overall"],
                    "reach_s": time_to_reach(r["curve"], base["overall"]),
                    "budget_s": r["budget_s"], "end_s": r["curve"][-1][0],
                    "marks": [c for _, _, c in r["curve"]]})
    return out


def summary(runs: list[dict]) -> str:
    """Markdown: per (sampler, samples), the iterations and time the runs reached, their final
    Chamfer paired against the reference's, and how often / how soon each reaches the
    reference's final Chamfer (budgets may differ between sample budgets)."""
    from neus_l0.evaluation.paired import compare

    ref = reference_arm(runs)
    rows = frontier_rows(runs)
    arms = sorted({_key(r) for r in rows}, key=_order)
    units = sorted({(r["scene"], r["seed"]) for r in rows})
    by = {(r["scene"], r["seed"], r["sampler"], r["samples"]): r for r in rows}
    lines = [f"Reference: `{ref[0]}` at {ref[1]} samples. Units: {len(units)} (scene, seed). "
             "Chamfer in world units, mean over the units; time counts the loop (steps and the "
             "step's compile from a warm cache), as `train.max_seconds` does.\n",
             "| sampler | samples | units | budget | iterations | time at the end | final "
             "Chamfer | vs reference (%, 95 % CI) | lower in | sign p | vs hvs at the same "
             "samples (%, lower in, p) | reaches the reference in | median time to reach |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for arm in arms:
        rs = [by[(*u, *arm)] for u in units if (*u, *arm) in by]
        c = compare([r["reference"] for r in rs], [r["overall"] for r in rs])
        reach = [r["reach_s"] for r in rs]
        hit = [t for t in reach if math.isfinite(t)]
        med = f"{np.median(reach):.0f} s" if len(hit) * 2 > len(reach) else "–"
        vs = ("(reference)" if arm == ref else
              f"{c['rel']:+.1f} ({c['rel_low']:+.1f} .. {c['rel_high']:+.1f})")
        same = "–"
        if arm[0] != "hvs":
            pairs = [(by[(*u, "hvs", arm[1])]["overall"], by[(*u, *arm)]["overall"])
                     for u in units if (*u, *arm) in by and (*u, "hvs", arm[1]) in by]
            if pairs:
                h = compare(*zip(*pairs))
                same = f"{h['rel']:+.1f}, {h['better']} of {h['n']}, p = {h['p']:.2g}"
        lines.append(f"| {arm[0]} | {arm[1]} | {len(rs)} | {rs[0]['budget_s']:g} s | "
                     f"{np.mean([r['iterations'] for r in rs]):.0f} | "
                     f"{np.mean([r['end_s'] for r in rs]):.0f} s | "
                     f"{np.mean([r['overall'] for r in rs]):.3f} | {vs} | "
                     f"{c['better'] if arm != ref else '–'} | "
                     f"{c['p']:.3g} | {same} | {len(hit)} of {len(rs)} | {med} |")
    return "\n".join(lines) + "\n"


def plot(runs: list[dict], path: str | Path) -> Path:
    """frontier.png: Chamfer against training time per scene, a line per (sampler, samples)
    (mean over seeds at each mark)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from neus_l0.atomic import atomic_write

    scenes = sorted({r["scene"] for r in runs})
    arms = sorted({_key(r) for r in runs}, key=_order)
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.2 * len(scenes), 3.6), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        for sampler, samples in arms:
            rs = [r for r in runs if r["scene"] == scene and _key(r) == (sampler, samples)]
            if not rs:
                continue
            n = min(len(r["curve"]) for r in rs)
            t = [np.mean([r["curve"][k][0] for r in rs]) for k in range(n)]
            c = [np.mean([r["curve"][k][2] for r in rs]) for k in range(n)]
            style = {"8+8": ":", "16+16": "--"}.get(samples, "-")
            ax.plot(t, c, style, marker="o", label=f"{sampler} {samples}")
        ax.set_title(f"{scene} (mean over seeds {sorted({r['seed'] for r in runs})})")
        ax.set_xlabel("training time (s)")
        ax.set_ylabel("Chamfer (world units)")
        ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize=7)
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110))
    plt.close(fig)
    return Path(path)


def write_outputs(benches: Sequence[str | Path], out: str | Path) -> str:
    """Read `benches`, write OUT/frontier.csv, summary.md and frontier.png; the summary."""
    from neus_l0.atomic import atomic_write_text

    runs = [r for b in benches for r in read_bench(b)]
    if not runs:
        raise NeusL0Error(f"{', '.join(map(str, benches))}: no finished runs")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = frontier_rows(runs)
    head = "scene,seed,sampler,samples,iterations,overall,reference,reach_s,marks\n"
    atomic_write_text(out / "frontier.csv", head + "".join(
        f"{r['scene']},{r['seed']},{r['sampler']},{r['samples']},{r['iterations']},"
        f"{r['overall']:.6g},{r['reference']:.6g},{r['reach_s']:.4g},"
        f"{' '.join(f'{m:.6g}' for m in r['marks'] if m is not None)}\n" for r in rows))
    text = summary(runs)
    atomic_write_text(out / "summary.md", text)
    plot(runs, out / "frontier.png")
    return text
