"""A benchmark sweep: every (scene, sampler, budget, seed) run, resumable, into one folder.

Layout of the sweep folder DIR::

    DIR/sweep.json                 the settings every run shares (checked on re-runs)
    DIR/results.csv, results.json  one row per run (`neus_l0.bench.results.COLUMNS`)
    DIR/scenes/<scene>/            built-in scenes synthesised here (folders given as paths
                                   are linked here)
    DIR/runs/<scene>__<sampler>__<budget>s__seed<seed>/
                                   the training run (config.yaml, checkpoints/, metrics.jsonl
                                   with `sample_dist`), mesh.ply, eval.json, status.json,
                                   spec.json, log.txt
    DIR/plots/                     figures and table.md (`neus_l0.bench.plots`)

Fairness rule for budgets. Every run of a sweep uses the same config (networks, batch size,
samples, and the learning-rate / annealing schedule over the config's `train.iters`), the
same training views, the same seed per seed index, one process per run with the same torch
thread count, and stops by wall-clock: ``train.max_seconds = budget``. The schedule is a
function of the iteration, not of the budget, so a run cut at budget B is exactly where the
same schedule has got to after B seconds; a sampler that costs less per iteration does more
iterations in the same budget, which is what the benchmark measures. Validation images are
off and checkpoints are written only at the end (both would count against the budget); the
sample-distance hook's time is not counted (`neus_l0.train.train`). A run that reaches
`train.iters` before its budget ends there (its `train_seconds` is below the budget).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Sequence
from pathlib import Path

from neus_l0.atomic import atomic_write_json
from neus_l0.bench.results import collect_rows, run_name, write_results
from neus_l0.bench.runner import BENCH_OVERRIDES, RunSpec, run_in_subprocess
from neus_l0.errors import NeusL0Error

#: Settings that must match between invocations on the same sweep folder.
SHARED_KEYS = ("config", "views", "width", "height", "holdout", "device",
               "threads", "resolution", "eval_density", "sample_rays")


@dataclasses.dataclass
class SweepOutcome:
    """What `run_sweep` did.

    Attributes:
        rows: every row of results.csv after the sweep.
        ran: names of the runs executed by this call.
        skipped: names of the runs already done before it.
    """

    rows: list[dict]
    ran: list[str]
    skipped: list[str]


def prepare_scene(entry: str, out_dir: Path, views: int, width: int, height: int,
                  progress: bool = True) -> tuple[str, Path]:
    """Resolve one ``--scenes`` entry to (name, folder).

    A built-in name (`neus_l0.data.synthetic.builtin_names`) that is not an existing path is
    synthesised once into ``DIR/scenes/<name>/``; a folder is used in place (and linked as
    ``DIR/scenes/<basename>``).

    Raises:
        NeusL0Error: an unknown name, or an existing synthesised scene of another size.
    """
    from neus_l0.data.synthetic import builtin_names, make_scene

    path = Path(entry)
    if path.is_dir():
        name = path.resolve().name
        link = out_dir / "scenes" / name
        if not link.exists() and not link.is_symlink():
            link.parent.mkdir(parents=True, exist_ok=True)
            try:
                link.symlink_to(path.resolve(), target_is_directory=True)
            except OSError:
                pass  # the layout link is a convenience
        return name, path.resolve()
    if entry not in builtin_names():
        raise NeusL0Error(f"--scenes {entry}: neither a scene folder nor a built-in scene "
                          f"({', '.join(builtin_names())})")
    folder = out_dir / "scenes" / entry
    info_path = folder / "scene.json"
    if info_path.is_file():
        info = json.loads(info_path.read_text(encoding="utf-8"))
        have = (info.get("views"), info.get("width"), info.get("height"))
        if have != (views, width, height):
            raise NeusL0Error(f"{folder}: made with {have[0]} views of {have[1]}x{have[2]}, "
                              f"asked for {views} of {width}x{height} (use another --out)")
        return entry, folder.resolve()
    make_scene(entry, folder, views=views, width=width, height=height, seed=0,
               progress=progress)
    return entry, folder.resolve()


def _dotted_diff(a, b, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two nested dicts."""
    if not (isinstance(a, dict) and isinstance(b, dict)):
        return [] if a == b else [prefix.rstrip(".") or "(value)"]
    out = []
    for k in sorted(set(a) | set(b), key=str):
        out += _dotted_diff(a.get(k), b.get(k), f"{prefix}{k}.")
    return out


def check_settings(out_dir: Path, settings: dict) -> None:
    """Write ``DIR/sweep.json``, or check that an existing one has the same settings.

    The resolved config is compared (not the override text), so a re-run may spell the
    same config differently.
    """
    path = out_dir / "sweep.json"
    if path.is_file():
        old = json.loads(path.read_text(encoding="utf-8"))
        differ = [k for k in SHARED_KEYS if k != "config" and old.get(k) != settings.get(k)]
        differ += [f"config {k}" for k in _dotted_diff(old.get("config"), settings["config"])]
        if differ:
            raise NeusL0Error(f"{path}: this sweep folder was made with other settings "
                              f"({', '.join(differ)}); use another --out so that its runs "
                              "stay comparable")
        return
    atomic_write_json(path, settings)


