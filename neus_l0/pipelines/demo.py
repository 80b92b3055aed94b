"""The demo's pipeline (`neus-l0 demo`): render the built-in scene, train on it, extract the
mesh, score it against the exact ground truth and draw both side by side.

`run_demo` does the work and returns a `DemoResult`; the command only parses and prints.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

from neus_l0.data.image_io import imread_bytes

#: Size of the demo scene (views, width, height): a step costs the same at any image size,
#: and a larger image gives the step more distinct pixels to draw from.
DEMO_SCENE = {"views": 24, "width": 200, "height": 150}
#: Marching-cubes resolution of the demo mesh.
DEMO_RESOLUTION = 96
#: Wall-clock target of the whole demo (seconds from the process's start, imports included);
#: training is a budget run (`train.budget` with `train.budget_up_to_iters`: the config's
#: iterations where they fit, compressed where they do not) of what is left of it when
#: training starts, minus `DEMO_RESERVE_S` for meshing, scoring and drawing (which took
#: 12.2-16.1 s on the 2-core VM). `--budget`, `train.budget=` or `train.max_seconds=` on the
#: command line replace it.
DEMO_BUDGET_S = 148.0
DEMO_RESERVE_S = 16.0
#: The least training budget the demo plans, however long the start took.
DEMO_MIN_TRAIN_S = 30.0
#: Training config of the demo (`confs/demo.yaml`).
DEMO_CONF = "demo"


#: A demo folder's records (any one makes a folder the demo's) and what it writes at its top.
DEMO_RECORDS = ("metrics.json", "scene/scene.json", "run/run.json", "run/checkpoints/ckpt_*.pt")
DEMO_NAMES = ("scene", "run", "mesh.ply", "metrics.json", "comparison.png")


@dataclasses.dataclass
class DemoOptions:
    """What `neus-l0 demo` was asked for (the command's flags, already checked)."""

    out: Path
    conf: str = DEMO_CONF
    overrides: list[str] = dataclasses.field(default_factory=list)
    device: str | None = None
    threads: int | None = None
    resolution: int = DEMO_RESOLUTION
    quiet: bool = False
    close_underside: bool = True
    """Close the mesh's underside, which no demo camera sees, flat (`neus-l0 mesh
    --close-underside`)."""
    drop_outside_masks: bool = True
    """Drop the mesh's pieces that a view sees outside its mask (`neus-l0 mesh
    --drop-outside-masks`)."""
    fill_missed: bool = True
    """Fill the thin parts the masks see and the mesh misses (`neus-l0 mesh
    --fill-missed`)."""
    budget: float = 0.0
    """Seconds for the training stage (``train.budget``: compile, steps and the final
    checkpoint; the iterations planned from the measured step rate, the ladder's capacity);
    0: the config's iterations where they fit in `DEMO_BUDGET_S` for the whole demo,
    compressed where they do not."""


@dataclasses.dataclass
class DemoResult:
    """What the demo made: ``metrics`` is what ``OUT/metrics.json`` holds; ``signal`` is set
    (and the rest empty) when a signal stopped training, with ``exit_code`` to return."""

    out: Path
    metrics: dict | None = None
    signal: str | None = None
    exit_code: int = 0
    iteration: int = 0
    checkpoint: Path | None = None

    @property
    def paths(self) -> dict[str, Path]:
        """The outputs by name: scene, run, mesh, metrics, picture."""
        return {"scene": self.out / "scene", "run": self.out / "run",
                "mesh": self.out / "mesh.ply", "metrics": self.out / "metrics.json",
                "picture": self.out / "comparison.png"}


def score_demo_mesh(mesh_path, scene_dir) -> dict:
    """Chamfer report (`neus_l0.evaluation.score.score_mesh`) of the demo mesh, sampled
    about 150 points across the object so that scoring takes seconds."""
    import numpy as np
    import trimesh

    from neus_l0.evaluation.score import ScoreSpec, score_mesh

    gt = trimesh.load(Path(scene_dir) / "gt_mesh.ply", force="mesh")
    extent = float(np.ptp(np.asarray(gt.vertices), axis=0).max())
    return score_mesh(mesh_path, ScoreSpec(scene=Path(scene_dir), density=extent / 150.0),
                      log=lambda _msg: None)


def run_demo(opts: DemoOptions) -> DemoResult:
    """The whole demo into ``opts.out``: scene, run, mesh, score, picture and metrics.json.

    Prints a progress line per stage. A second call on the same folder reuses the scene and
    resumes (or reuses) the run.

    Raises:
        NeusL0Error: a bad config, or a run in ``opts.out`` trained with other settings.
    """
    import torch

    from neus_l0.atomic import atomic_write_json
    from neus_l0.config.load import load_config
    from neus_l0.device import free_cpu_threads, pick_device
    from neus_l0.train.run_config import process_seconds

    cfg = load_config(opts.conf, _ladder(opts) + opts.overrides)  # fails before any work
    device = pick_device(opts.device)
    opts.out.mkdir(parents=True, exist_ok=True)
    threads = free_cpu_threads(opts.threads)
    torch.set_num_threads(threads)
    timings: dict[str, float] = {}
    t_all = time.monotonic()
    result = DemoResult(out=opts.out)
    paths = result.paths

    t0 = time.monotonic()
    _make_demo_scene(paths["scene"], opts.quiet)
    timings["scene_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    fit = _training_time(opts, cfg)
    trained = _train_demo(opts, cfg, paths["scene"], paths["run"], device, threads, fit)
    timings["train_s"] = time.monotonic() - t0
    if trained.signal:
        return dataclasses.replace(result, signal=trained.signal, exit_code=trained.exit_code,
                                   iteration=trained.iteration, checkpoint=trained.checkpoint)

    mesh, score = _mesh_score_draw(opts, paths, device, timings)
    timings["total_s"] = time.monotonic() - t_all
    timings["process_s"] = process_seconds()  # from the process's start, imports included
    metrics = {
        "chamfer": score,
        "iterations": trained.iteration,
        "train_final": trained.metrics,
        "mesh": {"path": str(paths["mesh"]), "vertices": len(mesh.vertices),
                 "faces": len(mesh.faces), "resolution": opts.resolution,
                 "close_underside": opts.close_underside,
                 "filled_missed": mesh.metadata.get("filled_missed"),
                 "underside_plane": mesh.metadata.get("underside_plane"),
                 "dropped_outside_masks": mesh.metadata.get("dropped_outside_masks")},
        "sampler": cfg.sampler.name,
        "conf": str(opts.conf),
        "device": device,
        "threads": threads,
        "timings": timings,
    }
    atomic_write_json(paths["metrics"], metrics)
    return dataclasses.replace(result, metrics=metrics, iteration=trained.iteration)


def _training_time(opts: DemoOptions, cfg) -> bool:
    """Set `cfg`'s training time: `--budget`'s, or (no time or budget among the overrides)
    a budget capped at the config's iterations whose seconds `_train_demo` fits to
    `DEMO_BUDGET_S` when a fresh run starts (a resume reads its recorded plan). Returns
    whether it is fitted."""
    if opts.budget > 0:
        cfg.train.budget, cfg.train.max_seconds = opts.budget, 0.0
        return False
    if any(o.startswith(("train.max_seconds=", "train.budget=")) for o in opts.overrides):
        return False
    cfg.train.budget, cfg.train.max_seconds = DEMO_BUDGET_S, 0.0  # a placeholder
    cfg.train.budget_up_to_iters = True
    return True


def _ladder(opts: DemoOptions) -> list[str]:
    """The CPU capacity ladder's overrides for a budget on the demo's own config
    (`neus_l0.train.budget.LADDER`), before the user's."""
    from neus_l0.train.budget import default_setting

    if opts.budget <= 0 or str(opts.conf) != DEMO_CONF:
        return []
    return list(default_setting("cpu", opts.budget)[1])


def _make_demo_scene(scene_dir: Path, quiet: bool) -> None:
    """Render the built-in scene into `scene_dir` unless it is there already."""
    from neus_l0.synthetic.scene import make_scene

    if (scene_dir / "scene.json").is_file():
        print(f"[1/4] reusing the scene in {scene_dir}", flush=True)
        return
    print(f"[1/4] rendering the demo scene into {scene_dir} ...", flush=True)
    make_scene("demo", scene_dir, seed=0, progress=not quiet, **DEMO_SCENE)


def _mesh_score_draw(opts: DemoOptions, paths: dict[str, Path], device: str,
                     timings: dict[str, float]):
    """Stages 3 and 4: the mesh, its Chamfer report and the picture (timed into
    `timings`). Returns the mesh and the report."""
    from neus_l0.mesh.extract import export_mesh
    from neus_l0.mesh.from_run import MeshSteps, mesh_from_run

    t0 = time.monotonic()
    print(f"[3/4] extracting the mesh at {opts.resolution}^3 ...", flush=True)
    mesh = mesh_from_run(paths["run"], opts.resolution, device, progress=not opts.quiet,
                         steps=MeshSteps(opts.close_underside, opts.drop_outside_masks,
                                         fill_missed=opts.fill_missed)).mesh
    mesh_path = export_mesh(mesh, paths["mesh"])
    timings["mesh_s"] = time.monotonic() - t0

    t0 = time.monotonic()
    print("[4/4] scoring and drawing ...", flush=True)
    score = score_demo_mesh(mesh_path, paths["scene"])
    timings["score_s"] = time.monotonic() - t0
    t0 = time.monotonic()
    draw_comparison(paths["scene"], mesh, paths["picture"], score)
    timings["picture_s"] = time.monotonic() - t0
    return mesh, score


def _train_demo(opts: DemoOptions, cfg, scene_dir: Path, run_dir: Path, device: str,
                threads: int, fit: bool):
    """Train (or resume) the demo's run. A resume resolves `train.compile: auto` first, so
    that it is checked against the settings the run really used; a fresh run leaves it to
    `train`, which times a few eager steps to decide (`neus_l0.train.compile_auto`). With
    `fit`, a fresh run's budget is what is left of `DEMO_BUDGET_S` (since the process
    started) less `DEMO_RESERVE_S`."""
    from neus_l0.formats.neus import load_scene
    from neus_l0.run.checkpoints import checkpoint_iteration, latest_checkpoint
    from neus_l0.train.compile_auto import resolve_compile
    from neus_l0.train.loop import train
    from neus_l0.train.run_config import process_seconds

    scene = load_scene(scene_dir, downscale=cfg.data.downscale, device=device)
    newest = latest_checkpoint(run_dir)
    resume = newest is not None
    if resume and cfg.train.budget > 0 and (run_dir / "config.yaml").is_file():
        from neus_l0.config.load import load_config
        from neus_l0.train.budget import planned_config

        recorded = load_config(run_dir / "config.yaml")  # the plan it recorded, not a new one
        # the user's settings, planned as the run was, against the run's
        check_same_settings(run_dir, planned_config(cfg, recorded.train.iters))
        cfg = recorded
    if resume:  # the choice the run made; a fresh run's `train` decides on a timed step
        cfg, line = resolve_compile(cfg, device, checkpoint_iteration(newest), run_dir)
        if line:
            print(f"neus-l0: {line}", file=sys.stderr, flush=True)
        check_same_settings(run_dir, cfg)
    if fit and not resume:
        left = DEMO_BUDGET_S - DEMO_RESERVE_S - process_seconds()
        cfg.train.budget = max(DEMO_MIN_TRAIN_S, left)
    cap = f", {cfg.train.max_seconds:.0f} s budget" if cfg.train.max_seconds else ""
    length = (f"iterations planned for a {cfg.train.budget:.0f} s budget" if cfg.train.budget
              else f"{cfg.train.iters} iterations at most{cap}")
    if cfg.train.budget and cfg.train.budget_up_to_iters:
        length = (f"at most {cfg.train.iters} iterations, fitted to {cfg.train.budget:.0f} s "
                  "of the demo's time")
    print(f"[2/4] training ({length}, sampler {cfg.sampler.name}, {threads} "
          f"thread{'s' if threads > 1 else ''}, {_compile_word(cfg.train.compile)})"
          f" into {run_dir}{' (resuming)' if resume else ''} ...", flush=True)
    return train(scene, cfg, run_dir, device=device, resume=resume, progress=not opts.quiet)


def _compile_word(choice) -> str:
    """The [2/4] line's word for ``train.compile`` (``auto``: `train` decides and says so)."""
    return {True: "compiled", False: "eager"}.get(choice, "compile: auto")


def draw_comparison(scene_dir, mesh, path, score: dict | None) -> Path:
    """Input view | ground-truth mesh | reconstruction, from the scene's first camera."""
    import cv2
    import trimesh

    from neus_l0.data.cameras import read_world_mats, scale_projection
    from neus_l0.figures.raster import raster_render, side_by_side

    scene_dir = Path(scene_dir)
    images = sorted((scene_dir / "image").glob("*.png"))
    img = imread_bytes(images[0], cv2.IMREAD_COLOR)[..., ::-1] / 255.0
    h, w = img.shape[:2]
    up = max(1, 300 // w)  # render the meshes at about 300 pixels wide
    P = scale_projection(read_world_mats(scene_dir)[0], up)
    gt = trimesh.load(scene_dir / "gt_mesh.ply", force="mesh")
    gt_shade = raster_render(gt, P, w * up, h * up)["shade"]
    rec_shade = raster_render(mesh, P, w * up, h * up)["shade"]
    title = None
    if score and all(score.get(k) is not None for k in ("accuracy", "completeness", "overall")):
        title = (f"Chamfer: accuracy {score['accuracy']:.2f}, completeness "
                 f"{score['completeness']:.2f}, overall {score['overall']:.2f} (world units)")
    return side_by_side(path, [("input view", img), ("ground truth", gt_shade),
                               ("reconstruction", rec_shade)], title)


def check_same_settings(run_dir: Path, cfg) -> None:
    """A re-run of the demo resumes its run: only with the settings it started with (beyond
    length and logging), or it would label an `l0` run `hvs`.

    Raises:
        NeusL0Error: naming the keys that differ and the way out.
    """
    from neus_l0.config.load import load_config
    from neus_l0.errors import NeusL0Error
    from neus_l0.run.resumes import changed_keys, guarded_keys, recorded_overrides

    if not (run_dir / "config.yaml").is_file():
        return
    before = load_config(run_dir / "config.yaml", recorded_overrides(run_dir))
    guarded = guarded_keys(changed_keys(before, cfg))
    if guarded:
        raise NeusL0Error(f"{run_dir}: holds a demo run trained with other settings "
                          f"({', '.join(guarded)}); choose another --out, or delete {run_dir} "
                          "to start that run over")
