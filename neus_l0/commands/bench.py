"""`neus-l0 bench`: sweep scenes x samplers x budgets x seeds and record time against error."""

from __future__ import annotations

import argparse

from neus_l0.commands._overrides import accept_overrides


def _list(kind):
    def parse(text: str) -> list:
        items = [t.strip() for t in text.split(",") if t.strip()]
        if not items:
            raise argparse.ArgumentTypeError("empty list")
        try:
            return [kind(t) for t in items]
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    return parse


def check_numbers(args: argparse.Namespace) -> None:
    """Refuse an out-of-range number among the flags, naming the flag, before any work."""
    import math

    from neus_l0.errors import NeusL0Error

    def refuse(flag: str, value, rule: str):
        raise NeusL0Error(f"{flag} {value}: {rule}")

    for b in args.seconds:
        if not (math.isfinite(b) and b > 0):
            refuse("--seconds", f"{b:g}", "budgets must be positive, finite seconds")
    for seed in args.seeds:
        if not 0 <= seed < 2**63:
            refuse("--seeds", seed, "seeds must be 0 or more (below 2^63)")
    if args.resolution is not None and args.resolution < 8:
        refuse("--resolution", args.resolution, "must be at least 8")
    if args.threads is not None and args.threads < 0:
        refuse("--threads", args.threads, "must be 0 (torch's default) or more")
    if args.views is not None and args.views < 1:
        refuse("--views", args.views, "must be at least 1")
    for flag, value in (("--width", args.width), ("--height", args.height)):
        if value is not None and value < 8:
            refuse(flag, value, "must be at least 8 pixels")
    if args.holdout < 0 or args.holdout == 1:
        refuse("--holdout", args.holdout, "must be 0 (none) or K >= 2 (1 holds out every view)")
    if args.eval_density is not None and not (math.isfinite(args.eval_density)
                                              and args.eval_density > 0):
        refuse("--eval-density", f"{args.eval_density:g}", "must be a positive, finite "
               "distance in world units")
    if args.sample_rays < 1:
        refuse("--sample-rays", args.sample_rays, "must be at least 1")
    if args.psnr_pixels < 1:
        refuse("--psnr-pixels", args.psnr_pixels, "must be at least 1")
    if args.timeout is not None and not (math.isfinite(args.timeout) and args.timeout > 0):
        refuse("--timeout", f"{args.timeout:g}", "must be positive, finite seconds")
    if args.snapshots < 0:
        refuse("--snapshots", args.snapshots, "must be 0 or more")


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(
        name, help="sweep scenes x samplers x budgets and record time against error",
        description="Train one run per (scene, sampler, budget, seed) with a wall-clock budget "
                    "(train.max_seconds), extract its mesh, score it (Chamfer), render the "
                    "held-out views (PSNR), and log the distance of the up-sampled samples to "
                    "the true surface during training. Every run uses the same config and "
                    "iteration schedule and stops by wall-clock. Results go to "
                    "DIR/results.csv and DIR/results.json, plots to DIR/plots/; re-running "
                    "skips finished runs.")
    p.add_argument("--scenes", type=_list(str), metavar="A,B",
                   help="built-in scene names (demo, pits-and-thin; synthesised into "
                        "DIR/scenes/) or scene folders")
    p.add_argument("--samplers", type=_list(str), default=["hvs", "l0"], metavar="A,B",
                   help="samplers (default hvs,l0)")
    p.add_argument("--seconds", type=_list(float), metavar="T1,T2",
                   help="wall-clock training budgets in seconds, e.g. 60,240")
    p.add_argument("--seeds", type=_list(int), default=[0], metavar="S1,S2",
                   help="seeds (default 0)")
    p.add_argument("--out", metavar="DIR", help="sweep folder")
    p.add_argument("--conf", default=None,
                   help="config shared by every run: demo, fast, wmask, womask or a YAML path "
                        "(default: demo on a CPU, fast on CUDA)")
    p.add_argument("--views", type=int, default=None,
                   help="views of synthesised scenes (default: 24 on a CPU, 49 on CUDA)")
    p.add_argument("--width", type=int, default=None,
                   help="width of synthesised scenes (default: 200 on a CPU, 400 on CUDA)")
    p.add_argument("--height", type=int, default=None,
                   help="height of synthesised scenes (default: 150 on a CPU, 300 on CUDA)")
    p.add_argument("--holdout", type=int, default=8, metavar="K",
                   help="hold out every K-th view (0, K, 2K, ...) from training for PSNR "
                        "(default 8; 0: none)")
    p.add_argument("--device", default=None, choices=["cpu", "cuda"],
                   help="default: cuda when available")
    p.add_argument("--backend", default="local", choices=["local", "ray"],
                   help="local: one run after another (default); ray: Ray tasks")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads per run (default: 1 on a CPU, where torch's one per "
                        "core slows a loaded machine down many times; 0: torch's default)")
    p.add_argument("--resolution", type=int, default=None,
                   help="marching-cubes resolution of each run's mesh (default: 128 on a CPU, "
                        "256 on CUDA)")
    p.add_argument("--eval-density", type=float, default=None,
                   help="Chamfer sampling density in world units (default: 0.5 on a CPU, the "
                        "synthetic scenes' point spacing; 0.2, the DTU protocol, on CUDA)")
    p.add_argument("--sample-rays", type=int, default=256,
                   help="rays of the fine-sample distance probe (256)")
    p.add_argument("--psnr-pixels", type=int, default=10000, metavar="N",
                   help="held-out PSNR renders at most N pixels per held-out view: every s-th "
                        "pixel, s the config's train.val_downscale or larger (default 10000; "
                        "e.g. a 400x300 view at s=4, 100x75); the cost is at most views x N "
                        "rays")
    p.add_argument("--timeout", type=float, default=None,
                   help="kill a run's process after this many seconds (default: no limit)")
    p.add_argument("--snapshots", type=int, default=0, metavar="N",
                   help="score each run at N points of its budget (budget * k / N, k = 1..N; "
                        "the last is the run's end): eval.json's curve of Chamfer against "
                        "training time (default 0: the end only)")
    p.add_argument("--plot-only", metavar="DIR", default=None,
                   help="only redraw DIR/plots/ from DIR/results.json")
    p.add_argument("--no-plots", action="store_true", help="do not draw DIR/plots/")
    p.add_argument("--quiet", action="store_true",
                   help="no progress bars (by default: one over the runs and one for the "
                        "running run's step: training, marching cubes, scoring, held-out views)")
    accept_overrides(p)
    return p


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from neus_l0.errors import NeusL0Error

    if args.plot_only:
        from neus_l0.bench.plots import write_plots

        folder = Path(args.plot_only)
        if not (folder / "results.json").is_file() and not (folder / "results.csv").is_file():
            raise NeusL0Error(f"{folder}: no results.json or results.csv (run a sweep first)")
        for path in write_plots(folder):
            print(path)
        return 0

    missing = [f"--{k}" for k in ("scenes", "seconds", "out") if not getattr(args, k)]
    if missing:
        raise NeusL0Error(f"bench needs {', '.join(missing)} (or --plot-only DIR)")
    from neus_l0.config.schema import SAMPLERS
    from neus_l0.device import pick_device

    bad = [s for s in args.samplers if s not in SAMPLERS]
    if bad:
        raise NeusL0Error(f"--samplers: unknown {', '.join(bad)} (choose from "
                          f"{', '.join(SAMPLERS)})")
    check_numbers(args)
    from neus_l0.commands._paths import check_output_dir

    check_output_dir(args.out, "--out")
    owned = [o for o in args.overrides
             if o.split("=", 1)[0] in ("sampler", "train.seed", "train.max_seconds")]
    if owned:
        raise NeusL0Error(f"{', '.join(owned)}: set by the sweep (use --samplers, --seeds, "
                          "--seconds)")

    from neus_l0.bench.sweep import SweepSpec, device_defaults, run_sweep

    spec = SweepSpec(
        out_dir=args.out, scenes=args.scenes, samplers=args.samplers, budgets=args.seconds,
        seeds=args.seeds, conf=args.conf, overrides=args.overrides, views=args.views,
        width=args.width, height=args.height, holdout=args.holdout,
        device=pick_device(args.device), threads=args.threads, resolution=args.resolution,
        eval_density=args.eval_density, sample_rays=args.sample_rays,
        psnr_pixels=args.psnr_pixels, backend=args.backend, timeout=args.timeout,
        snapshots=args.snapshots)
    if any(not Path(s).is_dir() for s in spec.scenes):
        from neus_l0.bench.holdout import split_views

        split_views(spec.views, spec.holdout)  # built-in scenes: some view must be left
    from neus_l0.mesh.extract import SPARSE_ABOVE
    from neus_l0.mesh.memory import plan_extraction

    plan_extraction("sparse" if spec.resolution > SPARSE_ABOVE else "dense", spec.resolution)
    chosen = [f"--{k.replace('_', '-')} {getattr(spec, k)}" for k in device_defaults(spec.device)
              if getattr(args, k) is None]
    if chosen and not args.quiet:
        print(f"bench: {spec.device} defaults: {' '.join(chosen)}")
    outcome = run_sweep(spec, progress=not args.quiet)
    return report(args, outcome)