def run_sweep(out_dir: str | Path, scenes: Sequence[str], samplers: Sequence[str],
              budgets: Sequence[float], seeds: Sequence[int], *, conf: str = "wmask",
              overrides: Sequence[str] = (), views: int = 49, width: int = 400,
              height: int = 300, holdout: int = 8, device: str = "cpu",
              threads: int | None = None, resolution: int = 256, eval_density: float = 0.2,
              sample_rays: int = 256, backend: str = "local", progress: bool = True,
              timeout: float | None = None,
              on_row: Callable[[dict], None] | None = None) -> SweepOutcome:
    """Run every (scene, sampler, budget, seed) not already done and write the results.

    Args:
        out_dir: the sweep folder DIR (see the module docstring for its layout).
        scenes: built-in scene names or scene folders.
        samplers, budgets, seeds: the grid (budgets in seconds).
        conf, overrides: the base config shared by every run.
        views, width, height: size of synthesised built-in scenes.
        holdout: hold out every K-th view for PSNR (0: none).
        device, threads: where runs train, and torch CPU threads per run (None: default).
        resolution: marching-cubes resolution. eval_density: Chamfer sampling density.
        sample_rays: rays of the sample-distance hook.
        backend: ``local`` (one run after another) or ``ray`` (Ray tasks).
        progress: tqdm over the runs.
        timeout: seconds after which a run's process is killed (None: no limit).
        on_row: called with each new row as its run finishes.

    Returns:
        a `SweepOutcome`. A failing run is recorded (status failed, error) and the sweep
        goes on; runs whose status.json says done are skipped.

    Raises:
        NeusL0Error: bad scenes or config, or a sweep folder made with other settings.
    """
    from neus_l0.config import load_config, to_dict

    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    if backend not in ("local", "ray"):
        raise NeusL0Error(f"--backend {backend}: choose local or ray")
    # The config is resolved once, here: user errors surface before any run, and every run
    # gets exactly this config even if the YAML file changes while the sweep runs.
    base = load_config(conf, [*BENCH_OVERRIDES, *overrides])
    settings = {
        "config": to_dict(base), "conf": str(conf), "overrides": list(overrides),
        "views": views, "width": width, "height": height, "holdout": holdout,
        "device": device, "threads": threads, "resolution": resolution,
        "eval_density": eval_density, "sample_rays": sample_rays,
    }
    check_settings(out_dir, settings)
    resolved = [prepare_scene(s, out_dir, views, width, height, progress) for s in scenes]
    names = [n for n, _ in resolved]
    if len(set(names)) != len(names):
        raise NeusL0Error(f"--scenes: two scenes share a name ({', '.join(names)})")

    specs, skipped = [], []
    # Samplers innermost: the runs that are compared with each other run back to back and
    # so see the same machine load (which moves wall-clock budgets more than the sampler).
    for scene, folder in resolved:
        for seed in seeds:
            for budget in budgets:
                for sampler in samplers:
                    name = run_name(scene, sampler, float(budget), int(seed))
                    spec = RunSpec(name=name, scene=scene, scene_dir=str(folder),
                                   sampler=sampler, budget_s=float(budget), seed=int(seed),
                                   out_dir=str(out_dir), conf=str(conf),
                                   overrides=list(overrides), device=device, threads=threads,
                                   holdout=holdout, resolution=resolution,
                                   eval_density=eval_density, sample_rays=sample_rays,
                                   config=settings["config"])
                    (skipped if is_done(spec.run_dir) else specs).append(spec)
    write_results(out_dir, collect_rows(out_dir))

    from tqdm import tqdm

    total = len(specs) + len(skipped)
    bar = tqdm(total=total, initial=len(skipped), disable=not progress, unit="run",
               desc="bench", dynamic_ncols=True)
    ran: list[str] = []

    def finished(row: dict, name: str) -> None:
        ran.append(name)
        write_results(out_dir, collect_rows(out_dir))
        bar.update(1)
        bar.set_postfix_str(f"last {name}: {row['status']}")
        if on_row is not None:
            on_row(row)

    try:
        if backend == "local":
            for spec in specs:
                bar.set_description(f"bench {spec.name}")
                finished(run_in_subprocess(spec, timeout), spec.name)
        else:
            from neus_l0.bench.ray_backend import run_with_ray

            bar.set_description(f"bench ({len(specs)} Ray tasks)")
            run_with_ray(specs, finished, timeout=timeout)
    finally:
        bar.close()
    return SweepOutcome(collect_rows(out_dir), ran, [s.name for s in skipped])


def is_done(run_dir: Path) -> bool:
    """Whether the run folder holds a status.json saying done."""
    try:
        data = json.loads((run_dir / "status.json").read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return False
    return isinstance(data, dict) and data.get("status") == "done"

