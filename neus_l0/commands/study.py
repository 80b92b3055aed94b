"""`neus-l0 study sampling|fork --out DIR`: studies of the sampler.

`sampling`: the oracle study on analytic SDFs (outside training). `fork`: the samplers
compared on the same sharp field late in training (`neus_l0.experiments.fork`).
"""

from __future__ import annotations

import argparse

from neus_l0.commands._overrides import accept_overrides


def _list(text: str) -> list[str]:
    return [s.strip() for s in text.split(",") if s.strip()]


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(
        name, help="studies of the sampler: oracle sampling on analytic SDFs, or the fork "
                   "study late in training",
        description="`sampling`: NeuS's up-sampling run exactly on analytic SDFs (sphere, "
                    "grazing planes, pits, rods, fins, the synthetic scenes) with every "
                    "sampler, three budgets and two sharpness regimes; writes sampling.csv, "
                    "summary.md and heat maps into DIR. `fork`: per scene and seed, train "
                    "one hvs run to --base-iters, then continue copies of it for --arm-iters "
                    "with each sampler from the same checkpoint (neus-l0 train --stop-at, "
                    "then --resume --change-config sampler=...), and score each (Chamfer, "
                    "pits and thin parts, the fine samples' distance to the true surface, "
                    "held-out PSNR); writes fork.csv and summary.md (paired against hvs "
                    "with t intervals and sign tests) into DIR. `frontier`: from `neus-l0 "
                    "bench --snapshots N` folders (one per sample budget), Chamfer against "
                    "training time per sampler and budget, and whether any reaches hvs's "
                    "Chamfer at the largest budget sooner; writes frontier.csv, summary.md "
                    "and frontier.png. docs/BENCHMARKS.md reads them.")
    p.add_argument("study", choices=["sampling", "fork", "frontier"], help="which study")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the results")
    p.add_argument("--rays", type=int, default=128, help="sampling: rays per shape (128)")
    p.add_argument("--quick", action="store_true",
                   help="sampling: 4 shapes, 16 rays, the 16+16 budget, sharp regime only "
                        "(seconds)")
    p.add_argument("--scenes", type=_list, default=["demo", "pits-and-thin"], metavar="A,B",
                   help="fork: built-in scenes or synthetic scene folders (default "
                        "demo,pits-and-thin)")
    p.add_argument("--seeds", type=lambda t: [int(x) for x in _list(t)], default=[0, 1, 2],
                   metavar="S1,S2", help="fork: training seeds (default 0,1,2)")
    p.add_argument("--arms", type=_list, default=None, metavar="A,B",
                   help="fork: arms (default: hvs, l0, 'l0 interp' (the paper's draw), "
                        "l0-inverse, neus-exact)")
    p.add_argument("--conf", default="demo", help="fork: config of every run (demo)")
    p.add_argument("--base-iters", type=int, default=2500,
                   help="fork: iterations of the hvs base run (2500)")
    p.add_argument("--arm-iters", type=int, default=1000,
                   help="fork: iterations of each arm after the fork (1000)")
    p.add_argument("--threads", type=int, default=1,
                   help="fork: torch CPU threads per training and for scoring (1)")
    p.add_argument("--bench", type=_list, default=None, metavar="DIR1,DIR2",
                   help="frontier: `neus-l0 bench --snapshots N` folders, one per sample "
                        "budget (render.n_samples / n_importance overrides)")
    p.add_argument("--resolution", type=int, default=128,
                   help="fork: marching-cubes resolution of each scored mesh (128)")
    p.add_argument("--eval-density", type=float, default=0.5,
                   help="fork: Chamfer sampling density in world units (0.5, the synthetic "
                        "scenes' point spacing)")
    accept_overrides(p)
    return p


#: What the studies write at the top of their folder (sampling, fork, frontier).
STUDY_NAMES = ("sampling.csv", "summary.md", "within_0.01.png", "depth_err.png", "scenes",
               "runs", "fork.csv", "fork.json", "frontier.csv", "frontier.png", ".lock")


def run(args: argparse.Namespace) -> int:
    import time
    from pathlib import Path

    from neus_l0.commands._paths import check_output_dir
    from neus_l0.errors import NeusL0Error

    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise NeusL0Error(f"{out}: cannot create the output folder ({exc.strerror})") from None
    check_output_dir(out, "--out", (), STUDY_NAMES, "a study folder")
    if args.study == "fork":
        return _fork(args, out)
    if args.study == "frontier":
        from neus_l0.experiments.frontier import write_outputs

        if not args.bench:
            raise NeusL0Error("study frontier needs --bench DIR1,DIR2,...")
        print(write_outputs(args.bench, out))
        print(f"wrote {out}/frontier.csv, summary.md, frontier.png")
        return 0
    if args.overrides:
        raise NeusL0Error(f"{' '.join(args.overrides)}: config overrides are for the fork "
                          "study")
    from neus_l0.atomic import atomic_write_text
    from neus_l0.experiments import oracle_report as report
    from neus_l0.experiments.oracle import BUDGETS, REGIMES, run_study

    if args.rays < 1:
        raise NeusL0Error(f"--rays {args.rays}: must be >= 1")
    t0 = time.perf_counter()
    if args.quick:
        rows = run_study(min(args.rays, 16),
                         cases=["sphere", "plane 80deg", "pit r0.05 d0.2", "rod r0.02"],
                         budgets=BUDGETS[:1], regimes={"sharp": REGIMES["sharp"]})
    else:
        rows = run_study(args.rays)
    report.write_csv(out / "sampling.csv", rows)
    text = "\n".join(report.summary(rows, m) for m in (report.HEADLINE, "within_0.003"))
    atomic_write_text(out / "summary.md", text)
    report.plot(out / "within_0.01.png", rows)
    report.plot(out / "depth_err.png", rows, "depth_err")
    print(text)
    print(f"wrote {out}/sampling.csv, summary.md, within_0.01.png, depth_err.png "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0


def _fork(args: argparse.Namespace, out) -> int:
    import time

    from neus_l0.experiments.fork import ARMS, ForkSpec, run_study

    spec = ForkSpec(out_dir=out, scenes=args.scenes, seeds=args.seeds,
                    arms=args.arms or tuple(ARMS), conf=args.conf,
                    overrides=list(args.overrides), base_iters=args.base_iters,
                    arm_iters=args.arm_iters, threads=args.threads,
                    resolution=args.resolution, eval_density=args.eval_density)
    spec.check()
    t0 = time.perf_counter()
    run_study(spec)
    print((out / "summary.md").read_text())
    print(f"wrote {out}/fork.csv, fork.json, summary.md ({time.perf_counter() - t0:.0f} s)")
    return 0
