"""One benchmark run, in its own process: train -> mesh -> Chamfer -> held-out PSNR.

`python -m neus_l0.experiments.runner RUN_DIR/spec.json` executes the spec (a JSON object, see
`RunSpec`) and writes into RUN_DIR, besides the training run's own files (config.yaml,
checkpoints/, metrics.jsonl, run.json):

* ``mesh.ply``: the final mesh in world units;
* ``snapshots/mesh_NNNNNNN.ply``: the meshes of the snapshot checkpoints (`RunSpec.snapshots`);
* ``eval.json``: the Chamfer report of `neus_l0.evaluation.score.score_mesh`, the held-out
  PSNR per view, memory, timings (``extract_s``: the final marching cubes alone), the final
  sample distance, and ``curve``: Chamfer against training time, one point per snapshot
  and the final model's last (see `execute`);
* ``status.json``: ``{"status": "done" | "failed" | "interrupted", "row": {...}}``, the
  run's results row (see `neus_l0.experiments.results.COLUMNS`), written last;
* ``progress.json``: the step the run is at (`neus_l0.experiments.progress`), which the sweep
  shows as a progress bar while it waits.

Held-out PSNR is bounded: each held-out view is rendered at a pixel stride, the config's
``train.val_downscale`` or more, chosen so that at most `RunSpec.psnr_pixels` pixels of it are
rendered (`psnr_stride`); the cost is at most ``views x psnr_pixels`` rays whatever the image
size.

A process per run gives per-run peak memory (``ru_maxrss`` of the process itself, or
``torch.cuda.max_memory_allocated`` on a GPU) and isolates crashes: the sweep records a run
whose process dies without a status.json as failed, with its exit code and the last line of
``log.txt``.

Signals. SIGTERM or SIGINT stops a run as it stops training (`neus_l0.train.signals`): the
training step ends, the checkpoint is written, and the run's process records the run as
*interrupted* (neither done nor failed; the next sweep runs it again) and exits 143 / 130;
outside training the signal stops the run's process at once, recorded the same way. The
sweep's process passes the signals it gets on to the running run (`ForwardSignals`), waits
for it, and stops too; a run whose sweep is killed outright stops in the same way
(`stop_when_orphaned`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import resource
import signal
import subprocess
import sys
import threading
import time
import traceback
from pathlib import Path

from neus_l0.atomic import atomic_write_json
from neus_l0.experiments.results import make_row
from neus_l0.run.metrics import snapshot_lines
from neus_l0.train.signals import STOP_SIGNALS, StopOnSignal

#: Settings every bench run gets before the user's overrides: no validation renders and a
#: checkpoint only at the end (both would count against the budget).
BENCH_OVERRIDES = ("train.val_every=0", "train.save_every=0")


def _merged(base: dict, extra: dict) -> dict:
    """`base` with `extra`'s nested keys set over it."""
    out = dict(base)
    for k, v in extra.items():
        out[k] = _merged(out.get(k) or {}, v) if isinstance(v, dict) else v
    return out


