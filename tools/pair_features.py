"""Pair two `neus-l0 bench` sweeps run by run (a remedy off, then on) on the total Chamfer
and on every feature's error, with the exact sign test.

Usage:
    python tools/pair_features.py OFF_DIR[,OFF_DIR2] ON_DIR[,ON_DIR2] [--metric overall|...]
        [--eval NAME]

Both sweeps ran the same scenes, samplers, budgets and seeds (so their run folders share
names, ``OFF_DIR/runs/NAME`` against ``ON_DIR/runs/NAME``) and differ in one setting, e.g.
``train.error_map.fraction=0.5``. Either side may be several folders, comma-separated (two
chains that ran different seeds side by side); a run name found twice on one side is refused.
Each run's ``eval.json`` holds its Chamfer report with the
per-feature errors of a synthetic scene (`neus_l0.evaluation.features`). Prints, per scene
and feature (and ``total``, ``all pits``, ``all thins``: the pooled kinds, also over every
scene together): the mean error off and on, their ratio, the pairs the remedy
won (lower error) of those not tied, and the two-sided sign test's p
(`neus_l0.evaluation.paired.sign_test_p`).

``--eval NAME`` reads each run's ``runs/RUN/NAME`` instead: the JSON of ``neus-l0 eval
MESH --scene SCENE --json RUN/NAME`` on the run re-meshed another way (e.g. the demo's mesh
steps, ``neus-l0 mesh RUN --close-underside --drop-outside-masks``); the scene is named by
the run's name (``SCENE__SAMPLER__...``).
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict
from pathlib import Path

from neus_l0.evaluation.paired import sign_test_p


def run_errors(eval_json: Path, metric: str) -> tuple[str, dict[str, float]]:
    """(scene name, {"total" | feature name: error}) of one run's ``eval.json`` (a bench
    run's record, or a `neus-l0 eval --json` report: ``--eval``)."""
    rec = json.loads(eval_json.read_text())
    if "spec" in rec:
        chamfer = rec.get("chamfer") or {}
        scene = Path(rec["spec"]["scene_dir"]).name
    else:
        chamfer, scene = rec, eval_json.parent.name.split("__")[0]
    out = {"total": chamfer.get(metric, math.nan)}
    feats = chamfer.get("features") or {}
    for f in feats.get("each", []):
        out[f["name"]] = f.get(metric, math.nan)
    for kind, f in (feats.get("by_kind") or {}).items():
        out[f"all {kind}s"] = f.get(metric, math.nan)
    return scene, {k: float(v) if v is not None else math.nan for k, v in out.items()}


def run_files(folders: list[Path], report: str = "eval.json") -> dict[str, Path]:
    """Run name -> its ``eval.json`` (or `report`) over several sweep folders (a name in two
    is an error)."""
    out: dict[str, Path] = {}
    for folder in folders:
        for path in sorted(folder.glob(f"runs/*/{report}")):
            name = path.parent.name
            if name in out:
                raise SystemExit(f"error: run {name} is in both {out[name].parents[2]} and "
                                 f"{folder}: give each run once per side")
            out[name] = path
    return out


def paired_rows(off: Path | list[Path], on: Path | list[Path], metric: str,
                eval_name: str = "eval.json") -> list[dict]:
    """One row per (scene, feature): means, ratio, wins, n and the sign test's p."""
    off_runs = run_files(off if isinstance(off, list) else [off], eval_name)
    on_runs = run_files(on if isinstance(on, list) else [on], eval_name)
    pairs: dict[tuple[str, str], list[tuple[float, float]]] = defaultdict(list)
    for run, a in sorted(off_runs.items()):
        b = on_runs.get(run)
        if b is None:
            continue
        scene, ea = run_errors(a, metric)
        _, eb = run_errors(b, metric)
        for name in ea.keys() & eb.keys():
            if math.isfinite(ea[name]) and math.isfinite(eb[name]):
                pairs[(scene, name)].append((ea[name], eb[name]))
                if name == "total" or name.startswith("all "):
                    pairs[("every scene", name)].append((ea[name], eb[name]))
    rows = []
    for (scene, name), vals in sorted(pairs.items()):
        wins = sum(b < a for a, b in vals)
        n = sum(b != a for a, b in vals)
        mean_off = sum(a for a, _ in vals) / len(vals)
        mean_on = sum(b for _, b in vals) / len(vals)
        rows.append({"scene": scene, "feature": name, "pairs": len(vals), "off": mean_off,
                     "on": mean_on, "on/off": mean_on / mean_off if mean_off else math.nan,
                     "wins": f"{wins}/{n}", "p": sign_test_p(wins, n)})
    return rows


def markdown_table(rows: list[dict], off: str = "off", on: str = "on") -> list[str]:
    """`paired_rows`' rows as a Markdown table, the arms' columns named `off` and `on`."""
    return [f"| scene | feature | pairs | {off} | {on} | {on}/{off} | {on} wins | sign test p |",
            "|---|---|---:|---:|---:|---:|---:|---:|",
            *(f"| {r['scene']} | {r['feature']} | {r['pairs']} | {r['off']:.3f} | "
              f"{r['on']:.3f} | {r['on/off']:.2f} | {r['wins']} | {r['p']:.3f} |" for r in rows)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("off", help="the sweep(s) with the remedy off, comma-separated")
    ap.add_argument("on", help="the sweep(s) with the remedy on, comma-separated")
    ap.add_argument("--metric", default="overall",
                    choices=("overall", "completeness", "accuracy"))
    ap.add_argument("--eval", default="eval.json", dest="eval_name",
                    help="each run's report to read: a `neus-l0 eval --json` file in the run "
                         "folder (default: the bench's eval.json)")
    args = ap.parse_args()
    rows = paired_rows([Path(f) for f in args.off.split(",") if f],
                       [Path(f) for f in args.on.split(",") if f], args.metric, args.eval_name)
    print("\n".join(markdown_table(rows)))


if __name__ == "__main__":
    main()
