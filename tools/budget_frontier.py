"""Chamfer against budget (issue #34): `--budget` runs against the fixed `demo` config, at
equal end-to-end time, median over seeds, per scene.

Usage:
    python tools/budget_frontier.py PLAN_DIR[,PLAN_DIR2] DEMO_DIR [--out DIR]

PLAN_DIR is a `neus-l0 bench --plan` sweep (each budget a `train.budget`: the iterations
planned from the measured step rate, the schedule finished); DEMO_DIR the same scenes and
seeds without `--plan` (the `demo` config's 3500 iterations, cut by `train.max_seconds`
where it runs longer). A run's end-to-end seconds are read from its folder: from the spec
the sweep wrote before starting it to its final checkpoint (start-up, compile, steps and
the checkpoint; not the mesh or the scoring). Several plan folders (comma-separated) merge
seed by seed: a run (scene, budget, seed) of a later folder replaces the same run of an
earlier one (a re-run after a fix), and seeds that ran in different folders join (two
chains side by side).

Prints a markdown table (also DIR/frontier.md) and draws DIR/budget_frontier.png: per scene,
the median Chamfer of the budget runs at each budget (bars: min and max over seeds) and the
fixed demo's arms at their end-to-end times. "At equal time" compares a budget with the
demo arm that scored best among those that took at most the budget (+5 %) end to end; where
every demo arm took longer, with the shortest one (the demo was given more time).
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections import defaultdict
from pathlib import Path

from neus_l0.evaluation.features import kind_overall


def run_record(eval_json: Path) -> dict | None:
    """scene, seed, budget, iterations, overall, pit and thin Chamfer, end-to-end seconds of
    one finished run (None when it has no score or no final checkpoint)."""
    rec = json.loads(eval_json.read_text())
    run = eval_json.parent
    ckpts = sorted((run / "checkpoints").glob("ckpt_*.pt"))
    chamfer = rec.get("chamfer") or {}
    if not ckpts or chamfer.get("overall") is None:
        return None
    spec = rec["spec"]
    return {"scene": Path(spec["scene_dir"]).name, "seed": spec["seed"],
            "budget": spec["budget_s"], "iterations": rec["row"]["iterations"],
            "overall": chamfer["overall"],
            "pit": kind_overall(chamfer, "pit"), "thin": kind_overall(chamfer, "thin"),
            "wall": ckpts[-1].stat().st_mtime - (run / "spec.json").stat().st_mtime}


def arms(folder: Path) -> dict[tuple[str, float], list[dict]]:
    """(scene, budget) -> the finished runs of a bench folder."""
    out: dict[tuple[str, float], list[dict]] = defaultdict(list)
    for path in sorted(folder.glob("runs/*/eval.json")):
        rec = run_record(path)
        if rec is not None:
            out[(rec["scene"], rec["budget"])].append(rec)
    return out


def merge(into: dict, later: dict) -> dict:
    """`into` with `later`'s runs added, a later run replacing the same (scene, budget, seed)."""
    for key, runs in later.items():
        kept = {r["seed"]: r for r in into.get(key, [])}
        kept.update({r["seed"]: r for r in runs})
        into[key] = [kept[s] for s in sorted(kept)]
    return into


def median(runs: list[dict], key: str) -> float:
    vals = [r[key] for r in runs if r[key] is not None]
    return statistics.median(vals) if vals else float("nan")


def _spread(runs: list[dict]) -> str:
    vals = sorted(r["overall"] for r in runs)
    return f"{median(runs, 'overall'):.3f} [{vals[0]:.2f}-{vals[-1]:.2f}]"


def demo_at(demo: dict, scene: str, seconds: float) -> tuple[float, list[dict]] | None:
    """The fixed demo arm for `scene` with the lowest median Chamfer among those that took
    at most `seconds` (+5 %) end to end, else the shortest; (its budget, its runs)."""
    options = sorted(((median(runs, "wall"), b, runs) for (s, b), runs in demo.items()
                      if s == scene), key=lambda t: t[0])
    if not options:
        return None
    fitting = [o for o in options if o[0] <= 1.05 * seconds]
    _, budget, runs = (min(fitting, key=lambda o: median(o[2], "overall")) if fitting
                       else options[0])
    return budget, runs


def table(plan: dict, demo: dict) -> str:
    """The markdown table: one row per (scene, budget)."""
    lines = ["| scene | budget | seeds | iterations | end to end | Chamfer (median [min-max]) "
             "| pits | thin | demo at equal time: arm, end to end, Chamfer | budget lower in |",
             "|---|---:|---:|---:|---:|---|---:|---:|---|---:|"]
    for (scene, budget), runs in sorted(plan.items()):
        pit, thin = (f"{v:.2f}" if v == v else "-" for v in (median(runs, "pit"),
                                                            median(runs, "thin")))
        row = (f"| {scene} | {budget:g} s | {len(runs)} | {median(runs, 'iterations'):.0f} | "
               f"{median(runs, 'wall'):.1f} s | {_spread(runs)} | {pit} | {thin} |")
        found = demo_at(demo, scene, budget)
        if found is None:
            lines.append(row + " - | - |")
            continue
        b, druns = found
        by_seed = {r["seed"]: r["overall"] for r in druns}
        pairs = [(r["overall"], by_seed[r["seed"]]) for r in runs if r["seed"] in by_seed]
        won = sum(a < d for a, d in pairs)
        lines.append(row + f" max_seconds {b:g}: {median(druns, 'wall'):.1f} s, "
                           f"{_spread(druns)} | {won} of {len(pairs)} |")
    return "\n".join(lines)


def plot(plan: dict, demo: dict, path: Path) -> Path:
    """Per scene: median Chamfer (min-max bars) against median end-to-end seconds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = sorted({s for s, _ in plan} | {s for s, _ in demo})
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.2 * len(scenes), 3.6), squeeze=False)
    for ax, scene in zip(axes[0], scenes, strict=True):
        for data, label, style in ((plan, "--budget (planned)", "o-"),
                                   (demo, "demo (3500 it., cut)", "s--")):
            pts = sorted((median(r, "wall"), median(r, "overall"),
                          min(x["overall"] for x in r), max(x["overall"] for x in r))
                         for (s, _), r in data.items() if s == scene)
            if pts:
                x, y, lo, hi = zip(*pts, strict=True)
                ax.errorbar(x, y, yerr=[[a - b for a, b in zip(y, lo, strict=True)],
                                        [b - a for a, b in zip(y, hi, strict=True)]],
                            fmt=style, capsize=3, label=label)
        ax.set_xscale("log")
        ax.minorticks_off()
        ax.set_xticks([40, 60, 120, 240, 600, 1200])
        ax.set_xticklabels(["40", "60", "120", "240", "600", "1200"])
        ax.set_title(scene)
        ax.set_xlabel("end-to-end seconds (1 thread)")
        ax.set_ylabel("Chamfer (median of seeds)")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("plan", help="`neus-l0 bench --plan` folders, comma-separated")
    ap.add_argument("demo", type=Path, help="the same sweep without --plan")
    ap.add_argument("--out", type=Path, default=None, help="folder for frontier.md and the plot")
    args = ap.parse_args()
    plan = {}
    for folder in str(args.plan).split(","):
        merge(plan, arms(Path(folder)))
    demo = arms(args.demo)
    text = table(plan, demo)
    print(text)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "frontier.md").write_text(text + "\n")
        print(plot(plan, demo, args.out / "budget_frontier.png"))


if __name__ == "__main__":
    main()
