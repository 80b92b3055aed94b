"""`neus-l0 train`: train NeuS on a scene (NeuS format or transforms.json)."""

from __future__ import annotations

import argparse

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
    p.add_argument("--conf", default="wmask",
                   help="config: a YAML path, confs/NAME.yaml or a built-in NAME "
                        f"({', '.join(conf_names())}); default wmask")
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

    import sys

    from neus_l0.commands._paths import check_output_dir
    from neus_l0.commands._threads import check_threads
    from neus_l0.config.load import load_config
    from neus_l0.device import pick_device, use_cpu_threads
    from neus_l0.errors import NeusL0Error
    from neus_l0.formats.open import open_scene
    from neus_l0.train.loop import train

    run_dir = check_output_dir(args.out, "--out")
    if args.holdout is not None:
        args.overrides = [*args.overrides, f"train.holdout={args.holdout}"]
    if args.resume and (run_dir / "config.yaml").is_file():
        cfg = _resumed_config(run_dir, args.overrides, args.change_config)
    else:
        cfg = load_config(args.conf, args.overrides)
    device = pick_device(args.device)
    check_threads(args.threads)
    if args.stop_at is not None and args.stop_at < 1:
        raise NeusL0Error(f"--stop-at {args.stop_at}: must be at least 1")
    threads = use_cpu_threads(args.threads or cfg.train.threads, device)
    if threads is not None:
        how = "as asked" if (args.threads or cfg.train.threads) else "the free cores"
        print(f"neus-l0 train: {threads} torch thread{'s' if threads > 1 else ''} ({how}; "
              "--threads N to set)", file=sys.stderr, flush=True)
    scene = open_scene(args.data, downscale=cfg.data.downscale, device=device)
    callbacks = []
    if args.viewer is not None:
        from neus_l0.viewer.live import LiveViewer

        callbacks.append(LiveViewer(args.viewer))
    result = train(scene, cfg, run_dir, device=device, resume=args.resume,
                   progress=not args.quiet, stop_at=args.stop_at, callbacks=callbacks)
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
    print(f"run folder: {run_dir}  ({', '.join(_run_files(run_dir))}; "
          f"see it: neus-l0 view {run_dir})")
    return 0


def _run_files(run_dir) -> list[str]:
    """What the run folder holds, as the end-of-training line lists it."""
    names = ["config.yaml", "metrics.jsonl"]
    if any((run_dir / "validation").glob("*.png")):
        names.append("validation/")
    names.append("checkpoints/")
    if any(run_dir.glob("events.out.tfevents.*")):
        names.append(f"TensorBoard events: tensorboard --logdir {run_dir}")
    return names


def _resumed_config(run_dir, overrides: list[str], change: bool):
    """The resumed run's config: ``config.yaml``, the overrides earlier resumes recorded, then
    these `overrides` (training records what they change: `neus_l0.run.resumes`).

    Raises:
        ConfigError: overrides that change what is learnt without ``--change-config``.
    """
    from neus_l0.config.load import load_config
    from neus_l0.errors import ConfigError
    from neus_l0.run.resumes import changed_keys, guarded_keys, recorded_overrides

    base = run_dir / "config.yaml"
    prior = recorded_overrides(run_dir)
    before = load_config(base, prior)
    cfg = load_config(base, prior + list(overrides))
    changed = changed_keys(before, cfg)
    guarded = guarded_keys(changed)
    if guarded and not change:
        raise ConfigError(f"{run_dir}: resuming with {', '.join(guarded)} changed would train "
                          "a different run; add --change-config to do it on purpose (recorded "
                          "in resumes.jsonl; config.yaml keeps the original)")
    return cfg
