"""Finding the runs to draw in a `neus-l0 bench` folder.

A bench folder holds ``results.csv`` (one row per run: scene, sampler, budget_s, seed,
status, ..., run_dir, mesh), ``scenes/<scene>/`` (a built-in scene, or a link to a scene
folder given by path, named after its basename) and
``runs/<scene>__<sampler>__<budget>s__seed<seed>/`` (config.yaml, checkpoints/, mesh.ply,
spec.json, whose ``scene_dir`` is the scene folder the run trained on).
"""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

from neus_l0.errors import NeusL0Error

#: Scene drawn when none is asked for and the bench holds it.
DEFAULT_SCENE = "pits-and-thin"


@dataclasses.dataclass
class BenchRun:
    """One finished run of the bench.

    Attributes:
        scene, sampler: names; budget_s: training budget (seconds); seed: training seed.
        run_dir: the training run folder; mesh: its world-unit mesh.
        row: the results.csv row (strings).
    """

    scene: str
    sampler: str
    budget_s: float
    seed: int
    run_dir: Path
    mesh: Path
    row: dict

    @property
    def label(self) -> str:
        """Short description: sampler, budget, seed."""
        return f"{self.sampler} ({self.budget_s:g} s, seed {self.seed})"


def read_results(bench: Path) -> list[dict]:
    """Rows of ``bench/results.csv`` (raises NeusL0Error if the folder or file is missing)."""
    bench = Path(bench)
    if not bench.is_dir():
        raise NeusL0Error(f"{bench}: no such bench folder (run `neus-l0 bench` first)")
    path = bench / "results.csv"
    if not path.is_file():
        raise NeusL0Error(f"{path}: missing (is {bench} a `neus-l0 bench` output folder?)")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    need = {"scene", "sampler", "budget_s", "seed", "status"}
    if rows and not need <= set(rows[0]):
        raise NeusL0Error(f"{path}: missing columns {', '.join(sorted(need - set(rows[0])))}")
    return rows


def _resolve(bench: Path, value: str | None, fallback: Path) -> Path:
    """A path from results.csv: absolute, relative to the bench folder, or the fallback."""
    if value:
        p = Path(value)
        for cand in (p, bench / p, bench.parent / p):
            if cand.exists():
                return cand
    return fallback


def _run_name(scene: str, sampler: str, budget: float, seed: int) -> str:
    return f"{scene}__{sampler}__{budget:g}s__seed{seed}"


def _scene_folder(bench: Path, scene: str, runs: dict[str, BenchRun]) -> Path:
    """``bench/scenes/<scene>``, or else the scene folder a run's spec.json names."""
    import json

    folder = bench / "scenes" / scene
    if folder.is_dir():
        return folder
    for r in runs.values():
        try:
            named = json.loads((r.run_dir / "spec.json").read_text(encoding="utf-8"))["scene_dir"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if named and Path(named).is_dir():
            return Path(named)
    raise NeusL0Error(f"{folder}: missing (the bench's scene folder, nor named by a run's "
                      "spec.json)")


def select_runs(bench: str | Path, samplers: list[str], scene: str | None = None,
                budget: float | None = None, seed: int | None = None
                ) -> tuple[Path, dict[str, BenchRun]]:
    """The scene folder and one finished run per sampler, all on the same scene/budget/seed.

    The scene folder may lack ground truth (a real scene: only cameras, images, masks).

    Defaults: scene `DEFAULT_SCENE` if the bench has finished runs of it (else the only
    scene), the largest budget and then the smallest seed that every sampler finished.

    Returns:
        (scene_dir, {sampler: BenchRun}).

    Raises:
        NeusL0Error: missing folder / file, no finished run of a sampler, missing run folder.
    """
    bench = Path(bench)
    rows = [r for r in read_results(bench) if r.get("status", "").strip() == "done"]
    where = bench / "results.csv"
    if scene is None:
        scenes = sorted({r["scene"] for r in rows})
        if not scenes:
            raise NeusL0Error(f"{where}: no finished runs (status 'done')")
        if DEFAULT_SCENE in scenes:
            scene = DEFAULT_SCENE
        elif len(scenes) == 1:
            scene = scenes[0]
        else:
            raise NeusL0Error(f"{where}: several scenes ({', '.join(scenes)}): choose one "
                              "with --scene")
    rows = [r for r in rows if r["scene"] == scene]
    for s in samplers:
        if not any(r["sampler"] == s for r in rows):
            raise NeusL0Error(f"{where}: no finished run of sampler '{s}' on scene '{scene}'")

    def key(r):
        return float(r["budget_s"]), int(float(r["seed"]))

    common = set.intersection(*({key(r) for r in rows if r["sampler"] == s} for s in samplers))
    if budget is not None:
        common = {k for k in common if abs(k[0] - budget) < 1e-9}
    if seed is not None:
        common = {k for k in common if k[1] == seed}
    if not common:
        raise NeusL0Error(f"{where}: no budget/seed that all of {', '.join(samplers)} finished "
                          f"on scene '{scene}'"
                          + (f" (asked budget {budget:g})" if budget is not None else "")
                          + (f" (asked seed {seed})" if seed is not None else ""))
    b, sd = max(common, key=lambda k: (k[0], -k[1]))
    runs = {}
    for s in samplers:
        row = next(r for r in rows if r["sampler"] == s and key(r) == (b, sd))
        run_dir = _resolve(bench, row.get("run_dir"), bench / "runs" / _run_name(scene, s, b, sd))
        if not run_dir.is_dir():
            raise NeusL0Error(f"{run_dir}: run folder of {s} (budget {b:g} s, seed {sd}) missing")
        mesh = _resolve(bench, row.get("mesh"), run_dir / "mesh.ply")
        if not mesh.is_file():
            raise NeusL0Error(f"{mesh}: mesh of the {s} run missing")
        runs[s] = BenchRun(scene, s, b, sd, run_dir, mesh, row)
    return _scene_folder(bench, scene, runs), runs


def select_arms(benches: list[Path], samplers: list[str], scene: str | None = None,
                budget: float | None = None, seed: int | None = None
                ) -> tuple[Path, dict[str, BenchRun]]:
    """`select_runs` over several bench folders (the arms of a paired comparison, e.g. a
    remedy off and on): the first folder picks the scene, budget and seed, the others must
    hold the same runs. One folder: `select_runs` as it is.

    Returns:
        (the first folder's scene_dir, {"<folder name> <sampler>": BenchRun}); the keys are
        the figures' column titles.

    Raises:
        NeusL0Error: as `select_runs`, or two folders with the same name.
    """
    if len(benches) == 1:
        return select_runs(benches[0], samplers, scene, budget, seed)
    names = [Path(b).name for b in benches]
    if len(set(names)) != len(names):
        raise NeusL0Error(f"--bench: two folders share a name ({', '.join(names)}): the "
                          "figures title their columns by folder name")
    scene_dir, first = select_runs(benches[0], samplers, scene, budget, seed)
    pick = next(iter(first.values()))
    runs = {f"{names[0]} {s}": r for s, r in first.items()}
    for bench, name in zip(benches[1:], names[1:], strict=True):
        _, more = select_runs(bench, samplers, pick.scene, pick.budget_s, pick.seed)
        runs.update({f"{name} {s}": r for s, r in more.items()})
    return scene_dir, runs
