"""NeuS-format scenes: loading, validation and the `Scene` container.

A scene folder holds ``image/*.png`` (sorted by name), optionally ``mask/*.png`` (paired with
the images by sorted order, since DTU names images ``000000.png`` and masks ``000.png``), and
``cameras_sphere.npz`` (or IDR's legacy ``cameras.npz``) with ``world_mat_i`` and
``scale_mat_i`` per view. See ``docs/ARCHITECTURE.md`` for the frames.

Downscaling convention. With integer factor ``s`` the image is cropped at the right/bottom to
a multiple of ``s`` and block-averaged (``cv2.INTER_AREA``), so new pixel ``j`` is the mean of
old pixels ``s*j .. s*j + s - 1``, whose centres average to ``s*j + (s - 1) / 2``. Keeping
NeuS's pixel-centre-at-integer convention therefore needs
``x_old = s * x_new + (s - 1) / 2``, i.e. ``K_new = S @ K`` with
``S = [[1/s, 0, -(s-1)/(2s)], [0, 1/s, -(s-1)/(2s)], [0, 0, 1]]``: the ray through a
downscaled pixel centre is exactly the ray through the centre of the block it averages.
(NeuS itself only divides K by ``s``, which shifts rays by (s-1)/2 old pixels.) Masks are
block-averaged the same way and kept as soft coverage in [0, 1].
"""

from __future__ import annotations

import dataclasses
import functools
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from neus_l0.data.cameras import decompose_projection
from neus_l0.errors import SceneError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
CAMERA_FILES = ("cameras_sphere.npz", "cameras.npz")


def ray_matrices(intrinsics: torch.Tensor, c2w: torch.Tensor) -> torch.Tensor:
    """Per-view matrices A = R K^-1 that map a pixel [x, y, 1] to its ray's direction.

    Computed in float64 (then cast back), once per scene: `rays_at` then needs one small
    product per ray (`pixel_rays` solves K per ray, which the same ray needs ~15 ops for).

    Args:
        intrinsics: (V, 3, 3) upper-triangular K; c2w: (V, 4, 4).

    Returns:
        (V, 3, 3) in intrinsics' dtype; ``A @ [x, y, 1]`` is the (unnormalised) direction.
    """
    k_inv = torch.linalg.inv(intrinsics.double())
    return (c2w[:, :3, :3].double() @ k_inv).to(intrinsics.dtype)


@dataclasses.dataclass
class Scene:
    """A loaded multi-view scene, everything on one device.

    Attributes:
        root: the scene folder.
        images: (n_views, H, W, 3) float32 RGB in [0, 1].
        masks: (n_views, H, W) float32, 1 = foreground (soft after a downscale); all ones
            when the scene has no ``mask/`` folder.
        has_masks: whether the scene came with masks.
        intrinsics: (n_views, 3, 3) float32, pixel units, after any downscale.
        c2w: (n_views, 4, 4) float32 camera-to-world poses in the normalised frame
            (the object's bounding sphere is the unit sphere).
        scale_mat: (4, 4) float64 numpy, normalised -> world (``scale_mat_0``).
        image_names: file names of the images, in view order.
    """

    root: Path
    images: torch.Tensor
    masks: torch.Tensor
    has_masks: bool
    intrinsics: torch.Tensor
    c2w: torch.Tensor
    scale_mat: np.ndarray
    image_names: list[str]

    @property
    def n_views(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    @property
    def device(self) -> torch.device:
        return self.images.device

    @functools.cached_property
    def ray_matrices(self) -> torch.Tensor:
        """(n_views, 3, 3) R K^-1 of each view (`ray_matrices`), computed on first use (a
        scene's cameras do not change after loading)."""
        return ray_matrices(self.intrinsics, self.c2w)

    @functools.cached_property
    def centres(self) -> torch.Tensor:
        """(n_views, 3) camera centres in the normalised frame, contiguous."""
        return self.c2w[:, :3, 3].contiguous()

    def to(self, device: str | torch.device) -> Scene:
        """Return a copy whose tensors live on `device`."""
        return dataclasses.replace(
            self, images=self.images.to(device), masks=self.masks.to(device),
            intrinsics=self.intrinsics.to(device), c2w=self.c2w.to(device))


def _list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)