@dataclasses.dataclass
class RunSpec:
    """Everything one run needs (JSON-serialisable).

    Attributes:
        name: run folder name, ``<scene>__<sampler>__<budget>s__seed<seed>``.
        scene: scene name (the results' ``scene`` column).
        scene_dir: absolute path of the scene folder.
        sampler: up-sampling draw (`neus_l0.config.schema.SAMPLERS`).
        budget_s: wall-clock training budget (``train.max_seconds``).
        seed: ``train.seed`` (network init and ray draws).
        out_dir: the sweep folder DIR (absolute); the run folder is ``DIR/runs/<name>``.
        conf: config name or path (what the user named; informative when `config` is set).
        overrides: the user's ``key=value`` overrides (before the run's own).
        config: the resolved base config (`neus_l0.config.load.to_dict` of `conf` + `overrides`
            + the bench's own settings), fixed by the sweep when it starts so that every run
            uses the same config even if the YAML file changes meanwhile; None: resolve
            `conf` and `overrides` in the run's process.
        device: ``cpu`` or ``cuda``.
        threads: torch CPU threads in the run's process (None or 0: torch's default).
        holdout: hold out every K-th view (0: none; see `neus_l0.data.split`).
        resolution: marching-cubes resolution.
        eval_density: Chamfer sampling density and thinning radius (world units).
        sample_rays: rays of the sample-distance hook.
        snapshots: training-loop times (seconds) at which to checkpoint; each snapshot's
            mesh is extracted and scored after training (``curve`` in eval.json).
        label: the run's name in a comparison (e.g. an arm of `tools/bench_fast_vs_neus.py`);
            informative only.
        psnr_pixels: at most this many pixels rendered per held-out view (`psnr_stride`).
        planned: train with ``train.budget`` (iterations planned from the measured step
            rate, capacity from the device's ladder: `neus_l0.train.budget.LADDER`) instead
            of cutting the schedule at ``train.max_seconds``.
        close_underside: close each mesh's unseen underside flat (`neus-l0 mesh
            --close-underside`; snapshots too).
        drop_outside_masks: drop each mesh's pieces a view sees outside its mask (`neus-l0
            mesh --drop-outside-masks`; snapshots too).
        inset: extract each mesh at the level -inset/s (`neus-l0 mesh --inset`; snapshots
            too).
        fill_missed: fill the parts the masks see and each mesh misses (`neus-l0 mesh
            --fill-missed`; snapshots too).
        photo_carve: carve the free space a plane sweep finds behind each mesh (`neus-l0
            mesh --photo-carve`; snapshots too).
    """

    name: str
    scene: str
    scene_dir: str
    sampler: str
    budget_s: float
    seed: int
    out_dir: str
    conf: str = "wmask"
    overrides: list[str] = dataclasses.field(default_factory=list)
    device: str = "cpu"
    threads: int | None = None
    holdout: int = 8
    resolution: int = 256
    eval_density: float = 0.2
    sample_rays: int = 256
    config: dict | None = None
    snapshots: list[float] = dataclasses.field(default_factory=list)
    label: str | None = None
    psnr_pixels: int = 10000
    planned: bool = False
    close_underside: bool = False
    drop_outside_masks: bool = False
    inset: float = 0.0
    fill_missed: bool = False
    photo_carve: bool = False

    @property
    def run_dir(self) -> Path:
        return Path(self.out_dir) / "runs" / self.name

    @property
    def mesh_steps(self):
        """The optional mesh steps (`neus_l0.mesh.from_run.MeshSteps`)."""
        from neus_l0.mesh.from_run import MeshSteps

        return MeshSteps(self.close_underside, self.drop_outside_masks, self.inset,
                         self.fill_missed, self.photo_carve)

    def run_overrides(self) -> list[str]:
        """The bench's settings, the user's overrides, then the run's own (which win).

        Validation images are switched off and checkpoints are written only at the end,
        because both would count against the budget.
        """
        return [*BENCH_OVERRIDES, *self.overrides, *self.own_overrides()]

    def own_overrides(self) -> list[str]:
        """What differs between the runs of a sweep: sampler, seed, budget."""
        if self.planned:
            return [*self.ladder(), f"sampler={self.sampler}", f"train.seed={self.seed}",
                    f"train.budget={self.budget_s:g}"]
        return [f"sampler={self.sampler}", f"train.seed={self.seed}",
                f"train.max_seconds={self.budget_s:g}"]

    def ladder(self) -> tuple[str, ...]:
        """The capacity ladder's overrides for this budget (none unless `planned`)."""
        if not self.planned:
            return ()
        from neus_l0.train.budget import default_setting

        return default_setting(self.device, self.budget_s)[1]

    def load_config(self):
        """The run's `neus_l0.config.schema.Config` (raises `ConfigError` for a bad one)."""
        import copy

        from neus_l0.config.load import config_from_dict, load_config, parse_overrides

        if self.config is None:
            return load_config(self.conf, self.run_overrides())
        data = copy.deepcopy(self.config)
        if self.planned:
            data = _merged(data, parse_overrides(list(self.ladder())))
        block = data.get("sampler")
        data["sampler"] = ({**block, "name": self.sampler} if isinstance(block, dict)
                           else self.sampler)
        timing = {"budget": self.budget_s} if self.planned else {"max_seconds": self.budget_s}
        data.setdefault("train", {}).update(seed=self.seed, **timing)
        return config_from_dict(data)

    def base_row(self) -> dict:
        return {"scene": self.scene, "sampler": self.sampler, "budget_s": self.budget_s,
                "seed": self.seed, "run_dir": f"runs/{self.name}"}


