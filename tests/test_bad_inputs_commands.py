"""Commands fail as a whole (issue #27 item 5): signals stop `demo` and `bench` with 130 / 143
and reach the bench's run process; a failed run fails the bench; a busy bench folder is
refused; every numeric flag of `demo`, `mesh` and `bench` is checked before any work; and no
resolution makes `mesh` dilate the visual hull for minutes."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from neus_l0.cli import main

ROOT = Path(__file__).resolve().parents[1]

#: A tiny network and an iteration count no run reaches: only the signal or the budget ends
#: training.
TINY = ["model.sdf.hidden=32", "model.sdf.layers=2", "model.sdf.skip=[]",
        "model.sdf.feature_dim=16", "model.sdf.encoding.n_freqs=2", "model.color.hidden=32",
        "model.color.layers=1", "render.n_samples=16", "render.n_importance=16",
        "render.up_sample_steps=2", "train.batch_size=64", "train.warm_up=0",
        "train.iters=100000", "train.log_every=4"]
#: The bench's flags that keep a run small.
BENCH_SMALL = ["--resolution", "24", "--eval-density", "3", "--sample-rays", "32",
               "--holdout", "4", "--quiet", "--no-plots"]


def one_line(err: str) -> str:
    """The single non-empty line of `err` (asserting there is exactly one, no traceback)."""
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    return lines[0]


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


# --- demo: a signal stops it after training's checkpoint ------------------------------------


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_demo_stops_after_the_checkpoint_on_a_signal(tiny_scene, small, tmp_path, sig):
    out = tmp_path / "demo"
    shutil.copytree(tiny_scene, out / "scene")  # the demo reuses a scene it finds
    proc = _start(["demo", "--out", str(out), "--quiet", "--threads", "1", *small,
                   "train.iters=100000", "train.max_seconds=120"])
    _wait_for(lambda: (out / "run" / "metrics.jsonl").is_file(), proc)
    proc.send_signal(sig)
    _, err = _finish(proc)
    assert proc.returncode == 128 + int(sig)
    line = one_line(err)
    assert f"stopped by {signal.Signals(sig).name}" in line and "checkpoint" in line
    assert list((out / "run" / "checkpoints").glob("ckpt_*.pt"))
    assert not (out / "mesh.ply").exists() and not (out / "metrics.json").exists()


# --- bench: signals reach the run, which is recorded as interrupted -------------------------


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
        assert main(_bench_args(tiny_scene, out)) == 2
        line = one_line(capsys.readouterr().err)
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


# --- bench: a failed run fails the bench ----------------------------------------------------


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


def test_bench_refuses_a_busy_out(tiny_scene, tmp_path, capsys):
    from neus_l0.run.lock import RunLock

    out = tmp_path / "sweep"
    with RunLock(out):  # as another bench holds it
        assert main(_bench_args(tiny_scene, out)) == 2
    line = one_line(capsys.readouterr().err)
    assert f"{out.resolve()}: in use by PID {os.getpid()}" in line
    assert not (out / "runs").exists() and not (out / "sweep.json").exists()


# --- every numeric flag is checked before any work ------------------------------------------


@pytest.mark.parametrize("flags, named", [
    (["--resolution", "0"], "--resolution 0"),
    (["--resolution", "7"], "--resolution 7"),
    (["--threads", "0"], "--threads 0"),
    (["--threads", "-2"], "--threads -2"),
    (["--resolution", "100000"], "--resolution 100000"),
])
def test_demo_checks_its_numbers_before_any_work(tmp_path, capsys, flags, named):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), *flags]) == 2
    assert named in one_line(capsys.readouterr().err)
    assert not out.exists()


def test_demo_checks_its_config_before_any_work(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "train.iters=0"]) == 2
    assert "train.iters" in one_line(capsys.readouterr().err)
    assert not out.exists()


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
    assert main(["mesh", str(tmp_path / "no-run"), *flags]) == 2
    assert named in one_line(capsys.readouterr().err)


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
    assert main(args) == 2
    assert named in one_line(capsys.readouterr().err)
    assert not out.exists()


# --- mesh: no resolution makes the hull's dilation slow -------------------------------------


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
    from neus_l0.data.scene import load_scene
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
