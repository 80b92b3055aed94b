"""Chamfer against wall-clock: NeuS's settings and the fast configuration side by side.

Usage:
    python tools/bench_fast_vs_neus.py --scenes pits-and-thin,/path/to/bunny --out DIR \
        [--neus-conf wmask --neus-sampler hvs --neus-seconds 480] \
        [--fast-conf fast --fast-sampler hvs --fast-seconds 120] [--snapshots-per-run 4] \
        [--budget 60] [--seed 0] [--device cpu|cuda] [--threads N] [--resolution 128] \
        [--eval-density 0.5] [--views 24 --width 200 --height 150] [--holdout 0] \
        [--timeout S] [--arms fast,budget,neus] [--neus-set KEY=VALUE ...] \
        [--fast-set KEY=VALUE ...] [override ...]

Per scene (a built-in name, synthesised into DIR/scenes/ at --views/--width/--height, or a
scene folder such as one made by ``neus-l0 synth MESH DIR``), two runs one after the other,
each in its own process (`neus_l0.experiments.runner`): the ``fast`` arm, then the ``neus`` arm.
Each trains for its wall-clock budget (``train.max_seconds``: the training loop only) with
snapshot checkpoints at budget * k / n (k = 1..n, n = --snapshots-per-run); after training,
each snapshot's mesh is extracted at --resolution and scored, so each arm has a curve of
Chamfer against training time. Overrides (``key=value``) apply to both arms, --neus-set /
--fast-set to one; each arm's config is resolved once, here.

Outputs in DIR: ``runs/<scene>__<arm>/`` (the runner's layout: eval.json with ``curve``),
``summary.json``, ``table.md`` (per scene and arm: budget, iterations, it/s, peak memory,
final mesh extraction time, Chamfer at the end; each arm's curve; the verdict: NeuS's final
Chamfer, the fast arm's at its budget, when the fast arm first reaches NeuS's final Chamfer,
whether it is still improving), ``chamfer_vs_time.png``, and results.csv / results.json.
Re-running on DIR skips the runs already done with the same settings (and refuses a done
run made with other settings); failed runs are recorded and run again. ``--arms`` runs only
the arms it names and reads the others as their folders hold them: on a GPU lent by the call,
``--arms neus --neus-seconds 480 --timeout 585`` fits NeuS's arm (8 minutes of training, its
compile included, then meshing and scoring) in one 600 s call.

With ``--budget SECONDS`` a third arm, ``budget``, trains the fast arm's config with
``train.budget`` (the whole run within SECONDS, its schedule planned and finished; see
`neus_l0.train.budget`) and is scored at its end.

The issue's target (on one H100, 49 views of 400x300 with masks): the fast arm reaches in
<= 120 s the Chamfer the NeuS arm reaches in 480 s, and is still improving; the budget arm
reaches it in a 60 s budget (issue #34). On a CPU give smaller budgets and
``--fast-conf demo``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from neus_l0.atomic import atomic_write_json, atomic_write_text
from neus_l0.errors import NeusL0Error
from neus_l0.experiments import arms
from neus_l0.experiments.results import collect_rows, write_results
from neus_l0.experiments.runner import BENCH_OVERRIDES, RunSpec, run_in_subprocess
from neus_l0.experiments.sweep import is_done, prepare_scene

#: The two arms, in the order they run on each scene.
ARMS = ("fast", "neus")
#: Spec fields that may differ between invocations on the same folder (paths).
UNCHECKED = ("out_dir", "scene_dir")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=__doc__.split("\n", 2)[2])
    p.add_argument("--scenes", required=True,
                   help="comma-separated built-in scene names or scene folders")
    p.add_argument("--out", required=True, help="output folder DIR")
    for arm, conf, sampler, seconds in (("neus", "wmask", "hvs", 480.0),
                                        ("fast", "fast", "hvs", 120.0)):
        p.add_argument(f"--{arm}-conf", default=conf, help=f"{arm} arm's config ({conf})")
        p.add_argument(f"--{arm}-sampler", default=sampler,
                       help=f"{arm} arm's sampler ({sampler})")
        p.add_argument(f"--{arm}-seconds", type=float, default=seconds,
                       help=f"{arm} arm's training budget in seconds ({seconds:g})")
        p.add_argument(f"--{arm}-set", action="append", default=[], metavar="KEY=VALUE",
                       help=f"an override for the {arm} arm only (repeatable)")
    p.add_argument("--budget", type=float, default=0.0, metavar="SECONDS",
                   help="add a third arm per scene, 'budget': the fast arm's config trained "
                        "with train.budget=SECONDS (iterations planned from the measured "
                        "step rate, start-up and compile counted; scored at its end)")
    p.add_argument("--arms", default=None, metavar="ARM,...",
                   help="run only these arms (fast, budget, neus; default: all): the others "
                        "are read as their folders hold them, so that one long arm can run "
                        "in a call of its own")
    p.add_argument("--snapshots-per-run", type=int, default=4,
                   help="snapshots per run at budget*k/n, the last at the budget (4)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads per run (default: torch's)")
    p.add_argument("--resolution", type=int, default=128, help="marching-cubes resolution")
    p.add_argument("--eval-density", type=float, default=0.5,
                   help="Chamfer sampling density (world units)")
    p.add_argument("--views", type=int, default=24)
    p.add_argument("--width", type=int, default=200)
    p.add_argument("--height", type=int, default=150)
    p.add_argument("--holdout", type=int, default=0,
                   help="hold out every K-th view for PSNR (0: train on all views)")
    p.add_argument("--sample-rays", type=int, default=256,
                   help="rays of the fine-sample distance probe")
    p.add_argument("--timeout", type=float, default=None,
                   help="seconds after which a run's process is killed")
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                   help="config overrides for both arms")
    return p.parse_args(argv)


def snapshot_marks(budget: float, n: int) -> list[float]:
    """``budget * k / n`` for k = 1..n."""
    return [budget * k / n for k in range(1, n + 1)]


def _check_args(args: argparse.Namespace) -> None:
    for arm in ARMS:
        if not getattr(args, f"{arm}_seconds") > 0:
            raise NeusL0Error(f"--{arm}-seconds must be positive")
    if args.budget < 0:
        raise NeusL0Error("--budget must be positive (or 0: no budget arm)")
    chosen = _chosen_arms(args)
    if not chosen:
        raise NeusL0Error("--arms: name at least one of fast, budget, neus")
    if "budget" in chosen and not args.budget:
        raise NeusL0Error("--arms budget needs --budget SECONDS")
    if args.snapshots_per_run < 1:
        raise NeusL0Error("--snapshots-per-run must be at least 1")
    for o in [*args.overrides, *args.neus_set, *args.fast_set]:
        key = o.split("=", 1)[0]
        if key in ("sampler", "train.seed", "train.max_seconds"):
            raise NeusL0Error(f"override {o}: set it with --*-sampler, --seed or "
                              "--*-seconds instead")


def _chosen_arms(args: argparse.Namespace) -> set[str]:
    """The arms this invocation runs (`--arms`; all when not given); an unknown name raises."""
    every = {*ARMS, *(("budget",) if args.budget else ())}
    if args.arms is None:
        return every
    names = {a.strip() for a in args.arms.split(",") if a.strip()}
    unknown = names - {*ARMS, "budget"}
    if unknown:
        raise NeusL0Error(f"--arms: unknown arm {', '.join(sorted(unknown))} "
                          "(fast, budget, neus)")
    return names


def build_specs(args: argparse.Namespace, out: Path) -> list[RunSpec]:
    """One `RunSpec` per (scene, arm): per scene the fast arm, the budget arm if any, then NeuS."""
    from neus_l0.config.load import load_config, to_dict

    arm_cfg = {}
    for arm in ARMS:
        conf, sampler = getattr(args, f"{arm}_conf"), getattr(args, f"{arm}_sampler")
        overrides = [*args.overrides, *getattr(args, f"{arm}_set")]
        cfg = load_config(conf, [*BENCH_OVERRIDES, *overrides, f"sampler={sampler}"])
        arm_cfg[arm] = (conf, sampler, overrides, to_dict(cfg))
    entries = [s.strip() for s in args.scenes.split(",") if s.strip()]
    if not entries:
        raise NeusL0Error("--scenes: give at least one scene")
    resolved = [prepare_scene(e, out, args.views, args.width, args.height) for e in entries]
    names = [n for n, _ in resolved]
    if len(set(names)) != len(names):
        raise NeusL0Error(f"--scenes: two scenes share a name ({', '.join(names)})")
    specs = []
    for scene, folder in resolved:
        for arm in ARMS:
            conf, sampler, overrides, config = arm_cfg[arm]
            budget = float(getattr(args, f"{arm}_seconds"))
            specs.append(RunSpec(
                name=f"{scene}__{arm}", scene=scene, scene_dir=str(folder), sampler=sampler,
                budget_s=budget, seed=args.seed, out_dir=str(out), conf=str(conf),
                overrides=overrides, device=args.device, threads=args.threads,
                holdout=args.holdout, resolution=args.resolution,
                eval_density=args.eval_density, sample_rays=args.sample_rays, config=config,
                snapshots=snapshot_marks(budget, args.snapshots_per_run), label=arm))
        if args.budget:  # before the NeuS arm: the longest run goes last
            specs.insert(len(specs) - 1, _budget_spec(specs[-2], args.budget))
    return specs


def _budget_spec(fast: RunSpec, seconds: float) -> RunSpec:
    """The budget arm: the fast arm's run with ``train.budget`` in place of its cut-off."""
    return dataclasses.replace(fast, name=fast.name.replace("__fast", "__budget"),
                               budget_s=float(seconds), snapshots=[], planned=True,
                               label="budget")


