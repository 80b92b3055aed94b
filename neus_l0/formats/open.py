"""Open a user's scene, whatever its format: NeuS format or transforms.json.

- NeuS format (``image/``, optional ``mask/``, ``cameras_sphere.npz``): read by
  `neus_l0.formats.neus.load_scene`, its ``scale_mat`` as the file gives it.
- transforms.json (NeRF-synthetic ``transforms_{train,val,test}.json``, instant-ngp,
  nerfstudio): parsed and undistorted by `neus_l0.formats.transforms`; the object sphere is
  found from the *train* split (`neus_l0.formats.sphere.find_sphere`), whichever split is
  loaded, and independently of the downscale, so that every split and resolution shares one
  ``scale_mat``. Poses stay in the file's world frame, so meshes come out in it.

Lines for the user (stderr, through `log`): the file, kind, split, views and where the
masks come from (one line); the undistortion, if any; the sphere and where its preview
(``sphere_preview.png``, next to the scene when the folder is writable, else in the temporary
folder) went.
"""

from __future__ import annotations

import hashlib
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from neus_l0.data.cameras import CAMERA_FILES, projection_matrix
from neus_l0.data.scene import Scene, scene_summary
from neus_l0.errors import SceneError
from neus_l0.formats.neus import load_scene
from neus_l0.formats.sphere import SphereFit, find_sphere
from neus_l0.formats.transforms import SPLITS, find_transforms, load_views, read_transforms

#: The preview's file name (as `neus-l0 colmap` writes it).
PREVIEW_FILE = "sphere_preview.png"
#: Views drawn in the preview.
PREVIEW_VIEWS = 4
#: Points drawn in the preview at most.
PREVIEW_POINTS = 4000

_MASK_WORDS = {
    "mask_path": "masks from the frames' mask_path files",
    "alpha": "masks from the images' alpha (alpha > 0.5; colour composited over black)",
    "none": "no masks (every pixel counts as foreground)",
}


def _stderr(line: str) -> None:
    print(f"neus-l0: {line}", file=sys.stderr, flush=True)


def scene_format(root: str | Path, split: str = "train") -> str:
    """``"neus"`` or ``"transforms"``: what the folder holds (NeuS format wins when both).

    Raises:
        SceneError: a folder with neither.
    """
    root = Path(root)
    if root.is_dir() and ((root / "image").is_dir()
                          or any((root / n).is_file() for n in CAMERA_FILES)):
        return "neus"
    if find_transforms(root, split) is not None or find_transforms(root, "train") is not None:
        return "transforms"
    if root.is_dir():
        raise SceneError(f"{root}: missing 'image/' folder (NeuS format) and no "
                         f"transforms.json or transforms_train.json")
    return "neus"  # load_scene says what is missing


def open_scene(root: str | Path, downscale: int = 1, device: str | torch.device = "cpu",
               split: str = "train", *, preview: bool = True, log=None) -> Scene:
    """Load a scene in NeuS format or as transforms.json (module docstring).

    Args:
        root: the scene folder (or a transforms JSON file).
        downscale: integer factor >= 1 (`neus_l0.formats.neus.load_scene`'s convention).
        device: where the tensors go.
        split: ``train``, ``val`` or ``test`` (transforms.json scenes; NeuS format has only
            ``train``).
        preview: write ``sphere_preview.png`` (transforms.json scenes).
        log: callable taking one line (default: ``neus-l0: LINE`` on stderr).

    Returns:
        The `Scene`; ``scene.info`` says how it was read (``format``, ``masks``, and for
        transforms.json ``split``, ``sphere``, ``preview``, ``undistorted``).

    Raises:
        SceneError: one line naming the file and the problem.
    """
    if split not in SPLITS:
        raise SceneError(f"{root}: split must be one of {', '.join(SPLITS)}, got '{split}'")
    if scene_format(root, split) == "neus":
        if split != "train":
            raise SceneError(f"{root}: a NeuS-format scene has no '{split}' split")
        return load_scene(root, downscale=downscale, device=device)
    return _open_transforms(Path(root), downscale, device, split, preview,
                            log if log is not None else _stderr)


