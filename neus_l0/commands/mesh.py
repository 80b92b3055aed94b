"""`neus-l0 mesh`: extract a mesh in world units from a trained run."""

from __future__ import annotations

import argparse

from neus_l0.commands._mesh_steps import add_mesh_step_flags
from neus_l0.commands._threads import add_threads_flag


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="extract a mesh from a trained run",
                       description="Marching cubes of the trained SDF, exported in world units. "
                                   "Optional clean-up through pymeshlab runs in this order: "
                                   "--min-component, --close-holes, --smooth, --simplify.")
    p.add_argument("run", metavar="RUN", help="run folder written by `neus-l0 train`")
    p.add_argument("--resolution", type=int, default=512,
                   help="grid samples per axis (512); refused with the largest resolution "
                        "that fits when the estimated memory exceeds what is available")
    p.add_argument("--out", default=None,
                   help="output mesh: .ply, .obj, .glb, .stl or .off (default RUN/mesh.ply); "
                        "vertex colours (--colors) are kept in .ply and .glb")
    p.add_argument("--clean", action=argparse.BooleanOptionalAction, default=True,
                   help="drop floating specks: pieces whose bounding-box diagonal is under 5%% "
                        "of the main piece's (default on; thin parts cut off by the grid stay)")
    add_mesh_step_flags(p)
    p.add_argument("--colors", action="store_true",
                   help="vertex colours from the colour network (view = -normal)")
    p.add_argument("--texture", action="store_true",
                   help="write OUT.obj with UVs (xatlas), OUT.mtl and an OUT.png texture baked "
                        "from the colour network (view = -normal); needs --out *.obj; xatlas "
                        "takes ~25 s per 50k faces on 2 cores: --simplify big meshes")
    p.add_argument("--texture-size", type=int, default=1024, metavar="TEXELS",
                   help="about how many texels a side the texture has (1024)")
    p.add_argument("--simplify", type=int, default=None, metavar="FACES",
                   help="quadric edge collapse to at most FACES faces (default: off)")
    p.add_argument("--smooth", type=int, default=0, metavar="ITERS",
                   help="Taubin smoothing iterations, no shrinking (default 0: off)")
    p.add_argument("--min-component", type=float, default=0.0, metavar="FRAC",
                   help="remove components whose bounding-box diagonal is below FRAC of the "
                        "mesh's (e.g. 0.1; default 0: off; MeshLab's, after --clean)")
    p.add_argument("--close-holes", type=int, default=0, metavar="MAXEDGES",
                   help="close holes with at most MAXEDGES boundary edges (e.g. 100; 0: off)")
    p.add_argument("--method", default="auto", choices=["auto", "dense", "sparse"],
                   help="dense grid, or sparse (the SDF evaluated only in blocks near the "
                        "surface); auto: sparse above 128 samples per axis (default)")
    p.add_argument("--checkpoint", default=None,
                   help="a specific checkpoint (default the newest that loads)")
    p.add_argument("--device", default=None, choices=["cpu", "cuda"])
    add_threads_flag(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar (by default one on "
                   "stderr while the SDF is evaluated, when that takes over a second)")
    return p


def _check(args: argparse.Namespace):
    """Validate the arguments before any work; return (out path, method, cleanup options)."""
    import sys
    from pathlib import Path

    from neus_l0.atomic import inside
    from neus_l0.commands._paths import check_not_input, check_output_file
    from neus_l0.errors import NeusL0Error
    from neus_l0.mesh.cleanup import CleanupOptions
    from neus_l0.mesh.extract import MESH_FORMATS, SPARSE_ABOVE
    from neus_l0.mesh.memory import plan_extraction

    if args.resolution < 8:
        raise NeusL0Error(f"--resolution {args.resolution}: must be at least 8")
    out = check_not_input(args.out if args.out else Path(args.run) / "mesh.ply", "--out",
                          [args.run, args.checkpoint])
    check_output_file(out, "--out")
    if not args.out:  # the run's own mesh stays inside the run
        inside(args.run, out)
    if out.suffix.lower().lstrip(".") not in MESH_FORMATS:
        raise NeusL0Error(f"--out {out}: unsupported mesh format (use "
                          f"{', '.join('.' + k for k in MESH_FORMATS)})")
    if args.texture and out.suffix.lower() != ".obj":
        raise NeusL0Error(f"--texture: --out {out} must end in .obj (written with .mtl, .png)")
    if args.texture and not 64 <= args.texture_size <= 16384:
        raise NeusL0Error(f"--texture-size {args.texture_size}: give 64 to 16384 texels")
    options = CleanupOptions(args.simplify, args.smooth, args.min_component, args.close_holes)
    options.check()
    method = args.method
    if method == "auto":
        method = "sparse" if args.resolution > SPARSE_ABOVE else "dense"
    method, note = plan_extraction(method, args.resolution)
    if note:
        print(f"neus-l0 mesh: {note}", file=sys.stderr)
    return out, method, options


def run(args: argparse.Namespace) -> int:
    import time
    from pathlib import Path

    import numpy as np

    from neus_l0.commands._threads import use_threads
    from neus_l0.data.cameras import to_normalised
    from neus_l0.device import pick_device
    from neus_l0.mesh.cleanup import clean_up
    from neus_l0.mesh.extract import export_mesh, vertex_colors
    from neus_l0.mesh.from_run import MeshSteps, mesh_from_run, steps_report

    out, method, options = _check(args)
    device = pick_device(args.device)
    use_threads(args.threads, device)
    t0 = time.monotonic()
    steps = MeshSteps(args.close_underside, args.drop_outside_masks, args.inset,
                      args.fill_missed, args.photo_carve)
    made = mesh_from_run(args.run, args.resolution, device, args.checkpoint, args.clean, method,
                         progress=not args.quiet, steps=steps)
    mesh, model, info, scale_mat = made.mesh, made.model, made.info, made.scale_mat
    st = mesh.metadata["extraction"]
    print(f"{st['method']} extraction at {st['resolution']}^3: {st['sdf_evals']:,} SDF "
          f"evaluations ({st['sdf_evals'] / st['dense_evals']:.1%} of the dense grid), "
          f"{st['seconds']:.1f} s")
    print("".join(f"{line}\n" for line in steps_report(mesh.metadata)), end="")
    if options.any():
        n_before = len(mesh.faces)
        mesh = clean_up(mesh, options)
        print(f"clean-up: {n_before} -> {len(mesh.faces)} faces")
    if args.texture:
        from neus_l0.mesh.texture import bake_texture, network_colors, write_textured_obj

        t_tex = time.monotonic()
        tex = bake_texture(to_normalised(mesh.vertices, scale_mat), np.asarray(mesh.faces),
                           network_colors(model, device), size=args.texture_size)
        tex.vertices = np.asarray(mesh.vertices, np.float64)  # world units
        paths = write_textured_obj(tex, out)
        h, w = tex.image.shape[:2]
        print(f"texture: {w}x{h} texels, {time.monotonic() - t_tex:.1f} s; "
              f"{paths[1].name}, {paths[2].name}")
    else:
        if args.colors:
            mesh.visual.vertex_colors = vertex_colors(model, to_normalised(mesh.vertices,
                                                                        scale_mat), device)
        export_mesh(mesh, out)
    print(f"{out}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces, world units "
          f"(checkpoint {Path(info['path']).name}, iteration {info['iteration']}, "
          f"{time.monotonic() - t0:.1f} s)")
    return 0
