"""`neus-l0 demo`: make a small built-in scene, reconstruct it, score and picture the mesh."""

from __future__ import annotations

import argparse

from neus_l0.commands._overrides import accept_overrides

#: Defaults shown in --help (the pipeline's own values, without importing it here).
_RESOLUTION, _CONF = 96, "demo"


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="make a small built-in scene, reconstruct it and score the mesh",
                       description="Render the built-in 'demo' scene, train NeuS with the "
                                   "L0-Sampler (confs/demo.yaml: a hash grid and small MLPs "
                                   "sized for a 2-core CPU), extract the mesh, score it and "
                                   "draw ground truth and reconstruction side by side.")
    p.add_argument("--out", default="neus-l0-demo", help="output folder (default ./neus-l0-demo)")
    p.add_argument("--device", default=None, choices=["cpu", "cuda"])
    p.add_argument("--resolution", type=int, default=_RESOLUTION,
                   help=f"marching-cubes resolution (default {_RESOLUTION})")
    p.add_argument("--conf", default=_CONF,
                   help=f"training config (default {_CONF}: the CPU-sized hash-grid setting)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads (default: free cores, from the load average)")
    p.add_argument("--budget", default=None, metavar="TIME",
                   help="time for training (90s, 4m, 1h; train.budget): the iterations are "
                        "planned from the step rate measured after the compile and the "
                        "schedule finishes; the scene, mesh and score come on top (default: "
                        "the config's 3500 iterations)")
    p.add_argument("--close-underside", action=argparse.BooleanOptionalAction, default=True,
                   help="close the mesh's underside, which no demo camera sees, flat just "
                        "below the lowest point the views see (as `neus-l0 mesh "
                        "--close-underside`; default on)")
    p.add_argument("--drop-outside-masks", action=argparse.BooleanOptionalAction, default=True,
                   help="drop mesh pieces a view sees outside its mask (as `neus-l0 mesh "
                        "--drop-outside-masks`; default on)")
    p.add_argument("--fill-missed", action=argparse.BooleanOptionalAction, default=True,
                   help="fill thin parts the masks see and the mesh misses from the visual "
                        "hull (as `neus-l0 mesh --fill-missed`; default on)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    accept_overrides(p)
    return p


def check_numbers(args: argparse.Namespace) -> None:
    """Refuse an out-of-range number among the flags, naming the flag, before any work."""
    from neus_l0.commands._threads import check_threads
    from neus_l0.errors import NeusL0Error
    from neus_l0.mesh.extract import SPARSE_ABOVE
    from neus_l0.mesh.memory import plan_extraction

    if args.resolution < 8:
        raise NeusL0Error(f"--resolution {args.resolution}: must be at least 8")
    check_threads(args.threads)
    plan_extraction("sparse" if args.resolution > SPARSE_ABOVE else "dense", args.resolution)


def run(args: argparse.Namespace) -> int:
    import json
    import sys

    from neus_l0.commands._paths import check_output_dir
    from neus_l0.config.duration import parse_seconds
    from neus_l0.pipelines.demo import DEMO_NAMES, DEMO_RECORDS, DemoOptions, run_demo

    check_numbers(args)
    budget = parse_seconds(args.budget, "--budget", allow_zero=False) if args.budget else 0.0
    out = check_output_dir(args.out, "--out", DEMO_RECORDS, DEMO_NAMES, "a demo folder")
    result = run_demo(DemoOptions(out=out, conf=args.conf, overrides=list(args.overrides),
                                  device=args.device, threads=args.threads,
                                  resolution=args.resolution, quiet=args.quiet,
                                  close_underside=args.close_underside,
                                  drop_outside_masks=args.drop_outside_masks,
                                  fill_missed=args.fill_missed, budget=budget))
    if result.signal:
        print(f"neus-l0 demo: stopped by {result.signal} at iteration {result.iteration}; "
              f"checkpoint {result.checkpoint} written; run the same command again to "
              "resume", file=sys.stderr)
        return result.exit_code
    m = result.metrics
    print(json.dumps({"chamfer": {k: (m["chamfer"] or {}).get(k) for k in
                                  ("accuracy", "completeness", "overall")},
                      "iterations": m["iterations"], "timings": m["timings"]}, indent=1))
    paths = result.paths
    print(f"scene:      {paths['scene']}/")
    print(f"run:        {paths['run']}/  (metrics.jsonl, validation/, checkpoints/)")
    print(f"mesh:       {paths['mesh']}")
    print(f"metrics:    {paths['metrics']}")
    print(f"picture:    {paths['picture']}")
    return 0
