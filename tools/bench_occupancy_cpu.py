"""What the occupancy grid costs and buys on the CPU without masks, variant by variant.

Usage:
    python tools/bench_occupancy_cpu.py [--conf demo] [--warm 300 1000] [--steps 10]
        [--rounds 3] [--rays 1024] [--variants 64:16 32:64 32:128 32:256] [override ...]

A variant is RES:EVERY[:WIDTHS] (resolution, update_every, and `widths`, default 6).

Builds the built-in ``demo`` scene (8 views, 100 x 75, with its ground truth), trains the
config without masks (default overrides: ``train.mask_weight=0``, a small background model,
``render.n_outside=16``: the womask path) and, at each ``--warm`` iteration count, for each
grid ``RES:EVERY`` (resolution, update_every):

* the update's time (median of 3) and its share of a step when amortised over EVERY steps;
* the step without update against the step without the grid (interleaved rounds of
  ``--steps`` steps, one process; the same model state, so the same work but the lookup);
* SDF points of one update, the occupied fraction of the cells, the fraction of the true
  surface (gt_points + gt_mesh vertices) in the dilated grid (what rays look up: must be
  100 %), and the fraction of 32 coarse samples on rays through mask pixels within 2 % of the
  object's size of the true surface (sphere chord against the grid's spans).

Why the decomposition instead of timing whole runs: every training batch keeps its shape
(no compaction), so the grid changes no step's network work; what it adds is the update and
the lookup, and what it buys is where the samples lie.
"""

from __future__ import annotations

import argparse
import copy
import datetime
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from neus_l0.bounds.occupancy import OccupancyGrid
from neus_l0.bounds.spans import ray_bounds
from neus_l0.config.load import load_config
from neus_l0.config.schema import OccupancyConfig, RenderConfig
from neus_l0.evaluation.io import load_mesh, load_points
from neus_l0.evaluation.sample_distance import SurfaceDistance, object_rays
from neus_l0.fields.model import make_model
from neus_l0.formats.neus import load_scene
from neus_l0.render.volume import coarse_z_vals
from neus_l0.sampling.upsample import build_sampler
from neus_l0.synthetic.scene import make_scene
from neus_l0.train.step import StepSetup, make_optimizer, train_step

WOMASK = ["train.mask_weight=0", "render.n_outside=16", "model.background.hidden=64",
          "model.background.layers=2"]


def timed_steps(model, cfg, scene, grid, it, steps, setup) -> float:
    """Seconds per step of `steps` steps from a copy of `model` (no grid update)."""
    m = copy.deepcopy(model)
    opt = make_optimizer(m, cfg)
    gen = torch.Generator().manual_seed(1)
    t0 = time.perf_counter()
    for k in range(steps):
        train_step(m, opt, scene, cfg, it + k, gen, occupancy=grid, setup=setup)
    return (time.perf_counter() - t0) / steps


def near_fraction(scene, surface, size, o, d, bounds) -> float:
    """Fraction of 32 coarse samples (no jitter) within 2 % of `size` of the true surface."""
    near, far, _ = ray_bounds(o, d, RenderConfig(cull_outside_sphere=True), bounds)
    t = coarse_z_vals(near, far, 32, perturb=False)
    pts = (o[:, None] + d[:, None] * t[..., None]).reshape(-1, 3).double().numpy()
    sm = np.asarray(scene.scale_mat)
    return float((surface(pts * sm[0, 0] + sm[:3, 3]) < 0.02 * size).mean())


