"""``transforms.json`` scenes: NeRF-synthetic, instant-ngp and nerfstudio (parsing only).

The three kinds share one layout: a JSON file with camera intrinsics at the top (shared by
every frame) and ``frames``, each with ``file_path`` (relative to the JSON file's folder,
often without extension: the image is then looked up as ``.png``, ``.jpg`` or ``.jpeg``)
and ``transform_matrix`` (4 x 4 camera-to-world).

- *NeRF-synthetic*: ``transforms_train.json`` (+ ``_val``, ``_test``) with ``camera_angle_x``
  (horizontal field of view, radians) only: square pixels, principal point at the centre.
- *instant-ngp*: one ``transforms.json`` with ``fl_x, fl_y, cx, cy, w, h`` (or
  ``camera_angle_x/y``), ``k1 k2 p1 p2`` and ``aabb_scale``.
- *nerfstudio* (``ns-process-data``): ``camera_model`` and intrinsics at the top or per frame
  (a frame's own values win), ``k1 k2 k3 k4 p1 p2``, per-frame ``mask_path``, optional
  ``ply_file_path`` (sparse points in the same world frame) and ``applied_transform`` (how
  nerfstudio rotated COLMAP's frame into this one: recorded, not undone).

Conventions. Poses are OpenGL's (camera x right, y up, looking down -z); the package uses
OpenCV's (x right, y down, z forward), so ``c2w_cv = c2w_gl @ diag(1, -1, -1, 1)``. The
world frame is the file's own: poses stay in it (`neus_l0.formats` adds the object sphere).
Intrinsics in these files put the top-left pixel's centre at (0.5, 0.5) (nerfstudio, ngp;
Blender's principal point is the image centre ``W / 2``), NeuS at (0, 0): ``K`` here has
0.5 subtracted from ``cx, cy``. Focal length: ``fl_x`` else ``0.5 w / tan(camera_angle_x
/ 2)``; ``fl_y`` else from ``camera_angle_y`` else ``fl_x``; ``cx, cy`` default to
``w / 2, h / 2``.

Distortion. ``PINHOLE`` and ``SIMPLE_PINHOLE`` are used as they are; ``OPENCV``,
``RADIAL`` and ``SIMPLE_RADIAL`` (``k1 k2 k3 p1 p2``, OpenCV's radial-tangential model) are
undistorted with ``cv2.initUndistortRectifyMap`` to a pinhole camera of the same size that
keeps only valid pixels (``cv2.getOptimalNewCameraMatrix`` with alpha 0), before any
downscale; masks go through the same map. Fisheye and other models, and a nonzero ``k4``
(``OPENCV``'s eighth-order term), are refused with a `SceneError` naming the file and the
model.

Checks (each a `SceneError` naming the file and the frame): a field of view in (0, pi), the
principal point inside the image, a pose's bottom row ``[0, 0, 0, 1]`` and its 3x3 block a
rotation, one pose per image file (two frames of one ``file_path`` must agree), JSON that
parses (also when nested too deeply).

Masks: ``mask_path`` when the frames give it (white = object), else the images' alpha
(``alpha > 0.5``, colour composited over black) when they carry it, else none.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np

from neus_l0.errors import SceneError
from neus_l0.formats.neus import area_downscale, check_empty_masks, downscale_matrix, read_image

#: The kinds of transforms.json files this module reads.
KINDS = ("nerf-synthetic", "instant-ngp", "nerfstudio")
#: The splits a scene may hold (``transforms_{split}.json`` or ``{split}_filenames``).
SPLITS = ("train", "val", "test")
#: Models without distortion.
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
#: OpenCV's radial-tangential model (undistorted with cv2).
OPENCV_MODELS = ("OPENCV", "RADIAL", "SIMPLE_RADIAL")
#: Extensions tried when ``file_path`` has none (or names a missing file).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
#: Longest side of the masks the object sphere is searched with (`Views.search_masks`).
SEARCH_SIDE = 128
#: Camera-frame flip between OpenGL (y up, looking down -z) and OpenCV (y down, +z).
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])

_CAMERA_KEYS = ("camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x",
                "camera_angle_y", "k1", "k2", "k3", "k4", "p1", "p2", "is_fisheye")


@dataclasses.dataclass
class Camera:
    """One view's camera as the file gives it.

    Attributes:
        width, height: image size in pixels.
        K: (3, 3) float64 intrinsics, NeuS pixel convention (pixel centres at integers).
        model: the camera model's name (upper case).
        dist: (5,) float64 OpenCV distortion ``k1, k2, p1, p2, k3`` (zeros for pinholes).
    """

    width: int
    height: int
    K: np.ndarray
    model: str
    dist: np.ndarray

    @property
    def distorted(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    def key(self) -> tuple:
        """A hashable identity (views with equal keys share one undistortion map)."""
        return (self.width, self.height, *self.K.ravel().tolist(), *self.dist.tolist())


@dataclasses.dataclass
class TransformsScene:
    """A parsed transforms.json scene (one split), before any image is read.

    Attributes:
        path: the JSON file.
        kind: one of `KINDS`.
        split: ``train``, ``val`` or ``test``.
        image_paths: one image per view.
        mask_paths: one mask per view (``mask_path``), or None.
        cameras: one `Camera` per view.
        c2w: (V, 4, 4) float64 camera-to-world, OpenCV axes, the file's world frame.
        points: (M, 3) float64 sparse points in the same frame (``ply_file_path``), or None.
        applied_transform: (4, 4) nerfstudio's ``applied_transform``, or None.
    """

    path: Path
    kind: str
    split: str
    image_paths: list[Path]
    mask_paths: list[Path] | None
    cameras: list[Camera]
    c2w: np.ndarray
    points: np.ndarray | None = None
    applied_transform: np.ndarray | None = None

    @property
    def n_views(self) -> int:
        return len(self.image_paths)

    @property
    def names(self) -> list[str]:
        """Image paths relative to the JSON file's folder (the views' names)."""
        base = self.path.parent
        return [p.relative_to(base).as_posix() if p.is_relative_to(base) else p.name
                for p in self.image_paths]


@dataclasses.dataclass
class Views:
    """The pixels of a `TransformsScene`, undistorted and downscaled.

    Attributes:
        images: (V, H, W, 3) float32 RGB in [0, 1] (composited over black with alpha).
        masks: (V, H, W) float32 coverage in [0, 1] (soft after a downscale), or None.
        intrinsics: (V, 3, 3) float64 pinhole K after undistortion and downscale.
        mask_source: ``mask_path``, ``alpha`` or ``none``.
        search_masks: (V, h, w) float32 full-resolution masks block-averaged to at most
            `SEARCH_SIDE` pixels (independent of the downscale), or None.
        search_intrinsics: (V, 3, 3) float64 K of `search_masks`, or None.
        undistorted: one line describing the undistortion, or "" when there was none.
    """

    images: np.ndarray
    masks: np.ndarray | None
    intrinsics: np.ndarray
    mask_source: str
    search_masks: np.ndarray | None = None
    search_intrinsics: np.ndarray | None = None
    undistorted: str = ""



def find_transforms(root: str | Path, split: str = "train") -> Path | None:
    """The JSON file of `split` in a folder: ``transforms_{split}.json``, else
    ``transforms.json``; `root` may also be the JSON file itself. None when there is none."""
    root = Path(root)
    if root.is_file() and root.suffix.lower() == ".json":
        return root
    if not root.is_dir():
        return None
    for name in (f"transforms_{split}.json", "transforms.json"):
        if (root / name).is_file():
            return root / name
    return None


def _load_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SceneError(f"{path}: not a readable JSON file ({exc})") from None
    except RecursionError:
        raise SceneError(f"{path}: not a readable JSON file (nested too deeply)") from None
    if not isinstance(data, dict):
        raise SceneError(f"{path}: expected a JSON object with 'frames'")
    return data


def _kind(data: dict, split_file: bool) -> str:
    frames = data.get("frames") or [{}]
    if "camera_model" in data or "ply_file_path" in data or any(
            isinstance(f, dict) and ("fl_x" in f or "mask_path" in f) for f in frames):
        return "nerfstudio"
    if "fl_x" in data or "aabb_scale" in data or "w" in data:
        return "instant-ngp"
    return "nerf-synthetic" if split_file or "camera_angle_x" in data else "instant-ngp"


def _number(path: Path, where: str, key: str, value) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = math.nan
    if not math.isfinite(x):
        raise SceneError(f"{path}: {where}'{key}' must be a finite number, got {value!r}")
    return x


def _focal(path: Path, where: str, key: str, angle: float, side: int) -> float:
    """The focal length, in pixels, of a field of view `angle` (radians) across `side`
    pixels.

    Raises:
        SceneError: an angle outside (0, pi).
    """
    if not 0.0 < angle < math.pi:
        raise SceneError(f"{path}: {where}'{key}' must be a field of view in (0, pi) "
                         f"radians, got {angle:g}")
    return 0.5 * side / math.tan(0.5 * angle)


def _camera(path: Path, top: dict, frame: dict, i: int,
            size_of) -> Camera:
    """The camera of frame `i`: the frame's own keys over the file's (see the module)."""
    merged = {k: top[k] for k in _CAMERA_KEYS if k in top}
    own = {k: frame[k] for k in _CAMERA_KEYS if k in frame}
    for axis in ("x", "y"):  # a frame's field of view replaces the file's focal length
        if f"camera_angle_{axis}" in own and f"fl_{axis}" not in own:
            merged.pop(f"fl_{axis}", None)
    merged.update(own)
    where = f"frame {i}: " if own else ""
    num = lambda k: _number(path, where, k, merged[k])  # noqa: E731
    if "w" in merged and "h" in merged:
        w, h = int(num("w")), int(num("h"))
    else:
        w, h = size_of()
    if "fl_x" in merged:
        fx = num("fl_x")
    elif "camera_angle_x" in merged:
        fx = _focal(path, where, "camera_angle_x", num("camera_angle_x"), w)
    else:
        raise SceneError(f"{path}: {where}no focal length ('fl_x' or 'camera_angle_x')")
    if "fl_y" in merged:
        fy = num("fl_y")
    elif "camera_angle_y" in merged:
        fy = _focal(path, where, "camera_angle_y", num("camera_angle_y"), h)
    else:
        fy = fx
    cx = num("cx") if "cx" in merged else 0.5 * w
    cy = num("cy") if "cy" in merged else 0.5 * h
    if not (fx > 0 and fy > 0 and w > 0 and h > 0):
        raise SceneError(f"{path}: {where}focal lengths and size must be > 0 "
                         f"(fl_x {fx:g}, fl_y {fy:g}, w {w}, h {h})")
    if not (0.0 <= cx <= w and 0.0 <= cy <= h):
        raise SceneError(f"{path}: frame {i}: principal point (cx {cx:g}, cy {cy:g}) lies "
                         f"outside its {w}x{h} image (pixels, from the top-left corner)")
    coef = {k: num(k) if k in merged else 0.0 for k in ("k1", "k2", "k3", "k4", "p1", "p2")}
    distorted = any(v != 0.0 for v in coef.values())
    model = str(merged.get("camera_model", "OPENCV" if distorted else "PINHOLE")).upper()
    if merged.get("is_fisheye"):
        model = "OPENCV_FISHEYE"
    if model in PINHOLE_MODELS:
        if distorted:
            raise SceneError(f"{path}: {where}camera_model {model} with distortion "
                             f"coefficients ({', '.join(k for k, v in coef.items() if v)}): "
                             f"use OPENCV")
    elif model in OPENCV_MODELS:
        if coef["k4"] != 0.0:
            raise SceneError(f"{path}: {where}camera_model {model} with k4 = {coef['k4']:g} "
                             f"is not supported (OpenCV's k1 k2 k3 p1 p2 only); undistort "
                             f"the images first")
    else:
        raise SceneError(f"{path}: {where}camera_model {model} is not supported "
                         f"(supported: {', '.join(PINHOLE_MODELS + OPENCV_MODELS)}); "
                         f"undistort the images to a pinhole camera first")
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    dist = np.array([coef["k1"], coef["k2"], coef["p1"], coef["p2"], coef["k3"]])
    return Camera(width=w, height=h, K=K, model=model, dist=dist)


def _pose(path: Path, frame: dict, i: int) -> np.ndarray:
    """(4, 4) OpenCV camera-to-world of frame `i` (rotation re-orthonormalised)."""
    if "transform_matrix" not in frame:
        raise SceneError(f"{path}: frame {i} has no 'transform_matrix'")
    try:
        m = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape not in ((4, 4), (3, 4)) or not np.isfinite(m).all():
        raise SceneError(f"{path}: frame {i}: 'transform_matrix' must be a finite 4x4 "
                         f"(or 3x4) matrix")
    if m.shape == (4, 4) and np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        raise SceneError(f"{path}: frame {i}: 'transform_matrix' bottom row must be "
                         f"[0, 0, 0, 1], got {m[3].tolist()}")
    c2w = np.eye(4)
    c2w[:3] = m[:3]
    R = c2w[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        raise SceneError(f"{path}: frame {i}: 'transform_matrix' is not a rigid pose "
                         f"(its 3x3 block is not a rotation)")
    u, _, vt = np.linalg.svd(R)
    c2w[:3, :3] = u @ vt
    return c2w @ OPENGL_TO_OPENCV


def _check_repeats(path: Path, image_paths: list[Path], c2w: np.ndarray) -> None:
    """One image in two frames must have one pose.

    Args:
        image_paths: (V,) the frames' image files; c2w: (V, 4, 4) their poses.

    Raises:
        SceneError: naming both frames and the image.
    """
    first: dict[Path, int] = {}
    for i, p in enumerate(image_paths):
        j = first.setdefault(p.resolve(), i)
        if j != i and not np.allclose(c2w[i], c2w[j], rtol=0.0,
                                      atol=1e-6 * max(1.0, np.abs(c2w[j]).max())):
            raise SceneError(f"{path}: frames {j} and {i} both show '{p.name}' but with "
                             f"different poses: one image has one camera")


def _find_file(path: Path, frame: dict, i: int, key: str) -> Path:
    rel = frame.get(key)
    if not isinstance(rel, str) or not rel:
        raise SceneError(f"{path}: frame {i} has no '{key}'")
    p = path.parent / rel
    if p.is_file():
        return p
    for suffix in IMAGE_SUFFIXES:
        q = p.with_name(p.name + suffix)
        if q.is_file():
            return q
    raise SceneError(f"{path}: frame {i}: {key} '{rel}' not found (also tried "
                     f"{', '.join(IMAGE_SUFFIXES[:3])})")


def _read_ply_points(path: Path, rel: str) -> np.ndarray:
    import trimesh

    p = path.parent / rel
    if not p.is_file():
        raise SceneError(f"{path}: ply_file_path '{rel}' not found")
    try:
        pc = trimesh.load(p, process=False)
        pts = np.asarray(pc.vertices, dtype=np.float64).reshape(-1, 3)
    except Exception as exc:  # noqa: BLE001 - any parse failure is the user's file
        raise SceneError(f"{p}: unreadable point cloud ({exc})") from None
    if not np.isfinite(pts).all():
        raise SceneError(f"{p}: non-finite points")
    return pts


def read_transforms(root: str | Path, split: str = "train") -> TransformsScene:
    """Parse a transforms.json scene's `split` (no pixel is read, except the first image's
    size when the file gives none).

    Split: ``transforms_{split}.json`` when it exists; else ``transforms.json``, whose
    frames are all in ``train`` unless it lists ``{split}_filenames`` (nerfstudio).

    Raises:
        SceneError: no such file or split, missing fields, missing images or masks, an
            unsupported camera model.
    """
    if split not in SPLITS:
        raise SceneError(f"{root}: split must be one of {', '.join(SPLITS)}, got '{split}'")
    path = find_transforms(root, split)
    if path is None:
        raise SceneError(f"{root}: no transforms_{split}.json or transforms.json")
    data = _load_json(path)
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise SceneError(f"{path}: no 'frames' list (or it is empty)")
    if any(not isinstance(f, dict) for f in frames):
        raise SceneError(f"{path}: every entry of 'frames' must be an object")
    split_file = path.name == f"transforms_{split}.json"
    listed = data.get(f"{split}_filenames")
    if not split_file and listed is not None:
        wanted = {str(Path(f)) for f in listed}
        frames = [f for f in frames if str(Path(str(f.get("file_path", "")))) in wanted]
        if not frames:
            raise SceneError(f"{path}: no frame matches '{split}_filenames'")
    elif not split_file and split != "train":
        raise SceneError(f"{path}: no {split} split (no transforms_{split}.json and no "
                         f"'{split}_filenames')")

    image_paths = [_find_file(path, f, i, "file_path") for i, f in enumerate(frames)]
    with_mask = ["mask_path" in f for f in frames]
    mask_paths = None
    if any(with_mask):
        if not all(with_mask):
            raise SceneError(f"{path}: frame {with_mask.index(False)} has no 'mask_path' "
                             f"but others do")
        mask_paths = [_find_file(path, f, i, "mask_path") for i, f in enumerate(frames)]

    size: list[tuple[int, int]] = []

    def size_of() -> tuple[int, int]:
        if not size:
            img, _ = read_image(image_paths[0])
            size.append((img.shape[1], img.shape[0]))
        return size[0]

    cameras = [_camera(path, data, f, i, size_of) for i, f in enumerate(frames)]
    c2w = np.stack([_pose(path, f, i) for i, f in enumerate(frames)])
    _check_repeats(path, image_paths, c2w)
    points = None
    if isinstance(data.get("ply_file_path"), str):
        points = _read_ply_points(path, data["ply_file_path"])
    applied = None
    if "applied_transform" in data:
        try:
            a = np.asarray(data["applied_transform"], dtype=np.float64)
            applied = np.eye(4)
            applied[: a.shape[0]] = a
        except (TypeError, ValueError, IndexError):
            raise SceneError(f"{path}: 'applied_transform' must be a 3x4 or 4x4 "
                             f"matrix") from None
    return TransformsScene(path=path, kind=_kind(data, split_file), split=split,
                           image_paths=image_paths, mask_paths=mask_paths, cameras=cameras,
                           c2w=c2w, points=points, applied_transform=applied)


def undistort_map(cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pinhole camera of `cam`'s size that keeps only valid pixels, and the maps.

    Returns:
        K_new: (3, 3) float64 (NeuS pixel convention);
        map_x, map_y: (H, W) float32 source coordinates for ``cv2.remap``.
    """
    size = (cam.width, cam.height)
    K_new, _ = cv2.getOptimalNewCameraMatrix(cam.K, cam.dist, size, 0.0, size)
    map_x, map_y = cv2.initUndistortRectifyMap(cam.K, cam.dist, None, K_new, size,
                                               cv2.CV_32FC1)
    return np.asarray(K_new, dtype=np.float64), map_x, map_y


