"""The attack as a test suite (issue #27 item 6): every bad input of issue #27 (its "Why", the
table's categories, the list still to check, and "What to build") and the six faults of issue
#18, one test per case. Each asserts the exit code and one clear line naming the file or the
key, without a traceback, or the correct result. The commands run in-process
(`neus_l0.cli.main`), in subprocesses only where a signal must reach a whole process.

Scenes: `scene96` (the demo object, 8 views at 96x72: the unit sphere's fit is judged from 72
pixels up) and conftest's `tiny_scene` (8 views at 64x48), each built once; trainings use
conftest's small network and a few iterations.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import trimesh

import neus_l0.synthetic.scene as synthetic
from neus_l0.cli import main
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation import score
from neus_l0.evaluation.cull import dilate_mask
from neus_l0.formats.neus import load_scene

ROOT = Path(__file__).resolve().parents[1]

#: A tiny network and an iteration count no run reaches: only the signal or the budget ends
#: training (eager: a long run would compile under `train.compile: auto`).
TINY = ["model.sdf.hidden=32", "model.sdf.layers=2", "model.sdf.skip=[]",
        "model.sdf.feature_dim=16", "model.sdf.encoding.n_freqs=2", "model.color.hidden=32",
        "model.color.layers=1", "render.n_samples=16", "render.n_importance=16",
        "render.up_sample_steps=2", "train.batch_size=64", "train.warm_up=0",
        "train.iters=100000", "train.log_every=4", "train.compile=false"]
#: The bench's flags that keep a run small.
BENCH_SMALL = ["--resolution", "24", "--eval-density", "3", "--sample-rays", "32",
               "--holdout", "4", "--quiet", "--no-plots"]
#: synth's flags for a small, quiet scene.
SYNTH_SMALL = ("--width", "32", "--height", "24", "--no-progress")


# ==========================================================================================
# Helpers and fixtures


def error_line(err: str, command: str, *named: str, alone: bool = False) -> str:
    """The one ``neus-l0 COMMAND: error:`` line of stderr `err`, naming every `named`; no
    traceback. `alone`: it is all of stderr (no notes before it)."""
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith(f"neus-l0 {command}: error: ")]
    assert len(lines) == 1, err
    if alone:
        assert [ln for ln in err.splitlines() if ln.strip()] == lines, err
    for needle in named:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def refused(capsys, argv: list[str], *named: str, code: int = 2, alone: bool = False) -> str:
    """Run the CLI; assert exit `code` and one error line naming `named` (`error_line`)."""
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == code, err
    return error_line(err, argv[0], *named, alone=alone)


def one_line(err: str) -> str:
    """The single non-empty line of `err` (asserting there is exactly one, no traceback)."""
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    return lines[0]


def checkpoints(run: Path) -> list[str]:
    """The names of the run's checkpoint files (none when it has no checkpoints folder)."""
    folder = run / "checkpoints"
    return sorted(p.name for p in folder.glob("ckpt_*")) if folder.is_dir() else []


def edit_cameras(root: Path, **changes) -> None:
    """Set (or, with None, drop) entries of the scene's cameras_sphere.npz."""
    cams = dict(np.load(root / "cameras_sphere.npz"))
    for key, value in changes.items():
        if value is None:
            cams.pop(key)
        else:
            cams[key] = value
    np.savez(root / "cameras_sphere.npz", **cams)


def scale_spheres(root: Path, factor: float, block: slice = slice(0, 3)) -> None:
    """Multiply the columns `block` of the top three rows of every scale_mat_i by `factor`."""
    cams = dict(np.load(root / "cameras_sphere.npz"))
    for key in [k for k in cams if k.startswith("scale_mat_")]:
        m = cams[key].copy()
        m[:3, block] *= factor
        cams[key] = m
    np.savez(root / "cameras_sphere.npz", **cams)


@pytest.fixture(scope="module")
def scene96(tmp_path_factory) -> Path:
    """The demo object, 8 views at 96x72 (read-only)."""
    out = tmp_path_factory.mktemp("scene96") / "demo"
    return synthetic.make_scene("demo", out, views=8, width=96, height=72, seed=0,
                                gt_voxel=4.0, point_spacing=2.0, progress=False)


@pytest.fixture
def scene_copy(scene96, tmp_path) -> Path:
    """A copy of `scene96`'s views (image/, mask/, cameras_sphere.npz, scene.json) to break."""
    root = tmp_path / "scene"
    for name in ("image", "mask"):
        shutil.copytree(scene96 / name, root / name)
    for name in ("cameras_sphere.npz", "scene.json"):
        shutil.copy(scene96 / name, root)
    return root


@pytest.fixture
def train_cli(small):
    """``train_cli(scene, run, *extra)``: the argv of a small, quiet training on one thread."""
    def argv(scene: Path, run: Path, *extra: str) -> list[str]:
        return ["train", str(scene), "--conf", "demo", "--out", str(run), "--quiet",
                "--threads", "1", *small, *extra]
    return argv


def resume_cli(scene: Path, run: Path, *extra: str) -> list[str]:
    """The argv of ``train --resume`` (config.yaml is the base; `extra` overrides)."""
    return ["train", str(scene), "--out", str(run), "--resume", "--quiet", "--threads", "1",
            *extra]


@pytest.fixture(scope="module")
def trained96(scene96, small_overrides, tmp_path_factory) -> Path:
    """A run of 4 iterations on `scene96` (checkpoints at 2 and 4), trained by the CLI under
    umask 022 (read-only: tests copy it with `run_copy`)."""
    run = tmp_path_factory.mktemp("trained96") / "run"
    old = os.umask(0o022)
    try:
        assert main(["train", str(scene96), "--conf", "demo", "--out", str(run), "--quiet",
                     "--threads", "1", *small_overrides, "train.iters=4",
                     "train.save_every=2"]) == 0
    finally:
        os.umask(old)
    assert checkpoints(run) == ["ckpt_0000002.pt", "ckpt_0000004.pt"]
    return run


@pytest.fixture
def run_copy(trained96, tmp_path) -> Path:
    """A copy of `trained96` to resume, damage or mesh."""
    return Path(shutil.copytree(trained96, tmp_path / "run"))


# ==========================================================================================
# Issue #27, "Why": images paired with the wrong cameras, silently


def test_names_that_sort_wrong_as_text_pair_by_number(scene96, scene_copy, capsys):
    """Unpadded names past 9 (0, 1, 10, 11, 2, ... as text) pair with their own cameras;
    inspect says the rule."""
    numbers = [0, 1, 2, 3, 4, 5, 10, 11]
    names = [f"{n}.png" for n in numbers]
    assert sorted(names) != names  # by position, view 2 would get camera 10
    cams = dict(np.load(scene_copy / "cameras_sphere.npz"))
    np.savez(scene_copy / "cameras_sphere.npz",
             **{f"{kind}_{n}": cams[f"{kind}_{i}"] for i, n in enumerate(numbers)
                for kind in ("world_mat", "scale_mat")})
    for folder in ("image", "mask"):
        for i, n in enumerate(numbers):
            (scene_copy / folder / f"{i:03d}.png").rename(scene_copy / folder / f"{n}.png")
    assert main(["inspect", str(scene_copy)]) == 0
    assert "pairing      views pair by the last number" in capsys.readouterr().out
    got, ref = load_scene(scene_copy), load_scene(scene96)
    assert got.image_names == names
    assert torch.equal(got.c2w, ref.c2w) and torch.equal(got.images, ref.images)
    assert torch.equal(got.masks, ref.masks)


def test_a_deleted_view_trains_on_the_rest_with_one_warning(scene_copy, train_cli, tmp_path,
                                                           capsys):
    """Image and mask 005 deleted, world_mat_5 kept: a one-line warning, 7 views train."""
    (scene_copy / "image" / "005.png").unlink()
    (scene_copy / "mask" / "005.png").unlink()
    run = tmp_path / "run"
    assert main(train_cli(scene_copy, run, "train.iters=2")) == 0
    warnings = [ln for ln in capsys.readouterr().err.splitlines() if "warning" in ln]
    assert len(warnings) == 1
    assert "world_mat_5" in warnings[0] and "7 views" in warnings[0]
    assert json.loads((run / "run.json").read_text())["n_views"] == 7


