"""A held-out object for the mesh-time filling of issue #35 (`neus-l0 mesh --fill-missed`): a
stool whose thin parts the low views see against the background, built after the step was
fixed and never used to tune it.

A seat (radius 90, 16 thick) on three legs (radius 3) joined by rungs (radius 1.5), two
antennas (radius 1 and 2) standing on the seat, on a base plate 250 x 250 x 12; designed z-up
at 250 across, so that `neus-l0 synth`'s scale for a mesh file is 1 and the radii stay in
world units. Writes ``OUT/stool.ply`` y-up (synth turns y-up to z-up) and
``OUT/features.json``: each leg, rung and antenna as a thin feature in synth's world frame
(the design shifted by ``WORLD_OFFSET`` minus its bounding box's centre), to copy into the
synthesised scene:

    python tools/make_stool.py OUT
    neus-l0 synth OUT/stool.ply SCENE --views 49 --width 400 --height 300
    cp OUT/features.json SCENE/features.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import trimesh

from neus_l0.synthetic.scene import WORLD_OFFSET


def stool() -> tuple[trimesh.Trimesh, list[dict]]:
    """The stool (z-up, world units) and its thin features (centres in the design's frame)."""
    parts, feats = [], []

    def rod(a, b, r, name):
        a, b = np.asarray(a, float), np.asarray(b, float)
        parts.append(trimesh.creation.cylinder(radius=r, segment=np.stack([a, b]), sections=32))
        feats.append({"kind": "thin", "name": name, "center": ((a + b) / 2).tolist(),
                      "radius": float(np.linalg.norm(b - a) / 2),
                      "axis": ((b - a) / np.linalg.norm(b - a)).tolist()})

    seat = trimesh.creation.cylinder(radius=90, height=16, sections=96)
    seat.apply_translation([0, 0, 128])
    base = trimesh.creation.box([250, 250, 12])
    base.apply_translation([0, 0, 6])
    parts += [seat, base]
    legs = [np.array([70 * np.cos(t), 70 * np.sin(t)]) for t in np.radians([90, 210, 330])]
    for i, leg in enumerate(legs):
        rod([*leg, 12], [*leg, 120], 3.0, f"leg r3 #{i}")
    for i in range(3):
        rod([*legs[i], 60], [*legs[(i + 1) % 3], 60], 1.5, f"rung r1.5 #{i}")
    rod([30, -25, 136], [30, -25, 210], 1.0, "antenna r1")
    rod([-40, 15, 136], [-40, 15, 190], 2.0, "antenna r2")
    return trimesh.util.concatenate(parts), feats


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out", help="folder for stool.ply and features.json")
    args = p.parse_args(argv)
    mesh, feats = stool()
    lo, hi = mesh.bounds
    shift = np.asarray(WORLD_OFFSET, dtype=np.float64) - (lo + hi) / 2
    for f in feats:
        f["center"] = (np.asarray(f["center"]) + shift).tolist()
    mesh.apply_transform([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])  # y-up
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    mesh.export(out / "stool.ply")
    (out / "features.json").write_text(json.dumps({"features": feats}, indent=1))
    print(f"{out / 'stool.ply'}: {len(mesh.faces)} faces, {len(feats)} thin features")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
