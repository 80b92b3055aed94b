"""Shared fixtures: the demo scenes on disk (and copies to break), a small trained run, an
in-memory sphere scene, an analytic sphere model, the small network overrides the training
tests run with, the command-line helpers the bad-input tests share, and the data in
``../shared`` (``NEUS_L0_SHARED``)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from neus_l0.cli import main
from neus_l0.config.schema import ColorConfig, VarianceConfig
from neus_l0.data.rays import pixel_grid, pixel_rays
from neus_l0.data.scene import Scene
from neus_l0.fields.color import ColorNetwork
from neus_l0.fields.model import NeuSModel
from neus_l0.fields.variance import SingleVariance


def pytest_configure(config):
    """Under pytest-xdist (`-n auto` in pyproject.toml) every worker is one process on a
    shared machine: give each its share of the cores for torch's in-process work, so that
    two workers on two cores do not run four threads. The commands the tests launch pick
    their own threads from the machine's load (`neus_l0.device.free_cpu_threads`)."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers:  # the cores this process may use, as `neus_l0.device.free_cpu_threads` counts
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        torch.set_num_threads(max(1, (cores or 1) // int(workers)))


@pytest.fixture
def tiny_demo(monkeypatch):
    """`neus-l0 demo` on a scene of 6 views at 40x30 with ground truth as coarse as
    `tiny_scene`'s (its scorings' exact point-to-mesh queries run over 16x fewer points
    than at the demo's spacing): the patched ``neus_l0.pipelines.demo`` module."""
    import neus_l0.pipelines.demo as demo

    monkeypatch.setattr(demo, "DEMO_SCENE", {"views": 6, "width": 40, "height": 30,
                                             "point_spacing": 2.0, "gt_voxel": 4.0})
    return demo


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """A small built-in `demo` scene (8 views, 64x48, coarse ground truth): its folder Path.

    Built once per test session (a couple of seconds); treat it as read-only.
    """
    from neus_l0.synthetic.scene import make_scene

    out = tmp_path_factory.mktemp("tiny_scene") / "demo"
    return make_scene("demo", out, views=8, width=64, height=48, seed=0, gt_voxel=4.0,
                      point_spacing=2.0, progress=False)


@pytest.fixture(scope="session")
def scene96(tmp_path_factory) -> Path:
    """The demo object, 8 views at 96x72 (the unit sphere's fit is judged from 72 pixels up):
    its folder Path. Built once per test session; treat it as read-only."""
    from neus_l0.synthetic.scene import make_scene

    out = tmp_path_factory.mktemp("scene96") / "demo"
    return make_scene("demo", out, views=8, width=96, height=72, seed=0, gt_voxel=4.0,
                      point_spacing=2.0, progress=False)


def _copy_views(scene: Path, root: Path) -> Path:
    """Copy `scene`'s views (image/, mask/, cameras_sphere.npz, scene.json) to `root`."""
    for name in ("image", "mask"):
        shutil.copytree(scene / name, root / name)
    for name in ("cameras_sphere.npz", "scene.json"):
        shutil.copy(scene / name, root)
    return root


@pytest.fixture
def scene_copy(tiny_scene, tmp_path) -> Path:
    """A copy of `tiny_scene`'s views (image/, mask/, cameras_sphere.npz, scene.json) to
    break."""
    return _copy_views(tiny_scene, tmp_path / "scene")


@pytest.fixture
def scene96_copy(scene96, tmp_path) -> Path:
    """A copy of `scene96`'s views, as `scene_copy`, to break."""
    return _copy_views(scene96, tmp_path / "scene")


# ------------------------------------------------------------------------------------------
# Data outside the repository: ../shared (or $NEUS_L0_SHARED), on development machines.

ROOT = Path(__file__).resolve().parent.parent
SHARED = {"bunny": "meshes/bunny.obj", "dtu_scan65": "data/dtu_scan65"}


@pytest.fixture(scope="session")
def shared_data():
    """``shared_data(name) -> Path``: the bunny (``"bunny"``, meshes/bunny.obj) or the DTU
    scan (``"dtu_scan65"``, data/dtu_scan65) in the folder ``$NEUS_L0_SHARED`` names
    (default ``../shared``; relative to the repository's root). A test that asks for one that
    is not there is skipped."""
    folder = ROOT / os.environ.get("NEUS_L0_SHARED", "../shared")

    def find(name: str) -> Path:
        path = (folder / SHARED[name]).resolve()
        if not path.exists():
            pytest.skip(f"{path} is not here (set NEUS_L0_SHARED to the shared data folder)")
        return path

    return find


# ------------------------------------------------------------------------------------------
# Small networks for training tests.

# A tiny frequency-encoded MLP on top of confs/demo.yaml (whose SDF is a hash grid since the
# "Speed" work; the demo tests run the hash grid itself).
SMALL = ("model.sdf.hidden=48", "model.sdf.layers=2", "model.sdf.skip=[]",
         "model.sdf.feature_dim=16", "model.sdf.encoding.kind=frequency",
         "model.sdf.encoding.n_freqs=2",
         "model.color.hidden=32", "model.color.layers=1", "render.n_samples=16",
         "render.n_importance=16", "render.up_sample_steps=2", "train.batch_size=64",
         "train.warm_up=0", "train.lr=2e-3",
         # this toy network loses NeuS's sharpness s early with `demo`'s hit colour (the
         # colour term no longer pulls the opacity up; docs/benchmarks/pits.md, session 18),
         # so a few steps need not lower the loss; tests/train/test_hit_color.py covers it
         "train.hit_color_floor=0",
         "train.log_every=5", "train.val_every=0", "train.save_every=0")  # the last 3: see
                                                                          # small[:-3]


@pytest.fixture
def small():
    """The small-network overrides (a fresh list per test): ``small + ["train.iters=4"]``."""
    return list(SMALL)


@pytest.fixture(scope="session")
def small_overrides():
    """`small` as a tuple, for fixtures wider than one test (module or session scope)."""
    return SMALL


@pytest.fixture
def train_cli(small):
    """``train_cli(scene, run, *extra)``: the argv of a small, quiet training on one thread."""
    def argv(scene: Path, run: Path, *extra: str) -> list[str]:
        return ["train", str(scene), "--conf", "demo", "--out", str(run), "--quiet",
                "--threads", "1", *small, *extra]
    return argv


@pytest.fixture(scope="session")
def resume_cli():
    """``resume_cli(scene, run, *extra)``: the argv of ``train --resume`` (config.yaml is the
    base; `extra` overrides)."""
    def argv(scene: Path, run: Path, *extra: str) -> list[str]:
        return ["train", str(scene), "--out", str(run), "--resume", "--quiet", "--threads",
                "1", *extra]
    return argv


def _checkpoint_names(run: Path) -> list[str]:
    folder = run / "checkpoints"
    return sorted(p.name for p in folder.glob("ckpt_*")) if folder.is_dir() else []


@pytest.fixture(scope="session")
def checkpoint_names():
    """``checkpoint_names(run) -> list[str]``: the names of the run's checkpoint files (none
    when it has no checkpoints folder)."""
    return _checkpoint_names


@pytest.fixture(scope="session")
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
    assert _checkpoint_names(run) == ["ckpt_0000002.pt", "ckpt_0000004.pt"]
    return run


@pytest.fixture(scope="session")
def tiny_trained(tiny_scene, small_overrides, tmp_path_factory) -> Path:
    """A run of 4 iterations on `tiny_scene` (checkpoints at 2 and 4), trained by the CLI
    (read-only: tests copy it)."""
    run = tmp_path_factory.mktemp("tiny_trained") / "run"
    assert main(["train", str(tiny_scene), "--conf", "demo", "--out", str(run), "--quiet",
                 "--threads", "1", *small_overrides, "train.iters=4",
                 "train.save_every=2"]) == 0
    return run


@pytest.fixture
def run_copy(trained96, tmp_path) -> Path:
    """A copy of `trained96` to resume, damage or mesh."""
    return Path(shutil.copytree(trained96, tmp_path / "run"))


# ------------------------------------------------------------------------------------------
# What a command says when it refuses: one line, no traceback.


def _error_line(err: str, command: str, *named: str, alone: bool = False) -> str:
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith(f"neus-l0 {command}: error: ")]
    assert len(lines) == 1, err
    if alone:
        assert [ln for ln in err.splitlines() if ln.strip()] == lines, err
    for needle in named:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


@pytest.fixture(scope="session")
def error_line():
    """``error_line(err, command, *named, alone=False) -> str``: the one ``neus-l0 COMMAND:
    error:`` line of stderr `err`, naming every `named`; no traceback. `alone`: it is all of
    stderr (no notes before it)."""
    return _error_line


@pytest.fixture
def refused(capsys):
    """``refused(argv, *named, code=2, alone=False) -> str``: run the CLI in-process; assert
    exit `code` and one error line naming `named` (`error_line`); that line."""
    def run(argv: list[str], *named: str, code: int = 2, alone: bool = False) -> str:
        rc = main(argv)
        err = capsys.readouterr().err
        assert rc == code, err
        return _error_line(err, argv[0], *named, alone=alone)
    return run


def _one_line(err: str) -> str:
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture(scope="session")
def one_line():
    """``one_line(err) -> str``: the single non-empty line of `err` (asserting there is
    exactly one, no traceback)."""
    return _one_line


class CliProcess:
    """``python -m neus_l0 ARGS`` in a subprocess, for tests whose signal must reach a whole
    process."""

    @staticmethod
    def start(args: list[str]) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "neus_l0", *args], cwd=ROOT,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    @staticmethod
    def wait_for(paths, proc: subprocess.Popen, seconds: float = 60.0) -> None:
        """Wait until `paths()` finds a file (training has logged), failing if `proc` ends
        first."""
        deadline = time.monotonic() + seconds
        while not paths():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "training did not start"
            time.sleep(0.05)

    @staticmethod
    def finish(proc: subprocess.Popen, seconds: float = 60.0) -> tuple[str, str]:
        try:
            return proc.communicate(timeout=seconds)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()

    @staticmethod
    def gone(pid: int) -> bool:
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


