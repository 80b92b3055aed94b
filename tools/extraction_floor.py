"""The meshing's own floor: a synthetic scene's exact SDF meshed and scored as a run is.

Usage:
    python tools/extraction_floor.py SCENE_DIR [--resolutions 128,256,512] [--density 0.5]
        [--no-clean] [--out DIR]

SCENE_DIR is a scene made by ``neus-l0 synth NAME`` from a built-in analytic shape
(``scene.json``'s ``source``: pits-and-thin, pits-deep, cup, demo, ...). Its exact SDF,
placed where the scene put it and taken to the normalised frame (``cameras_sphere.npz``'s
``scale_mat_0``), goes through the path a trained SDF takes
(`neus_l0.mesh.extract.extract_mesh`: the grid over ``[-1, 1]^3`` at each resolution,
marching cubes, `clean_mesh` unless ``--no-clean``: pieces under 5 % of the main piece's
diagonal dropped) and through the scoring a run gets
(`neus_l0.evaluation.score.score_mesh` at ``--density``, per feature). No network is
trained: what error remains is the grid's and the scoring's, the floor under every run
scored at that resolution (issue #35: is a thin rod missing from training, or from a grid
whose cell is wider than the rod?).

Prints one markdown row per resolution (cell size in world units, total Chamfer, each
feature's overall and completeness); with ``--out``, writes ``floor.md``, ``floor.json`` and
the meshes.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import types
from pathlib import Path

import numpy as np
import torch

from neus_l0.atomic import atomic_write_json, atomic_write_text
from neus_l0.errors import NeusL0Error


def exact_model(scene_dir: Path) -> tuple[types.SimpleNamespace, np.ndarray, str]:
    """(a stand-in with ``.sdf.sdf(p)`` in the normalised frame, scale_mat (4, 4), the shape's
    name) of a built-in synthetic scene."""
    from neus_l0.synthetic.scene import scene_world_sdf

    sdf, name = scene_world_sdf(scene_dir)  # names scene.json when it is not a built-in's
    try:
        scale_mat = np.asarray(np.load(scene_dir / "cameras_sphere.npz")["scale_mat_0"],
                               np.float64)
    except (OSError, ValueError, KeyError) as exc:
        raise NeusL0Error(f"{scene_dir}: not a scene made by `neus-l0 synth` ({exc})") from exc
    scale = float(scale_mat[0, 0])
    center = torch.as_tensor(scale_mat[:3, 3], dtype=torch.float64)

    def normalised_sdf(p: torch.Tensor) -> torch.Tensor:
        """(P, 3) normalised points -> (P, 1) SDF in normalised units."""
        world = p.to(torch.float64) * scale + center
        return (sdf(world) / scale).to(p.dtype)[:, None]

    return types.SimpleNamespace(sdf=types.SimpleNamespace(sdf=normalised_sdf)), scale_mat, name


def floor_row(scene_dir: Path, resolution: int, density: float, clean: bool,
              mesh_path: Path) -> dict:
    """Mesh the exact SDF at `resolution`, score it; the row (cell, total, per feature)."""
    from neus_l0.evaluation.score import ScoreSpec, score_mesh
    from neus_l0.mesh.extract import export_mesh, extract_mesh

    model, scale_mat, _ = exact_model(scene_dir)
    mesh = extract_mesh(model, scale_mat, resolution=resolution, clean=clean)
    export_mesh(mesh, mesh_path)  # atomic, like a run's mesh
    report = score_mesh(mesh_path, ScoreSpec(scene=scene_dir, density=density),
                        log=lambda msg: None)
    cell = 2.0 / (resolution - 1) * float(scale_mat[0, 0])
    features = {f["name"]: {"overall": f.get("overall"), "completeness": f.get("completeness"),
                            "accuracy": f.get("accuracy")}
                for f in (report.get("features") or {}).get("each", [])}
    return {"resolution": resolution, "cell": cell, "clean": clean,
            "overall": report["overall"], "accuracy": report["accuracy"],
            "completeness": report["completeness"], "faces": int(len(mesh.faces)),
            "features": features}


def table(rows: list[dict]) -> str:
    """Markdown: one row per resolution; each feature as ``overall (completeness)``."""
    names = list(rows[0]["features"]) if rows else []
    head = ("| resolution | cell (world) | total | " + " | ".join(names) + " |\n"
            + "|---:|---:|---:|" + "---:|" * len(names))
    lines = [head]
    for r in rows:
        cells = [f"{f['overall']:.2f} ({f['completeness']:.2f})"
                 if f["overall"] is not None else "-" for f in r["features"].values()]
        lines.append(f"| {r['resolution']} | {r['cell']:.2f} | {r['overall']:.3f} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path, help="a scene folder made by `neus-l0 synth NAME`")
    ap.add_argument("--resolutions", default="128,256,512",
                    help="marching-cubes samples per axis, comma-separated")
    ap.add_argument("--density", type=float, default=0.5,
                    help="Chamfer sampling density, world units (the CPU bench's 0.5)")
    ap.add_argument("--no-clean", action="store_true",
                    help="keep every piece (runs drop pieces under 5 %% of the main "
                         "one's diagonal)")
    ap.add_argument("--out", type=Path, default=None, help="folder for floor.md / .json")
    args = ap.parse_args(argv)
    try:
        resolutions = [int(r) for r in args.resolutions.split(",") if r.strip()]
        if not resolutions or min(resolutions) < 8:
            raise NeusL0Error("--resolutions: give integers of at least 8")
        exact_model(args.scene)  # a bad folder fails before any meshing
        rows = []
        with tempfile.TemporaryDirectory() as tmp:
            for res in resolutions:
                folder = args.out if args.out else Path(tmp)
                folder.mkdir(parents=True, exist_ok=True)
                rows.append(floor_row(args.scene, res, args.density, not args.no_clean,
                                      folder / f"exact_{res}.ply"))
                print(f"resolution {res}: total {rows[-1]['overall']:.3f}", file=sys.stderr)
    except (NeusL0Error, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    text = table(rows)
    print(text)
    if args.out:
        atomic_write_text(args.out / "floor.md", text + "\n")
        atomic_write_json(args.out / "floor.json", {"scene": str(args.scene), "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
