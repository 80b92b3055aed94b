"""The fork study: the samplers compared on the same sharp field, late in training.

For each scene and seed, one base run trains with `hvs` to ``base_iters`` of a schedule of
``base_iters + arm_iters`` iterations and stops with a checkpoint (``neus-l0 train
--stop-at``). Each arm is a copy of that run folder resumed with another sampler
(``neus-l0 train --resume --change-config sampler=...``) for the remaining ``arm_iters``:
the same weights, optimiser state, learning-rate schedule and random-generator state at
the fork, so that the arms differ only in the sampler from there on. The commands are the
user's own; the study prints each one.

Training uses the scene's training views (every ``holdout``-th view is held out, as in
`neus-l0 bench`: `neus_l0.data.split.split_views`), written once as a scene folder of its
own (`write_view_subset`). Each arm, and the base at the fork, is then scored:

* Chamfer (`neus_l0.evaluation.score.score_mesh` on the mesh at ``resolution``^3) and the
  same on the features' balls, pooled by kind (pits, thin parts:
  `neus_l0.evaluation.features.kind_errors`);
* ``sample_dist``: the mean distance of the fine samples to the true surface on a fixed set
  of object rays (`neus_l0.evaluation.sample_distance`);
* held-out PSNR (`neus_l0.experiments.runner.heldout_psnr`).

Layout of OUT: ``scenes/`` (built-in scenes synthesised, and each scene's training views),
``runs/<scene>__seed<seed>/<arm>/`` (run folders; ``score.json`` in each), ``fork.csv``
and ``summary.md`` (`neus_l0.experiments.fork_report`). A re-run skips what is done.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from neus_l0.atomic import atomic_write_json
from neus_l0.errors import NeusL0Error

#: The arms: label -> the overrides that turn the base's `hvs` run into it.
ARMS: dict[str, tuple[str, ...]] = {
    "hvs": ("sampler=hvs",),
    "l0": ("sampler=l0",),
    "l0 interp": ("sampler=l0", "sampler.l0.masses=interpolant"),
    "l0-inverse": ("sampler=l0-inverse",),
    "neus-exact": ("sampler=neus-exact",),
}
#: The label of the base run's own scores (the field at the fork).
BASE = "base"
#: Settings every training of the study gets: no validation images, no time limit, a
#: checkpoint only where the run stops.
TRAIN_OVERRIDES = ("train.val_every=0", "train.save_every=0", "train.max_seconds=0")


@dataclasses.dataclass
class ForkSpec:
    """What the study runs.

    Attributes:
        out_dir: the study folder OUT.
        scenes: built-in scene names (synthesised into OUT/scenes/) or scene folders with
            ground truth (`neus-l0 synth`).
        seeds: training seeds (``train.seed``).
        arms: `ARMS` labels.
        conf: the base config; overrides: ``key=value`` for every run.
        base_iters: iterations of the base (hvs) run; arm_iters: of each arm after the fork.
        holdout: hold out every K-th view (>= 2).
        threads: torch CPU threads of each training and of the scoring.
        views, width, height: size of synthesised built-in scenes.
        resolution: marching-cubes resolution; eval_density: Chamfer sampling density.
        sample_rays: rays of the sample-distance probe; psnr_pixels: pixels per held-out
            view (`neus_l0.experiments.runner.psnr_stride`).
    """

    out_dir: Path
    scenes: Sequence[str]
    seeds: Sequence[int] = (0, 1, 2)
    arms: Sequence[str] = tuple(ARMS)
    conf: str = "demo"
    overrides: Sequence[str] = ()
    base_iters: int = 2500
    arm_iters: int = 1000
    holdout: int = 8
    threads: int = 1
    views: int = 24
    width: int = 200
    height: int = 150
    resolution: int = 128
    eval_density: float = 0.5
    sample_rays: int = 256
    psnr_pixels: int = 10000

    def check(self) -> None:
        """Refuse settings that cannot run (before anything is trained).

        Raises:
            NeusL0Error: an unknown arm, no hvs arm, or a count out of range.
        """
        bad = [a for a in self.arms if a not in ARMS]
        if bad:
            raise NeusL0Error(f"--arms: unknown {', '.join(bad)} (choose from "
                              f"{', '.join(ARMS)})")
        if "hvs" not in self.arms:
            raise NeusL0Error("--arms: the study compares every arm with hvs; include hvs")
        for name in ("base_iters", "arm_iters", "threads", "resolution"):
            if getattr(self, name) < 1:
                raise NeusL0Error(f"--{name.replace('_', '-')} {getattr(self, name)}: "
                                  "must be at least 1")
        if self.holdout < 2:
            raise NeusL0Error(f"--holdout {self.holdout}: must be 2 or more (the study "
                              "scores held-out views)")
        if not (self.eval_density > 0 and np.isfinite(self.eval_density)):
            raise NeusL0Error(f"--eval-density {self.eval_density}: must be a positive "
                              "number")
        if not self.seeds or not self.scenes:
            raise NeusL0Error("the study needs at least one scene and one seed")

    @property
    def total_iters(self) -> int:
        return self.base_iters + self.arm_iters


def write_view_subset(scene_dir: Path, views: Sequence[int], out: Path) -> Path:
    """A NeuS-format copy of `views` of `scene_dir` (image/, mask/, cameras_sphere.npz),
    renumbered 0..len(views)-1 in the given order; done once (kept if ``out`` holds it).

    Args:
        scene_dir: a NeuS-format scene whose images are named by their index (``000.png``).
        views: view indices into the scene's sorted images.

    Returns:
        `out`.

    Raises:
        NeusL0Error: a view without its camera in ``cameras_sphere.npz``.
    """
    done = out / "views.json"
    if done.is_file() and json.loads(done.read_text())["views"] == list(views):
        return out
    from neus_l0.data.views import indexed_files

    cams = np.load(scene_dir / "cameras_sphere.npz")
    images = list(indexed_files(scene_dir / "image").items())  # [(number, path)] by number
    masks = indexed_files(scene_dir / "mask") if (scene_dir / "mask").is_dir() else {}
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "image").mkdir(parents=True)
    arrays = {}
    for new, v in enumerate(views):
        number, image = images[v]
        shutil.copy2(image, tmp / "image" / f"{new:03d}{image.suffix}")
        if masks:
            (tmp / "mask").mkdir(exist_ok=True)
            shutil.copy2(masks[number], tmp / "mask" / f"{new:03d}{masks[number].suffix}")
        for key in ("world_mat", "scale_mat"):
            if f"{key}_{number}" not in cams.files:
                shutil.rmtree(tmp, ignore_errors=True)
                raise NeusL0Error(f"{scene_dir / 'cameras_sphere.npz'}: no {key}_{number} "
                                  f"for image {image.name}")
            arrays[f"{key}_{new}"] = cams[f"{key}_{number}"]
    np.savez(tmp / "cameras_sphere.npz", **arrays)
    (tmp / "views.json").write_text(json.dumps({"source": str(scene_dir),
                                                "views": list(views)}))
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)
    return out


def train_command(spec: ForkSpec, data: Path, run_dir: Path, arm: str | None,
                  seed: int) -> list[str]:
    """The ``neus-l0 train`` command of the base (`arm` None: hvs, stopping at the fork) or
    of an arm (resuming a copy of the base with the arm's sampler)."""
    head = [sys.executable, "-m", "neus_l0", "train", str(data), "--out", str(run_dir),
            "--threads", str(spec.threads), "--quiet"]
    if arm is None:
        return [*head, "--conf", spec.conf, "--stop-at", str(spec.base_iters),
                *spec.overrides, *TRAIN_OVERRIDES, *ARMS["hvs"], f"train.seed={seed}",
                f"train.iters={spec.total_iters}"]
    return [*head, "--resume", "--change-config", *ARMS[arm]]


def _run(cmd: list[str], log: Callable[[str], None], log_file: Path) -> None:
    """Run `cmd`, its output into `log_file`; a failure names the command and its last line."""
    log("$ neus-l0 " + " ".join(c if " " not in c else repr(c) for c in cmd[3:]))
    with open(log_file, "a", encoding="utf-8") as f:
        rc = subprocess.call(cmd, stdout=f, stderr=subprocess.STDOUT)
    if rc != 0:
        lines = log_file.read_text(encoding="utf-8", errors="replace").strip().splitlines()
        raise NeusL0Error(f"{' '.join(cmd[2:5])}... exited {rc}: "
                          f"{lines[-1] if lines else '(no output)'} (see {log_file})")


def fork_arm(base: Path, arm_dir: Path) -> None:
    """Copy the base run folder (at the fork) to `arm_dir`, without its lock or events."""
    tmp = arm_dir.with_name(arm_dir.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(base, tmp, ignore=shutil.ignore_patterns(
        "*.lock", ".lock", "events.out.tfevents*", "score.json", "mesh.ply", "log.txt"))
    tmp.rename(arm_dir)


def score_run(run_dir: Path, scene_dir: Path, spec: ForkSpec) -> dict:
    """Score a run folder's newest checkpoint (see the module docstring).

    Returns:
        iteration, train_s (the loop's time of the last training), overall, accuracy,
        completeness, pit, thin (pooled feature overall; None without such features),
        sample_dist (world units), psnr (dB, mean over the held-out views).
    """
    import torch

    from neus_l0.data.split import split_views, subset_scene
    from neus_l0.evaluation.features import kind_overall
    from neus_l0.evaluation.sample_distance import SurfaceDistance
    from neus_l0.evaluation.score import ScoreSpec, score_mesh
    from neus_l0.experiments.runner import heldout_psnr
    from neus_l0.experiments.sample_hook import SampleDistanceHook
    from neus_l0.formats.open import open_scene
    from neus_l0.mesh.extract import export_mesh
    from neus_l0.mesh.from_run import mesh_from_run
    from neus_l0.run.metrics import last_log_line

    torch.set_num_threads(spec.threads)
    made = mesh_from_run(run_dir, spec.resolution, "cpu")
    iteration = int(made.info["iteration"])
    mesh = export_mesh(made.mesh, run_dir / "mesh.ply")
    score = score_mesh(mesh, ScoreSpec(scene=scene_dir, density=spec.eval_density,
                                       workers=spec.threads), log=lambda _: None)
    full = open_scene(scene_dir, downscale=made.cfg.data.downscale, device="cpu",
                      preview=False)
    train_views, test_views = split_views(full.n_views, spec.holdout)
    surface = SurfaceDistance.from_scene_dir(scene_dir)
    with torch.no_grad():
        hook = SampleDistanceHook(surface, spec.sample_rays)
        dist = hook(iteration, made.model, subset_scene(full, train_views), made.cfg,
                    force=True)["sample_dist"]
        psnrs = heldout_psnr(made.model, full, test_views, made.cfg, iteration,
                             spec.psnr_pixels)
    return {"iteration": iteration, "train_s": last_log_line(run_dir).get("elapsed"),
            "overall": score["overall"], "accuracy": score["accuracy"],
            "completeness": score["completeness"],
            "pit": kind_overall(score, "pit"), "thin": kind_overall(score, "thin"),
            "sample_dist": dist, "psnr": float(np.mean(psnrs)),
            "sampler": made.cfg.sampler.name, "masses": made.cfg.sampler.l0.masses}


def _scored(run_dir: Path, scene_dir: Path, spec: ForkSpec, iteration: int,
            unit: dict) -> dict:
    """`score_run`'s result with the `unit` (scene, seed, arm) ahead, kept in
    ``score.json`` (re-used when its iteration and the scoring settings match)."""
    path = run_dir / "score.json"
    how = {k: getattr(spec, k) for k in ("resolution", "eval_density", "sample_rays",
                                         "psnr_pixels", "holdout")}
    if path.is_file():
        old = json.loads(path.read_text())
        if old.get("iteration") == iteration and old.get("scoring") == how:
            return old
    out = {**unit, **score_run(run_dir, scene_dir, spec), "scoring": how}
    if out["iteration"] != iteration:
        raise NeusL0Error(f"{run_dir}: newest checkpoint at iteration {out['iteration']}, "
                          f"expected {iteration}")
    atomic_write_json(path, out)
    return out


def run_pair(spec: ForkSpec, scene: str, scene_dir: Path, train_dir: Path, seed: int,
             log: Callable[[str], None] = print) -> list[dict]:
    """The base run and every arm of one (scene, seed); their result rows."""
    from neus_l0.run.checkpoints import checkpoint_path

    folder = Path(spec.out_dir) / "runs" / f"{scene}__seed{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    base = folder / BASE
    if not checkpoint_path(base, spec.base_iters).is_file():
        shutil.rmtree(base, ignore_errors=True)
        _run(train_command(spec, train_dir, base, None, seed), log, folder / f"{BASE}.log")
    rows = [_scored(base, scene_dir, spec, spec.base_iters,
                    {"scene": scene, "seed": seed, "arm": BASE})]
    log(f"  {scene} seed {seed} {BASE}: Chamfer {rows[0]['overall']:.4g}")
    for arm in spec.arms:
        arm_dir = folder / arm.replace(" ", "_")
        if not checkpoint_path(arm_dir, spec.total_iters).is_file():
            shutil.rmtree(arm_dir, ignore_errors=True)
            fork_arm(base, arm_dir)
            _run(train_command(spec, train_dir, arm_dir, arm, seed), log,
                 folder / f"{arm_dir.name}.log")
        row = _scored(arm_dir, scene_dir, spec, spec.total_iters,
                      {"scene": scene, "seed": seed, "arm": arm})
        log(f"  {scene} seed {seed} {arm}: Chamfer {row['overall']:.4g}, "
            f"sample_dist {row['sample_dist']:.4g}, PSNR {row['psnr']:.2f}")
        rows.append(row)
    return rows


def run_study(spec: ForkSpec, log: Callable[[str], None] = print) -> list[dict]:
    """Every (scene, seed) of `spec`, scene-major; their rows. OUT's fork.csv and summary.md
    are rewritten after each (scene, seed) from every run scored in OUT (`collect_rows`), so
    that several studies may share OUT (e.g. one per seed, side by side)."""
    from neus_l0.data.split import split_views
    from neus_l0.data.views import indexed_files
    from neus_l0.experiments.fork_report import write_outputs
    from neus_l0.experiments.sweep import prepare_scene

    spec.check()
    out = Path(spec.out_dir)
    rows: list[dict] = []
    scenes = [prepare_scene(e, out, spec.views, spec.width, spec.height) for e in spec.scenes]
    for _, scene_dir in scenes:  # every scene checked before the first run trains
        if not (scene_dir / "gt_mesh.ply").is_file():
            raise NeusL0Error(f"{scene_dir}: no gt_mesh.ply (the study needs a synthetic "
                              "scene's ground truth: neus-l0 synth)")
    for scene, scene_dir in scenes:
        train_views, _ = split_views(len(indexed_files(scene_dir / "image")), spec.holdout)
        train_dir = write_view_subset(scene_dir, train_views,
                                      out / "scenes" / f"{scene}__train")
        for seed in spec.seeds:
            rows += run_pair(spec, scene, scene_dir, train_dir, int(seed), log)
            write_outputs(out, collect_rows(out), spec)
    return rows


def collect_rows(out: Path) -> list[dict]:
    """The rows of every run scored in OUT (``runs/*/*/score.json``), sorted."""
    rows = [json.loads(p.read_text()) for p in sorted(Path(out).glob("runs/*/*/score.json"))]
    return sorted(rows, key=lambda r: (r["scene"], r["seed"], r["arm"]))
