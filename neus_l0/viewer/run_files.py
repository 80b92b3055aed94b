"""What the viewer shows of a run folder, read from it: curves, validation images, the
checkpoints, the training cameras and the mesh of a checkpoint. No server here.

Everything the page shows comes from the run folder (``metrics.jsonl``, ``validation/``,
``checkpoints/``, ``hull.pt``, ``run.json``) and the scene ``run.json`` names (the training
cameras and their images). Poses are shown in world units, as the meshes are.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path

import cv2
import numpy as np

from neus_l0.data.image_io import imread_bytes
from neus_l0.errors import NeusL0Error
from neus_l0.run.checkpoints import checkpoint_iteration, list_checkpoints
from neus_l0.run.metrics import read_lines
from neus_l0.train.losses import LOSS_NAMES

#: Curves of the page: title -> the metrics keys drawn in it.
CURVES: dict[str, tuple[str, ...]] = {
    "loss": tuple(n for n in LOSS_NAMES if n.endswith("loss")),  # named once, in train/
    "PSNR (dB)": ("psnr",),
    "validation PSNR (dB)": ("val_psnr", "val_psnr_mask"),
    "sharpness inv_s": ("inv_s",),
    "learning rate": ("lr",),
}

_VALIDATION = re.compile(r"^(\d+)_v(\d+)\.png$")


@dataclasses.dataclass
class Camera:
    """One training camera as the page draws it.

    Attributes:
        index: the scene's view index; name: its image file.
        fov: vertical field of view (radians); aspect: width / height.
        wxyz: (4,) rotation camera -> world (OpenCV axes); position: (3,) world units.
        image: (h, w, 3) uint8 RGB thumbnail.
    """

    index: int
    name: str
    fov: float
    aspect: float
    wxyz: np.ndarray
    position: np.ndarray
    image: np.ndarray


def curves(run_dir: str | Path) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """The page's curves from ``metrics.jsonl``.

    Returns:
        title -> {key: (iterations (n,), values (n,))} for the keys of `CURVES` that the
        run logged (float64; empty dict entries are left out).
    """
    lines = list(read_lines(run_dir))
    out: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    for title, keys in CURVES.items():
        for key in keys:
            pts = [(m["iter"], m[key]) for m in lines
                   if "iter" in m and isinstance(m.get(key), (int, float))]
            if pts:
                it, val = np.asarray(pts, np.float64).T
                out.setdefault(title, {})[key] = (it, val)
    return out


def last_psnr(run_dir: str | Path) -> tuple[int, float, str] | None:
    """(iteration, PSNR, key) of the newest PSNR the run logged (at one iteration the
    validation PSNR inside the masks before the whole validation image's, before the training
    batch's), or None."""
    best = None
    for m in read_lines(run_dir):
        for key in ("psnr", "val_psnr", "val_psnr_mask"):
            if "iter" in m and isinstance(m.get(key), (int, float)):
                if best is None or m["iter"] >= best[0]:
                    best = (int(m["iter"]), float(m[key]), key)
    return best


def _within(run_dir: str | Path, path: Path) -> bool:
    """Whether `path` stays inside `run_dir` once links are followed."""
    home = Path(os.path.realpath(run_dir))
    return home in Path(os.path.realpath(path)).parents


def validation_images(run_dir: str | Path) -> list[tuple[int, int, Path]]:
    """(iteration, view, path) of every ``validation/NNNNNNN_vVVV.png``, by iteration; a
    link that leads out of the run folder is left out (the page shows nothing from outside
    the run through a link planted in it)."""
    folder = Path(run_dir) / "validation"
    found = []
    for p in folder.glob("*.png") if folder.is_dir() else ():
        m = _VALIDATION.match(p.name)
        if m and _within(run_dir, p):
            found.append((int(m.group(1)), int(m.group(2)), p))
    return sorted(found)


def read_rgb(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a PNG.

    Raises:
        NeusL0Error: it does not read.
    """
    bgr = imread_bytes(Path(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise NeusL0Error(f"{path}: not a readable image")
    return np.ascontiguousarray(bgr[..., ::-1])


def checkpoints(run_dir: str | Path) -> list[tuple[int, Path]]:
    """(iteration, path) of the run's checkpoints (snapshots included), oldest first."""
    return [(checkpoint_iteration(p), p) for p in list_checkpoints(run_dir)]


def run_meta(run_dir: str | Path) -> dict:
    """``RUN/run.json`` (empty when missing or unreadable)."""
    path = Path(run_dir) / "run.json"
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def _wxyz(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) unit quaternion (w, x, y, z)."""
    w = np.sqrt(max(1e-12, 1.0 + R[0, 0] + R[1, 1] + R[2, 2])) / 2.0
    if w > 1e-3:
        q = np.array([w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w),
                      (R[1, 0] - R[0, 1]) / (4 * w)])
    else:  # a half turn: take the largest diagonal
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        v = np.zeros(3)
        v[i] = np.sqrt(max(1e-12, 1.0 + R[i, i] - R[j, j] - R[k, k])) / 2.0
        v[j] = (R[j, i] + R[i, j]) / (4 * v[i])
        v[k] = (R[k, i] + R[i, k]) / (4 * v[i])
        q = np.array([(R[k, j] - R[j, k]) / (4 * v[i]), *v])
    return q / np.linalg.norm(q)


def training_cameras(run_dir: str | Path, thumb: int = 160) -> list[Camera]:
    """The cameras of the scene the run trained on (``run.json``'s ``scene``), with
    thumbnails `thumb` pixels wide; empty when the scene is not there any more."""
    from neus_l0.formats.open import open_scene

    meta = run_meta(run_dir)
    root = Path(meta.get("scene", ""))
    if not meta.get("scene") or not root.is_dir():
        return []
    scene = open_scene(root, downscale=1, device="cpu", preview=False, log=lambda _line: None)
    scale = np.asarray(meta.get("scale_mat", scene.scale_mat), np.float64)
    cams = []
    for i in range(scene.n_views):
        K = scene.intrinsics[i].double().numpy()
        c2w = scene.c2w[i].double().numpy()
        img = (scene.images[i].numpy() * 255.0 + 0.5).astype(np.uint8)
        h = max(1, round(img.shape[0] * thumb / img.shape[1]))
        small = cv2.resize(img, (thumb, h), interpolation=cv2.INTER_AREA)
        cams.append(Camera(i, scene.image_names[i], 2.0 * np.arctan(scene.height / (2 * K[1, 1])),
                           scene.width / scene.height, _wxyz(c2w[:3, :3]),
                           scale[:3, :3] @ c2w[:3, 3] + scale[:3, 3], small))
    return cams


def mesh_normal_colors(mesh) -> np.ndarray:
    """(V, 3) uint8 RGB of a trimesh's vertex normals as ``n / 2 + 1/2``."""
    n = np.asarray(mesh.vertex_normals, np.float64)
    return (np.clip(n * 0.5 + 0.5, 0, 1) * 255 + 0.5).astype(np.uint8)


def checkpoint_mesh(run_dir: str | Path, checkpoint: Path | None, resolution: int):
    """The run's mesh at `checkpoint` (default the newest) with vertex colours, world units.

    Returns:
        a trimesh, or None when the field has no surface yet.
    """
    from neus_l0.mesh.extract import vertex_colors
    from neus_l0.mesh.from_run import mesh_from_run

    try:
        got = mesh_from_run(run_dir, resolution, checkpoint=checkpoint)
    except NeusL0Error as exc:
        if "surface" in str(exc):
            return None
        raise
    mesh, scale = got.mesh, got.scale_mat
    norm = (np.asarray(mesh.vertices) - scale[:3, 3]) / scale[0, 0]
    mesh.visual.vertex_colors = vertex_colors(got.model, norm)
    return mesh