@pytest.fixture(scope="session")
def cli_process():
    """`CliProcess`: start, wait_for, finish and gone for ``python -m neus_l0`` subprocesses."""
    return CliProcess


@pytest.fixture(scope="session")
def snapshot():
    """``snapshot(folder) -> {relative path: bytes}`` of every file under `folder`."""
    def files(folder: Path) -> dict[str, bytes]:
        return {str(p.relative_to(folder)): p.read_bytes()
                for p in sorted(folder.rglob("*")) if p.is_file()}
    return files


@pytest.fixture(scope="session")
def one_point_obj():
    """``one_point_obj(path, point) -> path``: an OBJ tetrahedron whose four vertices are all
    `point`."""
    def write(path: Path, point) -> Path:
        x, y, z = (float(c) for c in point)
        path.write_text(f"v {x} {y} {z}\n" * 4 + "f 1 2 3\nf 1 2 4\nf 2 3 4\nf 1 3 4\n")
        return path
    return write


# ------------------------------------------------------------------------------------------
# An in-memory sphere scene.


def _look_at(eye):
    f = -eye / np.linalg.norm(eye)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = r, np.cross(f, r), f, eye
    return c2w


def _sphere_scene(root, n_views=6, H=16, W=20, radius=0.5):
    """A Scene built in memory: a sphere coloured by its normal, black background, masks."""
    K = torch.tensor([[W * 1.2, 0, (W - 1) / 2], [0, W * 1.2, (H - 1) / 2], [0, 0, 1.0]])
    imgs, masks, c2ws = [], [], []
    for i in range(n_views):
        a, el = 2 * np.pi * i / n_views, 0.3 + 0.3 * (i % 2)
        eye = 2.5 * np.array([np.cos(a) * np.cos(el), np.sin(a) * np.cos(el), np.sin(el)])
        c2w = torch.tensor(_look_at(eye), dtype=torch.float32)
        o, d = pixel_rays(K, c2w, pixel_grid(H, W).reshape(-1, 2))
        b = (o * d).sum(-1)
        disc = b * b - ((o * o).sum(-1) - radius**2)
        hit = disc > 0
        n = (o + (-b - disc.clamp_min(0).sqrt())[:, None] * d) / radius
        imgs.append(((0.5 + 0.4 * n) * hit[:, None]).reshape(H, W, 3))
        masks.append(hit.float().reshape(H, W))
        c2ws.append(c2w)
    scale = np.diag([2.0, 2.0, 2.0, 1.0])
    scale[:3, 3] = [1.0, -2.0, 0.5]
    return Scene(root=Path(root), images=torch.stack(imgs), masks=torch.stack(masks),
                 has_masks=True, intrinsics=K.expand(n_views, 3, 3).clone(),
                 c2w=torch.stack(c2ws), scale_mat=scale,
                 image_names=[f"{i:03d}.png" for i in range(n_views)])


