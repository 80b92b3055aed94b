"""`neus-l0 synth SCENE OUT`: render a synthetic NeuS-format scene with exact ground truth.

The numbers are checked first (`check_scene_args`, and the memory the rendering needs
against the memory available); OUT is replaced whole, at the end (see
`neus_l0.synthetic.scene`).
"""

from __future__ import annotations

import argparse

BUILTINS = ("demo", "pits-and-thin", "pits-deep", "cup", "well")


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(
        name, help="render a synthetic NeuS-format scene with exact ground truth",
        description="Render SCENE (a built-in name: " + ", ".join(BUILTINS) + "; or a mesh "
                    "file: OBJ/PLY/GLB) from a DTU-like camera cap into OUT in NeuS format "
                    "(image/, mask/, cameras_sphere.npz) plus ground truth (gt_mesh.ply, "
                    "gt_points.ply, gt_depth.npz, features.json, scene.json). OUT is new, "
                    "empty or an earlier synthetic scene, replaced whole at the end.")
    p.add_argument("scene", help="built-in scene name or mesh file")
    p.add_argument("out", help="output folder")
    p.add_argument("--views", type=int, default=49,
                   help="number of cameras, >= 1 (default 49)")
    p.add_argument("--width", type=int, default=400, help="image width, >= 8 (default 400)")
    p.add_argument("--height", type=int, default=300,
                   help="image height, >= 8 (default 300)")
    p.add_argument("--seed", type=int, default=0,
                   help="camera jitter and texture seed, in [0, 2^32 - 1]")
    p.add_argument("--spp", type=int, default=2,
                   help="anti-aliasing sub-samples per pixel axis, >= 1 (default 2, i.e. 4 "
                        "per pixel)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return p


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from neus_l0.commands._paths import check_not_input, check_output_dir
    from neus_l0.device import available_memory
    from neus_l0.synthetic.scene import check_render_memory, check_scene_args, make_scene

    check_not_input(args.out, "OUT", [Path(args.scene)])
    check_output_dir(args.out, "OUT", ("scene.json",), (), "a synthetic scene")
    check_scene_args(args.views, args.width, args.height, args.spp, args.seed)
    check_render_memory(args.views, args.width, args.height, args.spp, available_memory())
    out = make_scene(args.scene, args.out, views=args.views, width=args.width,
                     height=args.height, seed=args.seed, spp=args.spp,
                     progress=not args.no_progress)
    print(f"wrote {out}")
    return 0
