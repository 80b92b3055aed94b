"""`neus-l0 train`: train NeuS on a scene (NeuS format or transforms.json)."""

from __future__ import annotations

import argparse
import shutil
import sys

from neus_l0.commands._overrides import accept_overrides
from neus_l0.config.load import conf_names


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="train NeuS on a scene",
                       description="Train NeuS on a scene folder: NeuS format or "
                                   "transforms.json (NeRF-synthetic, instant-ngp, nerfstudio; "
                                   "the object sphere is then found from the masks or "
                                   "cameras, see neus-l0 inspect). The "
                                   "up-sampling draw is the config's `sampler`: wmask/womask "
                                   "use NeuS's own (hvs) as the reference; add sampler=l0 for "
                                   "the L0-Sampler. `neus-l0 config show --conf CONF "
                                   "[key=value ...]` lists every key with its meaning.")
    p.add_argument("data", metavar="DATA",
                   help="scene folder (image/, mask/, cameras_sphere.npz; or transforms.json)")
    p.add_argument("--conf", default=None,
                   help="config: a YAML path, confs/NAME.yaml or a built-in NAME "
                        f"({', '.join(conf_names())}); default: the device's setting, demo "
                        "on a CPU, fast on CUDA, with its capacity for --budget "
                        "(wmask/womask are NeuS's reference settings)")
    p.add_argument("--budget", default=None, metavar="TIME",
                   help="the whole run's time: seconds or 90s, 10m, 1h (start-up, compile "
                        "and the final checkpoint included); the iterations are planned "
                        "from the step rate measured after the compile, the schedule "
                        "finishes; sets train.budget")
    p.add_argument("--out", required=True, metavar="RUN", help="run folder to write")
    p.add_argument("--device", default=None, choices=["cpu", "cuda"],
                   help="default: cuda when available")
    p.add_argument("--resume", action="store_true",
                   help="continue from the newest checkpoint in RUN (its config.yaml is the "
                        "base config; overrides still apply)")
    p.add_argument("--change-config", action="store_true",
                   help="with --resume: allow overrides that change what is learnt (train.lr, "
                        "the sampler, the losses, ...); they are recorded in RUN/resumes.jsonl, "
                        "config.yaml stays the original")
    p.add_argument("--stop-at", type=int, default=None, metavar="ITER",
                   help="stop (with a checkpoint) at iteration ITER, keeping the learning-rate "
                        "schedule of train.iters; --resume continues it (to fork a run, e.g. "
                        "into copies resumed with another sampler)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads (default: train.threads, else the cores free when "
                        "training starts, from the load average)")
    p.add_argument("--holdout", type=int, default=None, metavar="K",
                   help="keep every K-th view (0, K, 2K, ...) out of training (train.holdout; "
                        "recorded in RUN/run.json; `neus-l0 render RUN --views test` renders "
                        "them)")
    p.add_argument("--viewer", type=int, nargs="?", const=8080, default=None, metavar="PORT",
                   help="serve the run's page live on 127.0.0.1:PORT (8080): metrics every "
                        "train.log_every, a coarse mesh every train.val_every (see neus-l0 "
                        "view)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    accept_overrides(p)
    return p


def run(args: argparse.Namespace) -> int:
    from neus_l0.commands._paths import check_not_input, check_output_dir
    from neus_l0.commands._threads import check_threads
    from neus_l0.config.duration import parse_seconds
    from neus_l0.device import pick_device, use_cpu_threads
    from neus_l0.errors import NeusL0Error
    from neus_l0.formats.open import open_scene
    from neus_l0.run.folder import RUN_LEFTOVERS, RUN_RECORDS
    from neus_l0.train.budget_run import BudgetTooShort
    from neus_l0.train.loop import train
    from neus_l0.train.run_config import fresh_config, process_seconds, resumed_config, with_budget

    if args.change_config and not args.resume:
        raise NeusL0Error("--change-config allows a resumed run to change its config; "
                          "without --resume it does nothing: add --resume, or drop it")
    check_not_input(args.out, "--out", [args.data])
    if not str(args.out).isprintable() or "\udc80" <= max(str(args.out)) <= "\udcff":
        raise NeusL0Error(f"--out {args.out!r}: a name with bytes that are not UTF-8 text or "
                          "with control characters; TensorBoard cannot write there (rename it)")
    if args.viewer is not None and not 0 <= args.viewer < 65536:
        raise NeusL0Error(f"--viewer {args.viewer}: a port must be 0..65535 (0: a free one)")
    run_dir = check_output_dir(args.out, "--out", RUN_RECORDS, RUN_LEFTOVERS, "a run folder")
    if args.holdout is not None:
        args.overrides = [*args.overrides, f"train.holdout={args.holdout}"]
    device = pick_device(args.device)
    if args.resume and args.budget is not None:
        raise NeusL0Error(f"--budget {args.budget}: a resumed run keeps the schedule its "
                          "config.yaml recorded; resume without --budget")
    budget = parse_seconds(args.budget, "--budget", allow_zero=False) if args.budget else 0.0
    if args.resume and (run_dir / "config.yaml").is_file():
        cfg = resumed_config(run_dir, args.overrides, args.change_config)
    else:
        cfg = fresh_config(args.conf, args.overrides, device, budget)
    check_threads(args.threads)
    if args.stop_at is not None and args.stop_at < 1:
        raise NeusL0Error(f"--stop-at {args.stop_at}: must be at least 1")
    threads = use_cpu_threads(args.threads or cfg.train.threads, device)
    if threads is not None:
        how = "as asked" if (args.threads or cfg.train.threads) else "the free cores"
        print(f"neus-l0 train: {threads} torch thread{'s' if threads > 1 else ''} ({how}; "
              "--threads N to set)", file=sys.stderr, flush=True)
    scene = open_scene(args.data, downscale=cfg.data.downscale, device=device)
    asked = cfg.train.budget
    given = f"--budget {args.budget}" if args.budget else f"train.budget={asked:g}"
    if asked > 0:  # train() counts from its call: hand it what start-up left
        cfg = with_budget(cfg, asked - process_seconds())
        if cfg.train.budget <= 0:
            raise NeusL0Error(f"{given}: too short: start-up alone took {process_seconds():.0f} s")
    callbacks = []
    if args.viewer is not None:
        from neus_l0.viewer.live import LiveViewer

        callbacks.append(LiveViewer(args.viewer))
    fresh = not run_dir.exists()
    try:
        result = train(scene, cfg, run_dir, device=device, resume=args.resume,
                       progress=not args.quiet, stop_at=args.stop_at, callbacks=callbacks)
    except BudgetTooShort as exc:
        if fresh:  # made by this command, holding no checkpoint: nothing of the user's
            shutil.rmtree(run_dir, ignore_errors=True)
        raise NeusL0Error(exc.line(given, asked - cfg.train.budget)) from None
    return report(args, run_dir, result, asked)


def report(args: argparse.Namespace, run_dir, result, asked: float) -> int:
    """Print how the run ended (and how much of its budget it took); the exit status."""
    from neus_l0.train.run_config import process_seconds, run_files

    if result.signal:
        print(f"neus-l0 train: stopped by {result.signal} at iteration {result.iteration}; "
              f"checkpoint {result.checkpoint} written; continue with: neus-l0 train "
              f"{args.data} --out {run_dir} --resume", file=sys.stderr)
        return result.exit_code
    state = "done"
    if result.stopped_early:
        state = ("stopped at --stop-at" if args.stop_at is not None
                 and result.iteration >= args.stop_at else "stopped at the time budget")
    print(f"{state}: {result.iteration} iterations in {result.seconds:.0f} s; "
          f"checkpoint {result.checkpoint}")
    if asked > 0:
        took = process_seconds()
        print(f"budget {asked:.0f} s: the run took {took:.1f} s end to end "
              f"({100 * took / asked:.0f} % of it)")
    print(f"run folder: {run_dir}  ({', '.join(run_files(run_dir))}; "
          f"see it: neus-l0 view {run_dir})")
    return 0
