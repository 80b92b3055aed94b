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

Images with an alpha channel (RGBA PNGs). Colour is composited over black
(``rgb * alpha``, the renderer's default background). Without a ``mask/`` folder, the masks
are ``alpha > 0.5`` (one line on stderr says so), unless the alpha is opaque everywhere (then
there are no masks); with one, ``mask/`` wins. Either every image carries alpha or none does.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from neus_l0.data.cameras import decompose_projection
from neus_l0.data.image_io import imread_bytes
from neus_l0.data.scene import Scene, scene_summary
from neus_l0.data.views import (
    PAIRING_RULE,
    indexed_files,
    pair_views,
    warn_unused,
)
from neus_l0.errors import SceneError

CAMERA_FILES = ("cameras_sphere.npz", "cameras.npz")


def find_files(root: str | Path) -> tuple[dict[int, Path], dict[int, Path] | None, Path]:
    """Locate a scene's images and masks by view index (None without ``mask/``) and its
    camera file (`neus_l0.data.views`).

    Raises:
        SceneError: missing folder, no images, a file without a view number, two files of
            one view, no camera file.
    """
    root = Path(root)
    if not root.is_dir():
        raise SceneError(f"{root}: scene folder not found")
    image_dir = root / "image"
    if not image_dir.is_dir():
        raise SceneError(f"{image_dir}: missing 'image/' folder")
    images = indexed_files(image_dir)
    if not images:
        raise SceneError(f"{image_dir}: no images (.png/.jpg) found")
    masks = None
    mask_dir = root / "mask"
    if mask_dir.exists():
        if not mask_dir.is_dir():
            raise SceneError(f"{mask_dir}: not a folder")
        masks = indexed_files(mask_dir)
        if not masks:
            raise SceneError(f"{mask_dir}: no masks (.png/.jpg) found")
    for name in CAMERA_FILES:
        if (root / name).is_file():
            return images, masks, root / name
    raise SceneError(f"{root}: no camera file ({' or '.join(CAMERA_FILES)})")


def camera_indices(path: Path) -> list[int]:
    """The indices i of the ``world_mat_i`` a camera file holds.

    Raises:
        SceneError: an unreadable file.
    """
    try:
        with np.load(path) as data:
            keys = list(data.files)
    except Exception as exc:  # noqa: BLE001 - any parse failure is the user's file
        raise SceneError(f"{path}: unreadable camera file ({exc})") from None
    return sorted(int(k[len("world_mat_"):]) for k in keys
                  if k.startswith("world_mat_") and k[len("world_mat_"):].isdigit())


def read_image(path: Path, shape: tuple[int, int] | None = None
               ) -> tuple[np.ndarray, np.ndarray | None]:
    """Read an image as RGB in [0, 1] and its alpha channel, if it has one.

    8- and 16-bit PNG/JPEG, grey, grey + alpha, colour and colour + alpha all work.

    Args:
        path: the image file.
        shape: (H, W) it must have (None: any).

    Returns:
        rgb: (H, W, 3) float32 in [0, 1], *not* composited (straight colour).
        alpha: (H, W) float32 in [0, 1], or None without an alpha channel.

    Raises:
        SceneError: unreadable, or not of `shape`.
    """
    cut = truncated(path)  # before decoding: libpng / libjpeg would print to stderr
    if cut:
        raise SceneError(f"{path}: {cut} (a partial copy or download?)")
    huge = oversized(path)
    if huge:
        raise SceneError(f"{path}: {huge}")
    try:
        img = imread_bytes(path, cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        why = str(exc).strip().splitlines()[-1][:120]
        raise SceneError(f"{path}: unreadable image (OpenCV: {why})") from None
    if img is None:
        raise SceneError(f"{path}: unreadable image")
    if shape is not None and img.shape[:2] != shape:
        raise SceneError(f"{path}: size {img.shape[1]}x{img.shape[0]} differs from "
                         f"{shape[1]}x{shape[0]} of the first image")
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(img.dtype, 1.0)
    img = img.astype(np.float32) / np.float32(scale)
    if img.ndim == 2:
        img = img[..., None]
    alpha = None
    if img.shape[2] in (2, 4):
        img, alpha = img[..., :-1], np.ascontiguousarray(img[..., -1])
    if img.shape[2] == 1:
        rgb = np.repeat(img, 3, axis=2)
    else:
        rgb = np.ascontiguousarray(img[..., 2::-1])  # BGR -> RGB
    return rgb, alpha


#: The first bytes of a PNG and of a JPEG file.
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SIGNATURE = b"\xff\xd8"


def truncated(path: Path) -> str | None:
    """Why an image file is cut short, or None: OpenCV decodes a truncated JPEG (and some
    truncated PNGs) without an error, filling the missing rows, and its decoders print to
    stderr, so the end of a file that starts as a PNG or a JPEG is checked before decoding.
    Files of other kinds (or not images at all, or not readable) are left to the decoder:
    None."""
    try:
        with open(path, "rb") as f:
            head = f.read(8)
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - 64))
            tail = f.read()
    except OSError:
        return None
    if head.startswith(PNG_SIGNATURE) and b"IEND" not in tail[-12:]:
        return "truncated PNG (no IEND chunk at its end)"
    if (head.startswith(JPEG_SIGNATURE)
            and b"\xff\xd9" not in tail.rstrip(b"\x00 \r\n")[-2:]):
        return "truncated JPEG (no end-of-image marker)"
    return None


