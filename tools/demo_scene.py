"""The small built-in scene the step benchmarks share (`count_ops.py`, `bench_*_step.py`,
`bench_sdf_gradient.py`, `bench_gpu_step.py`): the `demo` scene rendered into a folder and
loaded, with coarse ground truth (these tools never score a mesh)."""

from __future__ import annotations

from pathlib import Path

import torch

from neus_l0.data.scene import Scene, load_scene
from neus_l0.data.synthetic import make_scene


def small_demo_scene(folder: str | Path, views: int, width: int, height: int,
                     device: str | torch.device = "cpu") -> Scene:
    """Render the `demo` scene (seed 0) into ``folder/demo`` and load it on `device`."""
    root = make_scene("demo", Path(folder) / "demo", views=views, width=width, height=height,
                      seed=0, gt_voxel=4.0, point_spacing=2.0, progress=False)
    return load_scene(root, device=device)