def _open_transforms(root: Path, downscale: int, device, split: str, preview: bool,
                     log) -> Scene:
    train = read_transforms(root, "train")
    train_views = load_views(train, downscale, search=True)
    folder = train.path.parent
    sphere = find_sphere(folder, train.c2w, train_views.search_masks,
                         train_views.search_intrinsics, train.points, names=train.names,
                         where=train.path, log=log)
    if split == "train":
        ts, views = train, train_views
    else:
        ts = read_transforms(root, split)
        views = load_views(ts, downscale, search=False)
    V, H, W = views.images.shape[:3]
    log(f"{ts.path}: {ts.kind} transforms, {V} {split} views {W}x{H}; "
        f"{_MASK_WORDS[views.mask_source]}")
    if views.undistorted:
        log(views.undistorted)
    where = _write_preview(folder, train, train_views, sphere) if preview else None
    log(sphere.explain() + (f"; preview {where}" if where is not None else ""))

    c2w = ts.c2w.copy()
    c2w[:, :3, 3] = (c2w[:, :3, 3] - sphere.center) / sphere.radius
    masks = views.masks if views.masks is not None else np.ones((V, H, W), np.float32)
    dev = torch.device(device)
    return Scene(
        root=folder,
        images=torch.from_numpy(views.images).to(dev),
        masks=torch.from_numpy(masks).to(dev),
        has_masks=views.masks is not None,
        intrinsics=torch.from_numpy(views.intrinsics).float().to(dev),
        c2w=torch.from_numpy(c2w).float().to(dev),
        scale_mat=sphere.scale_mat(),
        image_names=ts.names,
        info={"format": ts.kind, "camera_file": ts.path.name, "masks": views.mask_source,
              "split": split, "sphere": sphere.to_dict(),
              "preview": None if where is None else str(where),
              "undistorted": views.undistorted,
              "applied_transform": (None if ts.applied_transform is None
                                    else ts.applied_transform.tolist())},
    )


def _preview_path(folder: Path) -> Path:
    if os.access(folder, os.W_OK):
        return folder / PREVIEW_FILE
    tag = hashlib.sha1(str(folder.resolve()).encode()).hexdigest()[:8]
    return Path(tempfile.gettempdir()) / f"neus-l0-{folder.name}-{tag}-{PREVIEW_FILE}"


def _write_preview(folder: Path, ts, views, sphere: SphereFit) -> Path | None:
    """Draw the sphere over a few train views (`neus_l0.formats.preview.write_preview`)."""
    from neus_l0.formats.preview import write_preview

    V = ts.n_views
    picks = np.unique(np.linspace(0, V - 1, min(PREVIEW_VIEWS, V)).round().astype(int))
    images = [np.clip(views.images[i] * 255.0 + 0.5, 0, 255).astype(np.uint8) for i in picks]
    mats = [projection_matrix(views.intrinsics[i], np.linalg.inv(ts.c2w[i])) for i in picks]
    pts = sphere.points
    if len(pts) > PREVIEW_POINTS:
        pts = pts[np.random.default_rng(0).choice(len(pts), PREVIEW_POINTS, replace=False)]
    path = _preview_path(folder)
    try:
        return write_preview(path, images, mats, pts, sphere.center, sphere.radius,
                             titles=[ts.names[i] for i in picks])
    except OSError:
        if path.parent == folder:  # the folder said writable but was not
            tmp = Path(tempfile.gettempdir()) / f"neus-l0-{folder.name}-{PREVIEW_FILE}"
            return write_preview(tmp, images, mats, pts, sphere.center, sphere.radius,
                                 titles=[ts.names[i] for i in picks])
        raise


def summarise(scene: Scene) -> dict:
    """`neus_l0.data.scene.scene_summary` plus how the scene was read (``split``,
    ``sphere_method``, ``sphere_detail``, ``preview``, ``undistorted``)."""
    info = scene_summary(scene)
    extra = scene.info
    if "sphere" in extra:
        info["sphere_method"] = extra["sphere"]["method"]
        info["sphere_detail"] = extra["sphere"]["detail"]
    for key in ("split", "preview", "undistorted"):
        if extra.get(key):
            info[key] = extra[key]
    return info
