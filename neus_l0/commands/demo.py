"""`neus-l0 demo`: make a small built-in scene, reconstruct it, score and picture the mesh."""

from __future__ import annotations

import argparse

from neus_l0.commands._overrides import accept_overrides

#: Size of the demo scene (views, width, height): small enough for a 2-core CPU budget.
DEMO_SCENE = {"views": 24, "width": 100, "height": 75}
#: Marching-cubes resolution of the demo mesh.
DEMO_RESOLUTION = 128
#: Wall-clock target of the whole demo (seconds); training gets what is left of it after the
#: scene, minus `DEMO_RESERVE_S` for meshing, scoring and drawing (unless
#: `train.max_seconds=...` is given on the command line).
DEMO_BUDGET_S = 280.0
DEMO_RESERVE_S = 35.0


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="make a small built-in scene, reconstruct it and score the mesh",
                       description="Render the built-in 'demo' scene, train NeuS with the "
                                   "L0-Sampler (confs/demo.yaml), extract the mesh, score it "
                                   "and draw ground truth and reconstruction side by side.")
    p.add_argument("--out", default="neus-l0-demo", help="output folder (default ./neus-l0-demo)")
    p.add_argument("--device", default=None, choices=["cpu", "cuda"])
    p.add_argument("--resolution", type=int, default=DEMO_RESOLUTION,
                   help=f"marching-cubes resolution (default {DEMO_RESOLUTION})")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    accept_overrides(p)
    return p


def score_mesh(mesh, scene_dir) -> dict | None:
    """Chamfer distance of a world-unit mesh against the synthetic scene's ground truth.

    Returns None when the evaluation module offers no synthetic scoring.
    """
    try:
        from neus_l0.evaluation.pointcloud import sample_mesh, thin_points
        from neus_l0.evaluation.synthetic import evaluate_synthetic, load_synthetic_gt
    except ImportError:  # pragma: no cover - evaluation issue not merged
        return None
    import numpy as np

    gt = load_synthetic_gt(scene_dir)
    extent = float(np.ptp(gt.points, axis=0).max())
    spacing = extent / 150.0  # about 150 samples across the object (scoring in seconds)
    pts = sample_mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), density=spacing)
    pts = thin_points(pts, radius=spacing)
    res, _ = evaluate_synthetic(pts, gt)  # DTU protocol: distances truncated at 20
    out = {k: getattr(res, k) for k in ("accuracy", "completeness", "overall")
           if hasattr(res, k)}
    out.update(counts=getattr(res, "counts", {}), sample_spacing=spacing,
               max_dist=getattr(res, "max_dist", None), object_extent=extent)
    return out


def run(args: argparse.Namespace) -> int:
    import json
    import time
    from pathlib import Path

    import numpy as np

    from neus_l0.atomic import atomic_write_json
    from neus_l0.checkpoint import latest_checkpoint
    from neus_l0.commands.train import pick_device
    from neus_l0.config import load_config
    from neus_l0.data.scene import load_scene
    from neus_l0.data.synthetic import make_scene
    from neus_l0.mesh import export_mesh, extract_mesh
    from neus_l0.train import load_trained_model, train

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    device = pick_device(args.device)
    timings: dict[str, float] = {}
    t_all = time.monotonic()

    scene_dir = out / "scene"
    t0 = time.monotonic()
    if not (scene_dir / "scene.json").is_file():
        print(f"[1/4] rendering the demo scene into {scene_dir} ...", flush=True)
        make_scene("demo", scene_dir, seed=0, progress=not args.quiet, **DEMO_SCENE)
    else:
        print(f"[1/4] reusing the scene in {scene_dir}", flush=True)
    timings["scene_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    run_dir = out / "run"
    cfg = load_config("demo", args.overrides)
    if not any(o.startswith("train.max_seconds=") for o in args.overrides):
        left = DEMO_BUDGET_S - (time.monotonic() - t_all) - DEMO_RESERVE_S
        cfg.train.max_seconds = max(30.0, left)
    scene = load_scene(scene_dir, downscale=cfg.data.downscale, device=device)
    resume = latest_checkpoint(run_dir) is not None
    print(f"[2/4] training ({cfg.train.iters} iterations, sampler {cfg.sampler}) into "
          f"{run_dir}{' (resuming)' if resume else ''} ...", flush=True)
    result = train(scene, cfg, run_dir, device=device, resume=resume, progress=not args.quiet)
    timings["train_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    print(f"[3/4] extracting the mesh at {args.resolution}^3 ...", flush=True)
    model, _, info = load_trained_model(run_dir, device)
    mesh = extract_mesh(model, np.asarray(info["scale_mat"]), resolution=args.resolution,
                        clean=True, device=device)
    mesh_path = export_mesh(mesh, out / "mesh.ply")
    timings["mesh_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    print("[4/4] scoring and drawing ...", flush=True)
    score = score_mesh(mesh, scene_dir)
    timings["score_s"] = time.monotonic() - t0
    t0 = time.monotonic()
    picture = draw_comparison(scene_dir, mesh, out / "comparison.png", score)
    timings["picture_s"] = time.monotonic() - t0
    timings["total_s"] = time.monotonic() - t_all

    metrics = {
        "chamfer": score,
        "chamfer_todo": None if score is not None else
        "neus_l0.evaluation offers no synthetic scoring yet",
        "iterations": result.iteration,
        "train_final": result.metrics,
        "mesh": {"path": str(mesh_path), "vertices": len(mesh.vertices),
                 "faces": len(mesh.faces), "resolution": args.resolution},
        "sampler": cfg.sampler,
        "device": device,
        "timings": timings,
    }
    atomic_write_json(out / "metrics.json", metrics)
    print(json.dumps({k: metrics[k] for k in ("chamfer", "timings")}, indent=1, default=str))
    print(f"scene:      {scene_dir}/")
    print(f"run:        {run_dir}/  (metrics.jsonl, validation/, checkpoints/)")
    print(f"mesh:       {mesh_path}")
    print(f"metrics:    {out / 'metrics.json'}")
    print(f"picture:    {picture}")
    return 0


def draw_comparison(scene_dir, mesh, path, score: dict | None):
    """Input view | ground-truth mesh | reconstruction, from the scene's first camera."""
    from pathlib import Path

    import cv2
    import numpy as np
    import trimesh

    from neus_l0.preview import side_by_side, splat_render

    scene_dir = Path(scene_dir)
    cams = np.load(scene_dir / "cameras_sphere.npz")
    images = sorted((scene_dir / "image").glob("*.png"))
    img = cv2.imread(str(images[0]))[..., ::-1] / 255.0
    h, w = img.shape[:2]
    up = max(1, 300 // w)  # render the meshes at about 300 pixels wide
    S = np.diag([up, up, 1.0])
    S[:2, 2] = (up - 1) / 2.0  # pixel centres stay at integers after upscaling
    P = S @ cams["world_mat_0"][:3, :4]
    gt = trimesh.load(scene_dir / "gt_mesh.ply", force="mesh")
    gt_shade, _ = splat_render(gt, P, w * up, h * up)
    rec_shade, _ = splat_render(mesh, P, w * up, h * up)
    title = None
    if score and "overall" in score:
        title = (f"Chamfer: accuracy {score['accuracy']:.2f}, completeness "
                 f"{score['completeness']:.2f}, overall {score['overall']:.2f} (world units)")
    return side_by_side(path, [("input view", img), ("ground truth", gt_shade),
                               ("reconstruction", rec_shade)], title)