def psnr_stride(height: int, width: int, base: int, pixels: int) -> int:
    """The smallest pixel stride >= `base` that leaves at most `pixels` pixels of a view.

    Every stride-th pixel in each direction is rendered: ``ceil(height / s) * ceil(width /
    s)`` pixels.

    Raises:
        ValueError: `pixels` below 1.
    """
    if pixels < 1:
        raise ValueError(f"pixel budget {pixels}: must be at least 1")
    s = max(1, int(base))
    while math.ceil(height / s) * math.ceil(width / s) > pixels:
        s += 1
    return s


def heldout_psnr(model, scene, views: list[int], cfg, iteration: int, pixels: int = 10000,
                 report=None) -> list[float]:
    """PSNR of the rendered held-out `views` against their images, on a bounded pixel grid.

    Rendered as `neus_l0.train.validation.validation_image` does (no jitter), on every
    s-th pixel with
    ``s = psnr_stride(H, W, cfg.train.val_downscale, pixels)``: at least the validation
    downscale, more where a view would have over `pixels` pixels. With masks, the error is
    averaged over foreground pixels only (the no-background model renders black where the
    images show the backdrop); without masks, over the whole image.

    Args:
        report: a `neus_l0.experiments.progress.StepReporter` (or None), told after each view.

    Returns:
        one PSNR (dB) per view.
    """
    import torch

    from neus_l0.render.views import psnr
    from neus_l0.render.volume import render_image
    from neus_l0.sampling.upsample import build_sampler
    from neus_l0.train.schedule import cos_anneal_ratio
    from neus_l0.train.validation import validation_views

    ds = psnr_stride(scene.height, scene.width, cfg.train.val_downscale, pixels)
    sampler = build_sampler(cfg.sampler)
    step = f"held-out PSNR (1/{ds} of each axis)"
    out = []
    with torch.no_grad():
        for i, v in enumerate(views):
            if report is not None:
                report(step, i, len(views), "view")
            o, d, rgb = validation_views(scene, v, ds)
            img = render_image(model, o, d, cfg.render, sampler,
                               cos_anneal_ratio(iteration, cfg.train.anneal_end))["color"]
            fg = (scene.masks[v, ::ds, ::ds] > 0.5).cpu().numpy() if scene.has_masks else None
            out.append(psnr(img.clamp(0, 1).cpu().numpy(), rgb.cpu().numpy(),
                            fg if fg is not None and fg.any() else None))
    if report is not None:
        report(step, len(views), len(views), "view")
    return out


class TrainProgress:
    """A training hook that reports the loop's progress against the budget (returns nothing).

    Args:
        report: a `neus_l0.experiments.progress.StepReporter`.
        budget_s: the run's wall-clock budget.
    """

    def __init__(self, report, budget_s: float):
        self.report, self.budget_s = report, float(budget_s)
        self.t0 = time.monotonic()

    def start(self) -> None:
        self.t0 = time.monotonic()
        self.report("train", 0, self.budget_s, "s")

    def __call__(self, iteration: int, model, scene, cfg) -> dict:
        seconds = min(time.monotonic() - self.t0, self.budget_s)
        self.report("train", round(seconds, 1), self.budget_s, "s", note=f"it {iteration}")
        return {}


