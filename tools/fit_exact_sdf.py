"""Can the SDF network hold a thin part at all? Fit it to a synthetic scene's exact SDF,
supervised (no rendering), then probe a rod (issue #35: is the missing r1 rod a matter of
capacity or of training?).

The config's SDF network (hash grid and MLP, every level on) is fitted for `--steps` Adam
steps (lr 3e-3, cosine to 5 %) on 4096 points a step near the true surface (its
``gt_points.ply`` jittered by 1 or 4 world units) and 1024 uniform in the unit sphere's box:
L1 to the exact SDF plus 0.1 x the Eikonal term. Prints the mean L1 (world units) as it
goes, then the lowest SDF across the rod (a 6-unit segment through its axis along x) at
four heights, fitted against exact: a rod the network holds reads negative. With `--mesh
OUT.ply` the fitted SDF's zero level is also written in world units (marching cubes at
`--resolution`), for `neus-l0 eval OUT.ply --scene SCENE`: what the network can hold at each
feature when training is no limit (a deep pit's floor, issue #35).

    python tools/fit_exact_sdf.py SCENE --axis=-63,-53 --z 55,110 [--steps 3000]
                                  [--conf demo] [--mesh OUT.ply [--resolution 256]]
                                  [override ...]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from neus_l0.config.load import load_config
from neus_l0.errors import NeusL0Error
from neus_l0.fields.model import make_model
from neus_l0.mesh.extract import export_mesh, marching_cubes, sdf_grid
from neus_l0.synthetic.scene import scene_world_sdf


def fit(net: torch.nn.Module, sdf, points: torch.Tensor, steps: int, unit: float,
        seed: int = 0, log=print) -> float:
    """Fit `net` (normalised frame) to ``sdf`` (normalised points (N, 3) float64 -> (N,))
    near ``points`` (P, 3), normalised; `unit`: one world unit in normalised units. Returns
    the last step's mean L1 (normalised)."""
    g = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    t0, l1 = time.time(), float("nan")
    for it in range(steps):
        idx = torch.randint(0, len(points), (4096,), generator=g)
        sigma = torch.where(torch.rand(4096, 1, generator=g) < 0.5, 1.0, 4.0)
        near = points[idx] + torch.randn(4096, 3, generator=g) * sigma * unit
        x = torch.cat([near, torch.rand(1024, 3, generator=g) * 2 - 1])
        with torch.no_grad():
            target = sdf(x.double()).float()
        out, grad = net.forward_and_gradient(x)
        err = (out[:, 0] - target).abs().mean()
        loss = err + 0.1 * ((grad.norm(dim=-1) - 1) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        for group in opt.param_groups:
            group["lr"] = 3e-3 * (0.05 + 0.475 * (1 + math.cos(math.pi * (it + 1) / steps)))
        l1 = err.item()
        if it % 500 == 0 or it == steps - 1:
            log(f"step {it}: L1 {l1 / unit:.3f} world units ({time.time() - t0:.0f} s)")
    return l1


def rod_minima(net: torch.nn.Module, sdf_world, center: np.ndarray, radius: float,
               axis: tuple[float, float], heights: list[float]) -> list[tuple[float, float]]:
    """(fitted, exact) lowest SDF in world units across the rod (x within 3 units of the
    axis) at each height."""
    rows = []
    for z in heights:
        xs = np.linspace(axis[0] - 3.0, axis[0] + 3.0, 121)
        pts = np.stack([xs, np.full_like(xs, axis[1]), np.full_like(xs, z)], 1)
        with torch.no_grad():
            f = net(torch.as_tensor((pts - center) / radius, dtype=torch.float32),
                    count=False)[:, 0].numpy() * radius
        exact = sdf_world(torch.as_tensor(pts)).numpy().ravel()
        rows.append((float(f.min()), float(exact.min())))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path, help="a synthetic scene folder (scene.json)")
    ap.add_argument("--axis", required=True, help="the rod's axis x,y (world units)")
    ap.add_argument("--z", required=True, help="the rod's bottom and top z (world units)")
    ap.add_argument("--steps", type=int, default=3000, help="Adam steps (3000)")
    ap.add_argument("--conf", default="demo", help="the config whose SDF network is fitted")
    ap.add_argument("--mesh", type=Path, help="also write the fitted zero level here")
    ap.add_argument("--resolution", type=int, default=256, help="its marching cubes (256)")
    ap.add_argument("overrides", nargs="*", help="config overrides, e.g. "
                    "model.sdf.encoding.finest_resolution=128")
    a = ap.parse_intermixed_args(argv)  # overrides may follow the options
    torch.set_num_threads(1)
    try:
        ax, ay = (float(v) for v in a.axis.split(","))
        z0, z1 = (float(v) for v in a.z.split(","))
    except ValueError:
        raise SystemExit("--axis and --z: two numbers a,b each") from None
    try:
        sdf_world, _ = scene_world_sdf(a.scene)
        sphere = json.loads((a.scene / "scene.json").read_text())["sphere"]
        center, radius = np.asarray(sphere["center"], dtype=np.float64), float(sphere["radius"])
        gt = a.scene / "gt_points.ply"
        if not gt.is_file():
            raise NeusL0Error(f"{gt}: missing (a scene from neus-l0 synth has one)")
        cfg = load_config(a.conf, a.overrides)
    except (NeusL0Error, KeyError) as exc:
        raise SystemExit(f"{a.scene}: {exc}") from None
    net = make_model(cfg).sdf
    if hasattr(net.encoding, "steps"):
        net.encoding.steps.fill_(10**9)  # every level of a progressive grid on
    try:
        vertices = np.asarray(trimesh.load(gt).vertices, dtype=np.float64)
    except Exception as exc:  # trimesh raises many kinds on a damaged file
        raise SystemExit(f"{gt}: unreadable ({exc})") from None
    if vertices.ndim != 2 or len(vertices) == 0:
        raise SystemExit(f"{gt}: no points")
    points = torch.as_tensor((vertices - center) / radius, dtype=torch.float32)
    c = torch.as_tensor(center)

    def sdf_norm(x: torch.Tensor) -> torch.Tensor:
        return sdf_world(x * radius + c).reshape(-1) / radius

    fit(net, sdf_norm, points, a.steps, 1.0 / radius)
    net.eval()
    heights = [z0 + f * (z1 - z0) for f in (0.3, 0.5, 0.7, 0.9)]
    print("| height | fitted | exact |")
    print("|---:|---:|---:|")
    minima = rod_minima(net, sdf_world, center, radius, (ax, ay), heights)
    for h, (got, want) in zip(heights, minima, strict=True):
        print(f"| {h:.1f} | {got:+.2f} | {want:+.2f} |")
    if a.mesh is not None:
        export_mesh(fitted_mesh(net, center, radius, a.resolution), a.mesh)
        print(f"wrote {a.mesh}")
    return 0


def fitted_mesh(net: torch.nn.Module, center: np.ndarray, radius: float,
                resolution: int) -> trimesh.Trimesh:
    """The fitted SDF's zero level (marching cubes on [-1, 1]^3 at `resolution`) in world
    units."""
    volume = sdf_grid(lambda x: net(x, count=False)[:, 0], resolution)
    verts, faces = marching_cubes(volume)
    return trimesh.Trimesh(verts * radius + center, faces, process=False)


if __name__ == "__main__":
    sys.exit(main())
