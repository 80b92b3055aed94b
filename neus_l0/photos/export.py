"""Undistortion to a pinhole camera and the NeuS-format scene writer.

Undistortion: pycolmap's ``undistort_camera`` picks the pinhole camera (focal length,
principal point, size) that keeps the valid undistorted pixels; each output pixel is then
mapped through that pinhole's inverse and the COLMAP camera's ``img_from_cam`` (any COLMAP
model), and the photo (and mask) is resampled with ``cv2.remap``. Distortion-free cameras
are copied unchanged. An optional longest-side limit resizes afterwards with
``cv2.INTER_AREA`` (pixel-centre exact, like `neus_l0.data.scene`'s downscale).

Pixel conventions: COLMAP puts the top-left pixel's centre at (0.5, 0.5), NeuS at (0, 0):
``K_neus = K_colmap`` with 0.5 subtracted from the principal point.
"""

from __future__ import annotations

import dataclasses
import io
from pathlib import Path

import cv2
import numpy as np

from neus_l0.atomic import atomic_write, atomic_write_png, atomic_write_text
from neus_l0.data.cameras import projection_matrix, sphere_scale_mat
from neus_l0.data.image_io import imread_bytes
from neus_l0.data.points import POINTS_FILE, write_points
from neus_l0.errors import NeusL0Error
from neus_l0.photos.sparse_io import SparseModel

#: COLMAP models without distortion parameters (copied without resampling).
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")


@dataclasses.dataclass
class Undistorter:
    """How one COLMAP camera becomes a pinhole camera of a given size.

    Attributes:
        K: (3, 3) pinhole intrinsics of the output, NeuS pixel convention.
        size: (width, height) of the output.
        maps: (map_x, map_y) float32 (H, W) source coordinates for ``cv2.remap``, or None
            when the image is only resized (or copied).
        resize: (width, height) to resize the remapped image to with INTER_AREA, or None.
    """

    K: np.ndarray
    size: tuple[int, int]
    maps: tuple[np.ndarray, np.ndarray] | None
    resize: tuple[int, int] | None

    def apply(self, img: np.ndarray, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
        """Undistort (and resize) one (H, W[, C]) image."""
        if self.maps is not None:
            img = cv2.remap(img, self.maps[0], self.maps[1], interpolation,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if self.resize is not None:
            img = cv2.resize(img, self.resize, interpolation=cv2.INTER_AREA)
        return img


def make_undistorter(camera, max_size: int = -1) -> Undistorter:
    """Build the `Undistorter` of a ``pycolmap.Camera``.

    Args:
        camera: the COLMAP camera (any perspective model).
        max_size: longest side of the output in pixels (-1: keep the undistorted size).
    """
    import pycolmap

    model = camera.model.name
    if model in PINHOLE_MODELS:
        fx, fy = camera.focal_length_x, camera.focal_length_y
        cx, cy = camera.principal_point_x, camera.principal_point_y
        w, h = int(camera.width), int(camera.height)
        maps = None
    else:
        new = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), camera)
        fx, fy = new.focal_length_x, new.focal_length_y
        cx, cy = new.principal_point_x, new.principal_point_y
        w, h = int(new.width), int(new.height)
        K_colmap = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
        # output pixel (x, y) -> COLMAP coords (x + 0.5, y + 0.5) -> normalised ray
        nx = (xs + 0.5 - K_colmap[0, 2]) / fx
        ny = (ys + 0.5 - K_colmap[1, 2]) / fy
        rays = np.stack([nx.ravel(), ny.ravel(), np.ones(nx.size)], -1)  # (H*W, 3)
        src = np.asarray(camera.img_from_cam(rays, check_cheirality=False)) - 0.5  # (H*W, 2)
        maps = (src[:, 0].reshape(h, w).astype(np.float32),
                src[:, 1].reshape(h, w).astype(np.float32))
    K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1.0]])
    resize = None
    if max_size > 0 and max(w, h) > max_size:
        f = max_size / max(w, h)
        nw, nh = max(1, int(round(w * f))), max(1, int(round(h * f)))
        fx_, fy_ = nw / w, nh / h  # exact per-axis factors after rounding
        # INTER_AREA: new pixel centre x_new covers old (x_new + 0.5) / f - 0.5
        S = np.array([[fx_, 0, 0.5 * fx_ - 0.5], [0, fy_, 0.5 * fy_ - 0.5], [0, 0, 1.0]])
        K = S @ K
        resize = (nw, nh)
        w, h = nw, nh
    return Undistorter(K=K, size=(w, h), maps=maps, resize=resize)