@pytest.fixture(scope="session")
def sphere_scene():
    """The builder ``sphere_scene(root, n_views=6, H=16, W=20, radius=0.5) -> Scene``: a
    sphere coloured by its normal, black background, masks; built in memory."""
    return _sphere_scene


# ------------------------------------------------------------------------------------------
# An analytic sphere model.

RADIUS = 0.5


class AnalyticSphere(nn.Module):
    """SDF network stand-in: |x - c| - r with a zero feature vector."""

    feature_dim = 8

    def __init__(self, radius=RADIUS, centre=(0.0, 0.0, 0.0)):
        super().__init__()
        self.radius = radius
        self.register_buffer("centre", torch.tensor(centre))
        self.dummy = nn.Parameter(torch.zeros(()))

    def forward(self, x):
        d = (x - self.centre).norm(dim=-1, keepdim=True) - self.radius + 0.0 * self.dummy
        return torch.cat([d, torch.zeros(x.shape[0], self.feature_dim, device=x.device)], -1)

    def sdf(self, x):
        return self.forward(x)[:, :1]


def _sphere_model(s_init=0.6):
    return NeuSModel(AnalyticSphere(), ColorNetwork(ColorConfig(hidden=16, layers=2), 8),
                     SingleVariance(VarianceConfig(init=s_init)))


@pytest.fixture(scope="session")
def analytic_sphere():
    """The class `AnalyticSphere(radius=0.5, centre=(0, 0, 0))`: an SDF network stand-in,
    |x - c| - r with a zero feature vector of 8 (to subclass or build directly)."""
    return AnalyticSphere


@pytest.fixture(scope="session")
def sphere_model():
    """The factory ``sphere_model(s_init=0.6) -> NeuSModel``: an `AnalyticSphere` of radius
    0.5 at the origin, a small colour network and a single variance."""
    return _sphere_model


@pytest.fixture(autouse=True, scope="session")
def _own_cache_folder(tmp_path_factory):
    """The tests keep their own cache folder: the user's compile record (which
    `train.compile: auto` reads) and inductor cache are neither read nor written."""
    patch = pytest.MonkeyPatch()
    patch.setenv("XDG_CACHE_HOME", str(tmp_path_factory.mktemp("xdg_cache")))
    yield
    patch.undo()
