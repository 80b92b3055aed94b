"""`neus-l0 demo`: make a small built-in scene, reconstruct it, score and picture the mesh."""

from __future__ import annotations

import argparse

from neus_l0.commands._overrides import accept_overrides

#: Size of the demo scene (views, width, height): a step costs the same at any image size, and
#: 200x150 scored 15-20 % lower Chamfer than 100x75 at equal iterations (docs/BENCHMARKS.md).
DEMO_SCENE = {"views": 24, "width": 200, "height": 150}
#: Marching-cubes resolution of the demo mesh.
DEMO_RESOLUTION = 96
#: Wall-clock target of the whole demo (seconds); training gets what is left of it after the
#: scene, minus `DEMO_RESERVE_S` for meshing, scoring and drawing (unless
#: `train.max_seconds=...` is given on the command line).
DEMO_BUDGET_S = 148.0
DEMO_RESERVE_S = 14.0
#: Training config of the demo (`confs/demo.yaml`).
DEMO_CONF = "demo"


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="make a small built-in scene, reconstruct it and score the mesh",
                       description="Render the built-in 'demo' scene, train NeuS with the "
                                   "L0-Sampler (confs/demo.yaml: a hash grid and small MLPs "
                                   "sized for a 2-core CPU), extract the mesh, score it and "
                                   "draw ground truth and reconstruction side by side.")
    p.add_argument("--out", default="neus-l0-demo", help="output folder (default ./neus-l0-demo)")
    p.add_argument("--device", default=None, choices=["cpu", "cuda"])
    p.add_argument("--resolution", type=int, default=DEMO_RESOLUTION,
                   help=f"marching-cubes resolution (default {DEMO_RESOLUTION})")
    p.add_argument("--conf", default=DEMO_CONF,
                   help=f"training config (default {DEMO_CONF}: the CPU-sized hash-grid setting)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch CPU threads (default: free cores, from the load average)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    accept_overrides(p)
    return p


def score_demo_mesh(mesh_path, scene_dir) -> dict:
    """Chamfer report (`neus_l0.evaluation.score.score_mesh`) of the demo mesh, sampled
    about 150 points across the object so that scoring takes seconds."""
    import numpy as np
    import trimesh

    from neus_l0.evaluation.score import ScoreSpec, score_mesh

    gt = trimesh.load(scene_dir / "gt_mesh.ply", force="mesh")
    extent = float(np.ptp(np.asarray(gt.vertices), axis=0).max())
    return score_mesh(mesh_path, ScoreSpec(scene=scene_dir, density=extent / 150.0),
                      log=lambda _msg: None)


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
    import time

    import torch

    from neus_l0.atomic import atomic_write_json
    from neus_l0.commands._paths import check_output_dir
    from neus_l0.config.load import load_config
    from neus_l0.data.synthetic import make_scene
    from neus_l0.device import free_cpu_threads, pick_device
    from neus_l0.mesh.extract import export_mesh
    from neus_l0.mesh.from_run import mesh_from_run

    check_numbers(args)
    out = check_output_dir(args.out, "--out")
    cfg = load_config(args.conf, args.overrides)  # a bad config fails before any work
    device = pick_device(args.device)
    out.mkdir(parents=True, exist_ok=True)
    threads = free_cpu_threads(args.threads)
    torch.set_num_threads(threads)
    timings: dict[str, float] = {}
    t_all = time.monotonic()

    scene_dir = out / "scene"
    t0 = time.monotonic()
    if not (scene_dir / "scene.json").is_file():
        print(f"[1/4] rendering the demo scene into {scene_dir} ...", flush=True)
        make_scene("demo", scene_dir, seed=0, progress=not args.quiet, threads=threads,
                   **DEMO_SCENE)
    else:
        print(f"[1/4] reusing the scene in {scene_dir}", flush=True)
    timings["scene_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    run_dir = out / "run"
    if not any(o.startswith("train.max_seconds=") for o in args.overrides):
        left = DEMO_BUDGET_S - (time.monotonic() - t_all) - DEMO_RESERVE_S
        cfg.train.max_seconds = max(30.0, left)
    result = _train_demo(args, cfg, scene_dir, run_dir, device, threads)
    timings["train_s"] = time.monotonic() - t0
    if result.signal:
        print(f"neus-l0 demo: stopped by {result.signal} at iteration {result.iteration}; "
              f"checkpoint {result.checkpoint} written; run the same command again to "
              "resume", file=sys.stderr)
        return result.exit_code

    t0 = time.monotonic()
    print(f"[3/4] extracting the mesh at {args.resolution}^3 ...", flush=True)
    mesh = mesh_from_run(run_dir, args.resolution, device, progress=not args.quiet).mesh
    mesh_path = export_mesh(mesh, out / "mesh.ply")
    timings["mesh_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    print("[4/4] scoring and drawing ...", flush=True)
    score = score_demo_mesh(mesh_path, scene_dir)
    timings["score_s"] = time.monotonic() - t0
    t0 = time.monotonic()
    picture = draw_comparison(scene_dir, mesh, out / "comparison.png", score)
    timings["picture_s"] = time.monotonic() - t0
    timings["total_s"] = time.monotonic() - t_all

    metrics = {
        "chamfer": score,
        "iterations": result.iteration,
        "train_final": result.metrics,
        "mesh": {"path": str(mesh_path), "vertices": len(mesh.vertices),
                 "faces": len(mesh.faces), "resolution": args.resolution},
        "sampler": cfg.sampler.name,
        "conf": str(args.conf),
        "device": device,
        "threads": threads,
        "timings": timings,
    }
    atomic_write_json(out / "metrics.json", metrics)
    print(json.dumps({"chamfer": {k: score.get(k) for k in
                                  ("accuracy", "completeness", "overall")},
                      "iterations": result.iteration, "timings": timings}, indent=1))
    print(f"scene:      {scene_dir}/")
    print(f"run:        {run_dir}/  (metrics.jsonl, validation/, checkpoints/)")
    print(f"mesh:       {mesh_path}")
    print(f"metrics:    {out / 'metrics.json'}")
    print(f"picture:    {picture}")
    return 0


def _train_demo(args: argparse.Namespace, cfg, scene_dir, run_dir, device: str, threads: int):
    """Train (or resume) the demo's run: `train.compile: auto` resolved first, so that a
    re-run is checked against the settings the run really used."""
    import sys

    from neus_l0.data.scene import load_scene
    from neus_l0.run.checkpoints import checkpoint_iteration, latest_checkpoint
    from neus_l0.train.compile_auto import resolve_compile
    from neus_l0.train.loop import train

    scene = load_scene(scene_dir, downscale=cfg.data.downscale, device=device)
    newest = latest_checkpoint(run_dir)
    resume = newest is not None
    cfg, line = resolve_compile(cfg, device, checkpoint_iteration(newest) if resume else 0,
                                run_dir)
    if line:
        print(f"neus-l0: {line}", file=sys.stderr, flush=True)
    if resume:
        _check_same_settings(run_dir, cfg)
    print(f"[2/4] training ({cfg.train.iters} iterations at most, "
          f"{cfg.train.max_seconds:.0f} s budget, sampler {cfg.sampler.name}, {threads} "
          f"thread{'s' if threads > 1 else ''}, {'compiled' if cfg.train.compile else 'eager'})"
          f" into {run_dir}{' (resuming)' if resume else ''} ...", flush=True)
    return train(scene, cfg, run_dir, device=device, resume=resume, progress=not args.quiet)


def draw_comparison(scene_dir, mesh, path, score: dict | None):
    """Input view | ground-truth mesh | reconstruction, from the scene's first camera."""
    from pathlib import Path

    import cv2
    import trimesh

    from neus_l0.data.cameras import read_world_mats, scale_projection
    from neus_l0.mesh.preview import side_by_side, splat_render

    scene_dir = Path(scene_dir)
    images = sorted((scene_dir / "image").glob("*.png"))
    img = cv2.imread(str(images[0]))[..., ::-1] / 255.0
    h, w = img.shape[:2]
    up = max(1, 300 // w)  # render the meshes at about 300 pixels wide
    P = scale_projection(read_world_mats(scene_dir)[0], up)
    gt = trimesh.load(scene_dir / "gt_mesh.ply", force="mesh")
    gt_shade, _ = splat_render(gt, P, w * up, h * up)
    rec_shade, _ = splat_render(mesh, P, w * up, h * up)
    title = None
    if score and all(score.get(k) is not None for k in ("accuracy", "completeness", "overall")):
        title = (f"Chamfer: accuracy {score['accuracy']:.2f}, completeness "
                 f"{score['completeness']:.2f}, overall {score['overall']:.2f} (world units)")
    return side_by_side(path, [("input view", img), ("ground truth", gt_shade),
                               ("reconstruction", rec_shade)], title)


def _check_same_settings(run_dir, cfg) -> None:
    """A re-run of the demo resumes its run: only with the settings it started with (beyond
    length and logging), or it would label an `l0` run `hvs`.

    Raises:
        NeusL0Error: naming the keys that differ and the way out.
    """
    from neus_l0.config.load import load_config
    from neus_l0.errors import NeusL0Error
    from neus_l0.run.resumes import changed_keys, guarded_keys, recorded_overrides

    if not (run_dir / "config.yaml").is_file():
        return
    before = load_config(run_dir / "config.yaml", recorded_overrides(run_dir))
    guarded = guarded_keys(changed_keys(before, cfg))
    if guarded:
        raise NeusL0Error(f"{run_dir}: holds a demo run trained with other settings "
                          f"({', '.join(guarded)}); choose another --out, or delete {run_dir} "
                          "to start that run over")