# ==========================================================================================
# "Why": an object bigger than the unit sphere


def test_an_object_the_sphere_cuts_is_refused_naming_the_fix(scene_copy, train_cli, tmp_path,
                                                             capsys):
    """scale_mat halved: refused before training, with the fix; once fixed, the same --out
    trains (the refused start left no hull behind)."""
    good = (scene_copy / "cameras_sphere.npz").read_bytes()
    scale_spheres(scene_copy, 0.5)
    run = tmp_path / "run"
    refused(capsys, train_cli(scene_copy, run, "train.iters=2"), str(scene_copy),
            "does not fit its unit sphere", "enlarge the sphere")
    assert checkpoints(run) == [] and not (run / "hull.pt").exists()
    (scene_copy / "cameras_sphere.npz").write_bytes(good)
    assert main(train_cli(scene_copy, run, "train.iters=2")) == 0
    assert checkpoints(run) == ["ckpt_0000002.pt"]


# ==========================================================================================
# "Why": numbers that cannot work; "Quietly wrong numbers"; "What to build" 2 (every config
# number in range, one rule per key)


@pytest.mark.parametrize("override", [
    "render.chunk=0", "train.save_every=-7", "train.max_seconds=-1", "train.lr=.nan",
    "render.chunk=-4", "train.igr_weight=-1", "train.lr_alpha=-1", "sampler.pad=.inf",
    "train.warm_up=-1", "train.val_downscale=0", "train.keep_checkpoints=-1",
    "train.lr=.inf",
])
def test_a_config_number_that_cannot_work_is_refused_before_training(scene96, train_cli,
                                                                     tmp_path, capsys,
                                                                     override):
    """Exit 2 naming the key; no run folder (so no checkpoint) is made."""
    run = tmp_path / "run"
    refused(capsys, train_cli(scene96, run, "train.iters=2", override),
            f"{override.split('=')[0]}:", alone=True)
    assert not run.exists()


# ==========================================================================================
# "Why": divergence ends as a success; "What to build" 3


def test_a_diverging_run_exits_non_zero_keeping_its_last_good_checkpoint(scene96, run_copy,
                                                                         capsys):
    """train.lr=1000 from iteration 4: exit 2, one line naming the last good checkpoint,
    which is intact and the newest a resume finds (later ones are set aside)."""
    line = refused(capsys, resume_cli(scene96, run_copy, "--change-config", "train.iters=60",
                                      "train.lr=1000", "train.save_every=5",
                                      "train.log_every=5"),
                   "diverged at iteration", "the last good checkpoint is ckpt_")
    good = line.split("the last good checkpoint is ")[1].split(";")[0]
    assert [n for n in checkpoints(run_copy) if n.endswith(".pt")][-1] == good
    state = torch.load(run_copy / "checkpoints" / good, weights_only=True)
    assert state["iteration"] == int(good[5:12]) >= 4
    assert all(torch.isfinite(v).all() for v in state["model"].values())


def test_the_divergence_advice_is_a_command_that_runs(scene96, run_copy, capsys):
    """The line's suggested resume is accepted (it needs --change-config)."""
    line = refused(capsys, resume_cli(scene96, run_copy, "--change-config", "train.iters=60",
                                      "train.lr=1000", "train.log_every=5"), "diverged")
    assert "--change-config" in line


def test_a_sharpness_beyond_neus_clamp_is_refused_before_training(scene96, train_cli,
                                                                  tmp_path, capsys):
    """model.variance.init=100 (s = e^1000): exit 2 naming the key and NeuS's clamp."""
    refused(capsys, train_cli(scene96, tmp_path / "run", "model.variance.init=100"),
            "model.variance.init", "clamp", alone=True)
    assert not (tmp_path / "run").exists()


# ==========================================================================================
# "Why": --resume with another scene's folder


def test_resume_on_another_scene_is_refused(scene_copy, run_copy, capsys):
    """A run trained on scene96, resumed on a 7-view scene: exit 2 naming both."""
    (scene_copy / "image" / "005.png").unlink()
    (scene_copy / "mask" / "005.png").unlink()
    before = checkpoints(run_copy)
    refused(capsys, resume_cli(scene_copy, run_copy, "train.iters=6"), str(run_copy),
            "was trained on", "(8 views)", f"not on {scene_copy} (7 views)")
    assert checkpoints(run_copy) == before


# ==========================================================================================
# "Why": raw tracebacks or errors that name no file or key; "What to build" 4


def test_object_arrays_in_the_camera_file_are_named(scene_copy, train_cli, tmp_path, capsys):
    """A cameras_sphere.npz holding an object array: exit 2 naming the file and the key."""
    cams = dict(np.load(scene_copy / "cameras_sphere.npz"))
    cams["world_mat_2"] = np.array([cams["world_mat_2"], "x"], dtype=object)
    np.savez(scene_copy / "cameras_sphere.npz", **cams)
    refused(capsys, train_cli(scene_copy, tmp_path / "run"),
            "cameras_sphere.npz", "'world_mat_2' is not a numeric matrix")
    assert checkpoints(tmp_path / "run") == []


def _eval(tiny_scene, tmp_path, *flags: str) -> list[str]:
    return ["eval", str(tiny_scene / "gt_mesh.ply"), "--scene", str(tiny_scene),
            "--json", str(tmp_path / "r.json"), *flags]


@pytest.mark.parametrize("workers", ["0", "-2"])
def test_eval_workers_zero_or_negative(tiny_scene, tmp_path, capsys, workers):
    refused(capsys, _eval(tiny_scene, tmp_path, "--workers", workers),
            f"--workers {workers}", "-1 (all cores)", alone=True)
    assert not (tmp_path / "r.json").exists()


# synth from a degenerate mesh: test_synth_degenerate_mesh below ("Odd files").


# ==========================================================================================
# "Why": outputs written with mode 0600; "What to build" 4 (normal file modes)


def test_outputs_get_mode_0644_under_umask_022(trained96, scene96, tmp_path):
    """A run's files, a mesh and an eval report: 0644, not the temporary file's 0600."""
    modes = {str(p.relative_to(trained96)): stat.S_IMODE(p.stat().st_mode)
             for p in trained96.rglob("*") if p.is_file()}
    for name in ("config.yaml", "run.json", "hull.pt", "checkpoints/ckpt_0000004.pt"):
        assert modes.pop(name) == 0o644, name
    assert set(modes.values()) <= {0o644}, modes
    old = os.umask(0o022)
    try:
        mesh = tmp_path / "m.ply"
        assert main(["mesh", str(trained96), "--resolution", "24", "--out", str(mesh)]) == 0
        report = tmp_path / "r.json"
        assert main(["eval", str(mesh), "--scene", str(scene96), "--json", str(report),
                     "--density", "2", "--no-progress"]) == 0
    finally:
        os.umask(old)
    assert stat.S_IMODE(mesh.stat().st_mode) == 0o644
    assert stat.S_IMODE(report.stat().st_mode) == 0o644


# ==========================================================================================
# Table: data lost


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _small_scene(out: Path, views: int) -> Path:
    return synthetic.make_scene("demo", out, views=views, width=32, height=24, gt_voxel=6.0,
                                point_spacing=6.0, progress=False)


@pytest.mark.parametrize("where", ["render", "png"])
def test_synth_interrupted_keeps_the_old_scene(tmp_path, monkeypatch, where):
    out = _small_scene(tmp_path / "scene", views=4)
    before = _snapshot(out)
    calls = {"n": 0}

    def failing(real):
        def wrapped(*args, **kwargs):
            calls["n"] += 1
            if calls["n"] == 3:
                raise RuntimeError("injected failure")
            return real(*args, **kwargs)
        return wrapped

    if where == "render":  # one view per batch: fails on the third view
        monkeypatch.setattr(synthetic, "RAYS_PER_BATCH", 1)
        monkeypatch.setattr(synthetic, "render_views", failing(synthetic.render_views))
    else:  # fails while writing the second view's image
        monkeypatch.setattr(synthetic, "_write_png", failing(synthetic._write_png))
    with pytest.raises(RuntimeError, match="injected"):
        synthetic.make_scene("demo", out, views=6, width=32, height=24, seed=1,
                             gt_voxel=6.0, point_spacing=6.0, progress=False)
    assert _snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]  # no temporary left
    assert load_scene(out).n_views == 4


