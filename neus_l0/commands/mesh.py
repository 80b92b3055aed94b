"""`neus-l0 mesh`: extract a mesh in world units from a trained run."""

from __future__ import annotations

import argparse


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="extract a mesh from a trained run",
                       description="Marching cubes of the trained SDF, exported in world units.")
    p.add_argument("run", metavar="RUN", help="run folder written by `neus-l0 train`")
    p.add_argument("--resolution", type=int, default=512, help="grid samples per axis (512)")
    p.add_argument("--out", default=None, help="output .ply or .obj (default RUN/mesh.ply)")
    p.add_argument("--clean", action=argparse.BooleanOptionalAction, default=True,
                   help="keep only the largest connected component (default on)")
    p.add_argument("--colors", action="store_true",
                   help="vertex colours from the colour network (view = -normal)")
    p.add_argument("--method", default="auto", choices=["auto", "dense", "sparse"],
                   help="dense grid, or sparse (the SDF evaluated only in blocks near the "
                        "surface); auto: sparse above 128 samples per axis (default)")
    p.add_argument("--checkpoint", default=None, help="a specific checkpoint (default newest)")
    p.add_argument("--device", default=None, choices=["cpu", "cuda"])
    return p


def run(args: argparse.Namespace) -> int:
    import time
    from pathlib import Path

    import numpy as np

    from neus_l0.commands.train import pick_device
    from neus_l0.errors import NeusL0Error
    from neus_l0.mesh import export_mesh, extract_mesh
    from neus_l0.train import load_trained_model

    if args.resolution < 8:
        raise NeusL0Error(f"--resolution {args.resolution}: must be at least 8")
    device = pick_device(args.device)
    t0 = time.monotonic()
    model, _, info = load_trained_model(args.run, device, args.checkpoint)
    mesh = extract_mesh(model, np.asarray(info["scale_mat"]), resolution=args.resolution,
                        clean=args.clean, colors=args.colors, device=device,
                        method=args.method)
    out = Path(args.out) if args.out else Path(args.run) / "mesh.ply"
    export_mesh(mesh, out)
    st = mesh.metadata["extraction"]
    print(f"{st['method']} extraction at {st['resolution']}^3: {st['sdf_evals']:,} SDF "
          f"evaluations ({st['sdf_evals'] / st['dense_evals']:.1%} of the dense grid), "
          f"{st['seconds']:.1f} s")
    print(f"{out}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces, world units "
          f"(checkpoint {info['path'].name}, iteration {info['iteration']}, "
          f"{time.monotonic() - t0:.1f} s)")
    return 0
