"""Where a reconstructed floor sits: the height of a mesh's vertices above a floor feature's
true centre, within its radius (issue #35: a deep pit's floor comes out raised).

The feature is a ``features.json`` entry of a synthetic scene whose axis is vertical (a
pit's floor: ``deep pit floor``, ``cavity floor``, ``shaft floor``): vertices whose
horizontal distance from its centre is below its radius and whose height is within
`--window` of it are kept; prints their count and the 5th / 50th / 95th percentiles of
their height above the true floor, per mesh.

    python tools/floor_height.py SCENE "cavity floor" MESH [MESH ...] [--window 25]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import trimesh


def floor_heights(vertices: np.ndarray, centre: np.ndarray, radius: float,
                  window: float) -> np.ndarray:
    """(K,) heights above ``centre[2]`` of the vertices (N, 3) within `radius` of the
    vertical axis through `centre` and within `window` of its height."""
    rel = vertices - centre
    near = (np.hypot(rel[:, 0], rel[:, 1]) < radius) & (np.abs(rel[:, 2]) < window)
    return rel[near, 2]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path, help="the synthetic scene folder (features.json)")
    ap.add_argument("feature", help="a floor feature's name, e.g. 'cavity floor'")
    ap.add_argument("meshes", type=Path, nargs="+", help="meshes in world units")
    ap.add_argument("--window", type=float, default=25.0,
                    help="height window around the floor, world units (default 25)")
    a = ap.parse_args(argv)
    path = a.scene / "features.json"
    if not path.is_file():
        raise SystemExit(f"{path}: missing (a synthetic scene from neus-l0 synth has one)")
    missing = [str(m) for m in a.meshes if not m.is_file()]
    if missing:
        raise SystemExit(f"no such mesh: {', '.join(missing)}")
    feats = json.loads(path.read_text())["features"]
    f = next((f for f in feats if f["name"] == a.feature), None)
    if f is None:
        raise SystemExit(f"{a.scene / 'features.json'}: no feature named {a.feature!r}")
    if f.get("axis") != [0.0, 0.0, 1.0]:
        raise SystemExit(f"{a.feature!r}: not a floor with a vertical axis")
    centre = np.asarray(f["center"], dtype=np.float64)
    print("| mesh | vertices | 5 % | median | 95 % |")
    print("|---|---:|---:|---:|---:|")
    for m in a.meshes:
        h = floor_heights(np.asarray(trimesh.load(m, process=False).vertices), centre,
                          float(f["radius"]), a.window)
        pct = np.percentile(h, [5, 50, 95]) if h.size else [np.nan] * 3
        print(f"| {m} | {h.size} | " + " | ".join(f"{p:+.1f}" for p in pct) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