#: The most pixels a scene image may declare (a 16k x 16k photo; beyond it decoding would
#: take gigabytes before any check of the scene could run).
MAX_IMAGE_PIXELS = 16384 * 16384


def oversized(path: Path) -> str | None:
    """Why a PNG's declared size is refused (more than `MAX_IMAGE_PIXELS`: a decompression
    bomb, or not a photo), read from its header before decoding; None otherwise."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return None
    if not head.startswith(PNG_SIGNATURE) or len(head) < 24 or head[12:16] != b"IHDR":
        return None
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if width * height <= MAX_IMAGE_PIXELS:
        return None
    return (f"declares {width}x{height} pixels, more than a scene image may have "
            f"({MAX_IMAGE_PIXELS:,}); a decompression bomb or not a photo")


#: How far two views' scale_mat may differ (relative to the largest entry) and still be one.
SCALE_MAT_RTOL = 1e-6


def _read_cameras(path: Path, indices: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Projection matrices P_i = (world_mat_i @ scale_mat_i)[:3, :4] of the views `indices`,
    and the first view's scale_mat.

    Returns:
        P: (len(indices), 3, 4) float64, normalised frame -> pixels.
        scale_mat: (4, 4) float64.
    """
    try:
        data = np.load(path)
        keys = set(data.files)
    except Exception as exc:  # noqa: BLE001 - any parse failure is the user's file
        raise SceneError(f"{path}: unreadable camera file ({exc})") from None
    Ps, scale_mat0, differ = [], None, []
    for i in indices:
        mats = {}
        for key in (f"world_mat_{i}", f"scale_mat_{i}"):
            if key not in keys:
                raise SceneError(f"{path}: missing '{key}' (image view {i} needs world_mat_{i} "
                                 f"and scale_mat_{i}; {PAIRING_RULE})")
            try:
                m = np.asarray(data[key], dtype=np.float64)
            except (ValueError, TypeError) as exc:  # object arrays, strings, ragged lists
                raise SceneError(f"{path}: '{key}' is not a numeric matrix "
                                 f"({str(exc).splitlines()[0]})") from None
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
        if scale_mat0 is None:
            scale_mat0, first = scale, i
        elif not np.allclose(scale, scale_mat0, rtol=0,
                             atol=SCALE_MAT_RTOL * np.abs(scale_mat0).max()):
            differ.append(i)
    if differ:
        shown = ", ".join(f"scale_mat_{i}" for i in differ[:5])
        raise SceneError(f"{path}: {shown}{' ...' if len(differ) > 5 else ''} differ from "
                         f"scale_mat_{first}: NeuS normalises every view with one sphere")
    return np.stack(Ps), scale_mat0


