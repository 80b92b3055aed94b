"""The whole "your own photos" chain against true cameras, on a synthetic scene.

Usage: python tools/photos_chain.py --out DIR [--max-seconds 150] [--resolution 128] \
    [--conf demo] [--threads 1] [override ...]

1. renders the built-in ``demo`` scene (30 views, 400 x 300) into DIR/true;
2. runs ``neus-l0 colmap DIR/true/image DIR/colmap --masks DIR/true/mask`` (cameras withheld);
3. trains the same config with the same wall-clock budget twice, one after the other, on
   one torch thread: on DIR/true (true cameras) and on DIR/colmap (recovered cameras), and
   extracts both meshes;
4. maps the colmap-chain mesh into the true world frame with the similarity (Umeyama) that
   takes the recovered camera centres onto the true ones (views paired through
   DIR/colmap/sources.txt; `neus_l0.experiments.photos_compare.compare_to_truth`);
5. scores both meshes against the true scene (`score_mesh`, the demo's sampling density),
   draws each next to the ground truth from the first true camera, and writes
   DIR/chain.json with pose errors, similarity scale, Chamfer numbers, iterations, seconds.

Steps whose outputs exist are reused (delete DIR/... to redo one).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch
from _common import add_scene_args


def train_and_mesh(scene_dir: Path, run_dir: Path, conf: str, overrides: list[str],
                   max_seconds: float, resolution: int) -> dict:
    """Train on `scene_dir` into `run_dir` and extract ``run_dir/mesh.ply`` (scene's world)."""
    from neus_l0.atomic import atomic_write_json
    from neus_l0.config.load import load_config
    from neus_l0.formats.neus import load_scene
    from neus_l0.mesh.extract import export_mesh
    from neus_l0.mesh.from_run import mesh_from_run
    from neus_l0.train.loop import train

    done = run_dir / "chain_run.json"
    if done.is_file():
        print(f"reusing {run_dir}", flush=True)
        return json.loads(done.read_text())
    cfg = load_config(conf, overrides)
    cfg.train.max_seconds = max_seconds
    scene = load_scene(scene_dir, downscale=cfg.data.downscale)
    print(f"training on {scene_dir} ({max_seconds:.0f} s budget) into {run_dir}", flush=True)
    load0 = os.getloadavg()[0]
    result = train(scene, cfg, run_dir, device="cpu", progress=False)
    load1 = os.getloadavg()[0]
    t0 = time.perf_counter()
    mesh = mesh_from_run(run_dir, resolution, "cpu").mesh  # inside the run's hull, if any
    export_mesh(mesh, run_dir / "mesh.ply")
    out = {"iterations": result.iteration, "train_seconds": round(result.seconds, 1),
           "stopped_early": result.stopped_early, "mesh_seconds":
           round(time.perf_counter() - t0, 1), "load_avg_1min_start_end": [load0, load1],
           "vertices": len(mesh.vertices), "faces": len(mesh.faces),
           "final_metrics": result.metrics}
    atomic_write_json(done, out)
    return out


def trimmed_icp(src: np.ndarray, dst: np.ndarray, iters: int = 60, keep: float = 0.8
                ) -> np.ndarray:
    """Rigid point-to-point ICP of `src` (N, 3) onto `dst` (M, 3) keeping, each round, the
    `keep` fraction of closest pairs (mesh parts the ground-truth points do not cover,
    such as unseen faces, would otherwise pull the fit). Returns the (4, 4) transform."""
    from scipy.spatial import cKDTree

    from neus_l0.experiments.photos_align import umeyama

    tree = cKDTree(dst)
    M = np.eye(4)
    for _ in range(iters):
        cur = src @ M[:3, :3].T + M[:3, 3]
        d, j = tree.query(cur)
        sel = d <= np.quantile(d, keep)
        _, R, t = umeyama(src[sel], dst[j[sel]], with_scale=False)
        M_new = np.eye(4)
        M_new[:3, :3], M_new[:3, 3] = R, t
        if np.abs(M_new - M).max() < 1e-9:
            return M_new
        M = M_new
    return M


def icp_to_truth(mesh_path: Path, true_dir: Path) -> tuple[Path, dict]:
    """Rigid ICP (no scale) of the mesh onto ``gt_points.ply``; writes ``*_icp.ply`` next to
    it and returns its path and the correction's rotation (degrees) and translation."""
    import trimesh
    from scipy.spatial import cKDTree

    from neus_l0.experiments.photos_align import rotation_angle_deg
    from neus_l0.mesh.extract import export_mesh

    mesh = trimesh.load(mesh_path, force="mesh", process=False)
    gt = np.asarray(trimesh.load(true_dir / "gt_points.ply", process=False).vertices)
    pts = np.asarray(mesh.sample(5000, seed=0), dtype=np.float64)
    M = trimmed_icp(pts, gt)
    cost = float(cKDTree(gt).query(pts @ M[:3, :3].T + M[:3, 3])[0].mean())
    mesh.apply_transform(M)
    path = export_mesh(mesh, mesh_path.with_name(mesh_path.stem + "_icp.ply"))
    return path, {"icp_rotation_deg": float(rotation_angle_deg(np.eye(3), M[:3, :3])),
                  "icp_translation": float(np.linalg.norm(M[:3, 3])),
                  "icp_mean_dist_after": cost}


def score_meshes(meshes: dict[str, Path], true_dir: Path, out: Path,
                 timings: dict[str, float]) -> dict[str, dict]:
    """Chamfer of each mesh against the true scene, as is and after a rigid ICP onto it,
    with a comparison picture per mesh (`timings` gets the seconds of each score)."""
    import trimesh

    from neus_l0.pipelines.demo import draw_comparison, score_demo_mesh

    keys = ("accuracy", "completeness", "overall")
    scores = {}
    for name, path in meshes.items():
        t0 = time.perf_counter()
        rep = score_demo_mesh(path, true_dir)
        scores[name] = {k: rep.get(k) for k in keys}
        timings[f"{name}_score_s"] = time.perf_counter() - t0
        draw_comparison(true_dir, trimesh.load(path, force="mesh", process=False),
                        out / f"comparison_{name}.png", rep)
        # Diagnostic: a rigid ICP of the mesh onto the ground truth separates what the
        # frame alignment leaves over from the shape itself.
        icp_path, icp_info = icp_to_truth(path, true_dir)
        rep = score_demo_mesh(icp_path, true_dir)
        scores[name]["after_rigid_icp"] = {**{k: rep.get(k) for k in keys}, **icp_info}
    return scores


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True)
    p.add_argument("--conf", default="demo")
    p.add_argument("--max-seconds", type=float, default=150.0)
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--threads", type=int, default=1, help="torch threads for training")
    add_scene_args(p, views=30, width=400, height=300)
    p.add_argument("overrides", nargs="*", help="config overrides (key=value)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)

    import trimesh

    from neus_l0.atomic import atomic_write_json
    from neus_l0.cli import main as cli_main
    from neus_l0.experiments.photos_compare import compare_to_truth
    from neus_l0.mesh.extract import export_mesh
    from neus_l0.synthetic.scene import make_scene

    out = Path(args.out)
    true_dir, colmap_dir = out / "true", out / "colmap"
    t_all = time.perf_counter()
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    if not (true_dir / "scene.json").is_file():
        print(f"rendering the demo scene into {true_dir}", flush=True)
        make_scene("demo", true_dir, views=args.views, width=args.width, height=args.height,
                   seed=0, progress=False)
    timings["scene_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if not (colmap_dir / "colmap_summary.json").is_file():
        rc = cli_main(["colmap", str(true_dir / "image"), str(colmap_dir), "--masks",
                       str(true_dir / "mask"), "--no-progress"])
        if rc:
            raise SystemExit(f"neus-l0 colmap failed (exit {rc})")
    timings["colmap_s"] = time.perf_counter() - t0
    summary = json.loads((colmap_dir / "colmap_summary.json").read_text())
    errs = compare_to_truth(colmap_dir, true_dir)
    s, R, t = errs["scale"], errs["R"], errs["t"]

    overrides = list(args.overrides)
    runs = {}
    for name, scene_dir in (("true_cameras", true_dir), ("colmap_chain", colmap_dir)):
        t0 = time.perf_counter()
        runs[name] = train_and_mesh(scene_dir, out / f"run_{name}", args.conf, overrides,
                                    args.max_seconds, args.resolution)
        timings[f"{name}_train_mesh_s"] = time.perf_counter() - t0

    # The chain's mesh is in the colmap scene's world; bring it to the true world.
    chain = trimesh.load(out / "run_colmap_chain" / "mesh.ply", force="mesh", process=False)
    chain.vertices = s * np.asarray(chain.vertices, dtype=np.float64) @ R.T + t
    chain_path = export_mesh(chain, out / "run_colmap_chain" / "mesh_true_frame.ply")
    meshes = {"true_cameras": out / "run_true_cameras" / "mesh.ply",
              "colmap_chain": chain_path}

    scores = score_meshes(meshes, true_dir, out, timings)

    report = {
        "command": "python tools/photos_chain.py " + " ".join(
            [f"--out {args.out}", f"--conf {args.conf}", f"--max-seconds {args.max_seconds:g}",
             f"--resolution {args.resolution}", f"--threads {args.threads}"] + overrides),
        "machine": f"{platform.node()} ({os.cpu_count()} CPUs, torch {torch.__version__})",
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "scene": {"views": args.views, "width": args.width, "height": args.height},
        "colmap": {"registered": summary["registered"], "photos": summary["photos"],
                   "points3D": summary["points3D"], "size": summary["size"],
                   "seconds": summary["seconds"], "sphere_source": summary["sphere"]["source"]},
        "poses": {"center_err_mean_pct": 100 * errs["center_err_mean_rel"],
                  "center_err_max_pct": 100 * errs["center_err_max_rel"],
                  "rot_err_mean_deg": errs["rot_err_mean_deg"],
                  "rot_err_max_deg": errs["rot_err_max_deg"],
                  "similarity_scale": s, "object_size": errs["object_size"],
                  "gt_inside_sphere": errs.get("gt_inside"),
                  "sphere_radius_true_units": errs["sphere_radius"],
                  "true_sphere_radius": None},
        "runs": {name: {**runs[name], "chamfer": scores[name]} for name in runs},
        "load_avg_end": list(os.getloadavg()),
        "timings_s": {k: round(v, 1) for k, v in timings.items()},
        "total_s": round(time.perf_counter() - t_all, 1),
    }
    true_cams = np.load(true_dir / "cameras_sphere.npz")
    report["poses"]["true_sphere_radius"] = float(true_cams["scale_mat_0"][0, 0])
    a, b = scores["colmap_chain"]["overall"], scores["true_cameras"]["overall"]
    if a is not None and b is not None:
        report["overall_ratio_chain_over_true"] = a / b
    atomic_write_json(out / "chain.json", report)
    print(json.dumps(report, indent=1, default=float))


if __name__ == "__main__":
    main()
