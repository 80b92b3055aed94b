"""`neus-l0 figures`: pits and thin structures compared between samplers, from a bench folder."""

from __future__ import annotations

import argparse


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="figures of pits and thin structures compared between samplers",
                       description="From a `neus-l0 bench` folder: the ground-truth mesh and "
                                   "each sampler's mesh rendered headless (shaded and coloured "
                                   "by the distance to the true surface), with zoomed crops on "
                                   "every pit and thin part; the coarse weights and the "
                                   "samplers' densities along a ray into a pit; and index.md. "
                                   "On a scene without ground truth (no gt_mesh.ply, e.g. a "
                                   "DTU scan): the samplers' meshes shaded side by side, with "
                                   "zoomed crops on the places where they differ most.")
    p.add_argument("--bench", required=True, metavar="DIR[,DIR2...]",
                   help="output folder of `neus-l0 bench`; several, comma-separated, put "
                        "their runs side by side (the arms of a paired comparison, e.g. "
                        "`--bench OFF,ON --samplers l0`: the first folder picks the scene, "
                        "budget and seed)")
    p.add_argument("--out", required=True, metavar="FIGDIR",
                   help="folder for the PNGs and index.md")
    p.add_argument("--scene", default=None,
                   help="scene name (default: pits-and-thin if the bench has it, else the "
                        "only one)")
    p.add_argument("--budget", type=float, default=None,
                   help="training budget in seconds (default: the largest all samplers finished)")
    p.add_argument("--seed", type=int, default=None,
                   help="training seed (default: the smallest all samplers finished)")
    p.add_argument("--samplers", default="hvs,l0",
                   help="comma-separated samplers to compare (default hvs,l0)")
    p.add_argument("--pit", default=None,
                   help="features.json name of the pit for the ray figure (default: the pit "
                        "whose bottom a camera sees deepest; scenes with ground truth only)")
    p.add_argument("--error-max", type=float, default=None,
                   help="top of the error colour scale, world units (default: 95th percentile; "
                        "scenes with ground truth only)")
    p.add_argument("--regions", type=int, default=4, metavar="K",
                   help="scenes without ground truth: how many places where the meshes differ "
                        "most to box and zoom on (4)")
    p.add_argument("--width", type=int, default=480, help="overview width in pixels (480)")
    p.add_argument("--crop", type=int, default=192, help="side of the zoomed crops in pixels (192)")
    return p


def run(args: argparse.Namespace) -> int:
    import sys
    from pathlib import Path

    import torch

    from neus_l0.commands._paths import check_output_dir
    from neus_l0.errors import NeusL0Error
    from neus_l0.figures.make import make_figures, write_index
    from neus_l0.figures.real import make_real_figures
    from neus_l0.figures.runs import select_arms

    samplers = [s.strip() for s in args.samplers.split(",") if s.strip()]
    if not samplers or len(set(samplers)) != len(samplers):
        raise NeusL0Error(f"--samplers {args.samplers!r}: give distinct sampler names")
    if args.width < 32 or args.crop < 32:
        raise NeusL0Error("--width and --crop must be at least 32 pixels")
    benches = [Path(b.strip()) for b in args.bench.split(",") if b.strip()]
    if not benches:
        raise NeusL0Error("--bench: give a bench folder")
    out = check_output_dir(args.out, "--out", (), ("*.png", "index.md"), "a figures folder")
    if args.regions < 1:
        raise NeusL0Error(f"--regions {args.regions}: give at least 1")
    scene_dir, runs = select_arms(benches, samplers, args.scene, args.budget, args.seed)
    first = next(iter(runs.values()))
    command = (f"neus-l0 figures --bench {','.join(map(str, benches))} --out {out} "
               f"--scene {first.scene}"
               f" --budget {first.budget_s:g} --seed {first.seed}"
               f" --samplers {','.join(samplers)}")
    if (scene_dir / "gt_mesh.ply").is_file():
        with torch.no_grad():
            entries = make_figures(scene_dir, runs, out, overview_width=args.width,
                                   crop_size=args.crop, error_max=args.error_max, pit=args.pit)
    else:
        if len(runs) < 2:
            raise NeusL0Error(f"{scene_dir}: no ground truth, so the figures compare runs: "
                              "give two or more samplers with --samplers (or bench folders)")
        print(f"{scene_dir}: no gt_mesh.ply: shaded meshes side by side and the "
              f"{args.regions} places where they differ most (no error colours)")
        for opt, value in (("--pit", args.pit), ("--error-max", args.error_max)):
            if value is not None:
                print(f"figures: {opt} ignored: the scene has no ground truth", file=sys.stderr)
        entries = make_real_figures(scene_dir, runs, out, overview_width=args.width,
                                    crop_size=args.crop, regions=args.regions)
        command += f" --regions {args.regions}"
    index = write_index(out, entries, benches if len(benches) > 1 else benches[0], runs,
                        scene_dir, command)
    for e in entries:
        print(out / e.file)
    print(index)
    return 0
