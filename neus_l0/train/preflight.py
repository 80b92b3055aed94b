"""Checks a run passes before its first step: the folder can be written and holds room for
the checkpoints, a resumed run continues on the scene it started on, and one training step
fits in memory.

The step's memory (`step_bytes`): every sample of every ray keeps its activations for the
backward pass (and the SDF's gradient, which the eikonal loss differentiates again), so the
peak grows as rays x samples x network width: ``BYTES_PER_ACTIVATION`` x rays x (surface
samples x the SDF and colour networks' width + outside samples x the background's) plus
``BYTES_PER_SAMPLE`` x rays x samples (what every sample costs besides the networks), where a
width is the sum of a network's layer outputs and its input encoding (per sample, floats).

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
#: Peak bytes of a training step per ray, sample and float of network width (fitted to the
#: peak memory of eager CPU steps; docs/BENCHMARKS.md)...
BYTES_PER_ACTIVATION = 12
#: ...plus these per ray and sample, whatever the networks (the sampler, the compositing,
#: the losses).
BYTES_PER_SAMPLE = 3500
#: The memory a step may take of what is available (the rest: the scene, the model, the
#: optimiser, the allocator's slack).
STEP_SHARE = 0.8


def scene_fingerprint(scene: Scene) -> str:
    """A short hash of what makes a scene this scene: its views' names, image size, cameras
    and sphere (not its pixels: re-encoding an image keeps the fingerprint)."""
    h = hashlib.sha1()
    h.update(json.dumps([scene.image_names, scene.height, scene.width]).encode())
    for t in (scene.intrinsics, scene.c2w):
        h.update(np.round(t.detach().double().cpu().numpy(), 5).tobytes())
    h.update(np.round(np.asarray(scene.scale_mat, np.float64), 6).tobytes())
    return h.hexdigest()[:16]


def check_same_scene(run_dir: Path, scene: Scene, checkpoint: dict | None = None) -> str:
    """On resume: the scene must be the one the run recorded.

    The record is ``RUN/run.json``'s ``scene_fingerprint``; where that file is missing or
    unreadable, the resumed checkpoint's own ``scene_fingerprint``. A run from before
    fingerprints (a run.json without one) is not held to any. With no record at all the
    scene cannot be checked, and the resume is refused rather than continued on what may be
    another scene.

    Args:
        run_dir: the run folder; scene: the scene given; checkpoint: the checkpoint resumed.

    Returns:
        the given scene's fingerprint.

    Raises:
        NeusL0Error: another scene (naming the run's and the one given), or no record.
    """
    mine = scene_fingerprint(scene)
    meta_path = run_dir / "run.json"
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
        meta = meta if isinstance(meta, dict) else None
    except (OSError, ValueError):
        meta = None
    if meta is None:
        known = (checkpoint or {}).get("scene_fingerprint")
        if not known:
            raise NeusL0Error(f"{meta_path}: missing or unreadable, and the checkpoint records "
                              "no scene either, so the scene this run trained on cannot be "
                              "checked; restore run.json, or train into another --out")
        meta = {"scene_fingerprint": known}
    known = meta.get("scene_fingerprint")
    if known and known != mine:
        raise NeusL0Error(f"{run_dir}: was trained on {meta.get('scene', 'another scene')} "
                          f"({meta.get('n_views', '?')} views), not on {scene.root} "
                          f"({scene.n_views} views): resume with the run's own scene, or "
                          "choose another --out")
    return mine


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


def network_width(net: torch.nn.Module | None) -> int:
    """Floats a network keeps per input point: its layers' outputs and its encodings'."""
    if net is None:
        return 0
    width = sum(m.out_features for m in net.modules() if isinstance(m, torch.nn.Linear))
    return width + sum(int(getattr(m, "out_dim", 0)) for m in net.modules()
                       if m is not net and hasattr(m, "raw_dims"))


def step_bytes(model: torch.nn.Module, cfg, rays: int) -> int:
    """About the peak memory of one training step of `rays` rays (module docstring)."""
    r = cfg.render
    surface = r.n_samples + (r.n_importance if r.up_sample_steps else 0)
    floats = (surface * (network_width(model.sdf) + network_width(model.color))
              + r.n_outside * network_width(getattr(model, "background", None)))
    per_ray = BYTES_PER_ACTIVATION * floats + BYTES_PER_SAMPLE * (surface + r.n_outside)
    return int(rays * per_ray)


def max_rays(cfg) -> int:
    """The most rays a step draws: `train.batch_size`, or 8x that under a sample budget."""
    t = cfg.train
    return 8 * t.batch_size if t.sample_budget else t.batch_size


def device_memory(device: torch.device) -> int | None:
    """Bytes available for a step on `device`: free GPU memory, or the host's (None: not
    known)."""
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return int(free)
    from neus_l0.device import available_memory

    return available_memory()


def check_step_memory(model: torch.nn.Module, cfg, available: int | None) -> None:
    """One training step must fit in `STEP_SHARE` of `available` bytes (None: no check).

    Raises:
        NeusL0Error: naming the estimate, the memory available and the largest batch that
            fits (or, when not even one ray does, the samples to lower).
    """
    rays = max_rays(cfg)
    need = step_bytes(model, cfg, rays)
    if available is None or need <= STEP_SHARE * available:
        return
    per_ray = max(step_bytes(model, cfg, 1), 1)
    fit = int(STEP_SHARE * available // per_ray) // (8 if cfg.train.sample_budget else 1)
    r = cfg.render
    samples = r.n_samples + (r.n_importance if r.up_sample_steps else 0) + r.n_outside
    how = (f"the largest batch that fits is about train.batch_size={fit}" if fit >= 1 else
           f"not even one ray fits: lower render.n_samples ({r.n_samples}), "
           f"render.n_importance ({r.n_importance}) or render.n_outside ({r.n_outside})")
    budget = ", x8 under train.sample_budget" if cfg.train.sample_budget else ""
    raise NeusL0Error(f"train.batch_size={cfg.train.batch_size}: one training step of "
                      f"{rays} rays{budget} x {samples} samples (render.n_samples + "
                      f"n_importance + n_outside) needs about {need / 2**30:.3g} GiB, "
                      f"{available / 2**30:.3g} GiB is available; {how}")
