"""What the tools share (a tool's folder is on ``sys.path`` when it runs as a script, so each
imports this as ``_common``).

`small_demo_scene`: the small built-in scene the step benchmarks share (`count_ops.py`,
`bench_*_step.py`, `bench_sdf_gradient.py`, `bench_gpu_step.py`, `bench_compile_step.py`):
the `demo` scene rendered into a folder and loaded, with coarse ground truth (these tools
never score a mesh).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import torch

from neus_l0.data.scene import Scene
from neus_l0.formats.neus import load_scene
from neus_l0.synthetic.scene import make_scene


def small_demo_scene(folder: str | Path, views: int, width: int, height: int,
                     device: str | torch.device = "cpu") -> Scene:
    """Render the `demo` scene (seed 0) into ``folder/demo`` and load it on `device`."""
    root = make_scene("demo", Path(folder) / "demo", views=views, width=width, height=height,
                      seed=0, gt_voxel=4.0, point_spacing=2.0, progress=False)
    return load_scene(root, device=device)


def add_scene_args(ap: argparse.ArgumentParser, views: int, width: int, height: int) -> None:
    """``--views``, ``--width``, ``--height`` of the synthetic scene, with this tool's
    defaults."""
    ap.add_argument("--views", type=int, default=views, help="views of the synthetic scene")
    ap.add_argument("--width", type=int, default=width, help="image width of the scene")
    ap.add_argument("--height", type=int, default=height, help="image height of the scene")


def device_sync(device: torch.device) -> Callable[[], None]:
    """What waits for `device`'s queued work before a clock is read (nothing on the CPU)."""
    return torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