def report(args: argparse.Namespace, outcome) -> int:
    """Print what the sweep did; the exit status: the signal's code (143, 130) when one
    stopped it, 1 when a run of this call failed, else 0."""
    import sys
    from pathlib import Path

    out = Path(args.out)
    this_call = {f"runs/{name}" for name in outcome.ran}
    rows = [r for r in outcome.rows if r["run_dir"] in this_call]
    failed = [r for r in rows if r["status"] == "failed"]
    stopped = [r for r in rows if r["status"] == "interrupted"]
    done = [r for r in rows if r["status"] == "done"]
    print(f"{len(done)} runs done now, {len(outcome.skipped)} skipped (done before), "
          f"{len(failed)} failed, {len(stopped)} interrupted in {args.out}")
    for r in failed + stopped:
        print(f"  {r['status']}: {r['run_dir']}: {r['error']}")
    print(f"results: {out / 'results.csv'}, {out / 'results.json'}")
    if outcome.signal:
        names = ", ".join(r["run_dir"] for r in stopped) or "no run"
        print(f"neus-l0 bench: stopped by {outcome.signal}: {names} recorded as interrupted, "
              f"{len(outcome.not_started)} not started; run the same command again to go on",
              file=sys.stderr)
        return outcome.exit_code
    if not args.no_plots:
        from neus_l0.bench.plots import write_plots

        write_plots(out, outcome.rows)
        print(f"plots:   {out / 'plots'}/ (chamfer_vs_time.png, psnr_vs_time.png, "
              "sample_distance.png, table.md)")
    if failed:
        logs = (f"its log: {out / failed[0]['run_dir'] / 'log.txt'}" if len(failed) == 1
                else f"their logs: {out / 'runs'}/<run>/log.txt")
        print(f"neus-l0 bench: {len(failed)} of {len(rows)} runs failed: "
              f"{', '.join(Path(r['run_dir']).name for r in failed)}; {logs}", file=sys.stderr)
        return 1
    return 0