def find_files(root: str | Path) -> tuple[list[Path], list[Path] | None, Path]:
    """Locate a scene's images, masks (None without ``mask/``) and camera file.

    Raises:
        SceneError: missing folder, no images, image/mask count mismatch, no camera file.
    """
    root = Path(root)
    if not root.is_dir():
        raise SceneError(f"{root}: scene folder not found")
    image_dir = root / "image"
    if not image_dir.is_dir():
        raise SceneError(f"{image_dir}: missing 'image/' folder")
    images = _list_images(image_dir)
    if not images:
        raise SceneError(f"{image_dir}: no images (.png/.jpg) found")
    masks = None
    mask_dir = root / "mask"
    if mask_dir.exists():
        if not mask_dir.is_dir():
            raise SceneError(f"{mask_dir}: not a folder")
        masks = _list_images(mask_dir)
        if len(masks) != len(images):
            raise SceneError(f"{mask_dir}: {len(masks)} masks for {len(images)} images "
                             f"in {image_dir}")
    for name in CAMERA_FILES:
        if (root / name).is_file():
            return images, masks, root / name
    raise SceneError(f"{root}: no camera file ({' or '.join(CAMERA_FILES)})")


def _read_image(path: Path, shape: tuple[int, int] | None) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise SceneError(f"{path}: unreadable image")
    if shape is not None and img.shape[:2] != shape:
        raise SceneError(f"{path}: size {img.shape[1]}x{img.shape[0]} differs from "
                         f"{shape[1]}x{shape[0]} of the first image")
    return img


def _read_cameras(path: Path, n_views: int) -> tuple[np.ndarray, np.ndarray]:
    """Projection matrices P_i = (world_mat_i @ scale_mat_i)[:3, :4] and scale_mat_0.

    Returns:
        P: (n_views, 3, 4) float64, normalised frame -> pixels.
        scale_mat: (4, 4) float64.
    """
    try:
        data = np.load(path)
        keys = set(data.files)
    except Exception as exc:  # noqa: BLE001 - any parse failure is the user's file
        raise SceneError(f"{path}: unreadable camera file ({exc})") from None
    Ps, scale_mat0 = [], None
    for i in range(n_views):
        mats = {}
        for key in (f"world_mat_{i}", f"scale_mat_{i}"):
            if key not in keys:
                raise SceneError(f"{path}: missing '{key}' ({n_views} images need "
                                 f"world_mat_0..{n_views - 1} and scale_mat_0..{n_views - 1})")
            m = np.asarray(data[key], dtype=np.float64)
            if m.shape not in ((4, 4), (3, 4)):
                raise SceneError(f"{path}: '{key}' has shape {m.shape}, expected (4, 4)")
            if not np.all(np.isfinite(m)):
                raise SceneError(f"{path}: '{key}' holds non-finite numbers")
            full = np.eye(4)
            full[: m.shape[0]] = m
            mats[key.split("_mat")[0]] = full
        scale = mats["scale"]
        if not np.linalg.cond(scale[:3, :3]) < 1e12:
            raise SceneError(f"{path}: 'scale_mat_{i}' is singular")
        P = (mats["world"] @ scale)[:3, :4]
        M = P[:, :3]
        if not np.linalg.cond(M) < 1e12:
            raise SceneError(f"{path}: projection matrix of view {i} "
                             f"(world_mat_{i} @ scale_mat_{i}) is singular")
        Ps.append(P)
        if i == 0:
            scale_mat0 = scale
    return np.stack(Ps), scale_mat0


def _downscale_matrix(s: int) -> np.ndarray:
    off = -(s - 1) / (2.0 * s)
    return np.array([[1.0 / s, 0.0, off], [0.0, 1.0 / s, off], [0.0, 0.0, 1.0]])