def warm_up_torch() -> None:
    """Pay torch's one-off lazy imports before the budget starts.

    The first `torch.optim.Adam` imports `torch._dynamo` (seconds on a small CPU), which
    `neus_l0.train.loop.train` would otherwise count against `train.max_seconds`.
    """
    import torch

    torch.optim.Adam([torch.zeros(1, requires_grad=True)])


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def curve_point(seconds: float, iteration: int, score: dict | None, mesh_s: float | None,
                error: str | None = None) -> dict:
    """One point of eval.json's ``curve``: a model's Chamfer at a training time."""
    from neus_l0.experiments.results import clean_number

    point = {"seconds": clean_number(seconds), "iteration": int(iteration)}
    for k in ("accuracy", "completeness", "overall"):
        point[k] = clean_number(score[k]) if score else None
    point["mesh_s"] = clean_number(mesh_s)
    if error:
        point["error"] = error
    return point


def score_snapshots(spec: RunSpec, snapshots: list[tuple[float, int, Path]], final_iter: int,
                    elapsed: dict[int, float], score_fn,
                    report=None) -> list[dict]:
    """Mesh and score every snapshot checkpoint except the final model's.

    Args:
        spec: the run (device, resolution).
        snapshots: `neus_l0.train.loop.TrainResult.snapshots`, ``(mark, iteration, checkpoint)``.
        final_iter: the final model's iteration (its snapshot is the final point).
        elapsed: loop time (s) of each snapshot iteration (metrics.jsonl's ``elapsed``).
        score_fn: ``score_fn(mesh_path) -> report or None``.
        report: a `neus_l0.experiments.progress.StepReporter` (or None), told after each snapshot.

    Returns:
        curve points in iteration order; a snapshot whose mesh cannot be made (no surface
        yet) gets missing numbers and an ``error``.
    """
    from neus_l0.errors import NeusL0Error
    from neus_l0.mesh.extract import export_mesh
    from neus_l0.mesh.from_run import mesh_from_run

    points = []
    seen = set()
    todo = len({it for _, it, _ in snapshots if it != final_iter})
    for _, iteration, ckpt in snapshots:
        if iteration == final_iter or iteration in seen:
            continue
        seen.add(iteration)
        if report is not None:
            report("snapshots: mesh and score", len(seen) - 1, todo, "snapshot")
        t0 = time.monotonic()
        try:
            mesh = mesh_from_run(spec.run_dir, spec.resolution, spec.device, ckpt,
                                 steps=spec.mesh_steps).mesh
        except NeusL0Error as exc:
            points.append(curve_point(elapsed[iteration], iteration, None, None, str(exc)))
            continue
        mesh_s = time.monotonic() - t0
        path = export_mesh(mesh, spec.run_dir / "snapshots" / f"mesh_{iteration:07d}.ply")
        points.append(curve_point(elapsed[iteration], iteration, score_fn(path), mesh_s))
    return points


def _snapshot_elapsed(run_dir: Path) -> dict[int, float]:
    """Loop time (s) of each snapshot iteration, from the run's metrics.jsonl."""
    out = {}
    for m in snapshot_lines(run_dir):
        out.setdefault(int(m["iter"]), float(m["elapsed"]))
    return out


def _score(spec: RunSpec, path: Path) -> dict | None:
    """The Chamfer report of the mesh at `path` against the scene (None: no ground truth)."""
    if not (Path(spec.scene_dir) / "gt_points.ply").is_file():
        return None
    from neus_l0.evaluation.score import ScoreSpec, score_mesh

    return score_mesh(path, ScoreSpec(scene=spec.scene_dir, density=spec.eval_density),
                      log=lambda msg: print(msg, file=sys.stderr, flush=True))