def find_masks(mask_dir: str | Path, names: list[str]) -> dict[str, Path]:
    """Pair each photo name with its mask file.

    A photo ``a/IMG_1.jpg`` takes ``IMG_1.png``, ``IMG_1.jpg.png`` (COLMAP's convention) or
    any image file with stem ``IMG_1`` in `mask_dir`; when names do not match at all and the
    counts agree, masks pair with the photos in sorted order (as the scene loader does).

    Raises:
        NeusL0Error: missing folder, or a photo without a mask.
    """
    mask_dir = Path(mask_dir)
    if not mask_dir.is_dir():
        raise NeusL0Error(f"{mask_dir}: mask folder not found")
    files = sorted(p for p in mask_dir.iterdir() if p.is_file()
                   and p.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"))
    by_stem: dict[str, Path] = {}
    for p in files:
        by_stem.setdefault(p.stem, p)
    out = {}
    for name in names:
        base = Path(name).name
        hit = by_stem.get(Path(base).stem) or by_stem.get(base)
        if hit is not None:
            out[name] = hit
    if len(out) == len(names):
        return out
    if not out and len(files) == len(names):
        return dict(zip(sorted(names), files, strict=True))
    missing = next(n for n in names if n not in out)
    raise NeusL0Error(f"{mask_dir}: no mask for photo '{missing}' (expected "
                      f"{Path(missing).stem}.png)")


def _read(path: Path, flags: int = cv2.IMREAD_COLOR) -> np.ndarray:
    img = imread_bytes(Path(path), flags)
    if img is None:
        raise NeusL0Error(f"{path}: unreadable image")
    return img


def _remove_stale(folder: Path, n: int) -> None:
    """Delete ``NNN.png`` files from an earlier run beyond the first `n` views."""
    if folder.is_dir():
        for p in folder.glob("*.png"):
            if p.stem.isdigit() and int(p.stem) >= n:
                p.unlink()


def write_cameras(path: Path, world_mats: np.ndarray, scale_mat: np.ndarray) -> None:
    """Write ``cameras_sphere.npz`` (``world_mat_i``, ``scale_mat_i``) atomically.

    Args:
        path: the .npz file.
        world_mats: (N, 4, 4) projections K[R|t] (world -> pixels).
        scale_mat: (4, 4) unit sphere -> object sphere (the same for every view).
    """
    arrays = {}
    for i, wm in enumerate(world_mats):
        arrays[f"world_mat_{i}"] = np.asarray(wm, dtype=np.float64)
        arrays[f"scale_mat_{i}"] = np.asarray(scale_mat, dtype=np.float64)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    data = buf.getvalue()
    atomic_write(path, lambda p: p.write_bytes(data))


def export_scene(out: str | Path, model: SparseModel, photo_dir: str | Path,
                 center: np.ndarray, radius: float, masks: dict[str, Path] | None = None,
                 max_size: int = -1, progress: bool = True) -> dict:
    """Write the registered views of `model` as a NeuS-format scene in `out`.

    Writes ``image/NNN.png``, ``mask/NNN.png`` (3-channel 0/255, when `masks` is given),
    ``cameras_sphere.npz``, ``sources.txt`` (one source photo per line, view order) and
    ``sparse_points.npz`` (the SfM points in world units and their track lengths, for
    `neus_l0.bounds.points`).

    Args:
        out: output folder.
        model: the registered views (view order = ``model.names``).
        photo_dir: folder the names are relative to.
        center: (3,) object-sphere centre, world units.
        radius: object-sphere radius.
        masks: photo name -> mask file, or None.
        max_size: longest side of the written images (-1: the undistorted size).
        progress: show a tqdm bar.

    Returns:
        dict with ``K`` (N, 3, 3) written intrinsics, ``world_mats`` (N, 4, 4),
        ``scale_mat`` (4, 4), ``size`` (width, height).

    Raises:
        NeusL0Error: cameras that undistort to different sizes, unreadable photos or masks,
            a mask whose size differs from its photo.
    """
    out = Path(out)
    photo_dir = Path(photo_dir)
    und = {cid: make_undistorter(cam, max_size) for cid, cam in model.cameras.items()}
    sizes = {u.size for u in und.values()}
    if len(sizes) > 1:
        raise NeusL0Error(f"{photo_dir}: the cameras undistort to different sizes "
                          f"{sorted(sizes)}; NeuS needs one image size (use one camera)")
    Ks, world_mats = [], []
    it = range(model.n_views)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc="undistorting", unit="img", leave=False)
    for i in it:
        name = model.names[i]
        u = und[int(model.camera_ids[i])]
        src = photo_dir / name
        img = _read(src)
        atomic_write_png(out / "image" / f"{i:03d}.png", u.apply(img))
        if masks is not None:
            m = _read(masks[name], cv2.IMREAD_GRAYSCALE)
            if m.shape[:2] != img.shape[:2]:
                raise NeusL0Error(f"{masks[name]}: mask size {m.shape[1]}x{m.shape[0]} differs "
                                  f"from photo {src.name} ({img.shape[1]}x{img.shape[0]})")
            fg = u.apply(m.astype(np.float32) / 255.0) > 0.5
            atomic_write_png(out / "mask" / f"{i:03d}.png",
                       np.repeat((fg * 255).astype(np.uint8)[..., None], 3, axis=-1))
        w2c = np.eye(4)
        w2c[:3] = model.w2c[i]
        Ks.append(u.K)
        world_mats.append(projection_matrix(u.K, w2c))
    _remove_stale(out / "image", model.n_views)
    _remove_stale(out / "mask", model.n_views if masks is not None else 0)
    scale_mat = sphere_scale_mat(np.asarray(center, dtype=np.float64), float(radius))
    world_mats = np.stack(world_mats)
    write_cameras(out / "cameras_sphere.npz", world_mats, scale_mat)
    atomic_write_text(out / "sources.txt",
                      "".join(f"{photo_dir / n}\n" for n in model.names))
    write_points(out / POINTS_FILE, model.points, model.track_len)
    return {"K": np.stack(Ks), "world_mats": world_mats, "scale_mat": scale_mat,
            "size": sizes.pop()}