def measure_grid(model, cfg, res, every, truth, widths=6.0) -> dict:
    """Update time and points, occupancy, safety and sample placement of one grid."""
    scene, surface, size, gt_unit, o, d = truth
    gcfg = OccupancyConfig(enabled=True, resolution=res, update_every=every, widths=widths)
    grid = OccupancyGrid(gcfg)
    calls = {"points": 0}

    def sdf(x, f=model.sdf.sdf):
        calls["points"] += x.shape[0]
        return f(x)

    times = []
    for _ in range(3):
        calls["points"] = 0
        grid = OccupancyGrid(gcfg)
        t0 = time.perf_counter()
        grid.update(sdf, model.variance.inv_s())
        times.append(time.perf_counter() - t0)
    kept = float(grid.contains(gt_unit).float().mean())
    return {"grid": grid, "update_s": statistics.median(times), "points": calls["points"],
            "occ": float(grid.fraction_occupied()), "kept": kept,
            "near": near_fraction(scene, surface, size, o, d, (grid,))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--conf", default="demo")
    ap.add_argument("--warm", type=int, nargs="+", default=[300, 1000])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--rays", type=int, default=1024)
    ap.add_argument("--variants", nargs="+", default=["64:16", "32:64", "32:128", "32:256"])
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args()
    torch.set_num_threads(1)
    tmp = tempfile.mkdtemp()
    root = make_scene("demo", Path(tmp) / "demo", views=8, width=100, height=75, seed=0,
                      gt_voxel=4.0, point_spacing=2.0, progress=False)
    scene = load_scene(root)
    verts, _ = load_mesh(root / "gt_mesh.ply")
    gt = np.concatenate([load_points(root / "gt_points.ply"), verts])
    surface = SurfaceDistance(points=gt)
    sm = np.asarray(scene.scale_mat)
    gt_unit = torch.as_tensor((gt - sm[:3, 3]) / sm[0, 0], dtype=torch.float32)
    size = float(np.linalg.norm(verts.max(0) - verts.min(0)))
    o, d = object_rays(scene, args.rays)
    truth = (scene, surface, size, gt_unit, o, d)
    cfg = load_config(args.conf, WOMASK + args.overrides)
    model = make_model(cfg)
    opt = make_optimizer(model, cfg)
    gen = torch.Generator().manual_seed(0)
    setup = StepSetup(sampler=build_sampler(cfg.sampler))
    it = 0
    print(f"# {datetime.date.today()} torch {torch.__version__} threads 1 load "
          f"{os.getloadavg()[0]:.1f}; conf {args.conf} {' '.join(WOMASK + args.overrides)}")
    print("| warm its | 1/s | grid R:every[:widths] | update (ms) | SDF points / update "
          "| update share "
          "of a step | step without update (x no grid) | occupied cells | true surface in "
          "grid | coarse samples near surface (sphere chord) |")
    print("|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for warm in args.warm:
        while it < warm:
            train_step(model, opt, scene, cfg, it, gen, setup=setup)
            it += 1
        near_sphere = near_fraction(scene, surface, size, o, d, ())
        grids = {v: measure_grid(model, cfg, *map(int, v.split(":")[:2]), truth,
                                 *map(float, v.split(":")[2:]))
                 for v in args.variants}
        frozen = copy.deepcopy(cfg)
        frozen.render.occupancy.start = 10**9  # the timed steps never update the grid
        base, with_grid = [], {v: [] for v in args.variants}
        for _ in range(args.rounds):
            base.append(timed_steps(model, cfg, scene, None, it, args.steps, setup))
            for v, r in grids.items():
                with_grid[v].append(timed_steps(model, frozen, scene, r["grid"], it,
                                                args.steps, setup))
        step = min(base)
        inv_s = float(model.variance.inv_s().detach())
        for v, r in grids.items():
            every = int(v.split(":")[1])
            print(f"| {warm} | {inv_s:.0f} | {v} | {1000 * r['update_s']:.0f} | "
                  f"{r['points']} | {r['update_s'] / every / step:.3f} | "
                  f"{min(with_grid[v]) / step:.3f} | {r['occ']:.3f} | {100 * r['kept']:.2f} % | "
                  f"{r['near']:.3f} ({near_sphere:.3f}) |", flush=True)
        print(f"<!-- warm {warm}: step without grid {1000 * step:.0f} ms -->", flush=True)


if __name__ == "__main__":
    main()