def _eval_record(spec: RunSpec, row: dict, result, score, psnrs, views: tuple,
                 measures: dict) -> dict:
    """What ``eval.json`` holds besides the row (see the module docstring)."""
    import torch

    train_views, test_views, psnr_stride_ = views
    return {
        "row": row, "chamfer": score, "psnr_views": dict(zip(test_views, psnrs)),
        "train_views": train_views, "heldout_views": test_views,
        "stopped_early": result.stopped_early, "final_metrics": result.metrics,
        "peak_rss_mb_train": measures["peak_rss"], "peak_rss_mb_total": _peak_rss_mb(),
        "peak_gpu_mb_train": measures["peak_gpu"], "sample_dist_rays": spec.sample_rays,
        "sample_dist_surface": measures["surface"], "psnr_stride": psnr_stride_,
        "timings": measures["timings"], "torch_threads": torch.get_num_threads(),
        "curve": measures["curve"], "snapshots": [
            {"mark": m, "iteration": it, "checkpoint": str(Path(p).relative_to(spec.run_dir))}
            for m, it, p in result.snapshots],
        "label": spec.label, "spec": dataclasses.asdict(spec),
    }


def execute(spec: RunSpec, progress: bool = False, report=None) -> dict:
    """Run `spec` in this process and return its done row (raises on failure).

    With `spec.snapshots`, eval.json's ``curve`` lists ``{seconds, iteration, accuracy,
    completeness, overall, mesh_s}`` per snapshot (seconds: the loop time when it was taken;
    mesh_s: its marching cubes) and ends with the final model (seconds: ``train_seconds``).

    Args: progress: the training loop's own tqdm bar; report: a `StepReporter` told each
    step (`neus_l0.experiments.progress`; None: a silent one).
    """
    from neus_l0.experiments.progress import StepReporter

    report = report if report is not None else StepReporter(None)
    report("load config and scene")
    cfg = spec.load_config()  # a bad config fails before torch loads

    import torch

    from neus_l0.data.split import split_views, subset_scene
    from neus_l0.evaluation.sample_distance import SurfaceDistance
    from neus_l0.experiments.sample_hook import SampleDistanceHook
    from neus_l0.formats.open import open_scene
    from neus_l0.train.loop import train

    if spec.threads:
        torch.set_num_threads(spec.threads)
    run_dir = spec.run_dir
    timings = {}
    full = open_scene(spec.scene_dir, downscale=cfg.data.downscale, device=spec.device,
                      preview=False)
    train_views, test_views = split_views(full.n_views, spec.holdout)
    train_scene = subset_scene(full, train_views)
    # `train` holds the same views out of the full scene, so that run.json records the full
    # scene's indices (the mesh steps and `render --views test` read them)
    cfg.train.holdout = int(spec.holdout)
    surface = SurfaceDistance.from_scene_dir(spec.scene_dir)
    hook = SampleDistanceHook(surface, spec.sample_rays) if surface is not None else None
    warm_up_torch()
    if spec.device == "cuda":
        torch.cuda.reset_peak_memory_stats()

    ticker = TrainProgress(report, spec.budget_s)
    ticker.start()
    result = train(full, cfg, run_dir, device=spec.device, progress=progress,
                   hooks=[hook, ticker] if hook else [ticker], snapshots=spec.snapshots)
    timings["train_s"] = result.seconds
    if result.signal:
        raise RunInterrupted(result.exit_code - 128, f"stopped by {result.signal} at "
                             f"iteration {result.iteration}; checkpoint "
                             f"{Path(result.checkpoint).name} written")
    peak_rss = _peak_rss_mb()
    peak_gpu = (torch.cuda.max_memory_allocated() / 2**20 if spec.device == "cuda" else None)

    made, mesh_path = _mesh_stage(spec, timings, report)
    sample_dist = None
    if hook is not None:
        report("final sample distance")
        with torch.no_grad():
            sample_dist = hook(result.iteration, made.model, train_scene.to(spec.device),
                               cfg, force=True)["sample_dist"]
    score, curve = _score_stage(spec, result, mesh_path, timings, report)

    t0 = time.monotonic()
    psnrs = heldout_psnr(made.model, full.to(spec.device), test_views, cfg, result.iteration,
                         spec.psnr_pixels, report)
    timings["psnr_s"] = time.monotonic() - t0

    row = _done_row(spec, result, score, psnrs, peak_gpu if peak_gpu is not None else peak_rss,
                    sample_dist, timings["extract_s"])
    stride = psnr_stride(full.height, full.width, cfg.train.val_downscale, spec.psnr_pixels)
    atomic_write_json(run_dir / "eval.json", _eval_record(
        spec, row, result, score, psnrs, (train_views, test_views, stride),
        {"peak_rss": peak_rss, "peak_gpu": peak_gpu, "timings": timings, "curve": curve,
         "surface": surface.kind if surface is not None else None}))
    return row


