"""`neus-l0 eval`: score a mesh by Chamfer distance (DTU protocol or a synthetic scene).

The protocol and the JSON it writes are documented in docs/EVALUATION.md. Every flag is
checked before any work (`ScoreSpec.check`); a --density whose sampling would not fit in
the memory available is refused before sampling, naming the smallest density that fits;
the JSON is strict (no NaN or Infinity: a missing number is null).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(
        name, help="score a mesh by Chamfer distance (DTU protocol or a synthetic scene)",
        description="Sample the mesh (DTU style), thin it, keep the points in the evaluation "
                    "region and report accuracy, completeness and overall (world units). "
                    "The last line printed is the JSON that is also written to --json.")
    p.add_argument("mesh", type=Path, help="predicted mesh (world units), e.g. a PLY")
    gt = p.add_mutually_exclusive_group(required=True)
    gt.add_argument("--scene", type=Path, metavar="SCENE",
                    help="synthetic scene folder (gt_points.ply, gt_depth.npz, cameras_sphere.npz)")
    gt.add_argument("--dtu", type=Path, metavar="DTU_EVAL_DIR",
                    help="DTU evaluation folder (Points/stl, ObsMask); needs --scan")
    p.add_argument("--scan", type=int, help="DTU scan number (with --dtu), e.g. 24")
    p.add_argument("--cull", type=Path, metavar="SCENE",
                   help="first remove mesh parts outside the dilated masks of this scene")
    p.add_argument("--cull-dilate", type=int, default=None, metavar="PX",
                   help="mask dilation radius in pixels, >= 0 (default: round(24 * width / "
                        "1600))")
    p.add_argument("--error-maps", type=Path, metavar="DIR",
                   help="write accuracy.ply and completeness.ply coloured by distance")
    p.add_argument("--vmax", type=float, default=None,
                   help="top of the error-map colour scale, > 0 (default: --max-dist)")
    p.add_argument("--cmap", default="jet",
                   help="matplotlib colormap of the error maps (checked before scoring)")
    p.add_argument("--json", type=Path, default=None, metavar="PATH",
                   help="where to write the JSON (default: MESH.eval.json next to the mesh)")
    p.add_argument("--density", type=float, default=0.2,
                   help="sampling density and thinning radius (world units, > 0; DTU: 0.2); "
                        "refused where the sampling (about mesh area / density^2 points) "
                        "would not fit in memory")
    p.add_argument("--max-dist", type=float, default=20.0,
                   help="distances >= this are left out of both means (> 0; DTU: 20)")
    p.add_argument("--margin-low", type=float, default=60.0,
                   help="box margin below the GT box (>= 0; DTU: 60)")
    p.add_argument("--margin-high", type=float, default=120.0,
                   help="box margin above the GT box (>= 0; DTU: 120)")
    p.add_argument("--depth-tol", type=float, default=2.0,
                   help="synthetic: how far behind the true surface a point still counts as "
                        "observed (world units, >= 0)")
    p.add_argument("--seed", type=int, default=0, help="seed of the thinning order (>= 0)")
    p.add_argument("--workers", type=int, default=-1,
                   help="kd-tree threads (-1: all cores, else >= 1)")
    p.add_argument("--no-progress", action="store_true",
                   help="hide the progress bars of long samplings")
    return p


def run(args: argparse.Namespace) -> int:
    from neus_l0.atomic import atomic_write_text
    from neus_l0.commands._paths import (
        check_not_in_input_folder,
        check_not_input,
        check_output_dir,
        check_output_file,
    )
    from neus_l0.device import available_memory
    from neus_l0.evaluation.score import ScoreSpec, score_mesh

    out = args.json if args.json is not None else args.mesh.with_name(args.mesh.name + ".eval.json")
    inputs = [args.mesh, args.scene, args.dtu, args.cull]
    check_not_input(out, "--json", inputs)
    check_not_in_input_folder(out, "--json", [args.scene, args.dtu, args.cull])
    check_output_file(out, "--json")
    if args.error_maps is not None:
        check_output_dir(args.error_maps, "--error-maps", (), ("accuracy.ply", "completeness.ply"),
                         "an error-map folder")
        check_not_input(args.error_maps, "--error-maps", inputs)
    spec = ScoreSpec(
        scene=args.scene, dtu_dir=args.dtu, scan=args.scan, cull=args.cull,
        cull_dilate=args.cull_dilate, error_maps=args.error_maps, vmax=args.vmax,
        cmap=args.cmap, density=args.density, max_dist=args.max_dist,
        margin_low=args.margin_low, margin_high=args.margin_high, depth_tol=args.depth_tol,
        seed=args.seed, workers=args.workers)
    report = score_mesh(args.mesh, spec, memory=available_memory(),
                        progress=not args.no_progress)
    # strict JSON: score_mesh turns NaN / infinity into null, and allow_nan=False holds it
    atomic_write_text(out, json.dumps(report, indent=2, sort_keys=True, allow_nan=False) + "\n")
    print(f"eval: wrote {out}", file=sys.stderr, flush=True)

    def fmt(x: float | None) -> str:
        return "n/a" if x is None else f"{x:.4f}"

    counts = report["counts"]
    print(f"accuracy {fmt(report['accuracy'])}  completeness {fmt(report['completeness'])}  "
          f"overall {fmt(report['overall'])}  ({counts['pred_kept']} predicted points kept, "
          f"{counts['gt_used']} GT points)")
    print(json.dumps(report, sort_keys=True, allow_nan=False))
    return 0
