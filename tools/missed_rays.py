"""Do the rays that see a thin part render it, and what gradient reaches it? (issue #35: the
r1 rod is missing in every run)

The part is a vertical rod given by its axis (x, y), radius and height range, in world units
(``features.json`` names the rods; their geometry is in `neus_l0.synthetic.shapes`). Its
pixels are those of every view whose true first hit (``gt_depth.npz``) lies on it, in the
mask. Each run's newest checkpoint renders them inside the run's visual hull, without
jitter; per run the tool prints:

- the share of those rays that render below 0.5 opacity (*missed*), and for the missed ones
  the 10/50/90 % quantiles of their opacity, of the lowest SDF over their samples (world
  units) and of that sample's distance from the axis;
- the share of missed rays on which NeuS's mask BCE (`neus_l0.train.losses.mask_bce`) has a
  zero gradient (opacity under its clip, 1e-3), and the gradient norm on the SDF network of
  the mask BCE and of silhouette filling (`neus_l0.train.losses.missed_rays`), each summed
  over the missed rays.

    python tools/missed_rays.py SCENE RUN [RUN ...] --axis=-63,-53 --radius 1 --z 55,110

(write negative pairs with "=": ``--axis=-63,-53``)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from neus_l0.bounds.hull import load_run_hull
from neus_l0.data.rays import pixel_rays
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.synthetic import first_hits
from neus_l0.formats.open import open_scene
from neus_l0.render.volume import render_rays
from neus_l0.run.checkpoints import load_trained_model
from neus_l0.sampling.upsample import build_sampler
from neus_l0.train.losses import mask_bce, missed_rays

#: The mask BCE's clip (`mask_bce`): below it the term has no gradient.
BCE_CLIP = 1e-3


def rod_pixels(hits: np.ndarray, masks: np.ndarray, axis: tuple[float, float], radius: float,
               z: tuple[float, float]) -> np.ndarray:
    """(K, 3) (view, row, column) of the pixels whose first hit ``hits`` (V, H, W, 3), world,
    NaN for misses, lies within ``radius + 0.5`` of the vertical axis at (x, y), between
    ``z[0] + 1`` and ``z[1] - 0.5`` (its side, not the face it stands on), with ``masks``
    (V, H, W) over 0.5."""
    d = np.hypot(hits[..., 0] - axis[0], hits[..., 1] - axis[1])
    with np.errstate(invalid="ignore"):
        on = ((d < radius + 0.5) & (hits[..., 2] > z[0] + 1.0) & (hits[..., 2] < z[1] - 0.5)
              & (masks > 0.5))
    return np.argwhere(on)


def _norm(grads) -> float:
    return float(torch.sqrt(sum((g ** 2).sum() for g in grads if g is not None)))


def quantiles(x: np.ndarray) -> str:
    return " / ".join(f"{q:.2f}" for q in np.percentile(x, [10, 50, 90]))


def run_row(run: Path, scene, pixels: np.ndarray, axis: tuple[float, float]) -> str:
    """One markdown row for `run` (see the module docstring)."""
    model, cfg, info = load_trained_model(run)
    hull = load_run_hull(run)
    scale = np.asarray(info["scale_mat"], dtype=np.float64)
    v, yy, xx = (torch.as_tensor(pixels[:, k]) for k in range(3))
    o, d = pixel_rays(scene.intrinsics[v], scene.c2w[v], torch.stack([xx, yy], -1).float())
    out = render_rays(model, o, d, cfg.render, build_sampler(cfg.sampler),
                      bounds=(hull,) if hull is not None else (), create_graph=True)
    missed = out.weight_sum[:, 0] < 0.5
    n_miss = int(missed.sum())
    head = f"| {run} | {info.get('iteration')} | {len(pixels)} | {n_miss / len(pixels):.2f} |"
    if n_miss == 0:
        return head + " - | - | - | - | - | - |"
    sdf, ws = out.sdf[missed], out.weight_sum[missed]
    counted = (out.inside_sphere * out.active[:, None].float())[missed]
    masked = torch.where(counted > 0, sdf, torch.full_like(sdf, float("inf")))
    lowest, at = masked.min(dim=1)
    t = out.t_mid[missed].gather(1, at[:, None])[:, 0]
    p = (o[missed] + d[missed] * t[:, None]).detach().double().numpy() * scale[0, 0] + scale[:3, 3]
    dist = np.hypot(p[:, 0] - axis[0], p[:, 1] - axis[1])
    params = list(model.sdf.parameters())
    ones = torch.ones(n_miss, 1)
    g_bce = torch.autograd.grad(mask_bce(ws, ones) * n_miss, params, retain_graph=True,
                                allow_unused=True)
    g_fill = torch.autograd.grad(missed_rays(sdf, ones[:, 0], counted, ws) * n_miss, params,
                                 retain_graph=True, allow_unused=True)
    dead = (ws[:, 0] < BCE_CLIP).float().mean().item()
    return (head + f" {quantiles(ws[:, 0].detach().numpy())} | "
            f"{quantiles(lowest.detach().double().numpy() * scale[0, 0])} | {quantiles(dist)} | "
            f"{dead:.2f} | {_norm(g_bce):.3g} | {_norm(g_fill):.3g} |")


def _pair(text: str, name: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise SystemExit(f"--{name}: two numbers a,b, not {text!r}") from None
    return a, b


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path, help="the synthetic scene folder (gt_depth.npz)")
    ap.add_argument("runs", type=Path, nargs="+", help="run folders trained on it")
    ap.add_argument("--axis", required=True, help="the rod's axis x,y (world units)")
    ap.add_argument("--radius", type=float, required=True, help="the rod's radius")
    ap.add_argument("--z", required=True, help="the rod's bottom and top z (world units)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (2)")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    axis, z = _pair(a.axis, "axis"), _pair(a.z, "z")
    try:
        hits, _, _ = first_hits(a.scene)
        scene = open_scene(a.scene, preview=False)
        pixels = rod_pixels(hits, scene.masks.numpy(), axis, a.radius, z)
        if len(pixels) == 0:
            raise SystemExit(f"{a.scene}: no view sees a rod at {a.axis} r {a.radius} z {a.z}")
        print(f"{len(pixels)} pixels in {len(set(pixels[:, 0].tolist()))} views see the rod")
        print("| run | iteration | pixels | missed | missed: opacity 10/50/90 % | lowest SDF "
              "(world) | its distance from the axis | BCE gradient 0 | BCE gradient | "
              "filling gradient |")
        print("|---|---:|---:|---:|---|---|---|---:|---:|---:|")
        for run in a.runs:
            print(run_row(run, scene, pixels, axis))
    except NeusL0Error as exc:
        raise SystemExit(str(exc)) from None
    return 0


if __name__ == "__main__":
    sys.exit(main())
