"""Checks a run passes before its first step: the folder can be written and holds room for
the checkpoints, and a resumed run continues on the scene it started on.

(The scene's own files are checked as it loads, `neus_l0.data.scene`; the config's numbers
as it is built, `neus_l0.config.checks`; whether the object fits the unit sphere when the
hull is carved, `neus_l0.bounds.static.check_fit`.)
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch

from neus_l0.data.scene import Scene
from neus_l0.errors import NeusL0Error

#: Room left on the disk beyond the checkpoints (metrics, validation images, the hull).
DISK_SLACK = 64 * 2**20


def scene_fingerprint(scene: Scene) -> str:
    """A short hash of what makes a scene this scene: its views' names, image size, cameras
    and sphere (not its pixels: re-encoding an image keeps the fingerprint)."""
    h = hashlib.sha1()
    h.update(json.dumps([scene.image_names, scene.height, scene.width]).encode())
    for t in (scene.intrinsics, scene.c2w):
        h.update(np.round(t.detach().double().cpu().numpy(), 5).tobytes())
    h.update(np.round(np.asarray(scene.scale_mat, np.float64), 6).tobytes())
    return h.hexdigest()[:16]


def check_same_scene(run_dir: Path, scene: Scene) -> None:
    """On resume: the scene must be the one ``RUN/run.json`` recorded.

    Raises:
        NeusL0Error: naming the run's scene and the one given.
    """
    meta_path = run_dir / "run.json"
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return  # a run from before fingerprints (or a damaged record): nothing to hold to
    known = meta.get("scene_fingerprint")
    if known and known != scene_fingerprint(scene):
        raise NeusL0Error(f"{run_dir}: was trained on {meta.get('scene', 'another scene')} "
                          f"({meta.get('n_views', '?')} views), not on {scene.root} "
                          f"({scene.n_views} views): resume with the run's own scene, or "
                          "choose another --out")


def checkpoint_bytes(model: torch.nn.Module, optimizer: torch.optim.Optimizer) -> int:
    """About the size of one checkpoint: the parameters and the optimiser's state."""
    n = sum(p.numel() * p.element_size() for p in model.parameters())
    n += sum(b.numel() * b.element_size() for b in model.buffers())
    return 3 * n + 2**20  # Adam keeps two moments per parameter; plus the pickle's framing


def check_writable(run_dir: Path, need: int) -> None:
    """`run_dir` and its checkpoints folder can be written, with `need` bytes free.

    Raises:
        NeusL0Error: naming the folder and why (permission, a file in the way, no room).
    """
    for folder in (run_dir, run_dir / "checkpoints"):
        try:
            folder.mkdir(parents=True, exist_ok=True)
            with tempfile.NamedTemporaryFile(dir=folder, prefix=".write_check.", delete=True):
                pass
        except OSError as exc:
            raise NeusL0Error(f"{folder}: cannot write there ({exc.strerror or exc}); "
                              "choose another --out") from None
    free = shutil.disk_usage(run_dir).free
    if free < need + DISK_SLACK:
        raise NeusL0Error(f"{run_dir}: {free / 2**20:.0f} MB free on its disk, but the "
                          f"checkpoints need about {(need + DISK_SLACK) / 2**20:.0f} MB; free "
                          "some space, lower train.keep_checkpoints or choose another --out")