def test_synth_fewer_views_leaves_no_stale_images(tmp_path, capsys):
    out = tmp_path / "scene"
    assert main(["synth", "demo", str(out), "--views", "6", *SYNTH_SMALL]) == 0
    assert main(["synth", "demo", str(out), "--views", "3", *SYNTH_SMALL]) == 0
    for sub in ("image", "mask"):
        assert sorted(p.name for p in (out / sub).iterdir()) == ["000.png", "001.png",
                                                                  "002.png"]
    assert sorted(np.load(out / "cameras_sphere.npz").files) == sorted(
        [f"world_mat_{i}" for i in range(3)] + [f"scale_mat_{i}" for i in range(3)])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]
    capsys.readouterr()
    assert main(["inspect", str(out)]) == 0
    assert "views        3" in capsys.readouterr().out


def test_resume_with_a_new_lr_keeps_config_yaml_and_records_it(scene96, run_copy, capsys):
    """--resume train.lr=1e5: refused without --change-config; with it, config.yaml stays
    the original and resumes.jsonl records the change."""
    original = (run_copy / "config.yaml").read_bytes()
    refused(capsys, resume_cli(scene96, run_copy, "train.lr=1e5"), "train.lr",
            "--change-config", alone=True)
    assert not (run_copy / "resumes.jsonl").exists()
    assert main(resume_cli(scene96, run_copy, "--change-config", "train.iters=6",
                           "train.lr=1e-4")) == 0
    assert (run_copy / "config.yaml").read_bytes() == original
    (record,) = [json.loads(x) for x in (run_copy / "resumes.jsonl").read_text().splitlines()]
    assert record["iteration"] == 4 and record["changed"] == ["train.iters", "train.lr"]
    assert "train.lr=0.0001" in record["overrides"]


# ==========================================================================================
# Table: hang (mesh at a coarse resolution dilated the hull for minutes); "What to build" 5


def _ball_hull(R: int = 128, radius: float = 0.3):
    """A hull like a run's: 128 cells a side, a carved ball dilated by one cell."""
    from neus_l0.bounds.grid import cell_axis, dilate
    from neus_l0.bounds.hull import VisualHull

    c = cell_axis(R)
    r2 = c[:, None, None] ** 2 + c[None, :, None] ** 2 + c[None, None, :] ** 2
    return VisualHull(dilate(r2 <= radius ** 2))


@pytest.fixture
def pool_kernels(monkeypatch):
    """The kernel sizes of every max-pool (the old dilation) called while the test runs."""
    import torch.nn.functional as F

    seen: list[int] = []
    real = F.max_pool3d

    def spy(x, kernel_size, *args, **kw):
        seen.append(int(np.max(kernel_size)))
        return real(x, kernel_size, *args, **kw)

    monkeypatch.setattr(F, "max_pool3d", spy)
    return seen