def _same_spec(spec: RunSpec) -> bool:
    """Whether the run folder's spec.json describes `spec` (paths aside; the configs compared
    by their non-default keys, so a key the schema gained at its default still matches)."""
    from neus_l0.config.load import non_default, to_dict
    from neus_l0.config.schema import Config

    try:
        old = json.loads((spec.run_dir / "spec.json").read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return False
    new = json.loads(json.dumps(dataclasses.asdict(spec)))  # tuples -> lists, as stored
    defaults = json.loads(json.dumps(to_dict(Config())))

    def comparable(d: dict) -> dict:
        d = {k: v for k, v in d.items() if k not in UNCHECKED}
        if isinstance(d.get("config"), dict):
            d["config"] = non_default(d["config"], defaults)
        return d

    return comparable(old) == comparable(new)


def write_summary(out: Path, specs: list[RunSpec], machine: dict, argv: list[str]) -> dict:
    """Write summary.json, table.md, chamfer_vs_time.png and results.csv; return the summary."""
    scenes: dict[str, dict] = {}
    for spec in specs:
        arm = arms.read_arm(spec.run_dir)
        entry = scenes.setdefault(spec.scene, {"scene_dir": spec.scene_dir, "arms": {}})
        entry["arms"][spec.label] = arms.arm_summary(arm, spec.conf, spec.sampler,
                                                     spec.budget_s)
        entry["arms"][spec.label]["run_dir"] = f"runs/{spec.name}"
    for entry in scenes.values():
        a = entry["arms"]
        entry["verdict"] = arms.verdict(a.get("neus", {}).get("curve", []),
                                        a.get("fast", {}).get("curve", []))
        if "budget" in a:  # the same comparison for the budget arm (its end point)
            entry["budget_verdict"] = arms.verdict(a.get("neus", {}).get("curve", []),
                                                   a["budget"].get("curve", []))
    table = arms.summary_table(scenes)
    summary = {"machine": machine, "command": ["tools/bench_fast_vs_neus.py", *argv],
               "scenes": scenes, "table": table}
    atomic_write_json(out / "summary.json", summary)
    atomic_write_text(out / "table.md", table + "\n" + arms.machine_line(machine) + "\n")
    arms.plot_curves(scenes, out / "chamfer_vs_time.png")
    write_results(out, collect_rows(out))
    return summary


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; 0 when every run of `--arms` is done, 1 when one failed, 2 on a user
    error."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    out = Path(args.out).resolve()
    try:
        _check_args(args)
        out.mkdir(parents=True, exist_ok=True)
        specs = build_specs(args, out)
        chosen = _chosen_arms(args)
        stale = [s.name for s in specs
                 if s.label in chosen and is_done(s.run_dir) and not _same_spec(s)]
        if stale:
            raise NeusL0Error(f"{out}: runs {', '.join(stale)} were made with other settings; "
                              "use another --out so that the arms stay comparable")
    except NeusL0Error as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    machine = arms.machine_info(args.device)
    print(arms.machine_line(machine), flush=True)
    for spec in specs:
        if spec.label not in chosen:
            print(f"{spec.name}: not in --arms, read as its folder holds it", flush=True)
            continue
        if is_done(spec.run_dir):
            print(f"{spec.name}: done before, skipped", flush=True)
            continue
        print(f"{spec.name}: {spec.conf}, sampler {spec.sampler}, {spec.budget_s:g} s, "
              f"snapshots at {', '.join(f'{m:g}' for m in spec.snapshots)} s ...", flush=True)
        row = run_in_subprocess(spec, args.timeout)
        print(f"{spec.name}: {row['status']}"
              + (f" ({row['error']})" if row["error"] else
                 f", {row['iterations']} iterations, Chamfer {row['overall']}"), flush=True)
        write_summary(out, specs, machine, argv)
    summary = write_summary(out, specs, machine, argv)
    print()
    print(summary["table"])
    print(arms.machine_line(machine))
    print(f"written: {out / 'summary.json'}, {out / 'table.md'}, "
          f"{out / 'chamfer_vs_time.png'}")
    done = all(a["status"] == "done" for s in summary["scenes"].values()
               for label, a in s["arms"].items() if label in chosen)
    return 0 if done else 1


if __name__ == "__main__":
    sys.exit(main())