def _done_row(spec: RunSpec, result, score: dict | None, psnrs: list, peak_mb: float,
              sample_dist: float | None, mesh_s: float) -> dict:
    """A finished run's row of results.csv (`make_row`)."""
    import numpy as np

    from neus_l0.evaluation.features import kind_overall

    return make_row(
        **spec.base_row(), status="done", error=None, train_seconds=result.seconds,
        iterations=result.iteration, its_per_s=result.iteration / max(result.seconds, 1e-9),
        accuracy=score and score["accuracy"], completeness=score and score["completeness"],
        overall=score and score["overall"], pits=kind_overall(score, "pit"),
        thin=kind_overall(score, "thin"),
        psnr_heldout=float(np.mean(psnrs)) if psnrs else None, peak_mem_mb=peak_mb,
        sample_dist_final=sample_dist, mesh=f"runs/{spec.name}/mesh.ply", mesh_seconds=mesh_s)


def _mesh_stage(spec: RunSpec, timings: dict, report):
    """The run's final mesh (`mesh_from_run`, exported as ``mesh.ply``), timed into
    `timings`. Returns the `mesh_from_run` result and the mesh's path."""
    from neus_l0.mesh.extract import export_mesh
    from neus_l0.mesh.from_run import mesh_from_run

    t0 = time.monotonic()
    report(f"mesh: marching cubes {spec.resolution}^3")
    made = mesh_from_run(spec.run_dir, spec.resolution, spec.device, steps=spec.mesh_steps)
    timings["extract_s"] = time.monotonic() - t0
    mesh_path = export_mesh(made.mesh, spec.run_dir / "mesh.ply")
    timings["mesh_s"] = time.monotonic() - t0
    return made, mesh_path


def _score_stage(spec: RunSpec, result, mesh_path: Path, timings: dict,
                 report) -> tuple[dict | None, list[dict]]:
    """The final mesh's Chamfer report and the curve over the snapshots (ending with the
    final model), timed into `timings`."""
    score_fn = functools.partial(_score, spec)
    t0 = time.monotonic()
    report("score: Chamfer")
    score = score_fn(mesh_path)
    timings["score_s"] = time.monotonic() - t0
    t0 = time.monotonic()
    curve = score_snapshots(spec, result.snapshots, result.iteration,
                            _snapshot_elapsed(spec.run_dir) if result.snapshots else {},
                            score_fn, report)
    curve.append(curve_point(result.seconds, result.iteration, score, timings["extract_s"]))
    timings["snapshots_s"] = time.monotonic() - t0
    return score, curve


def failed_row(spec: RunSpec, error: str) -> dict:
    """The results row of a run that failed with `error`."""
    return make_row(**spec.base_row(), status="failed", error=error)


