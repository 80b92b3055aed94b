"""How far a reconstructed surface sits outside the true one: the exact SDF of a built-in
synthetic scene at points spread over each mesh (issue #35: the trained zero level sits
outside).

Points within `--near` world units of the true surface count (floaters and far misses are
the Chamfer's business, not the level's); prints per mesh their number, the median signed
distance (positive: outside), the share outside, and the same per feature ball of
``features.json`` with `--features`.

    python tools/surface_offset.py SCENE MESH [MESH ...] [--samples 200000] [--near 3]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
import trimesh

from neus_l0.errors import NeusL0Error
from neus_l0.synthetic.scene import scene_world_sdf


def signed_distances(points: np.ndarray, sdf) -> np.ndarray:
    """(N,) the exact SDF (world units) at (N, 3) world points, in chunks."""
    out = []
    for chunk in np.array_split(points, max(1, len(points) // 65536)):
        with torch.no_grad():
            out.append(sdf(torch.as_tensor(chunk, dtype=torch.float32)).reshape(-1).numpy())
    return np.concatenate(out) if out else np.zeros(0)


def offset_row(d: np.ndarray, near: float) -> tuple[int, float, float]:
    """(count, median, share > 0) of the distances `d` with ``|d| < near``."""
    d = d[np.abs(d) < near]
    if d.size == 0:
        return 0, float("nan"), float("nan")
    return int(d.size), float(np.median(d)), float((d > 0).mean())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path, help="a built-in synthetic scene's folder (scene.json)")
    ap.add_argument("meshes", type=Path, nargs="+", help="meshes in world units")
    ap.add_argument("--samples", type=int, default=200_000, help="points per mesh")
    ap.add_argument("--near", type=float, default=3.0, help="world units (default 3)")
    ap.add_argument("--features", action="store_true", help="a row per feature ball too")
    a = ap.parse_args(argv)
    try:
        sdf, _ = scene_world_sdf(a.scene)
    except NeusL0Error as exc:
        raise SystemExit(str(exc)) from None
    missing = [str(m) for m in a.meshes if not m.is_file()]
    if missing:
        raise SystemExit(f"no such mesh: {', '.join(missing)}")
    feats = []
    if a.features:
        path = a.scene / "features.json"
        try:
            feats = json.loads(path.read_text(encoding="utf-8"))["features"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise SystemExit(f"{path}: unreadable ({exc})") from None
    print("| mesh | part | points | median (world) | outside |")
    print("|---|---|---:|---:|---:|")
    for m in a.meshes:
        mesh = trimesh.load(m, process=False)
        pts = np.asarray(trimesh.sample.sample_surface(mesh, a.samples, seed=0)[0])
        d = signed_distances(pts, sdf)
        parts = [("all", np.ones(len(pts), bool))]
        parts += [(f["name"], np.linalg.norm(pts - np.asarray(f["center"]), axis=1)
                   < float(f["radius"])) for f in feats]
        for part, keep in parts:
            n, med, out = offset_row(d[keep], a.near)
            print(f"| {m} | {part} | {n} | {med:+.3f} | {out:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
