"""Shared fixtures: the demo scene on disk, an in-memory sphere scene, an analytic sphere
model and the small network overrides the training tests run with."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from neus_l0.config.schema import ColorConfig, VarianceConfig
from neus_l0.data.rays import pixel_grid, pixel_rays
from neus_l0.data.scene import Scene
from neus_l0.fields.color import ColorNetwork
from neus_l0.fields.model import NeuSModel
from neus_l0.fields.variance import SingleVariance


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """A small built-in `demo` scene (8 views, 64x48, coarse ground truth): its folder Path.

    Built once per test session (a couple of seconds); treat it as read-only.
    """
    from neus_l0.synthetic.scene import make_scene

    out = tmp_path_factory.mktemp("tiny_scene") / "demo"
    return make_scene("demo", out, views=8, width=64, height=48, seed=0, gt_voxel=4.0,
                      point_spacing=2.0, progress=False)


# ------------------------------------------------------------------------------------------
# Small networks for training tests.

# A tiny frequency-encoded MLP on top of confs/demo.yaml (whose SDF is a hash grid since the
# "Speed" work; the demo tests run the hash grid itself).
SMALL = ("model.sdf.hidden=48", "model.sdf.layers=2", "model.sdf.skip=[]",
         "model.sdf.feature_dim=16", "model.sdf.encoding.kind=frequency",
         "model.sdf.encoding.n_freqs=2",
         "model.color.hidden=32", "model.color.layers=1", "render.n_samples=16",
         "render.n_importance=16", "render.up_sample_steps=2", "train.batch_size=64",
         "train.warm_up=0", "train.lr=2e-3", "train.log_every=5", "train.val_every=0",
         "train.save_every=0")


@pytest.fixture
def small():
    """The small-network overrides (a fresh list per test): ``small + ["train.iters=4"]``."""
    return list(SMALL)


@pytest.fixture(scope="session")
def small_overrides():
    """`small` as a tuple, for fixtures wider than one test (module or session scope)."""
    return SMALL


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