def downscale_matrix(s: int) -> np.ndarray:
    """(3, 3) S with ``K_new = S @ K`` for an integer downscale `s` (module docstring)."""
    off = -(s - 1) / (2.0 * s)
    return np.array([[1.0 / s, 0.0, off], [0.0, 1.0 / s, off], [0.0, 0.0, 1.0]])


def area_downscale(a: np.ndarray, s: int) -> np.ndarray:
    """Crop (H, W, ...) to multiples of s and block-average with cv2.INTER_AREA."""
    h, w = (a.shape[0] // s) * s, (a.shape[1] // s) * s
    a = a[:h, :w]
    return cv2.resize(a, (w // s, h // s), interpolation=cv2.INTER_AREA)


def check_empty_masks(empty: list[Path], n_views: int, where: Path) -> None:
    """Warn (one line on stderr) about empty masks; refuse a scene whose masks are all empty.

    An empty mask is true data when the object has left a view's frame: every pixel of
    that view is background, and training and culling treat it so.
    """
    if not empty:
        return
    if len(empty) == n_views:
        raise SceneError(f"{where}: every mask is empty (no foreground pixel), e.g. "
                         f"{empty[0]}")
    names = ", ".join(p.name for p in empty[:8]) + (", ..." if len(empty) > 8 else "")
    print(f"neus-l0: warning: {where}: {len(empty)} of {n_views} masks are empty "
          f"(no foreground pixel): {names}; those views count as all background",
          file=sys.stderr, flush=True)


def read_views(paths: list[Path], shape: tuple[int, int], s: int = 1
               ) -> tuple[np.ndarray, list[np.ndarray | None]]:
    """Read images (composited over black where they carry alpha) and downscale them by `s`.

    Args:
        paths: image files, all of size `shape` (H, W).
        s: integer downscale (`area_downscale`).

    Returns:
        images: (n, H // s, W // s, 3) float32 RGB in [0, 1], ``rgb * alpha`` with alpha.
        alpha_masks: per image, ``alpha > 0.5`` as float32 (H // s, W // s), block-averaged
            like a mask file (soft coverage after a downscale), or None without alpha.
    """
    H, W = shape
    images = np.empty((len(paths), H // s, W // s, 3), np.float32)
    alpha_masks: list[np.ndarray | None] = []
    for i, p in enumerate(paths):
        rgb, alpha = read_image(p, shape)
        fg = None
        if alpha is not None:
            rgb = rgb * alpha[..., None]
            fg = (alpha > 0.5).astype(np.float32)
            fg = area_downscale(fg, s) if s > 1 else fg
        images[i] = area_downscale(rgb, s) if s > 1 else rgb
        alpha_masks.append(fg)
    return images, alpha_masks


def read_masks(paths: list[Path], shape: tuple[int, int], s: int = 1
               ) -> tuple[np.ndarray, list[Path]]:
    """Read mask images (foreground: any channel > 0.5, i.e. > 127 in 8 bits), downscaled.

    Returns:
        masks: (n, H // s, W // s) float32 coverage in [0, 1].
        empty: the files without any foreground pixel.
    """
    H, W = shape
    masks = np.empty((len(paths), H // s, W // s), np.float32)
    empty = []
    for i, p in enumerate(paths):
        m, _ = read_image(p, shape)
        fg = (m.max(axis=-1) > 0.5).astype(np.float32)
        if not fg.any():
            empty.append(p)
        masks[i] = area_downscale(fg, s) if s > 1 else fg
    return masks, empty


def masks_from_alpha(alpha_masks: list[np.ndarray | None], paths: list[Path]
                     ) -> tuple[np.ndarray | None, str]:
    """The masks of images with alpha (one line on stderr says which masks a scene uses).

    Args:
        alpha_masks: per image, the coverage of ``alpha > 0.5`` (`read_views`) or None.
        paths: the images (for the messages).

    Returns:
        masks: (n, H, W) float32 or None (no image has alpha, or the alpha is opaque
            everywhere); and the source: ``"alpha"`` or ``"none"``.

    Raises:
        SceneError: some images carry alpha and others do not, or every alpha is empty.
    """
    have = [a is not None for a in alpha_masks]
    if not any(have):
        return None, "none"
    if not all(have):
        odd = paths[have.index(not have[0])]
        raise SceneError(f"{odd}: {'no' if have[0] else 'an'} alpha channel, unlike "
                         f"{paths[0].name}: give every image alpha or none")
    masks = np.stack(alpha_masks)
    where = paths[0].parent
    if masks.min() >= 1.0:
        print(f"neus-l0: {where}: images carry alpha but it is opaque everywhere: no masks",
              file=sys.stderr, flush=True)
        return None, "none"
    empty = [p for p, m in zip(paths, masks, strict=True) if not m.any()]
    check_empty_masks(empty, len(paths), where)
    print(f"neus-l0: {where}: masks from the images' alpha channel (alpha > 0.5; colour "
          f"composited over black)", file=sys.stderr, flush=True)
    return masks, "alpha"


def _split_projections(P: np.ndarray, indices: list[int], cam_path: Path,
                       s: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Intrinsics (downscaled by `s`) and camera-to-world poses of the projections P (V, 3, 4)
    of views `indices`.

    Raises:
        SceneError: a projection OpenCV cannot split, or one giving non-finite numbers.
    """
    Ks, c2ws = [], []
    S = downscale_matrix(s)
    for v, Pv in zip(indices, P, strict=True):
        try:
            K, c2w = decompose_projection(Pv)
        except cv2.error:
            raise SceneError(f"{cam_path}: world_mat_{v} @ scale_mat_{v} is not a camera "
                             "projection (OpenCV cannot split it into K, R, t)") from None
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(c2w))):
            raise SceneError(f"{cam_path}: view {v} decomposes into non-finite K/pose")
        Ks.append(S @ K)
        c2ws.append(c2w)
    return Ks, c2ws


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
    images_by_index, masks_by_index, cam_path = find_files(root)
    pairing = pair_views(images_by_index, masks_by_index, camera_indices(cam_path), cam_path)
    warn_unused(pairing, cam_path)
    image_paths, mask_paths = pairing.images, pairing.masks
    n = len(image_paths)
    P, scale_mat = _read_cameras(cam_path, pairing.indices)

    first = read_image(image_paths[0], None)
    H, W = first[0].shape[:2]
    if H < s or W < s:
        raise SceneError(f"{image_paths[0]}: {W}x{H} is too small for downscale {s}")
    if n == 1:
        print(f"neus-l0: warning: {root}: one view only; NeuS needs many views around the "
              "object (a few dozen) to recover its shape", file=sys.stderr, flush=True)
    images, alpha_masks = read_views(image_paths, (H, W), s)
    if mask_paths is not None:
        masks, empty = read_masks(mask_paths, (H, W), s)
        check_empty_masks(empty, n, root / "mask")
        source = "mask/"
    else:
        masks, source = masks_from_alpha(alpha_masks, image_paths)
    if masks is None:
        masks = np.ones((n, H // s, W // s), np.float32)

    Ks, c2ws = _split_projections(P, pairing.indices, cam_path, s)
    dev = torch.device(device)
    return Scene(
        root=root,
        images=torch.from_numpy(images).to(dev),
        masks=torch.from_numpy(masks).to(dev),
        has_masks=source != "none",
        intrinsics=torch.from_numpy(np.stack(Ks)).float().to(dev),
        c2w=torch.from_numpy(np.stack(c2ws)).float().to(dev),
        scale_mat=scale_mat,
        image_names=[p.name for p in image_paths],
        info={"format": "neus", "camera_file": cam_path.name, "masks": source,
              "mask_files": [f"mask/{p.name}" for p in mask_paths or []],
              "pairing": PAIRING_RULE, "view_indices": pairing.indices,
              "unused_cameras": pairing.unused_cameras},
    )


def validate_scene(root: str | Path) -> dict:
    """Load a NeuS-format scene fully (raising `SceneError` on any problem) and summarise it
    (`scene_summary`)."""
    return scene_summary(load_scene(root))


