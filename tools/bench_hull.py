"""Visual hull measurements: build cost and tightness against the grid size, safety on
synthetic scenes, and how much the per-ray bounds shorten the rays.

    python tools/bench_hull.py cost SCENE [--upscale 4] [--resolutions 64,96,128,192,256]
    python tools/bench_hull.py safety SCENE [SCENE ...] [--margin 2]
    python tools/bench_hull.py rays SCENE [SCENE ...]

`cost` upscales the masks by an integer factor (nearest) with the matching intrinsics
(``x_old = s x_new + (s - 1) / 2`` inverted), e.g. the shared DTU scan at 400x300 x 4 =
49 views of 1600x1200. `safety` needs synthetic scenes (gt_points.ply, gt_mesh.ply,
features.json): the fraction of true surface points inside the hull for clean masks, masks
eroded by a 2-px disc, and view 5's principal point moved by 1 px, also without the points
near the "thin" features. Timings on a shared CPU are noisy.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from neus_l0.bounds.hull import DEFAULT_MARGIN_PX, carve_hull, hull_from_scene
from neus_l0.data.rays import random_rays
from neus_l0.evaluation.io import load_points
from neus_l0.formats.neus import load_scene


def erode(masks: torch.Tensor, px: int) -> torch.Tensor:
    """Binary masks eroded by a disc of radius `px`."""
    r = torch.arange(-px, px + 1, dtype=torch.float32)
    disc = ((r[:, None] ** 2 + r[None, :] ** 2) <= px * px + 1e-6).float()
    hit = F.conv2d((masks <= 0.5).float()[:, None], disc[None, None], padding=px)[:, 0] > 0
    return (~hit).float() * (masks > 0.5).float()


def cost(args) -> None:
    s = load_scene(args.scene)
    up = args.upscale
    m = (F.interpolate(s.masks[:, None], scale_factor=up, mode="nearest")[:, 0] > 0.5).float()
    Sinv = torch.tensor([[up, 0, (up - 1) / 2], [0, up, (up - 1) / 2], [0, 0, 1]],
                        dtype=torch.float32)
    K = Sinv @ s.intrinsics
    print(f"masks {tuple(m.shape)}, torch threads {torch.get_num_threads()}")
    for R in (int(r) for r in args.resolutions.split(",")):
        t = time.perf_counter()
        hull = carve_hull(m, K, s.c2w, resolution=R, margin_px=args.margin)
        print(f"R={R}: {time.perf_counter() - t:.2f} s, keeps "
              f"{hull.report.fraction_kept:.4f} of the sphere, "
              f"{len(hull.report.warnings)} warnings", flush=True)


def safety(args) -> None:
    for root in (Path(r) for r in args.scenes):
        s = load_scene(root)
        S = s.scale_mat
        pts = np.concatenate([load_points(root / "gt_points.ply"),
                              load_points(root / "gt_mesh.ply")])
        feats = json.loads((root / "features.json").read_text())["features"]
        thin = np.zeros(len(pts), bool)
        for f in feats:
            if f["kind"] == "thin":
                thin |= np.linalg.norm(pts - np.array(f["center"]), axis=1) <= 1.2 * f["radius"]
        x = torch.from_numpy((pts - S[:3, 3]) @ np.linalg.inv(S[:3, :3]).T).float()
        K1 = s.intrinsics.clone()
        K1[5, 0, 2] += 1.0
        out = [f"{root.name} {s.n_views}x{s.width}x{s.height} ({len(pts)} points)"]
        for case, m, K in (("clean", s.masks, s.intrinsics),
                           ("eroded 2px", erode(s.masks, 2), s.intrinsics),
                           ("view 5 moved 1px", s.masks, K1)):
            t = time.perf_counter()
            h = carve_hull(m, K, s.c2w, margin_px=args.margin)
            dt = time.perf_counter() - t
            c = h.contains(x).numpy()
            out.append(f"{case}: {100 * c.mean():.3f} % inside ({100 * c[~thin].mean():.3f} % "
                       f"off thin parts), keeps {100 * h.report.fraction_kept:.1f} %, "
                       f"{dt:.1f} s, {len(h.report.warnings)} warnings")
        print(" | ".join(out), flush=True)


def rays(args) -> None:
    for root in args.scenes:
        s = load_scene(root)
        hull = hull_from_scene(s)
        r = random_rays(s, 20000, torch.Generator().manual_seed(0))
        o, d = r["origins"], r["dirs"]
        b = (o * d).sum(-1, keepdim=True)
        disc = b * b - ((o * o).sum(-1, keepdim=True) - 1)
        sph = (disc > 0)[:, 0]
        near = (-b - disc.clamp_min(0).sqrt()).clamp_min(0)
        far = -b + disc.clamp_min(0).sqrt()
        lo, hi, hits = hull.ray_bounds(o, d, near, far)
        fg = r["mask"][:, 0] > 0.5
        chord, span = float((far - near)[fg].mean()), float((hi - lo)[fg].mean())
        print(f"{root}: keeps {hull.report.fraction_kept:.3f}; of the rays that meet the "
              f"sphere {float(hits[sph].float().mean()):.3f} meet the hull; foreground rays: "
              f"chord {chord:.3f} -> [lo, hi] {span:.3f} ({chord / span:.2f}x shorter)")
        for B in (1024, 4096):
            args_b = (o[:B], d[:B], near[:B], far[:B])
            hull.ray_bounds(*args_b)
            t = time.perf_counter()
            for _ in range(20):
                hull.ray_bounds(*args_b)
            print(f"  ray_bounds, {B} rays: {(time.perf_counter() - t) / 20 * 1e3:.1f} ms")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="what", required=True)
    c = sub.add_parser("cost")
    c.add_argument("scene")
    c.add_argument("--upscale", type=int, default=4)
    c.add_argument("--resolutions", default="64,96,128,192,256")
    c.add_argument("--margin", type=float, default=DEFAULT_MARGIN_PX)
    s = sub.add_parser("safety")
    s.add_argument("scenes", nargs="+")
    s.add_argument("--margin", type=float, default=DEFAULT_MARGIN_PX)
    r = sub.add_parser("rays")
    r.add_argument("scenes", nargs="+")
    args = p.parse_args()
    {"cost": cost, "safety": safety, "rays": rays}[args.what](args)


if __name__ == "__main__":
    main()
