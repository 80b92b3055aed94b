"""Export a NeuS-format scene as a transforms.json scene in a moved world frame.

Usage:
    python tools/export_transforms.py SCENE OUT [--kind nerfstudio|ngp|blender]
        [--rotate DEG] [--scale S] [--translate X Y Z] [--rgba] [--holdout N]

The new world frame is ``x_new = S * R @ x + T``: R turns by DEG degrees about the fixed
axis (1, 2, 3) / |(1, 2, 3)| (a generic rotation), S and T as given. No NeuS normalisation
is written: the loader has to find the object sphere itself. ``similarity.json`` holds the
4x4 maps ``new_to_original`` and ``original_to_new``, so that a mesh made from OUT can be
mapped back and scored against SCENE's ground truth (``gt_mesh.ply``, ``gt_points.ply``).

Kinds (cameras are OpenGL camera-to-world; intrinsics with the top-left pixel's centre at
(0.5, 0.5), i.e. NeuS's K with 0.5 added to cx, cy):

- ``nerfstudio``: ``transforms.json``, ``camera_model`` PINHOLE, per-frame ``fl_x fl_y cx
  cy w h``, ``images/frame_NNNNN.png`` and per-frame ``mask_path`` (``masks/``).
- ``ngp``: ``transforms.json`` with global ``fl_x fl_y cx cy w h``, zero ``k1 k2 p1 p2``,
  ``aabb_scale`` 1; ``images/NNN.png``; masks only with ``--rgba``.
- ``blender``: ``transforms_train.json`` (and ``_val``/``_test`` with ``--holdout N``: every
  Nth view moves there) with ``camera_angle_x`` only and extension-less ``file_path``
  (``./train/r_N``). That format has no principal point, so each image is shifted by the
  sub-pixel offset that centres it (bilinear ``cv2.warpAffine``); fx must equal fy.

``--rgba`` writes the images as RGBA PNGs with alpha = mask (colour unchanged).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np

from neus_l0.atomic import atomic_write_json, atomic_write_png
from neus_l0.data.cameras import decompose_projection, read_world_mats
from neus_l0.formats.transforms import OPENGL_TO_OPENCV

AXIS = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)


def similarity(rotate_deg: float, scale: float, translate) -> np.ndarray:
    """(4, 4) original -> new world: ``x_new = scale * R @ x + translate``."""
    rvec = AXIS * math.radians(rotate_deg)
    R, _ = cv2.Rodrigues(rvec)
    T = np.eye(4)
    T[:3, :3] = scale * R
    T[:3, 3] = np.asarray(translate, dtype=np.float64)
    return T


def move_pose(c2w: np.ndarray, T: np.ndarray) -> np.ndarray:
    """A camera-to-world pose (4, 4) carried into the new frame (rotation stays rigid)."""
    s = np.cbrt(np.linalg.det(T[:3, :3]))
    out = np.eye(4)
    out[:3, :3] = (T[:3, :3] / s) @ c2w[:3, :3]
    out[:3, 3] = T[:3, :3] @ c2w[:3, 3] + T[:3, 3]
    return out


def _images(scene: Path) -> tuple[list[Path], list[Path] | None]:
    images = sorted((scene / "image").glob("*.png"))
    masks = sorted((scene / "mask").glob("*.png")) if (scene / "mask").is_dir() else None
    if not images:
        raise SystemExit(f"{scene / 'image'}: no PNG images")
    if masks is not None and len(masks) != len(images):
        raise SystemExit(f"{scene / 'mask'}: {len(masks)} masks for {len(images)} images")
    return images, masks


def _write_image(path: Path, img: np.ndarray, mask: np.ndarray | None, rgba: bool) -> None:
    if rgba:
        if mask is None:
            raise SystemExit("--rgba needs the scene's mask/ folder")
        img = np.dstack([img, np.where(mask > 127, 255, 0).astype(np.uint8)])
    atomic_write_png(path, img)


def export(scene: Path, out: Path, kind: str = "nerfstudio", rotate: float = 0.0,
           scale: float = 1.0, translate=(0.0, 0.0, 0.0), rgba: bool = False,
           holdout: int = 0) -> dict:
    """Write OUT (module docstring) and return what ``similarity.json`` holds."""
    images, masks = _images(scene)
    mats = read_world_mats(scene)
    if len(mats) != len(images):
        raise SystemExit(f"{scene}: {len(mats)} cameras for {len(images)} images")
    T = similarity(rotate, scale, translate)
    out.mkdir(parents=True, exist_ok=True)
    frames, split_of = [], []
    top: dict = {}
    for i, (img_path, P) in enumerate(zip(images, mats, strict=True)):
        K, c2w = decompose_projection(P)
        c2w_gl = move_pose(c2w, T) @ OPENGL_TO_OPENCV
        img = cv2.imread(str(img_path), cv2.IMREAD_COLOR)
        mask = None if masks is None else cv2.imread(str(masks[i]), cv2.IMREAD_GRAYSCALE)
        H, W = img.shape[:2]
        frame = {"transform_matrix": c2w_gl.tolist()}
        if kind == "blender":
            if abs(K[0, 0] - K[1, 1]) > 1e-6 * K[0, 0] or abs(K[0, 1]) > 1e-9:
                raise SystemExit(f"{scene}: view {i} has fx != fy or skew: not expressible "
                                 f"with camera_angle_x")
            shift = np.array([[1.0, 0.0, (W - 1) / 2 - K[0, 2]],
                              [0.0, 1.0, (H - 1) / 2 - K[1, 2]]])
            img = cv2.warpAffine(img, shift, (W, H), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE)
            if mask is not None:
                mask = cv2.warpAffine(mask, shift, (W, H), flags=cv2.INTER_LINEAR,
                                      borderMode=cv2.BORDER_REPLICATE)
            split = "test" if holdout and i % holdout == 0 else "train"
            rel = f"./{split}/r_{i}"
            _write_image(out / f"{rel}.png", img, mask, rgba)
            frame["file_path"] = rel
            top["camera_angle_x"] = 2.0 * math.atan(0.5 * W / K[0, 0])
            split_of.append(split)
        else:
            cam = {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2] + 0.5, "cy": K[1, 2] + 0.5,
                   "w": W, "h": H}
            name = f"images/frame_{i + 1:05d}.png" if kind == "nerfstudio" else \
                f"images/{i:03d}.png"
            _write_image(out / name, img, mask, rgba)
            frame["file_path"] = name
            if kind == "nerfstudio":
                frame.update(cam)
                if mask is not None and not rgba:
                    mname = f"masks/frame_{i + 1:05d}.png"
                    atomic_write_png(out / mname, mask)
                    frame["mask_path"] = mname
            else:
                top.update(cam, k1=0.0, k2=0.0, p1=0.0, p2=0.0, aabb_scale=1)
            split_of.append("train")
        frames.append(frame)
    if kind == "blender":
        for split in ("train", "val", "test"):
            chosen = [f for f, s in zip(frames, split_of, strict=True)
                      if s == ("test" if split == "val" else split)]
            if chosen:
                atomic_write_json(out / f"transforms_{split}.json", {**top, "frames": chosen})
    elif kind == "nerfstudio":
        atomic_write_json(out / "transforms.json", {"camera_model": "PINHOLE",
                                                    "frames": frames})
    else:
        atomic_write_json(out / "transforms.json", {**top, "frames": frames})
    info = {"new_to_original": np.linalg.inv(T).tolist(), "original_to_new": T.tolist(),
            "rotate_deg": rotate, "axis": AXIS.tolist(), "scale": scale,
            "translate": list(map(float, translate)), "kind": kind, "rgba": rgba,
            "source": str(scene)}
    atomic_write_json(out / "similarity.json", info)
    for name in ("gt_mesh.ply", "gt_points.ply"):
        if (scene / name).is_file():  # the truth stays in the original frame, for scoring
            shutil.copy(scene / name, out / f"original_{name}")
    return info


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", type=Path, help="NeuS-format scene (image/, mask/, cameras)")
    p.add_argument("out", type=Path, help="folder to write")
    p.add_argument("--kind", choices=("nerfstudio", "ngp", "blender"), default="nerfstudio")
    p.add_argument("--rotate", type=float, default=0.0, metavar="DEG")
    p.add_argument("--scale", type=float, default=1.0, metavar="S")
    p.add_argument("--translate", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                   metavar=("X", "Y", "Z"))
    p.add_argument("--rgba", action="store_true", help="images with alpha = mask")
    p.add_argument("--holdout", type=int, default=0, metavar="N",
                   help="blender: every Nth view goes to transforms_val/test.json")
    args = p.parse_args()
    if not args.scale > 0:
        raise SystemExit("--scale must be > 0")
    info = export(args.scene, args.out, args.kind, args.rotate, args.scale, args.translate,
                  args.rgba, args.holdout)
    print(json.dumps({"out": str(args.out), "kind": info["kind"],
                      "new_to_original": info["new_to_original"]}))


if __name__ == "__main__":
    main()