def interrupted_row(spec: RunSpec, why: str) -> dict:
    """The results row of a run that a signal stopped (`why`: by which, where)."""
    return make_row(**spec.base_row(), status="interrupted", error=why)


class RunInterrupted(BaseException):  # noqa: N818 - like KeyboardInterrupt, not an error
    """A signal stopped the run (a BaseException, so that ``except Exception`` lets it by).

    Attributes:
        signum: the signal's number; why: one line saying where the run stopped.
    """

    def __init__(self, signum: int, why: str = ""):
        super().__init__(signum, why)
        self.signum, self.why = int(signum), why


def _raise_interrupted(signum: int, frame) -> None:
    raise RunInterrupted(signum, f"stopped by {signal.Signals(signum).name}")


def stop_when_orphaned(every: float = 1.0) -> threading.Thread:
    """SIGTERM to this process once its parent (the sweep) is gone.

    A sweep killed outright (SIGKILL) cannot pass a signal on; its run then stops as if it
    had (checkpoint, recorded as interrupted) instead of training on for its budget.
    """
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(every)
        os.kill(os.getpid(), signal.SIGTERM)

    thread = threading.Thread(target=watch, name="stop-when-orphaned", daemon=True)
    thread.start()
    return thread


class ForwardSignals(StopOnSignal):
    """`StopOnSignal` for a process that waits on a child: each SIGTERM / SIGINT is also
    passed on to the child named by `watch` (which stops as training does: the step ends,
    the checkpoint is written, it exits 143 / 130); a third signal kills the child.

    Unlike `StopOnSignal`, a second SIGINT raises nothing here: it is passed on (and the
    child's training stops at once), and this process goes on waiting for the child.
    """

    def __init__(self, signals=STOP_SIGNALS):
        super().__init__(signals)
        self.count = 0
        self._child: subprocess.Popen | None = None

    def watch(self, child: subprocess.Popen | None) -> None:
        """Pass the signals on to `child` from now on (None: to no one); a signal that came
        before it is passed on at once."""
        self._child = child
        if child is not None and self.requested:
            self._forward(int(self.signum))

    def _forward(self, signum: int) -> None:
        child = self._child
        if child is None or child.returncode is not None:
            return
        try:
            if self.count <= 2:
                child.send_signal(signum)
            else:
                child.kill()
        except ProcessLookupError:  # it has just exited
            pass

    def _handle(self, signum: int, frame) -> None:
        self.count += 1
        if not self.requested:
            self.requested = True
            self.signum = int(signum)
            self.signal_name = signal.Signals(signum).name
        self._forward(signum)


def write_status(spec: RunSpec, row: dict) -> None:
    atomic_write_json(spec.run_dir / "status.json", {"status": row["status"], "row": row})


def read_spec(path: str | Path) -> RunSpec:
    return RunSpec(**json.loads(Path(path).read_text(encoding="utf-8")))


def main(argv: list[str] | None = None) -> int:
    """Subprocess entry point: execute the spec file, write status.json, exit 0 / 1."""
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python -m neus_l0.experiments.runner RUN_DIR/spec.json", file=sys.stderr)
        return 2
    from neus_l0.experiments.progress import PROGRESS_FILE, StepReporter

    spec = read_spec(argv[0])
    # outside training (whose own handlers stop it after a step) a signal stops the run now
    previous = {s: signal.signal(s, _raise_interrupted) for s in STOP_SIGNALS}
    stop_when_orphaned()
    try:
        try:
            row = execute(spec, report=StepReporter(spec.run_dir / PROGRESS_FILE))
        except RunInterrupted as exc:
            why = exc.why or f"stopped by {signal.Signals(exc.signum).name}"
            signum = exc.signum
        except KeyboardInterrupt:  # a second Ctrl-C inside training
            why, signum = "stopped by a second SIGINT (no final checkpoint)", signal.SIGINT
        except Exception as exc:  # recorded, never raised: the sweep goes on
            traceback.print_exc()
            msg = str(exc).splitlines()[0] if str(exc) else ""
            write_status(spec, failed_row(spec, f"{type(exc).__name__}: {msg}"))
            return 1
        else:
            write_status(spec, row)
            return 0
        print(f"{spec.name}: {why}", file=sys.stderr, flush=True)
        write_status(spec, interrupted_row(spec, why))
        return 128 + int(signum)
    finally:
        for s, h in previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