def _read_view(path: Path, cam, mask_path: Path | None, shape: tuple[int, int],
               maps: dict, json_name: str) -> tuple[np.ndarray, np.ndarray | None, bool,
                                                    np.ndarray]:
    """One frame: colour (composited over black where it has alpha), its mask (from
    `mask_path`, else the alpha; None), whether it had alpha, and its pinhole K, all
    undistorted when the camera is (`maps` caches the remaps by camera)."""
    H, W = shape
    rgb, alpha = read_image(path, shape)
    if (cam.width, cam.height) != (W, H):
        raise SceneError(f"{path}: size {W}x{H} differs from the camera's "
                         f"{cam.width}x{cam.height} in {json_name}")
    fg = None
    if mask_path is not None:
        m, _ = read_image(mask_path, shape)
        fg = (m.max(axis=-1) > 0.5).astype(np.float32)
    elif alpha is not None:
        fg = (alpha > 0.5).astype(np.float32)
    if alpha is not None:
        rgb = rgb * alpha[..., None]
    K = cam.K
    if cam.distorted:
        if cam.key() not in maps:
            maps[cam.key()] = undistort_map(cam)
        K, mx, my = maps[cam.key()]
        rgb = cv2.remap(rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        if fg is not None:
            fg = cv2.remap(fg, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            fg = (fg > 0.5).astype(np.float32)
    return rgb, fg, alpha is not None, K


def _mask_source(ts: TransformsScene, have_alpha: list[bool], masks: np.ndarray) -> str:
    """Where the masks came from: ``mask_path``, ``alpha`` or ``none``.

    Raises:
        SceneError: some images with alpha and some without.
    """
    if ts.mask_paths is not None:
        return "mask_path"
    if all(have_alpha):
        return "none" if masks.min() >= 1.0 else "alpha"  # opaque alpha: no information
    if any(have_alpha):
        odd = ts.image_paths[have_alpha.index(not have_alpha[0])]
        raise SceneError(f"{odd}: {'no' if have_alpha[0] else 'an'} alpha channel, unlike "
                         f"{ts.image_paths[0].name}: give every image alpha or none")
    return "none"


def _undistortion_note(ts: TransformsScene, maps: dict) -> str:
    """One line on what was undistorted and how the focal length changed."""
    n = sum(cam.distorted for cam in ts.cameras)
    cam = next(c for c in ts.cameras if c.distorted)
    k1, k2, p1, p2, k3 = cam.dist
    K_new = maps[cam.key()][0]
    return (f"undistorted {n} of {ts.n_views} views ({cam.model} k1 {k1:.4g} k2 {k2:.4g} "
            f"k3 {k3:.4g} p1 {p1:.4g} p2 {p2:.4g}) to pinhole cameras with OpenCV "
            f"(valid pixels only: focal {cam.K[0, 0]:.1f} -> {K_new[0, 0]:.1f} px)")


def load_views(ts: TransformsScene, downscale: int = 1, search: bool = True) -> Views:
    """Read, undistort and downscale the images and masks of a parsed scene.

    Args:
        ts: the parsed scene.
        downscale: integer factor >= 1 (as `neus_l0.formats.neus.load_scene`).
        search: also keep the full-resolution masks block-averaged to `SEARCH_SIDE`
            (`Views.search_masks`, what the object sphere is searched with).

    Raises:
        SceneError: unreadable or differently sized images, images whose size is not the
            camera's, every mask empty.
    """
    s = int(downscale)
    if s != downscale or s < 1:
        raise SceneError(f"{ts.path}: downscale must be an integer >= 1, got {downscale}")
    first, _ = read_image(ts.image_paths[0])
    H, W = first.shape[:2]
    if H < s or W < s:
        raise SceneError(f"{ts.image_paths[0]}: {W}x{H} is too small for downscale {s}")
    s_search = max(1, math.ceil(max(H, W) / SEARCH_SIDE))
    V = ts.n_views
    images = np.empty((V, H // s, W // s, 3), np.float32)
    masks = np.empty((V, H // s, W // s), np.float32)
    search_masks = np.empty((V, H // s_search, W // s_search), np.float32) if search else None
    Ks = np.empty((V, 3, 3))
    Ks_full = np.empty((V, 3, 3))
    maps: dict[tuple, tuple] = {}
    have_alpha: list[bool] = []
    empty: list[Path] = []
    for i, (p, cam) in enumerate(zip(ts.image_paths, ts.cameras, strict=True)):
        mask_path = ts.mask_paths[i] if ts.mask_paths is not None else None
        rgb, fg, has_alpha, K = _read_view(p, cam, mask_path, (H, W), maps, ts.path.name)
        have_alpha.append(has_alpha)
        images[i] = area_downscale(rgb, s) if s > 1 else rgb
        Ks_full[i] = K
        Ks[i] = downscale_matrix(s) @ K
        if fg is not None:
            if not fg.any():
                empty.append(ts.mask_paths[i] if ts.mask_paths is not None else p)
            masks[i] = area_downscale(fg, s) if s > 1 else fg
            if search_masks is not None:
                search_masks[i] = area_downscale(fg, s_search) if s_search > 1 else fg
    source = _mask_source(ts, have_alpha, masks)
    if source != "none":
        check_empty_masks(empty, V, ts.path)
    undistorted = _undistortion_note(ts, maps) if maps else ""
    has = source != "none"
    keep_search = has and search_masks is not None
    return Views(images=images, masks=masks if has else None, intrinsics=Ks,
                 mask_source=source, search_masks=search_masks if keep_search else None,
                 search_intrinsics=downscale_matrix(s_search) @ Ks_full if keep_search else None,
                 undistorted=undistorted)
