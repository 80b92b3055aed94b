"""A benchmark sweep: every (scene, sampler, budget, seed) run, resumable, into one folder.

Layout of the sweep folder DIR::

    DIR/sweep.json                 the settings every run shares (checked on re-runs)
    DIR/results.csv, results.json  one row per run (`neus_l0.experiments.results.COLUMNS`)
    DIR/scenes/<scene>/            built-in scenes synthesised here (folders given as paths
                                   are linked here)
    DIR/runs/<scene>__<sampler>__<budget>s__seed<seed>/
                                   the training run (config.yaml, checkpoints/, metrics.jsonl
                                   with `sample_dist`), mesh.ply, eval.json, status.json,
                                   spec.json, log.txt
    DIR/plots/                     figures and table.md (`neus_l0.experiments.plots`)

Fairness rule for budgets. Every run of a sweep uses the same config (networks, batch size,
samples, and the learning-rate / annealing schedule over the config's `train.iters`), the
same training views, the same seed per seed index, one process per run with the same torch
thread count, and stops by wall-clock: ``train.max_seconds = budget``. The schedule is a
function of the iteration, not of the budget, so a run cut at budget B is exactly where the
same schedule has got to after B seconds; a sampler that costs less per iteration does more
iterations in the same budget, which is what the benchmark measures. Validation images are
off and checkpoints are written only at the end (both would count against the budget); the
sample-distance hook's time is not counted (`neus_l0.train.loop.train`). A run that reaches
`train.iters` before its budget ends there (its `train_seconds` is below the budget).

One sweep at a time: the sweep folder is locked (`neus_l0.run.lock.RunLock`, ``DIR/.lock``)
for the whole sweep, so a second sweep into it is refused before it touches a run. SIGTERM
or SIGINT stops the sweep: the running run is told (`neus_l0.experiments.runner.ForwardSignals`;
under Ray its task is cancelled, `neus_l0.experiments.ray_backend`), checkpoints, is recorded as
interrupted, and no further run starts (`SweepOutcome.signal`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from neus_l0.atomic import atomic_write_json
from neus_l0.errors import NeusL0Error
from neus_l0.experiments.results import collect_rows, run_name, write_results
from neus_l0.experiments.runner import BENCH_OVERRIDES, ForwardSignals, RunSpec, run_in_subprocess
from neus_l0.run.lock import RunLock
from neus_l0.train.signals import StopOnSignal

#: What a sweep writes at the top of its folder (its own, for --out checks).
SWEEP_NAMES = ("sweep.json", "runs", "scenes", "plots", "results.csv", "results.json", ".lock",
               "progress.json")
#: Settings that must match between invocations on the same sweep folder.
SHARED_KEYS = ("config", "views", "width", "height", "holdout", "device",
               "threads", "resolution", "eval_density", "sample_rays", "psnr_pixels",
               "snapshots", "planned", "close_underside",
               "drop_outside_masks", "inset", "fill_missed", "photo_carve")


@dataclasses.dataclass
class SweepOutcome:
    """What `run_sweep` did.

    Attributes:
        rows: every row of results.csv after the sweep.
        ran: names of the runs executed by this call.
        skipped: names of the runs already done before it.
        signal: ``SIGTERM`` / ``SIGINT`` when one stopped the sweep (the running run is
            recorded as interrupted, the runs after it did not start), else None.
        exit_code: the shell's code for that signal (143, 130), else 0.
        not_started: names of the runs a signal kept from starting.
    """

    rows: list[dict]
    ran: list[str]
    skipped: list[str]
    signal: str | None = None
    exit_code: int = 0
    not_started: list[str] = dataclasses.field(default_factory=list)


def prepare_scene(entry: str, out_dir: Path, views: int, width: int, height: int,
                  progress: bool = True) -> tuple[str, Path]:
    """Resolve one ``--scenes`` entry to (name, folder).

    A built-in name (`neus_l0.synthetic.scene.builtin_names`) that is not an existing path is
    synthesised once into ``DIR/scenes/<name>/``; a folder is used in place (and linked as
    ``DIR/scenes/<basename>``).

    Raises:
        NeusL0Error: an unknown name, or an existing synthesised scene of another size.
    """
    from neus_l0.synthetic.scene import builtin_names, make_scene

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
    if progress:  # the ground truth after the rendering shows no bar of its own
        print(f"bench: making the scene {entry} ({views} views, {width}x{height}, with "
              f"ground truth) in {folder} ...", file=sys.stderr, flush=True)
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


def _with_defaults(config):
    """A recorded config with the keys a later version added at their defaults (so that a
    sweep made before a new option existed still matches, unless the option is set)."""
    if not isinstance(config, dict):
        return config
    from neus_l0.config.load import config_from_dict, to_dict

    try:
        return to_dict(config_from_dict(config))
    except NeusL0Error:
        return config  # a config this version cannot read: compared as recorded


def check_settings(out_dir: Path, settings: dict) -> None:
    """Write ``DIR/sweep.json``, or check that an existing one has the same settings.

    The resolved config is compared (not the override text), so a re-run may spell the
    same config differently.
    """
    path = out_dir / "sweep.json"
    if path.is_file():
        old = json.loads(path.read_text(encoding="utf-8"))
        differ = [k for k in SHARED_KEYS if k != "config" and old.get(k) != settings.get(k)]
        differ += [f"config {k}" for k in _dotted_diff(_with_defaults(old.get("config")),
                                                      settings["config"])]
        if differ:
            raise NeusL0Error(f"{path}: this sweep folder was made with other settings "
                              f"({', '.join(differ)}); use another --out so that its runs "
                              "stay comparable")
        return
    atomic_write_json(path, settings)


#: What a sweep uses for the settings not given, by device. On a CPU: the `demo` config
#: (NeuS's 8x256 `wmask` would spend a CPU's budget on a few hundred iterations), one torch
#: thread per run (runs share the cores, and torch's default of one thread per core makes
#: the threads wait on each other), built-in scenes of 24 views at 200x150 (a larger scene
#: takes long to synthesise on a CPU), meshes at 128^3 and Chamfer
#: sampled every 0.5 world units (the synthetic scenes' ground-truth point spacing), so that
#: meshing and scoring stay short next to the training budget (docs/BENCHMARKS.md, "How long
#: do `neus-l0 bench` and `neus-l0 figures` take with the defaults?"). On CUDA: `fast`,
#: torch's thread count, 49 views at 400x300, 256^3 and 0.2.
DEVICE_DEFAULTS = {
    "cpu": {"conf": "demo", "threads": 1, "views": 24, "width": 200, "height": 150,
            "resolution": 128, "eval_density": 0.5},
    "cuda": {"conf": "fast", "threads": 0, "views": 49, "width": 400, "height": 300,
             "resolution": 256, "eval_density": 0.2},
}


def snapshot_marks(budget: float, n: int) -> list[float]:
    """The snapshot marks of a run of `budget` seconds scored at `n` points: ``budget * k / n``
    for k = 1..n-1 (the n-th point is the run's end, scored anyway); [] for n <= 1."""
    return [budget * k / n for k in range(1, n)]


def device_defaults(device: str) -> dict:
    """`DEVICE_DEFAULTS` of ``cuda`` (any ``cuda:N``) or else ``cpu``."""
    return dict(DEVICE_DEFAULTS["cuda" if str(device).startswith("cuda") else "cpu"])


def default_conf(device: str) -> str:
    """The config a sweep uses when none is named: ``fast`` on CUDA, ``demo`` on a CPU."""
    return device_defaults(device)["conf"]


@dataclasses.dataclass
class SweepSpec:
    """What a sweep runs: the grid, the config every run shares, and how runs are scored.

    Attributes:
        out_dir: the sweep folder DIR (see the module docstring for its layout).
        scenes: built-in scene names or scene folders.
        samplers: up-sampling draws (`neus_l0.config.schema.SAMPLERS`).
        budgets: wall-clock training budgets in seconds.
        seeds: training seeds.
        conf: the base config (name or YAML path) shared by every run.
        overrides: ``key=value`` overrides of `conf`.
        views, width, height: size of synthesised built-in scenes.
        holdout: hold out every K-th view for PSNR (0: none).
        device: where runs train (``cpu`` or ``cuda``).
        threads: torch CPU threads per run (0: torch's default).
        resolution: marching-cubes resolution.
        eval_density: Chamfer sampling density (world units).
            (`conf`, `threads`, `views`, `width`, `height`, `resolution`, `eval_density`:
            None picks `device_defaults`.)
        sample_rays: rays of the sample-distance hook.
        psnr_pixels: at most this many pixels rendered per held-out view
            (`neus_l0.experiments.runner.psnr_stride`).
        backend: ``local`` (one run after another) or ``ray`` (Ray tasks).
        timeout: seconds after which a run's process is killed (None: no limit).
        snapshots: score each run at ``budget * k / snapshots`` seconds, k = 1..snapshots-1,
            besides its end (`snapshot_marks`; 0: the end only).
        planned: budgets are ``train.budget`` (planned iterations and the device's capacity
            ladder) rather than ``train.max_seconds`` cut-offs (`RunSpec.planned`).
        close_underside: mesh each run with its unseen underside closed flat
            (`RunSpec.close_underside`).
        drop_outside_masks: drop each mesh's pieces a view sees outside its mask.
        inset: mesh each run at the level -inset/s (`RunSpec.inset`).
        fill_missed: fill the parts the masks see and each mesh misses
            (`RunSpec.fill_missed`).
        photo_carve: carve the free space a plane sweep finds behind each mesh
            (`RunSpec.photo_carve`).
    """

    out_dir: str | Path
    scenes: Sequence[str]
    samplers: Sequence[str]
    budgets: Sequence[float]
    seeds: Sequence[int] = (0,)
    conf: str | None = None
    overrides: Sequence[str] = ()
    views: int | None = None
    width: int | None = None
    height: int | None = None
    holdout: int = 8
    device: str = "cpu"
    threads: int | None = None
    resolution: int | None = None
    eval_density: float | None = None
    sample_rays: int = 256
    psnr_pixels: int = 10000
    backend: str = "local"
    timeout: float | None = None
    snapshots: int = 0
    planned: bool = False
    close_underside: bool = False
    drop_outside_masks: bool = False
    inset: float = 0.0
    fill_missed: bool = False
    photo_carve: bool = False

    def __post_init__(self):
        for key, value in device_defaults(self.device).items():
            if getattr(self, key) is None:
                setattr(self, key, value)
        self.conf = str(self.conf)

    def settings(self, config: dict) -> dict:
        """What ``DIR/sweep.json`` records (`SHARED_KEYS` must match on a re-run)."""
        return {
            "config": config, "conf": self.conf, "overrides": list(self.overrides),
            "views": self.views, "width": self.width, "height": self.height,
            "holdout": self.holdout, "device": self.device, "threads": self.threads,
            "resolution": self.resolution, "eval_density": self.eval_density,
            "sample_rays": self.sample_rays, "psnr_pixels": self.psnr_pixels,
            # only when set, so that folders from before --snapshots still match
            **({"snapshots": self.snapshots} if self.snapshots else {}),
            **({"planned": True} if self.planned else {}),
            **({"close_underside": True} if self.close_underside else {}),
            **({"drop_outside_masks": True} if self.drop_outside_masks else {}),
            **({"inset": self.inset} if self.inset else {}),
            **({"fill_missed": True} if self.fill_missed else {}),
            **({"photo_carve": True} if self.photo_carve else {}),
        }

    def run_spec(self, scene: str, folder: Path, sampler: str, budget: float, seed: int,
                 config: dict) -> RunSpec:
        """The `RunSpec` of one grid point, with the resolved base `config`."""
        return RunSpec(name=run_name(scene, sampler, float(budget), int(seed)), scene=scene,
                       scene_dir=str(folder), sampler=sampler, budget_s=float(budget),
                       seed=int(seed), out_dir=str(Path(self.out_dir).resolve()),
                       conf=self.conf, overrides=list(self.overrides),
                       device=self.device, threads=self.threads, holdout=self.holdout,
                       resolution=self.resolution, eval_density=self.eval_density,
                       sample_rays=self.sample_rays, config=config,
                       psnr_pixels=self.psnr_pixels, planned=self.planned,
                       snapshots=snapshot_marks(float(budget), self.snapshots),
                       close_underside=self.close_underside,
                       drop_outside_masks=self.drop_outside_masks, inset=self.inset,
                       fill_missed=self.fill_missed, photo_carve=self.photo_carve)


def plan_runs(spec: SweepSpec, resolved: Sequence[tuple[str, Path]],
              config: dict) -> tuple[list[RunSpec], list[RunSpec]]:
    """Every run of the grid, split into (to run, already done).

    Samplers are innermost: the runs that are compared with each other run back to back and
    so see the same machine load (which moves wall-clock budgets more than the sampler).
    """
    todo, done = [], []
    for scene, folder in resolved:
        for seed in spec.seeds:
            for budget in spec.budgets:
                for sampler in spec.samplers:
                    run = spec.run_spec(scene, folder, sampler, budget, seed, config)
                    (done if is_done(run.run_dir) else todo).append(run)
    return todo, done


def run_sweep(spec: SweepSpec, *, progress: bool = True,
              on_row: Callable[[dict], None] | None = None) -> SweepOutcome:
    """Run every (scene, sampler, budget, seed) of `spec` not already done; write the results.

    Args:
        spec: the sweep.
        progress: tqdm bars: one over the runs, one for the running run's current step
            (training, marching cubes, scoring, held-out views; `neus_l0.experiments.progress`).
        on_row: called with each new row as its run finishes.

    Returns:
        a `SweepOutcome`. A failing run is recorded (status failed, error) and the sweep
        goes on; runs whose status.json says done are skipped. SIGTERM / SIGINT stop the
        sweep (see the module docstring).

    Raises:
        NeusL0Error: bad scenes or config, a sweep folder made with other settings, or one
            that another sweep is using.
    """
    from neus_l0.config.load import load_config, to_dict

    out_dir = Path(spec.out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    if spec.backend not in ("local", "ray"):
        raise NeusL0Error(f"--backend {spec.backend}: choose local or ray")
    if spec.psnr_pixels < 1:
        raise NeusL0Error(f"--psnr-pixels {spec.psnr_pixels}: must be at least 1")
    # The config is resolved once, here: user errors surface before any run, and every run
    # gets exactly this config even if the YAML file changes while the sweep runs.
    config = to_dict(load_config(spec.conf, [*BENCH_OVERRIDES, *spec.overrides]))
    with RunLock(out_dir):
        check_settings(out_dir, spec.settings(config))
        resolved = [prepare_scene(s, out_dir, spec.views, spec.width, spec.height, progress)
                    for s in spec.scenes]
        names = [n for n, _ in resolved]
        if len(set(names)) != len(names):
            raise NeusL0Error(f"--scenes: two scenes share a name ({', '.join(names)})")
        specs, skipped = plan_runs(spec, resolved, config)
        write_results(out_dir, collect_rows(out_dir))
        ran, stop = _execute(specs, out_dir, spec, len(skipped), progress, on_row)
        rows = collect_rows(out_dir)
    stopped = stop is not None and stop.requested
    return SweepOutcome(rows, ran, [s.name for s in skipped],
                        signal=stop.signal_name if stopped else None,
                        exit_code=stop.exit_code if stopped else 0,
                        not_started=[s.name for s in specs if s.name not in ran]
                        if stopped else [])


def _execute(specs: list[RunSpec], out_dir: Path, spec: SweepSpec, n_skipped: int,
             progress: bool, on_row: Callable[[dict], None] | None
             ) -> tuple[list[str], StopOnSignal | None]:
    """Run `specs` on the sweep's backend, with the progress bars.

    Returns:
        the names that ran, and the signal watcher: after a SIGTERM / SIGINT, passed on to
        the running run (local) or cancelling the Ray tasks, no further run starts.
    """
    from tqdm import tqdm

    from neus_l0.experiments.progress import StepDisplay

    bar = tqdm(total=len(specs) + n_skipped, initial=n_skipped, disable=not progress,
               unit="run", desc="bench", dynamic_ncols=True, position=0)
    step_bar = tqdm(total=None, disable=not progress or spec.backend != "local",
                    dynamic_ncols=True, position=1, leave=False)
    display = StepDisplay(step_bar)
    ran: list[str] = []

    def finished(row: dict, name: str) -> None:
        ran.append(name)
        write_results(out_dir, collect_rows(out_dir))
        bar.update(1)
        bar.set_postfix_str(f"last {name}: {row['status']}")
        if on_row is not None:
            on_row(row)

    stop = None
    try:
        if spec.backend == "local":
            with ForwardSignals() as stop:
                for run in specs:
                    if stop.requested:
                        break
                    bar.set_description(f"bench {run.name}")
                    display.start(run.name)
                    watch = display.poll if progress else None
                    finished(run_in_subprocess(run, spec.timeout, watch, stop), run.name)
        else:
            from neus_l0.experiments.ray_backend import run_with_ray

            bar.set_description(f"bench ({len(specs)} Ray tasks)")
            with StopOnSignal() as stop:
                run_with_ray(specs, finished, timeout=spec.timeout, stop=stop)
    finally:
        step_bar.close()
        bar.close()
    return ran, stop


def is_done(run_dir: Path) -> bool:
    """Whether the run folder holds a status.json saying done."""
    try:
        data = json.loads((run_dir / "status.json").read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return False
    return isinstance(data, dict) and data.get("status") == "done"


def check_spec(spec: SweepSpec) -> None:
    """Refuse a sweep that cannot run, naming the flag of `neus-l0 bench`, before any work:
    out-of-range numbers, unknown samplers, overrides the sweep sets itself, a hold-out that
    leaves no training view, a mesh resolution that does not fit in memory.

    Raises:
        NeusL0Error: one line naming the flag and the rule.
    """
    from neus_l0.config.schema import SAMPLERS
    from neus_l0.data.split import split_views
    from neus_l0.mesh.extract import SPARSE_ABOVE
    from neus_l0.mesh.memory import plan_extraction

    _check_numbers(spec)
    names = [Path(s).resolve().name if Path(s).is_dir() else s for s in spec.scenes]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:  # before any scene is built
        raise NeusL0Error(f"--scenes: two scenes share a name ({', '.join(twice)})")
    from neus_l0.mesh.from_run import MeshSteps

    MeshSteps(spec.close_underside, spec.drop_outside_masks, spec.inset)  # --inset's range
    bad = [s for s in spec.samplers if s not in SAMPLERS]
    if bad:
        raise NeusL0Error(f"--samplers: unknown {', '.join(bad)} (choose from "
                          f"{', '.join(SAMPLERS)})")
    owned = [o for o in spec.overrides
             if o.split("=", 1)[0] in ("sampler", "train.seed", "train.max_seconds")]
    if owned:
        raise NeusL0Error(f"{', '.join(owned)}: set by the sweep (use --samplers, --seeds, "
                          "--seconds)")
    if any(not Path(s).is_dir() for s in spec.scenes):
        split_views(spec.views, spec.holdout)  # built-in scenes: some view must be left
    plan_extraction("sparse" if spec.resolution > SPARSE_ABOVE else "dense", spec.resolution)


def _check_numbers(spec: SweepSpec) -> None:
    """The numeric rules of `check_spec`."""
    def refuse(flag: str, value, rule: str):
        raise NeusL0Error(f"{flag} {value}: {rule}")

    for b in spec.budgets:
        if not (math.isfinite(b) and b > 0):
            refuse("--seconds", f"{b:g}", "budgets must be positive, finite seconds")
    for seed in spec.seeds:
        if not 0 <= seed < 2**63:
            refuse("--seeds", seed, "seeds must be 0 or more (below 2^63)")
    if spec.resolution is not None and spec.resolution < 8:
        refuse("--resolution", spec.resolution, "must be at least 8")
    if spec.threads is not None and spec.threads < 0:
        refuse("--threads", spec.threads, "must be 0 (torch's default) or more")
    if spec.views is not None and spec.views < 1:
        refuse("--views", spec.views, "must be at least 1")
    for flag, value in (("--width", spec.width), ("--height", spec.height)):
        if value is not None and value < 8:
            refuse(flag, value, "must be at least 8 pixels")
    if spec.holdout < 0 or spec.holdout == 1:
        refuse("--holdout", spec.holdout, "must be 0 (none) or K >= 2 (1 holds out every view)")
    if spec.eval_density is not None and not (math.isfinite(spec.eval_density)
                                              and spec.eval_density > 0):
        refuse("--eval-density", f"{spec.eval_density:g}", "must be a positive, finite "
               "distance in world units")
    if spec.sample_rays < 1:
        refuse("--sample-rays", spec.sample_rays, "must be at least 1")
    if spec.psnr_pixels < 1:
        refuse("--psnr-pixels", spec.psnr_pixels, "must be at least 1")
    if spec.timeout is not None and not (math.isfinite(spec.timeout) and spec.timeout > 0):
        refuse("--timeout", f"{spec.timeout:g}", "must be positive, finite seconds")
    if spec.snapshots < 0:
        refuse("--snapshots", spec.snapshots, "must be 0 or more")


def finish_sweep(out: Path, outcome: SweepOutcome, plots: bool = True) -> int:
    """Print what the sweep did and draw ``out/plots/`` (unless a signal stopped it or
    `plots` is off); the exit status: the signal's code (143, 130) when one stopped it, 1 when
    a run of this call failed, else 0."""
    this_call = {f"runs/{name}" for name in outcome.ran}
    rows = [r for r in outcome.rows if r["run_dir"] in this_call]
    failed = [r for r in rows if r["status"] == "failed"]
    stopped = [r for r in rows if r["status"] == "interrupted"]
    done = [r for r in rows if r["status"] == "done"]
    print(f"{len(done)} runs done now, {len(outcome.skipped)} skipped (done before), "
          f"{len(failed)} failed, {len(stopped)} interrupted in {out}")
    for r in failed + stopped:
        print(f"  {r['status']}: {r['run_dir']}: {r['error']}")
    print(f"results: {out / 'results.csv'}, {out / 'results.json'}")
    if outcome.signal:
        names = ", ".join(r["run_dir"] for r in stopped) or "no run"
        print(f"neus-l0 bench: stopped by {outcome.signal}: {names} recorded as interrupted, "
              f"{len(outcome.not_started)} not started; run the same command again to go on",
              file=sys.stderr)
        return outcome.exit_code
    if plots:
        from neus_l0.experiments.plots import write_plots

        write_plots(out, outcome.rows)
        print(f"plots:   {out / 'plots'}/ (chamfer_vs_time.png, psnr_vs_time.png, "
              "sample_distance.png, table.md)")
    if failed:
        logs = (f"its log: {out / failed[0]['run_dir'] / 'log.txt'}" if len(failed) == 1
                else f"their logs: {out / 'runs'}/<run>/log.txt")
        print(f"neus-l0 bench: {len(failed)} of {len(rows)} runs failed: "
              f"{', '.join(Path(r['run_dir']).name for r in failed)}; {logs}", file=sys.stderr)
        return 1
    return 0
