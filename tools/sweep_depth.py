"""Would a plane sweep at mesh time find a pit's true floor? (issue #35, outside training)

For every pixel whose first true hit (`first_hits`) lies in a feature's ball
(``features.json``), the trained mesh's depth along the pixel's ray is taken
(`neus_l0.mesh.plane_sweep.depth_map`), then depths from `--before` world units in front of
it to `--behind` behind it are swept (`sweep_depths`, as `neus-l0 mesh --photo-carve`
sweeps): at each, a `--patch` x `--patch` patch on the plane through the point, normal to
the mesh there, is carried into every other view, each scored (1 - NCC) / 2 on grey
values, and the best `--best` views count (the others may not see the point; nothing here
knows which do). The depth of least cost is the sweep's answer. Prints, per feature, the
median |depth - true depth| of the mesh and of the sweep, the signed medians, and the share
of pixels each puts within `--tol` of the truth; with `--open` the same for as many pixels
of the surface outside every feature's balls (where the mesh is right, a sweep should not
move it). The defaults (5x5, best 2) are the first measurement's; `--photo-carve` sweeps with
`neus_l0.mesh.plane_sweep.PATCH` and `BEST`.

    python tools/sweep_depth.py SCENE MESH [--features "cavity floor"] [--open 500]
        [--max-pixels 1000] [--before 4] [--behind 20] [--step 0.25] [--patch 5] [--best 2]
        [--out t.json]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
import trimesh

from neus_l0.atomic import atomic_write_json
from neus_l0.data.cameras import read_grays
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.features import load_features
from neus_l0.evaluation.synthetic import first_hits
from neus_l0.mesh.plane_sweep import INVALID, depth_map, sample_count, sweep_depths
from neus_l0.mesh.raster import finest_footprint


def table(root: Path, mesh_path: Path, names: list[str] | None, n_open: int, a) -> list[dict]:
    """One row per feature in `names` (all when None), and the open surface when `n_open`:
    the pixels counted and the mesh's and the sweep's depth errors (medians, signed medians,
    shares within ``a.tol``). ``a`` holds the sweep's settings (`main`'s arguments)."""
    pts, depth, P = first_hits(root)
    grays = read_grays(root)
    if sorted(grays) != list(range(len(P))):
        raise SystemExit(f"{root / 'image'}: views {sorted(grays)[:5]}... for {len(P)} cameras")
    gray = torch.as_tensor(np.stack([grays[v] for v in range(len(P))]))
    mesh = trimesh.load(mesh_path, process=False)
    foot = finest_footprint(mesh, P)
    samples, face = trimesh.sample.sample_surface(mesh, sample_count(mesh, foot), seed=0)
    normals = np.asarray(mesh.face_normals)[face]
    feats = load_features(root)
    unknown = sorted(set(names or ()) - {f["name"] for f in feats})
    if unknown:
        raise SystemExit(f"{root / 'features.json'}: no feature {unknown} (it has "
                         f"{[f['name'] for f in feats]})")
    groups = [(f["name"], np.linalg.norm(pts - np.asarray(f["center"]), axis=-1) <= f["radius"])
              for f in feats if names is None or f["name"] in names]
    if n_open:
        anywhere = np.zeros(depth.shape, bool)
        for f in feats:
            anywhere |= np.linalg.norm(pts - np.asarray(f["center"]), axis=-1) <= f["radius"] * 1.5
        sel = np.isfinite(depth) & ~anywhere
        rng = np.random.default_rng(0)
        flat = np.flatnonzero(sel)
        keep = np.zeros(sel.size, bool)
        keep[rng.choice(flat, min(n_open, flat.size), replace=False)] = True
        groups.append(("open surface", keep.reshape(sel.shape)))
    rng = np.random.default_rng(1)
    for _, inside in groups:  # at most --max-pixels per group, drawn at random
        flat = np.flatnonzero(inside)
        if flat.size > a.max_pixels:
            inside.reshape(-1)[rng.choice(flat, flat.size - a.max_pixels, replace=False)] = False
    zs = np.arange(-a.before, a.behind + 1e-9, a.step)
    rows = []
    for name, inside in groups:
        err_m, err_s = [], []
        for v in range(len(P)):
            ys, xs = np.nonzero(inside[v])
            if not len(xs):
                continue
            pix = np.stack([xs, ys], -1)
            zbuf, nbuf = depth_map(samples, normals, P[v], depth.shape[1:], foot)
            z0, n = zbuf[ys, xs], nbuf[ys, xs]
            hit = np.isfinite(z0)
            if not hit.any():
                continue
            zb, cost, _ = sweep_depths(gray, P, v, pix[hit], n[hit], z0[hit], zs, a.patch,
                                       a.best)
            truth = depth[v][ys[hit], xs[hit]]
            ok = cost < INVALID
            err_m.append((z0[hit] - truth)[ok])
            err_s.append((zb - truth)[ok])
        em, es = np.concatenate(err_m), np.concatenate(err_s)
        rows.append({"feature": name, "pixels": int(em.size),
                     "mesh_median_abs": float(np.median(np.abs(em))),
                     "sweep_median_abs": float(np.median(np.abs(es))),
                     "mesh_median": float(np.median(em)), "sweep_median": float(np.median(es)),
                     "mesh_within_tol": float(np.mean(np.abs(em) < a.tol)),
                     "sweep_within_tol": float(np.mean(np.abs(es) < a.tol))})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path, help="a synthetic scene folder (neus-l0 synth)")
    ap.add_argument("mesh", type=Path, help="a mesh in world units (neus-l0 mesh)")
    ap.add_argument("--features", default="", help="comma-separated names (default: all)")
    ap.add_argument("--open", type=int, default=0, help="also this many open-surface pixels")
    ap.add_argument("--max-pixels", type=int, default=1000,
                    help="at most this many pixels per feature, drawn at random")
    ap.add_argument("--before", type=float, default=4.0, help="sweep start, world units")
    ap.add_argument("--behind", type=float, default=20.0, help="sweep end, world units")
    ap.add_argument("--step", type=float, default=0.25, help="sweep step, world units")
    ap.add_argument("--patch", type=int, default=5, help="odd patch side, pixels")
    ap.add_argument("--best", type=int, default=2, help="views that count")
    ap.add_argument("--tol", type=float, default=1.5, help="world units")
    ap.add_argument("--out", type=Path, help="also write the table as JSON")
    a = ap.parse_args(argv)
    if a.patch < 3 or a.patch % 2 == 0:
        raise SystemExit(f"--patch {a.patch}: an odd side of 3 or more")
    names = [n.strip() for n in a.features.split(",") if n.strip()] or None
    try:
        rows = table(a.scene, a.mesh, names, a.open, a)
    except NeusL0Error as exc:
        raise SystemExit(f"sweep_depth: {exc}") from None
    print("| feature | pixels | mesh: median abs / signed / within tol | sweep: median abs / "
          "signed / within tol |")
    print("|---|---:|---|---|")
    for r in rows:
        print(f"| {r['feature']} | {r['pixels']} | {r['mesh_median_abs']:.2f} / "
              f"{r['mesh_median']:+.2f} / {r['mesh_within_tol']:.2f} | "
              f"{r['sweep_median_abs']:.2f} / {r['sweep_median']:+.2f} / "
              f"{r['sweep_within_tol']:.2f} |")
    if a.out:
        atomic_write_json(a.out, {"scene": str(a.scene), "mesh": str(a.mesh), "rows": rows,
                                  "args": {k: str(v) for k, v in vars(a).items()}})
    return 0


if __name__ == "__main__":
    sys.exit(main())
