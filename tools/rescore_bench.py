"""Re-mesh and re-score every finished run of a `neus-l0 bench` sweep, into a new sweep
folder that `tools/pair_features.py` reads like the original.

Usage:
    python tools/rescore_bench.py SWEEP --out NEW [--resolution 256] [--density D]
        [--no-clean] [--threads 1]

Issue #35: the CPU bench meshes at 128 samples, whose cell (2.27 world units on the
400x300 scenes) is wider than the thinnest rod, and earlier sweeps were cleaned up with
"the largest piece only". This tool takes each run's final checkpoint
(``SWEEP/runs/NAME/checkpoints``), meshes it the way the bench does now
(`neus_l0.mesh.from_run.mesh_from_run`: the run's hull, `clean` as it stands) at
``--resolution``, scores it against the run's scene (`neus_l0.evaluation.score.score_mesh`,
per feature) and writes ``NEW/runs/NAME/eval.json``: the run's own eval.json with
``chamfer`` replaced, the row's accuracy / completeness / overall updated, the spec's
resolution set, and ``rescored`` (from where, resolution, clean-up, seconds). The mesh goes
to ``NEW/runs/NAME/mesh.ply``. Training numbers (iterations, time, PSNR) are the run's.
A run whose new eval.json exists is skipped (re-running resumes); a run without an
eval.json or a checkpoint is reported and skipped.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

import torch

from neus_l0.atomic import atomic_write_json
from neus_l0.errors import NeusL0Error


def rescored_record(old: dict, report: dict, resolution: int, clean: bool, source: Path,
                    seconds: float) -> dict:
    """The run's eval.json `old` with the new Chamfer `report` in its place (pure)."""
    rec = copy.deepcopy(old)
    rec["chamfer"] = report
    row = rec.setdefault("row", {})
    for key in ("accuracy", "completeness", "overall"):
        row[key] = report.get(key)
    rec.setdefault("spec", {})["resolution"] = resolution
    rec["rescored"] = {"from": str(source), "resolution": resolution, "clean": clean,
                       "seconds": round(seconds, 2),
                       "old": {k: (old.get("chamfer") or {}).get(k)
                               for k in ("accuracy", "completeness", "overall")},
                       "old_resolution": (old.get("spec") or {}).get("resolution")}
    return rec


#: What this tool writes into a run's folder under --out (anything else there is not ours).
WRITES = ("mesh.ply", "eval.json")


def foreign_files(folder: Path) -> list[str]:
    """Names in `folder` this tool did not write (its atomic writes' temporaries aside)."""
    if not folder.exists():
        return []
    return sorted(p.name for p in folder.iterdir()
                  if p.name not in WRITES and not p.name.startswith((".mesh.ply.", ".eval.json.")))


def rescore_run(run_dir: Path, out_dir: Path, resolution: int, density: float | None,
                clean: bool) -> dict:
    """Mesh and score one run; write ``out_dir/eval.json`` and ``out_dir/mesh.ply``."""
    from neus_l0.evaluation.score import ScoreSpec, score_mesh
    from neus_l0.mesh.extract import export_mesh
    from neus_l0.mesh.from_run import mesh_from_run

    eval_path = run_dir / "eval.json"
    try:
        old = json.loads(eval_path.read_text(encoding="utf-8"))
        scene_dir = Path(old["spec"]["scene_dir"])
        density = density if density is not None else float(old["spec"]["eval_density"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise NeusL0Error(f"{eval_path}: not a bench run's eval.json ({exc})") from exc
    if not (scene_dir / "gt_points.ply").is_file():
        raise NeusL0Error(f"{eval_path}: its scene {scene_dir} has no gt_points.ply")
    if foreign_files(out_dir):
        raise NeusL0Error(f"{out_dir}: holds files this tool did not write "
                          f"({', '.join(foreign_files(out_dir)[:3])}): not written over (is --out "
                          "a bench sweep?)")
    t0 = time.monotonic()
    mesh = mesh_from_run(run_dir, resolution, "cpu", clean=clean).mesh
    out_dir.mkdir(parents=True, exist_ok=True)
    mesh_path = export_mesh(mesh, out_dir / "mesh.ply")
    report = score_mesh(mesh_path, ScoreSpec(scene=scene_dir, density=density),
                        log=lambda msg: None)
    rec = rescored_record(old, report, resolution, clean, eval_path, time.monotonic() - t0)
    atomic_write_json(out_dir / "eval.json", rec)
    return rec


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sweep", type=Path, help="a `neus-l0 bench` folder (with runs/)")
    ap.add_argument("--out", type=Path, required=True, help="the new sweep folder")
    ap.add_argument("--resolution", type=int, default=256, help="marching-cubes samples")
    ap.add_argument("--density", type=float, default=None,
                    help="Chamfer sampling density (default: each run's own)")
    ap.add_argument("--no-clean", action="store_true", help="keep every mesh piece")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = ap.parse_args(argv)
    if not (args.sweep / "runs").is_dir():
        print(f"error: {args.sweep}: no runs/ folder (not a `neus-l0 bench` sweep)",
              file=sys.stderr)
        return 2
    if args.out.resolve().is_relative_to(args.sweep.resolve()):
        print("error: --out must lie outside the sweep (its eval.json files are kept)",
              file=sys.stderr)
        return 2
    if args.resolution < 8:
        print("error: --resolution: give at least 8", file=sys.stderr)
        return 2
    torch.set_num_threads(max(1, args.threads))
    failed = 0
    for run_dir in sorted(p for p in (args.sweep / "runs").iterdir() if p.is_dir()):
        target = args.out / "runs" / run_dir.name
        if (target / "eval.json").is_file():
            continue
        if not (run_dir / "eval.json").is_file():
            print(f"{run_dir.name}: skipped (no eval.json: not finished)", file=sys.stderr)
            continue
        try:
            rec = rescore_run(run_dir, target, args.resolution, args.density,
                              not args.no_clean)
        except NeusL0Error as exc:
            print(f"{run_dir.name}: skipped ({exc})", file=sys.stderr)
            failed += 1
            continue
        old = rec["rescored"]["old"]["overall"]
        print(f"{run_dir.name}: {old if old is None else round(old, 3)} -> "
              f"{rec['chamfer']['overall']:.3f} ({rec['rescored']['seconds']:.0f} s)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