def _area_downscale(a: np.ndarray, s: int) -> np.ndarray:
    """Crop (H, W, ...) to multiples of s and block-average with cv2.INTER_AREA."""
    h, w = (a.shape[0] // s) * s, (a.shape[1] // s) * s
    a = a[:h, :w]
    return cv2.resize(a, (w // s, h // s), interpolation=cv2.INTER_AREA)


def _check_empty_masks(empty: list[Path], n_views: int, root: Path) -> None:
    """Warn (one line on stderr) about empty masks; refuse a scene whose masks are all empty.

    An empty mask is true data when the object has left a view's frame: every pixel of
    that view is background, and training and culling treat it so.
    """
    if not empty:
        return
    if len(empty) == n_views:
        raise SceneError(f"{root / 'mask'}: every mask is empty (no pixel > 127), e.g. "
                         f"{empty[0]}")
    names = ", ".join(p.name for p in empty[:8]) + (", ..." if len(empty) > 8 else "")
    print(f"neus-l0: warning: {empty[0].parent}: {len(empty)} of {n_views} masks are empty "
          f"(no pixel > 127): {names}; those views count as all background",
          file=sys.stderr, flush=True)


def load_scene(root: str | Path, downscale: int = 1, device: str | torch.device = "cpu") -> Scene:
    """Load a NeuS-format scene.

    Args:
        root: scene folder (``image/``, optional ``mask/``, ``cameras_sphere.npz``).
        downscale: integer factor >= 1 (see the module docstring for the pixel convention).
        device: where the tensors go.

    Returns:
        The `Scene`.

    Raises:
        SceneError: one line naming the file and the problem.
    """
    root = Path(root)
    if int(downscale) != downscale or downscale < 1:
        raise SceneError(f"{root}: downscale must be an integer >= 1, got {downscale}")
    s = int(downscale)
    image_paths, mask_paths, cam_path = find_files(root)
    n = len(image_paths)
    P, scale_mat = _read_cameras(cam_path, n)

    first = _read_image(image_paths[0], None)
    H, W = first.shape[:2]
    if H < s or W < s:
        raise SceneError(f"{image_paths[0]}: {W}x{H} is too small for downscale {s}")
    Hs, Ws = H // s, W // s
    images = np.empty((n, Hs, Ws, 3), np.float32)
    masks = np.ones((n, Hs, Ws), np.float32)
    for i, p in enumerate(image_paths):
        img = first if i == 0 else _read_image(p, (H, W))
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
        images[i] = _area_downscale(img, s) if s > 1 else img
    if mask_paths is not None:
        empty = []
        for i, p in enumerate(mask_paths):
            m = _read_image(p, (H, W))
            fg = (m.max(axis=-1) > 127).astype(np.float32)
            if not fg.any():
                empty.append(p)
            masks[i] = _area_downscale(fg, s) if s > 1 else fg
        _check_empty_masks(empty, n, root)

    Ks, c2ws = [], []
    S = _downscale_matrix(s)
    for i in range(n):
        K, c2w = decompose_projection(P[i])
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(c2w))):
            raise SceneError(f"{cam_path}: view {i} decomposes into non-finite K/pose")
        Ks.append(S @ K)
        c2ws.append(c2w)
    dev = torch.device(device)
    return Scene(
        root=root,
        images=torch.from_numpy(images).to(dev),
        masks=torch.from_numpy(masks).to(dev),
        has_masks=mask_paths is not None,
        intrinsics=torch.from_numpy(np.stack(Ks)).float().to(dev),
        c2w=torch.from_numpy(np.stack(c2ws)).float().to(dev),
        scale_mat=scale_mat,
        image_names=[p.name for p in image_paths],
    )


def validate_scene(root: str | Path) -> dict:
    """Load a scene fully (raising `SceneError` on any problem) and summarise it.

    Returns:
        A JSON-serialisable dict: ``root``, ``camera_file``, ``views``, ``width``,
        ``height``, ``has_masks``, ``mask_coverage`` (min/mean/max foreground fraction),
        ``sphere_center`` and ``sphere_radius`` (world units), ``camera_distance``
        (min/mean/max in normalised units), ``focal`` (min/max, pixels), ``empty_masks``
        (views whose mask is empty), ``warnings`` (cameras inside the unit sphere or
        looking away from it, empty masks).
    """
    root = Path(root)
    scene = load_scene(root)
    _, mask_paths, cam_path = find_files(root)
    centres = scene.c2w[:, :3, 3].double().numpy()
    axes = scene.c2w[:, :3, 2].double().numpy()
    dist = np.linalg.norm(centres, axis=-1)
    # distance of the origin from each optical axis, and whether it lies in front
    along = -(centres * axes).sum(-1)
    miss = np.linalg.norm(centres + along[:, None] * axes, axis=-1)
    warnings = []
    inside = np.nonzero(dist <= 1.0)[0]
    if inside.size:
        warnings.append(f"cameras inside the unit sphere: views {inside.tolist()}")
    away = np.nonzero((along <= 0) | (miss > 1.0))[0]
    if away.size:
        warnings.append(f"optical axis misses the unit sphere: views {away.tolist()}")
    cover = scene.masks.mean(dim=(1, 2)).numpy()
    empty = np.nonzero(cover == 0)[0] if scene.has_masks else np.zeros(0, np.int64)
    if empty.size:
        names = [mask_paths[i].name for i in empty]
        warnings.append(f"empty masks (all background in those views): views "
                        f"{empty.tolist()} (mask/{', mask/'.join(names)})")
    sm = scene.scale_mat
    fx = scene.intrinsics[:, 0, 0].double().numpy()
    return {
        "root": str(root),
        "camera_file": cam_path.name,
        "views": scene.n_views,
        "width": scene.width,
        "height": scene.height,
        "has_masks": scene.has_masks,
        "mask_coverage": {"min": float(cover.min()), "mean": float(cover.mean()),
                          "max": float(cover.max())},
        "sphere_center": [float(v) for v in sm[:3, 3]],
        "sphere_radius": float(abs(np.linalg.det(sm[:3, :3])) ** (1.0 / 3.0)),
        "camera_distance": {"min": float(dist.min()), "mean": float(dist.mean()),
                            "max": float(dist.max())},
        "axis_miss": {"max": float(miss.max())},
        "focal": {"min": float(fx.min()), "max": float(fx.max())},
        "empty_masks": empty.tolist(),
        "warnings": warnings,
    }
