"""`neus-l0 bench`: sweep scenes x samplers x budgets x seeds and record time against error."""

from __future__ import annotations

import argparse

from neus_l0.commands._mesh_steps import add_mesh_step_flags
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
                   help="built-in scene names (demo, pits-and-thin, pits-deep, cup; synthesised "
                        "into DIR/scenes/) or scene folders")
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
    add_mesh_step_flags(p)  # each run's mesh, as `neus-l0 mesh`
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
    p.add_argument("--plan", action="store_true",
                   help="each budget is train.budget: iterations planned from the measured "
                        "step rate, capacity from the device's ladder, start-up and compile "
                        "counted (default: train.max_seconds cuts the config's schedule)")
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
        from neus_l0.experiments.plots import write_plots

        folder = Path(args.plot_only)
        if not (folder / "results.json").is_file() and not (folder / "results.csv").is_file():
            raise NeusL0Error(f"{folder}: no results.json or results.csv (run a sweep first)")
        for path in write_plots(folder):
            print(path)
        return 0

    missing = [f"--{k}" for k in ("scenes", "seconds", "out") if not getattr(args, k)]
    if missing:
        raise NeusL0Error(f"bench needs {', '.join(missing)} (or --plot-only DIR)")
    from neus_l0.commands._paths import check_output_dir
    from neus_l0.device import pick_device
    from neus_l0.experiments.sweep import (
        SWEEP_NAMES,
        SweepSpec,
        check_spec,
        device_defaults,
        finish_sweep,
        run_sweep,
    )

    spec = SweepSpec(
        out_dir=args.out, scenes=args.scenes, samplers=args.samplers, budgets=args.seconds,
        seeds=args.seeds, conf=args.conf, overrides=args.overrides, views=args.views,
        width=args.width, height=args.height, holdout=args.holdout,
        device=pick_device(args.device), threads=args.threads, resolution=args.resolution,
        eval_density=args.eval_density, sample_rays=args.sample_rays,
        psnr_pixels=args.psnr_pixels, backend=args.backend, timeout=args.timeout,
        snapshots=args.snapshots, planned=args.plan, close_underside=args.close_underside,
        drop_outside_masks=args.drop_outside_masks, inset=args.inset,
        fill_missed=args.fill_missed, photo_carve=args.photo_carve)
    check_spec(spec)
    check_output_dir(args.out, "--out", ("sweep.json",), SWEEP_NAMES, "a bench folder")
    chosen = [f"--{k.replace('_', '-')} {getattr(spec, k)}" for k in device_defaults(spec.device)
              if getattr(args, k) is None]
    if chosen and not args.quiet:
        print(f"bench: {spec.device} defaults: {' '.join(chosen)}")
    outcome = run_sweep(spec, progress=not args.quiet)
    return finish_sweep(Path(args.out), outcome, plots=not args.no_plots)