def test_box_dilation_equals_the_max_pool_at_every_radius():
    from neus_l0.bounds.grid import dilate
    from neus_l0.bounds.hull import dilate_box

    g = torch.Generator().manual_seed(0)
    for R in (5, 8, 13):
        occ = torch.rand(R, R, R, generator=g) < 0.03
        occ[R // 2, 0, R - 1] = True
        for n in range(R + 3):
            assert torch.equal(dilate_box(occ, n), dilate(occ, n)), (R, n)
    assert not dilate_box(torch.zeros(6, 6, 6, dtype=torch.bool), 9).any()


@pytest.mark.parametrize("resolution, radius", [(8, 0.9), (9, 0.6), (16, 0.6)])
def test_coarse_extraction_does_not_grow_the_dilation(sphere_model, pool_kernels, resolution,
                                                      radius):
    from neus_l0.mesh.extract import extract_mesh

    hull = _ball_hull(radius=radius)  # holds the model's sphere of radius 0.5
    region = hull.for_grid(2.0 / (resolution - 1))
    assert max(pool_kernels, default=1) <= 3  # no kernel of (2n + 1)^3 cells, n ~ 15-32
    if radius == 0.9:
        assert bool(region.occupancy.all())  # the hull's region covers the whole grid
    model = sphere_model()
    inside = extract_mesh(model, np.eye(4), resolution=resolution, clean=False, hull=hull)
    plain = extract_mesh(model, np.eye(4), resolution=resolution, clean=False)
    assert max(pool_kernels, default=1) <= 3
    # inside the carved hull the mesh is the one without a hull
    assert len(plain.faces) > 0
    assert np.array_equal(np.asarray(inside.vertices), np.asarray(plain.vertices))
    assert np.array_equal(np.asarray(inside.faces), np.asarray(plain.faces))


@pytest.fixture(scope="module")
def tiny_run(tiny_scene, small_overrides, tmp_path_factory):
    """A run of 4 iterations on the tiny scene (with its hull.pt)."""
    from neus_l0.config.load import load_config
    from neus_l0.train.loop import train

    run = tmp_path_factory.mktemp("mesh") / "run"
    cfg = load_config("demo", [*small_overrides, "train.iters=4", "train.tensorboard=false"])
    train(load_scene(tiny_scene), cfg, run, progress=False)
    assert (run / "hull.pt").is_file()
    return run


@pytest.mark.parametrize("resolution", ["8", "9", "16"])
def test_mesh_command_at_a_coarse_resolution(tiny_run, tmp_path, capsys, pool_kernels,
                                             resolution):
    out = tmp_path / "m.ply"
    assert main(["mesh", str(tiny_run), "--resolution", resolution, "--out", str(out)]) == 0
    assert out.is_file() and max(pool_kernels, default=1) <= 3
    assert "Traceback" not in capsys.readouterr().err


# ==========================================================================================
# Table: signals (Ctrl-C / SIGTERM stop demo and bench with 130 / 143 and reach their
# subprocesses); "What to build" 5


def _start(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "neus_l0", *args], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(paths, proc: subprocess.Popen, seconds: float = 60.0) -> None:
    """Wait until `paths()` finds a file (training has logged), failing if `proc` ends first."""
    deadline = time.monotonic() + seconds
    while not paths():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "training did not start"
        time.sleep(0.05)


def _finish(proc: subprocess.Popen, seconds: float = 60.0) -> tuple[str, str]:
    try:
        return proc.communicate(timeout=seconds)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def _gone(pid: int) -> bool:
    """Whether `pid` has exited (a zombie that nobody has reaped yet counts as gone)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state in ("Z", "X")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_demo_stops_after_the_checkpoint_on_a_signal(tiny_scene, small, tmp_path, sig):
    out = tmp_path / "demo"
    shutil.copytree(tiny_scene, out / "scene")  # the demo reuses a scene it finds
    proc = _start(["demo", "--out", str(out), "--quiet", "--threads", "1", *small,
                   "train.iters=100000", "train.max_seconds=120", "train.compile=false"])
    _wait_for(lambda: (out / "run" / "metrics.jsonl").is_file(), proc)
    proc.send_signal(sig)
    _, err = _finish(proc)
    assert proc.returncode == 128 + int(sig)
    line = one_line(err)
    assert f"stopped by {signal.Signals(sig).name}" in line and "checkpoint" in line
    assert list((out / "run" / "checkpoints").glob("ckpt_*.pt"))
    assert not (out / "mesh.ply").exists() and not (out / "metrics.json").exists()


def _bench_args(scene: Path, out: Path, samplers: str = "hvs,l0", seconds: str = "60"):
    return ["bench", "--scenes", str(scene), "--samplers", samplers, "--seconds", seconds,
            "--out", str(out), *BENCH_SMALL, *TINY]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_bench_passes_a_signal_to_its_run_and_records_it_interrupted(tiny_scene, tmp_path,
                                                                    capsys, sig):
    out = tmp_path / "sweep"
    proc = _start(_bench_args(tiny_scene, out))
    _wait_for(lambda: list(out.glob("runs/*/metrics.jsonl")), proc)
    child = json.loads(next(out.glob("runs/*/.lock")).read_text())["pid"]
    if sig == signal.SIGTERM:  # meanwhile a second bench into the same folder is refused
        line = refused(capsys, _bench_args(tiny_scene, out), alone=True)
        assert str(out.resolve()) in line and f"PID {proc.pid}" in line
    proc.send_signal(sig)
    out_text, err = _finish(proc)
    assert proc.returncode == 128 + int(sig)
    assert _gone(child), "the run's process outlived the bench"
    line = one_line(err)
    assert f"stopped by {signal.Signals(sig).name}" in line and "interrupted" in line
    rows = json.loads((out / "results.json").read_text())
    assert [r["status"] for r in rows] == ["interrupted"]  # the second run never started
    assert f"stopped by {signal.Signals(sig).name} at iteration" in rows[0]["error"]
    run = out / rows[0]["run_dir"]
    assert list((run / "checkpoints").glob("ckpt_*.pt"))  # training checkpointed
    assert not (run / "mesh.ply").exists()
    assert not (out / ".lock").exists()


def test_a_run_stops_when_its_bench_is_killed_outright(tiny_scene, tmp_path):
    out = tmp_path / "sweep"
    proc = _start(_bench_args(tiny_scene, out))
    _wait_for(lambda: list(out.glob("runs/*/metrics.jsonl")), proc)
    child = json.loads(next(out.glob("runs/*/.lock")).read_text())["pid"]
    proc.kill()  # SIGKILL: nothing can pass a signal on
    _finish(proc)
    status = next(out.glob("runs/*")) / "status.json"
    deadline = time.monotonic() + 30
    while not _gone(child) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _gone(child), "the run's process trains on without its bench"
    row = json.loads(status.read_text())["row"]
    assert row["status"] == "interrupted" and "stopped by SIGTERM" in row["error"]


class FakeRay:
    """Just enough of Ray for `run_with_ray`: tasks never run; `on_wait` is called at each
    ``ray.wait`` and gives what it returns; cancels are recorded."""

    def __init__(self, on_wait):
        self.on_wait, self.refs, self.cancelled = on_wait, [], []

    def is_initialized(self):
        return True  # the caller's Ray: neither started nor shut down here

    def remote(self, **_options):
        ray = self

        class Task:
            def options(self, **_kw):
                return self

            def remote(self, spec, _timeout):
                ray.refs.append((f"ref{len(ray.refs)}", spec))
                return ray.refs[-1][0]

        return lambda fn: Task()

    def wait(self, refs, num_returns=1, timeout=None):
        assert timeout is not None, "the sweep must not block without looking for signals"
        return self.on_wait(refs)

    def get(self, ref):
        return {"ref": ref}

    def cancel(self, ref, force=False):
        self.cancelled.append((ref, force))


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_bench_on_ray_cancels_its_tasks_on_a_signal(tiny_scene, tmp_path, capsys, monkeypatch,
                                                    sig):
    """--backend ray: a signal force-cancels every task (the run, orphaned, checkpoints and
    stops), records the started run interrupted, exits 143 / 130."""
    def first_run_starts_then_signal(refs):
        if not fake.cancelled and not getattr(fake, "signalled", False):
            spec = fake.refs[0][1]  # what a run's start leaves: spec.json, no status.json
            spec.run_dir.mkdir(parents=True, exist_ok=True)
            (spec.run_dir / "spec.json").write_text("{}")
            fake.signalled = True
            os.kill(os.getpid(), sig)
        return [], list(refs)

    fake = FakeRay(first_run_starts_then_signal)
    monkeypatch.setitem(sys.modules, "ray", fake)
    out = tmp_path / "sweep"
    args = _bench_args(tiny_scene, out)
    assert main([args[0], "--backend", "ray", *args[1:]]) == 128 + int(sig)
    name = signal.Signals(sig).name
    line = one_line(capsys.readouterr().err)
    assert f"stopped by {name}" in line and "1 not started" in line
    assert fake.cancelled == [(ref, True) for ref, _ in fake.refs] and len(fake.refs) == 2
    (row,) = json.loads((out / "results.json").read_text())
    assert row["status"] == "interrupted" and row["error"].startswith(f"stopped by {name}")
    assert row["run_dir"] == f"runs/{fake.refs[0][1].name}" and row["run_dir"] in line
    assert not (out / ".lock").exists()


def test_a_second_ctrl_c_under_ray_still_cancels_the_tasks(monkeypatch):
    """KeyboardInterrupt while waiting (a second Ctrl-C): every task cancelled, then raised."""
    from neus_l0.experiments.ray_backend import run_with_ray

    class Spec:
        device, threads, name = "cpu", 1, "a"

    def interrupted(_refs):
        raise KeyboardInterrupt

    fake = FakeRay(interrupted)
    monkeypatch.setitem(sys.modules, "ray", fake)
    with pytest.raises(KeyboardInterrupt):
        run_with_ray([Spec(), Spec()], lambda row, name: None)
    assert fake.cancelled == [("ref0", True), ("ref1", True)]


def test_ray_rows_come_back_as_tasks_finish():
    """Without a signal, the polling loop hands every task's row on."""
    from neus_l0.experiments.ray_backend import run_with_ray
    from neus_l0.train.signals import StopOnSignal

    class Spec:
        device, threads = "cpu", 1

        def __init__(self, name):
            self.name = name

    waits = []

    def one_by_one(refs):
        waits.append(len(refs))
        return ([refs[0]], refs[1:]) if len(waits) > 1 else ([], list(refs))

    fake = FakeRay(one_by_one)
    seen = []
    with pytest.MonkeyPatch.context() as mp, StopOnSignal() as stop:
        mp.setitem(sys.modules, "ray", fake)
        run_with_ray([Spec("a"), Spec("b")], lambda row, name: seen.append((row, name)),
                     stop=stop)
    assert seen == [({"ref": "ref0"}, "a"), ({"ref": "ref1"}, "b")]
    assert waits == [2, 2, 1] and fake.cancelled == []


# ==========================================================================================
# Table: late failures (demo --resolution 0, render.chunk=0 and eval --cmap are refused
# before any work; write failures surface before the work, as one line)


@pytest.mark.parametrize("flags, named", [
    (["--resolution", "0"], "--resolution 0"),
    (["--resolution", "7"], "--resolution 7"),
    (["--threads", "0"], "--threads 0"),
    (["--threads", "-2"], "--threads -2"),
    (["--resolution", "100000"], "--resolution 100000"),
])
def test_demo_checks_its_numbers_before_any_work(tmp_path, capsys, flags, named):
    out = tmp_path / "demo"
    refused(capsys, ["demo", "--out", str(out), *flags], named, alone=True)
    assert not out.exists()


def test_demo_checks_its_config_before_any_work(tmp_path, capsys):
    out = tmp_path / "demo"
    refused(capsys, ["demo", "--out", str(out), "train.iters=0"], "train.iters", alone=True)
    assert not out.exists()


# render.chunk=0: test_a_config_number_that_cannot_work_is_refused_before_training above.


def test_eval_unknown_cmap_refused_before_any_work(tiny_scene, tmp_path, capsys, monkeypatch):
    def never(*_a, **_k):
        raise AssertionError("read the ground truth despite the bad --cmap")

    monkeypatch.setattr(score, "load_ground_truth", never)
    refused(capsys, _eval(tiny_scene, tmp_path, "--cmap", "nosuchcmap",
                          "--error-maps", str(tmp_path / "maps")),
            "--cmap nosuchcmap", "not a matplotlib colormap", alone=True)
    assert not (tmp_path / "maps").exists()


def test_an_unwritable_checkpoints_folder_is_named_before_training(scene96, train_cli,
                                                                   tmp_path, capsys):
    """RUN/checkpoints cannot be made (a file is in the way; as root, permissions would not
    stop the write): exit 2 naming it, before the hull or any step."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "checkpoints").write_text("in the way")
    refused(capsys, train_cli(scene96, run, "train.iters=2"), f"{run / 'checkpoints'}",
            "cannot write there")
    assert sorted(p.name for p in run.iterdir()) == ["checkpoints"]


@pytest.mark.parametrize("argv", [
    ["train", "SCENE", "--out", "{f}/run"],
    ["mesh", "RUN", "--resolution", "24", "--out", "{f}/m.ply"],
    ["eval", "SCENE/gt_mesh.ply", "--scene", "SCENE", "--json", "{f}/r.json"],
    ["eval", "SCENE/gt_mesh.ply", "--scene", "SCENE", "--error-maps", "{f}/maps"],
], ids=["train --out", "mesh --out", "eval --json", "eval --error-maps"])
def test_an_output_under_a_file_is_named_before_any_work(scene96, trained96, tmp_path,
                                                         capsys, argv):
    """An output path whose parent is a file: exit 2 naming that file."""
    f = tmp_path / "afile"
    f.write_text("keep me\n")
    args = [a.format(f=f).replace("SCENE", str(scene96)).replace("RUN", str(trained96))
            for a in argv]
    refused(capsys, args, str(f))
    assert f.read_text() == "keep me\n"


def test_a_full_disk_is_refused_before_training(scene96, train_cli, tmp_path, capsys,
                                                monkeypatch):
    """1 MB free: exit 2 naming the run folder and the room the checkpoints need."""
    import neus_l0.train.preflight as preflight

    monkeypatch.setattr(preflight.shutil, "disk_usage",
                        lambda _p: shutil._ntuple_diskusage(2**40, 2**40 - 2**20, 2**20))
    run = tmp_path / "run"
    refused(capsys, train_cli(scene96, run, "train.iters=2"), str(run), "1 MB free",
            "the checkpoints need")
    assert checkpoints(run) == []


def test_a_disk_that_fills_during_training_is_one_line(scene96, train_cli, tmp_path, capsys,
                                                       monkeypatch):
    """torch's "unexpected pos" at the second checkpoint: exit 2 naming the file; the first
    checkpoint stays and no temporary file is left."""
    real, calls = torch.save, []

    def full_disk(obj, f, *a, **kw):
        calls.append(f)
        if len(calls) >= 3:  # the hull, ckpt 2, then ckpt 4
            raise RuntimeError("[enforce fail at inline_container.cc:778] . unexpected pos "
                               "1234 vs 1180")
        return real(obj, f, *a, **kw)

    monkeypatch.setattr(torch, "save", full_disk)
    run = tmp_path / "run"
    refused(capsys, train_cli(scene96, run, "train.iters=6", "train.save_every=2"),
            f"{run / 'checkpoints' / 'ckpt_0000004.pt'}: cannot write", "is the disk full")
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["ckpt_0000002.pt"]


# ==========================================================================================
# Table: quietly wrong numbers (the config's: see the parametrised test above; eval's here)


@pytest.mark.parametrize("density", ["inf", "0", "-0.5", "nan"])
def test_eval_density_not_positive_finite(tiny_scene, tmp_path, capsys, density):
    refused(capsys, _eval(tiny_scene, tmp_path, "--density", density),
            "--density", "positive finite", alone=True)
    assert not (tmp_path / "r.json").exists()


def test_eval_density_too_fine_is_refused_before_sampling(tiny_scene, tmp_path, capsys,
                                                          monkeypatch):
    import neus_l0.mesh.memory as memory

    budget = 4 * 2**30
    monkeypatch.setattr(memory, "available_memory", lambda: budget)

    def never(*_a, **_k):
        raise AssertionError("sampled despite the refusal")

    monkeypatch.setattr(score, "sample_mesh", never)
    err = refused(capsys, _eval(tiny_scene, tmp_path, "--density", "0.001"),
                  "--density 0.001", "points", "4 GiB is available",
                  "smallest density that fits is about", alone=True)
    smallest = float(err.rsplit("about ", 1)[1])
    # the density named fits the same budget, and a slightly finer one does not
    gt = trimesh.load(tiny_scene / "gt_mesh.ply", process=False)
    v, f = np.asarray(gt.vertices), np.asarray(gt.faces)
    score.check_sampling(v, f, smallest, budget)
    with pytest.raises(NeusL0Error):
        score.check_sampling(v, f, 0.9 * smallest, budget)


@pytest.mark.parametrize("flag, value", [
    ("--depth-tol", "-100"), ("--depth-tol", "nan"), ("--max-dist", "inf"),
    ("--max-dist", "0"), ("--vmax", "0"), ("--vmax", "inf"), ("--margin-low", "-1"),
    ("--margin-high", "inf"), ("--cull-dilate", "-1"), ("--seed", "-1"),
])
def test_eval_numeric_flags_out_of_range(tiny_scene, tmp_path, capsys, flag, value):
    refused(capsys, _eval(tiny_scene, tmp_path, flag, value), f"{flag} {value}", alone=True)
    assert not (tmp_path / "r.json").exists()


def _strict(text: str):
    def refuse(name):
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


def test_eval_json_is_strict_json(tiny_scene, tmp_path, capsys):
    """A mesh far outside the evaluation box scores no point: accuracy is null, not NaN."""
    far = trimesh.creation.icosphere(subdivisions=1, radius=5.0)
    far.apply_translation([1e5, 0, 0])
    path = tmp_path / "far.ply"
    far.export(path)
    rc = main(["eval", str(path), "--scene", str(tiny_scene), "--density", "2"])
    out = capsys.readouterr().out
    assert rc == 0
    written = (tmp_path / "far.ply.eval.json").read_text()
    report = _strict(written)
    assert _strict(out.strip().splitlines()[-1]) == report
    assert report["accuracy"] is None and report["overall"] is None
    assert report["counts"]["pred_kept"] == 0
    assert score.finite_json({"a": [math.inf, np.float32(math.nan), 1.5], "b": np.int64(3)}) \
        == {"a": [None, None, 1.5], "b": 3}


def test_eval_huge_cull_dilate_is_the_same_disk_fast():
    """--cull-dilate past LARGE_DILATE uses a distance transform: the same disk."""
    from neus_l0.evaluation.cull import LARGE_DILATE

    m = np.zeros((201, 221), bool)
    m[100, 110] = m[10, 5] = True
    r = LARGE_DILATE + 11
    yy, xx = np.mgrid[:2 * r + 1, :2 * r + 1] - r
    disk = (xx**2 + yy**2 <= r**2).astype(np.uint8)
    expected = cv2.dilate(m.astype(np.uint8), disk).astype(bool)
    assert np.array_equal(dilate_mask(m, r), expected)
    assert dilate_mask(m, 10**9).all()  # wider than the image: everything, at once
    assert not dilate_mask(np.zeros((5, 5), bool), 10**9).any()


# ==========================================================================================
# Table: bench (a failed run fails the bench; a busy --out is refused; its numbers are
# checked before any work)


def test_bench_exits_non_zero_naming_the_failed_run(tiny_scene, tmp_path, capsys):
    broken = tmp_path / "broken"
    shutil.copytree(tiny_scene, broken)
    (broken / "cameras_sphere.npz").unlink()  # the run's process fails to open the scene
    out = tmp_path / "sweep"
    assert main(_bench_args(broken, out, samplers="hvs", seconds="5")) == 1
    line = one_line(capsys.readouterr().err)
    assert "1 of 1 runs failed: broken__hvs__5s__seed0" in line
    assert f"its log: {out / 'runs' / 'broken__hvs__5s__seed0' / 'log.txt'}" in line
    assert (out / "runs" / "broken__hvs__5s__seed0" / "log.txt").is_file()
    assert not (out / ".lock").exists()


def test_bench_shows_progress_over_its_runs(tiny_scene, tmp_path, capsys):
    """(bench printed nothing for minutes.) Without --quiet a bar counts the runs."""
    broken = tmp_path / "broken"
    shutil.copytree(tiny_scene, broken)
    (broken / "cameras_sphere.npz").unlink()  # a run that ends at once
    args = [a for a in _bench_args(broken, tmp_path / "sweep", "hvs", "5") if a != "--quiet"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "1/1" in err and "last broken__hvs__5s__seed0: failed" in err


def test_bench_refuses_a_busy_out(tiny_scene, tmp_path, capsys):
    from neus_l0.run.lock import RunLock

    out = tmp_path / "sweep"
    with RunLock(out):  # as another bench holds it
        refused(capsys, _bench_args(tiny_scene, out),
                f"{out.resolve()}: in use by PID {os.getpid()}", alone=True)
    assert not (out / "runs").exists() and not (out / "sweep.json").exists()


@pytest.mark.parametrize("flags, named", [
    (["--seconds", "0"], "--seconds 0"),
    (["--seconds", "-3"], "--seconds -3"),
    (["--seconds", "inf"], "--seconds inf"),
    (["--seconds", "60,nan"], "--seconds nan"),
    (["--seeds", "-1"], "--seeds -1"),
    (["--resolution", "0"], "--resolution 0"),
    (["--resolution", "100000"], "--resolution 100000"),
    (["--threads", "-1"], "--threads -1"),
    (["--views", "0"], "--views 0"),
    (["--width", "4"], "--width 4"),
    (["--height", "0"], "--height 0"),
    (["--holdout", "1"], "--holdout 1"),
    (["--holdout", "-2"], "--holdout -2"),
    (["--holdout", "4", "--views", "1"], "--holdout 4"),
    (["--eval-density", "0"], "--eval-density 0"),
    (["--eval-density", "inf"], "--eval-density inf"),
    (["--sample-rays", "0"], "--sample-rays 0"),
    (["--psnr-pixels", "0"], "--psnr-pixels 0"),
    (["--timeout", "0"], "--timeout 0"),
    (["--timeout", "nan"], "--timeout nan"),
])
def test_bench_checks_its_numbers_before_any_work(tmp_path, capsys, flags, named):
    out = tmp_path / "sweep"
    base = {"--seconds": "60", "--scenes": "demo"}
    for flag in flags[::2]:
        base.pop(flag, None)
    args = ["bench", "--out", str(out), *[x for kv in base.items() for x in kv], *flags]
    refused(capsys, args, named, alone=True)
    assert not out.exists()


# ==========================================================================================
# Table: odd files


def test_macos_resource_forks_are_not_views(scene_copy, capsys):
    """A ``._000.png`` beside the images: skipped, still 8 views."""
    (scene_copy / "image" / "._000.png").write_bytes(b"\x00\x05\x16\x07 not a png")
    (scene_copy / "mask" / "._000.png").write_bytes(b"\x00\x05\x16\x07 not a png")
    assert main(["inspect", str(scene_copy)]) == 0
    captured = capsys.readouterr()
    assert "views        8" in captured.out and "Traceback" not in captured.err


def test_a_one_view_scene_trains_with_a_warning(scene_copy, train_cli, tmp_path, capsys):
    """One view left: it trains, and one line says NeuS needs many views."""
    for folder in ("image", "mask"):
        for p in sorted((scene_copy / folder).glob("*.png"))[1:]:
            p.unlink()
    assert main(train_cli(scene_copy, tmp_path / "run", "train.iters=2")) == 0
    err = capsys.readouterr().err
    assert len([ln for ln in err.splitlines() if "one view only" in ln]) == 1


def test_a_huge_scale_mat_is_named_not_a_traceback(scene_copy, train_cli, tmp_path, capsys):
    """scale_mat x1e30 (was a cv2 traceback): inspect warns; train refuses, naming the
    cameras inside the sphere (not advising a larger sphere)."""
    scale_spheres(scene_copy, 1e30, slice(0, 4))
    assert main(["inspect", str(scene_copy)]) == 0
    assert "cameras inside the unit sphere" in capsys.readouterr().out
    line = refused(capsys, train_cli(scene_copy, tmp_path / "run", "train.iters=2"),
                   str(scene_copy), "inside the unit sphere", "scale_mat")
    assert "enlarge" not in line
    assert checkpoints(tmp_path / "run") == []


def _ply(path: Path, vertices, faces) -> Path:
    lines = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}",
             "property float x", "property float y", "property float z",
             f"element face {len(faces)}", "property list uchar int vertex_indices",
             "end_header"]
    lines += [" ".join(str(c) for c in v) for v in vertices]
    lines += ["3 " + " ".join(str(i) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


TETRA = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
TETRA_FACES = [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]


@pytest.mark.parametrize("vertices, faces, why", [
    ([[1, 1, 1]] * 4, TETRA_FACES, "all vertices are the same point"),
    ([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], TETRA_FACES, "zero surface area"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], "lie in one plane"),
    (TETRA, [], "no triangles"),
    ([*TETRA[:3], ["nan", 0, 1]], TETRA_FACES, "NaN or infinite"),
    (TETRA, [[0, 1, 9], *TETRA_FACES[1:]], "do not exist"),
], ids=["one-point", "zero-area", "one-triangle", "no-faces", "nan", "bad-index"])
def test_synth_degenerate_mesh(tmp_path, capsys, vertices, faces, why):
    mesh = _ply(tmp_path / "bad.ply", vertices, faces)
    out = tmp_path / "out"
    refused(capsys, ["synth", str(mesh), str(out), "--views", "2", *SYNTH_SMALL],
            str(mesh), why, alone=True)
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.ply"]


def test_synth_solid_mesh_still_works(tmp_path):
    mesh = _ply(tmp_path / "tetra.ply", TETRA, TETRA_FACES)
    out = synthetic.make_scene(str(mesh), tmp_path / "t", views=2, width=32, height=24,
                               point_spacing=8.0, progress=False)
    assert load_scene(out).n_views == 2


def _one_point_obj(path: Path, point) -> Path:
    """An OBJ tetrahedron whose four vertices are all `point`."""
    x, y, z = (float(c) for c in point)
    path.write_text(f"v {x} {y} {z}\n" * 4 + "f 1 2 3\nf 1 2 4\nf 2 3 4\nf 1 3 4\n")
    return path


def test_an_all_equal_vertex_obj_is_refused_by_synth(tmp_path, capsys):
    """(Was a ZeroDivisionError.) synth: exit 2 naming the file, no scene written."""
    obj = _one_point_obj(tmp_path / "point.obj", (1, 1, 1))
    refused(capsys, ["synth", str(obj), str(tmp_path / "out"), "--views", "2", *SYNTH_SMALL],
            str(obj), "all vertices are the same point", alone=True)
    assert not (tmp_path / "out").exists()


def test_an_all_equal_vertex_obj_scores_as_the_point_it_is(scene96, tmp_path, capsys):
    """(Was a ZeroDivisionError.) eval: its degenerate triangles give their vertices, so the
    mesh scores as one point on the surface: accuracy 0, completeness the mean distance of the
    ground-truth points to it (those within max_dist)."""
    from neus_l0.evaluation.chamfer import truncated_mean
    from neus_l0.evaluation.io import load_points

    gt = trimesh.load(scene96 / "gt_mesh.ply", process=False)
    p = np.asarray(gt.vertices)[0]
    obj = _one_point_obj(tmp_path / "point.obj", p)
    assert main(["eval", str(obj), "--scene", str(scene96), "--json",
                 str(tmp_path / "r.json")]) == 0
    assert "Traceback" not in capsys.readouterr().err
    report = _strict((tmp_path / "r.json").read_text())
    assert report["counts"]["mesh_vertices"] == 4 and report["counts"]["pred_kept"] == 1
    assert report["accuracy"] == pytest.approx(0.0, abs=1e-9)
    points = load_points(scene96 / "gt_points.ply")
    expected = truncated_mean(np.linalg.norm(points - p, axis=1),
                              report["settings"]["max_dist"])
    assert report["completeness"] == pytest.approx(expected, rel=1e-9)


# ==========================================================================================
# "Still to check against today's code": write failures (above), orphan temporaries,
# truncated images, a differing scale_mat, the resumed lr (above), the demo re-run with
# another sampler, the sampler's unsorted or NaN positions, long work that shows nothing


def test_orphan_checkpoint_temporaries_are_removed_at_start(scene96, run_copy, capsys):
    """`.ckpt_*.tmp.pt` (and any writer's temporary) a killed run left: removed, one line."""
    orphans = [run_copy / "checkpoints" / ".ckpt_0000006.pt.k1ll3d.tmp.pt",
               run_copy / ".config.yaml.k1ll3d.tmp.yaml"]
    for p in orphans:
        p.write_bytes(b"cut short")
    assert main(resume_cli(scene96, run_copy, "train.iters=6")) == 0
    assert not any(p.exists() for p in orphans)
    notes = [ln for ln in capsys.readouterr().err.splitlines() if "killed run left" in ln]
    assert len(notes) == 1 and "removed 2 temporary file(s)" in notes[0]
    assert checkpoints(run_copy)[-1] == "ckpt_0000006.pt"


def _as_jpegs(root: Path) -> None:
    for p in sorted((root / "image").glob("*.png")):
        cv2.imwrite(str(p.with_suffix(".jpg")), cv2.imread(str(p)))
        p.unlink()


@pytest.mark.parametrize("kind, name, cut", [
    ("png", "003.png", 12), ("png", "003.png", 400), ("jpg", "005.jpg", None),
], ids=["png-without-IEND", "png-cut", "jpeg-cut"])
def test_a_truncated_image_is_named(scene_copy, train_cli, tmp_path, capfd, kind, name, cut):
    """A PNG or JPEG cut short (OpenCV decodes a JPEG silently): exit 2 naming it, and no
    decoder noise on stderr."""
    if kind == "jpg":
        _as_jpegs(scene_copy)
    p = scene_copy / "image" / name
    data = p.read_bytes()
    p.write_bytes(data[:-cut] if cut else data[: len(data) // 2])
    rc = main(train_cli(scene_copy, tmp_path / "run", "train.iters=2"))
    err = capfd.readouterr().err
    assert rc == 2
    error_line(err, "train", f"{p}: truncated {'PNG' if kind == 'png' else 'JPEG'}")
    assert "libpng" not in err and "Premature end" not in err
    assert checkpoints(tmp_path / "run") == []


def test_a_view_whose_scale_mat_differs_is_named(scene_copy, train_cli, tmp_path, capsys):
    """One view's sphere moved: exit 2 naming the view and the first."""
    s = np.load(scene_copy / "cameras_sphere.npz")["scale_mat_4"].copy()
    s[:3, 3] += 1.0
    edit_cameras(scene_copy, scale_mat_4=s)
    refused(capsys, train_cli(scene_copy, tmp_path / "run"), "cameras_sphere.npz",
            "scale_mat_4 differ from scale_mat_0")


def test_demo_rerun_with_another_sampler_is_refused(scene96, small, train_cli, tmp_path,
                                                    capsys):
    """An --out whose run trained with l0, re-run with sampler=hvs: refused naming the key
    (it resumed the l0 run and labelled it hvs); the run is untouched."""
    out = tmp_path / "demo"
    shutil.copytree(scene96, out / "scene")
    assert main(train_cli(out / "scene", out / "run", "train.iters=2")) == 0
    before = _snapshot(out / "run" / "checkpoints")
    capsys.readouterr()
    refused(capsys, ["demo", "--out", str(out), "--quiet", "--threads", "1", "--resolution",
                     "24", *small, "train.iters=4", "sampler=hvs"],
            "sampler.name", "another --out")
    assert _snapshot(out / "run" / "checkpoints") == before
    assert not (out / "mesh.ply").exists()


def _positions(bad: str) -> torch.Tensor:
    """(3, 4, 9) sorted positions with ray [1, 2] (the 7th of the flattened batch) made bad."""
    t = torch.linspace(0.0, 1.0, 9, dtype=torch.float64).repeat(3, 4, 1)
    t[0, 0, 3:5] = 0.4  # repeated positions are sorted
    if bad == "unsorted":
        t[1, 2] = t[1, 2].flip(-1)
    elif bad != "good":
        t[1, 2, 4] = {"nan": math.nan, "inf": math.inf}[bad]
    return t


def _draw(name: str, t: torch.Tensor, **kw) -> torch.Tensor:
    from neus_l0.sampling import kernels

    w = torch.ones_like(t[..., :-1])
    if name == "sample_l0":
        return kernels.sample_l0(t, torch.ones_like(t), 8, **kw)
    if name == "sample_neus_sections":
        return kernels.sample_neus_sections(t, w, -w, w, 64.0, 8, **kw)
    return getattr(kernels, name)(t, w, 8, **kw)


SAMPLER_FUNCTIONS = ["sample_pdf", "sample_l0", "sample_l0_sections", "sample_neus_sections"]


@pytest.mark.parametrize("name", SAMPLER_FUNCTIONS)
@pytest.mark.parametrize("bad, what", [("unsorted", "1 are not sorted"),
                                       ("nan", "1 hold NaN or inf"),
                                       ("inf", "1 hold NaN or inf")])
def test_the_samplers_refuse_unsorted_or_non_finite_positions(name, bad, what):
    """Unsorted positions gave zeros, NaN ones NaN: a ValueError naming the function, the
    rays and the first bad one (the batch flattened)."""
    with pytest.raises(ValueError) as exc:
        _draw(name, _positions(bad))
    msg = str(exc.value)
    assert msg.startswith(f"{name}: ") and "finite and sorted" in msg
    assert f"of its 12 rays (the batch flattened), {what} (first: ray 6)" in msg


@pytest.mark.parametrize("name", SAMPLER_FUNCTIONS)
def test_the_samplers_draw_inside_sorted_positions(name):
    """Sorted positions, repeats included: finite, sorted samples inside each ray."""
    t = _positions("good")
    out = _draw(name, t)
    assert torch.isfinite(out).all() and (out.diff(dim=-1) >= 0).all()
    assert (out >= t[..., :1]).all() and (out <= t[..., -1:]).all()


@pytest.mark.parametrize("sampler", ["hvs", "l0", "l0-linear", "neus-exact"])
def test_the_training_path_never_checks_positions(sampler, monkeypatch):
    """NeuS's up-sampling passes check=False: no host synchronisation in the step."""
    from neus_l0.sampling import kernels
    from neus_l0.sampling.upsample import build_sampler, up_sample

    def never(*_a, **_k):
        raise AssertionError("the up-sampling checked its positions")

    monkeypatch.setattr(kernels, "check_positions", never)
    g = torch.Generator().manual_seed(0)
    origins = torch.tensor([[0.0, 0.0, -2.0]]).repeat(4, 1)
    dirs = torch.nn.functional.normalize(torch.randn(4, 3, generator=g) * 0.1
                                         + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    z = torch.linspace(1.0, 3.0, 16).repeat(4, 1)
    z_all, _ = up_sample(lambda p: p.norm(dim=-1) - 0.5, origins, dirs, z,
                         build_sampler(sampler), 8, 2)
    assert z_all.shape == (4, 24) and (z_all.diff(dim=-1) >= 0).all()
    with pytest.raises(AssertionError, match="checked"):
        _draw("sample_pdf", _positions("good"))  # the public functions do check


def test_mesh_shows_progress_while_it_evaluates(trained96, tmp_path, capsys, monkeypatch):
    """(mesh at 512 printed nothing for a minute.) The SDF evaluation shows a bar."""
    import neus_l0.mesh.extract as extract

    monkeypatch.setattr(extract, "PROGRESS_DELAY_S", 0.0)
    assert main(["mesh", str(trained96), "--resolution", "24", "--out",
                 str(tmp_path / "m.ply")]) == 0
    assert "SDF grid" in capsys.readouterr().err


def test_eval_long_scoring_shows_progress_bars(tiny_scene, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(score, "PROGRESS_POINTS", 1)
    assert main(_eval(tiny_scene, tmp_path, "--density", "2")) == 0
    err = capsys.readouterr().err
    assert "eval: sampling about" in err and "eval: sample" in err and "eval: thin" in err
    assert main(_eval(tiny_scene, tmp_path, "--density", "2", "--no-progress")) == 0
    err = capsys.readouterr().err
    assert "eval: sampling about" in err and "pt/s" not in err


# ==========================================================================================
# "What to build" 1: views paired by number, never by position (the rule printed by inspect
# and a gap: above)


@pytest.mark.parametrize("case, named", [
    ("duplicate", ["001.png and view_1.png are both view 1"]),
    ("no-number", ["image/front.png: no view number"]),
    ("no-mask", ["mask: no mask for 007.png"]),
    ("no-camera", ["cameras_sphere.npz: missing world_mat_12 (012.png)"]),
])
def test_a_view_that_cannot_pair_is_an_error_naming_the_files(scene_copy, train_cli,
                                                              tmp_path, capsys, case, named):
    image, mask = scene_copy / "image", scene_copy / "mask"
    if case == "duplicate":
        shutil.copy(image / "001.png", image / "view_1.png")
    elif case == "no-number":
        shutil.copy(image / "001.png", image / "front.png")
    elif case == "no-mask":
        (mask / "007.png").unlink()
    else:
        shutil.copy(image / "001.png", image / "012.png")
        shutil.copy(mask / "001.png", mask / "012.png")
    refused(capsys, train_cli(scene_copy, tmp_path / "run"), *named, "views pair by the last")
    assert not (tmp_path / "run").exists()


# ==========================================================================================
# "What to build" 5: every numeric flag of mesh checked before any work (demo's and bench's:
# above)


@pytest.mark.parametrize("flags, named", [
    (["--resolution", "0"], "--resolution 0"),
    (["--resolution", "-5"], "--resolution -5"),
    (["--resolution", "100000"], "--resolution 100000"),
    (["--simplify", "2"], "--simplify 2"),
    (["--smooth", "-1"], "--smooth -1"),
    (["--min-component", "nan"], "--min-component nan"),
    (["--close-holes", "-1"], "--close-holes -1"),
    (["--texture", "--out", "x.obj", "--texture-size", "0"], "--texture-size 0"),
])
def test_mesh_checks_its_numbers_before_any_work(tmp_path, capsys, flags, named):
    flags = [str(tmp_path / f) if f == "x.obj" else f for f in flags]
    refused(capsys, ["mesh", str(tmp_path / "no-run"), *flags], named, alone=True)


@pytest.mark.parametrize("flags, named", [
    (["--views", "0"], "--views 0"), (["--width", "7"], "--width 7"),
    (["--height", "-3"], "--height -3"), (["--spp", "0"], "--spp 0"),
    (["--seed", "-1"], "--seed -1"),
    (["--width", "100000", "--height", "100000"], "of memory"),
])
def test_synth_numeric_flags(tmp_path, capsys, flags, named):
    out = tmp_path / "out"
    refused(capsys, ["synth", "demo", str(out), "--no-progress", *flags], named, alone=True)
    assert not out.exists()


def test_synth_never_replaces_a_folder_that_is_not_a_scene(tmp_path, capsys):
    own = tmp_path / "mine"
    own.mkdir()
    (own / "notes.txt").write_text("keep me")
    refused(capsys, ["synth", "demo", str(own), "--views", "2", *SYNTH_SMALL],
            str(own), "not a synthetic scene", alone=True)
    scene = _small_scene(tmp_path / "scene", views=2)
    (scene / "run").mkdir()
    refused(capsys, ["synth", "demo", str(scene), "--views", "2", *SYNTH_SMALL],
            "holds run", alone=True)
    assert (own / "notes.txt").read_text() == "keep me" and (scene / "run").is_dir()


# ==========================================================================================
# Issue #18's six faults


def test_18_1_train_out_that_is_a_file_is_one_line(scene96, train_cli, tmp_path, capsys):
    """`train --out afile`: exit 2 naming it (was FileExistsError); the file is kept."""
    afile = tmp_path / "afile"
    afile.write_text("keep me\n")
    refused(capsys, train_cli(scene96, afile), f"--out {afile}", "not a folder", alone=True)
    assert afile.read_text() == "keep me\n"


def test_18_2_mesh_resolution_100000_is_refused_with_the_estimate(trained96, capsys):
    """(Was a 7 TiB allocation.) Exit 2 with the estimate and the largest that fits."""
    line = refused(capsys, ["mesh", str(trained96), "--resolution", "100000"],
                   "--resolution 100000", "largest resolution that fits", alone=True)
    assert "TiB" in line or "PiB" in line
    assert not (trained96 / "mesh.ply").exists()


def test_18_3_a_corrupt_newest_checkpoint_falls_back(scene96, run_copy, tmp_path, capsys):
    """ckpt 4 truncated: mesh uses ckpt 2 and says so in one line, keeping the damaged file
    as .corrupt; a resume continues from ckpt 2."""
    newest = run_copy / "checkpoints" / "ckpt_0000004.pt"
    newest.write_bytes(newest.read_bytes()[:1000])
    mesh = tmp_path / "m.ply"
    assert main(["mesh", str(run_copy), "--resolution", "24", "--out", str(mesh)]) == 0
    captured = capsys.readouterr()
    assert one_line(captured.err).endswith("using ckpt_0000002.pt (iteration 2)")
    assert "iteration 2" in captured.out and mesh.is_file()
    assert checkpoints(run_copy) == ["ckpt_0000002.pt", "ckpt_0000004.pt.corrupt"]
    assert main(resume_cli(scene96, run_copy, "train.iters=4")) == 0
    assert checkpoints(run_copy) == ["ckpt_0000002.pt", "ckpt_0000004.pt",
                                     "ckpt_0000004.pt.corrupt"]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_18_4_a_signal_checkpoints_and_exits_non_zero(scene96, train_cli, tmp_path, capsys,
                                                      sig):
    """SIGTERM / SIGINT during training: the step ends, a checkpoint is written, exit 143 /
    130 with one line; a resume continues from it."""
    run = tmp_path / "run"

    def preempt():  # a scheduler's signal, once training has logged
        deadline = time.monotonic() + 60
        while not (run / "metrics.jsonl").is_file() and time.monotonic() < deadline:
            time.sleep(0.01)
        os.kill(os.getpid(), sig)

    sender = threading.Thread(target=preempt, daemon=True)
    sender.start()
    rc = main(train_cli(scene96, run, "train.iters=100000", "train.max_seconds=60",
                        "train.log_every=2", "train.compile=false"))
    sender.join()
    captured = capsys.readouterr()
    assert rc == 128 + int(sig), captured
    assert "Traceback" not in captured.err
    (line,) = [ln for ln in captured.err.splitlines() if "stopped by" in ln]
    assert f"stopped by {signal.Signals(sig).name} at iteration" in line
    (ckpt,) = checkpoints(run)
    assert ckpt in line
    it = int(ckpt[5:12])
    assert main(resume_cli(scene96, run, f"train.iters={it + 2}")) == 0
    assert checkpoints(run)[-1] == f"ckpt_{it + 2:07d}.pt"


def test_18_5_a_second_training_into_a_locked_folder_is_refused(scene96, train_cli, tmp_path,
                                                                capsys):
    """Two trainings into one folder: the second names the holder's PID; nothing written."""
    from neus_l0.run.lock import RunLock

    run = tmp_path / "run"
    with RunLock(run):
        refused(capsys, train_cli(scene96, run, "train.iters=2"), str(run),
                f"in use by PID {os.getpid()}")
    assert sorted(p.name for p in run.iterdir()) == []


def test_18_6_one_empty_mask_warns_and_all_empty_is_an_error(scene_copy, train_cli, tmp_path,
                                                             capsys):
    """One empty mask: a one-line warning naming it, training goes on; every mask empty:
    exit 2."""
    blank = np.zeros((72, 96, 3), np.uint8)
    cv2.imwrite(str(scene_copy / "mask" / "005.png"), blank)
    assert main(train_cli(scene_copy, tmp_path / "run", "train.iters=2")) == 0
    warned = [ln for ln in capsys.readouterr().err.splitlines() if "masks are empty" in ln]
    assert len(warned) == 1 and "005.png" in warned[0] and "1 of 8" in warned[0]
    for p in (scene_copy / "mask").iterdir():
        cv2.imwrite(str(p), blank)
    refused(capsys, train_cli(scene_copy, tmp_path / "run2", "train.iters=2"),
            "every mask is empty")
    assert checkpoints(tmp_path / "run2") == []