def _last_line(path: Path) -> str:
    try:
        lines = [ln for ln in path.read_text(encoding="utf-8", errors="replace").splitlines()
                 if ln.strip()]
    except OSError:
        return ""
    return lines[-1] if lines else ""


def _wait(proc: subprocess.Popen, timeout: float | None, watch, every: float = 0.5) -> int | None:
    """Wait for `proc`, calling `watch()` every `every` seconds; None if it timed out (killed)."""
    deadline = None if timeout is None else time.monotonic() + timeout
    while True:
        wait = every if deadline is None else min(every, max(0.0, deadline - time.monotonic()))
        try:
            return proc.wait(timeout=wait)
        except subprocess.TimeoutExpired:
            pass
        if deadline is not None and time.monotonic() >= deadline:
            proc.kill()
            proc.wait()
            return None
        if watch is not None:
            watch()


def run_in_subprocess(spec: RunSpec, timeout: float | None = None, watch=None,
                      stop: ForwardSignals | None = None) -> dict:
    """Execute `spec` in a fresh Python process and return its row (never raises for the run).

    The run folder is emptied of an unfinished earlier attempt first; the process's output
    goes to ``log.txt`` in the run folder.

    Args:
        timeout: seconds after which the process is killed (None: no limit).
        watch: called with the run's progress file (`neus_l0.experiments.progress`) about twice a
            second while the process runs, e.g. `StepDisplay.poll`.
        stop: the caller's active `ForwardSignals`: the process then runs in its own session
            (a Ctrl-C in the terminal reaches it once, through `stop`, not twice), `stop`
            passes SIGTERM / SIGINT on to it, and a run that a signal stopped is recorded
            as interrupted. None: the process shares this one's session (as under Ray,
            whose workers cannot handle signals).
    """
    import shutil

    from neus_l0.experiments.progress import PROGRESS_FILE

    run_dir = spec.run_dir
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    spec_path = run_dir / "spec.json"
    atomic_write_json(spec_path, dataclasses.asdict(spec))
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    log = run_dir / "log.txt"
    progress_path = run_dir / PROGRESS_FILE
    forward = stop is not None and stop.active
    with open(log, "w", encoding="utf-8") as f:
        cmd = [sys.executable, "-m", "neus_l0.experiments.runner", str(spec_path)]
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=env,
                                start_new_session=forward)
        try:
            if forward:
                stop.watch(proc)
            rc = _wait(proc, timeout, None if watch is None else lambda: watch(progress_path))
        except BaseException:  # e.g. Ctrl-C in the sweep: do not leave the run behind
            proc.kill()
            proc.wait()
            raise
        finally:
            if forward:
                stop.watch(None)
    status = run_dir / "status.json"
    if status.is_file():
        try:
            return make_row(**json.loads(status.read_text(encoding="utf-8"))["row"])
        except (OSError, json.JSONDecodeError, KeyError, TypeError):
            pass
    if rc is None:
        why = f"timed out after {timeout:g} s"
    elif rc < 0:
        why = f"killed by signal {-rc}"
    else:
        why = f"exit code {rc}"
    if forward and stop.requested:
        row = interrupted_row(spec, f"stopped by {stop.signal_name} (run process {why}); "
                                    f"{_last_line(log)}")
        write_status(spec, row)
        return row
    row = failed_row(spec, f"run process {why}; {_last_line(log)}")
    write_status(spec, row)
    return row


if __name__ == "__main__":
    sys.exit(main())
