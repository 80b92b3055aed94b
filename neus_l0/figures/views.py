"""Cameras of the figures: an overview scene camera, a virtual camera per feature, crop boxes.

A camera is a NeuS projection ``P`` (3, 4) world -> pixels (pixel centres at integers) and
an image size. Features are a synthetic scene's (`neus_l0.evaluation.features.load_features`):
``kind`` (pit | thin), ``name``, ``center`` (3,), ``radius``, ``axis`` (3,) or null; on a
scene without ground truth, the places where the meshes differ most
(`neus_l0.figures.real.disagreement_regions`, ``kind`` region, no axis).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from neus_l0.data.cameras import (
    camera_z_depth,
    decompose_projection,
    look_at,
    read_world_mats,
    scale_projection,
)
from neus_l0.data.image_io import imread_bytes

#: Half-width of a crop box, in feature radii.
CROP_MARGIN = 1.3
#: Angle (degrees) between a pit camera's view and the pit axis (0 = straight down it).
PIT_TILT_DEG = 25.0
#: Elevation (degrees) of a thin-structure camera above the plane normal to its axis.
THIN_TILT_DEG = 20.0


@dataclasses.dataclass
class Camera:
    """A pinhole camera: ``P`` (3, 4) world -> pixels, image ``width`` x ``height``."""

    P: np.ndarray
    width: int
    height: int

    @property
    def centre(self) -> np.ndarray:
        """(3,) camera centre in world units."""
        return decompose_projection(self.P)[1][:3, 3]

    @property
    def up(self) -> np.ndarray:
        """(3,) unit world direction that points up (-y) in the image."""
        return -decompose_projection(self.P)[1][:3, 1]

    def scaled(self, factor: float) -> Camera:
        """The same view at `factor` times the resolution (pixel centres stay at integers)."""
        return Camera(scale_projection(self.P, factor), int(round(self.width * factor)),
                      int(round(self.height * factor)))


def scene_cameras(scene_dir: str | Path) -> list[Camera]:
    """The cameras of a NeuS-format scene (``cameras_sphere.npz``; size from ``scene.json``
    or the first image)."""
    scene_dir = Path(scene_dir)
    world_mats = read_world_mats(scene_dir)  # (V, 3, 4)
    info = scene_dir / "scene.json"
    if info.is_file():
        meta = json.loads(info.read_text())
        w, h = int(meta["width"]), int(meta["height"])
    else:
        import cv2

        img = imread_bytes(sorted((scene_dir / "image").glob("*.png"))[0], cv2.IMREAD_COLOR)
        h, w = img.shape[:2]
    return [Camera(P, w, h) for P in world_mats]


def crop_box(cam: Camera, center: np.ndarray, radius: float,
             margin: float = CROP_MARGIN) -> np.ndarray:
    """Square pixel box (x0, y0, x1, y1) around a feature's projection.

    The half-width is the projected size of ``margin * radius`` at the feature's depth.
    """
    K, _ = decompose_projection(cam.P)
    xy, z = camera_z_depth(cam.P, np.asarray(center, np.float64)[None])
    half = margin * radius * K[0, 0] / max(float(z[0]), 1e-9)
    x, y = xy[0]
    return np.array([x - half, y - half, x + half, y + half])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _perpendicular(v: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Unit part of `v` normal to the unit `axis` (any normal direction if v is along it)."""
    p = v - (v @ axis) * axis
    if np.linalg.norm(p) < 1e-6:
        p = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    return _unit(p)


def feature_camera(feature: dict, ref: Camera, size: int = 192,
                   margin: float = CROP_MARGIN) -> Camera:
    """A virtual camera looking at one feature from the side of the reference camera.

    Pits are seen from above, `PIT_TILT_DEG` off their axis (so the bottom and a wall
    show); thin structures from the side, `THIN_TILT_DEG` above the plane normal to their
    axis; a feature without an axis straight from the reference camera's side, upright as
    in the reference camera's image. The eye is as far from the feature as the reference
    camera; the focal length makes ``margin * radius`` fill half the `size` x `size` image.
    """
    c = feature["center"]
    eye_ref = ref.centre
    to_ref = _unit(eye_ref - c)
    axis = feature["axis"]
    if axis is None:
        view = to_ref
        up = ref.up
    else:
        axis = _unit(axis)
        if axis @ to_ref < 0:  # the axis points towards the open side / the viewer
            axis = -axis
        side = _perpendicular(to_ref, axis)
        if feature.get("kind") == "pit":
            tilt = np.radians(PIT_TILT_DEG)
            view = np.cos(tilt) * axis + np.sin(tilt) * side
            up = -side
        else:
            tilt = np.radians(THIN_TILT_DEG)
            view = np.cos(tilt) * side + np.sin(tilt) * axis
            up = axis
    dist = float(np.linalg.norm(eye_ref - c))
    eye = c + dist * view
    w2c = look_at(eye, c, up)
    f = 0.5 * size * dist / (margin * feature["radius"])
    K = np.array([[f, 0.0, (size - 1) / 2], [0.0, f, (size - 1) / 2], [0.0, 0.0, 1.0]])
    return Camera(K @ w2c[:3, :4], size, size)


def overview_camera(cams: list[Camera], features: list[dict]) -> int:
    """Index of the scene camera that sees the most features whole (ties: looks most
    along the pits' axes, i.e. into them; features without an axis, such as regions, count
    only as seen or not; then the first camera)."""
    centres = np.stack([f["center"] for f in features]) if features else np.zeros((0, 3))
    best, best_score = 0, -np.inf
    for i, cam in enumerate(cams):
        if len(centres) == 0:
            return 0
        boxes = np.stack([crop_box(cam, f["center"], f["radius"], 1.0) for f in features])
        _, z = camera_z_depth(cam.P, centres)
        inside = ((boxes[:, 0] >= 0) & (boxes[:, 1] >= 0) & (boxes[:, 2] <= cam.width - 1)
                  & (boxes[:, 3] <= cam.height - 1) & (z > 0))
        into = [abs(_unit(cam.centre - f["center"]) @ _unit(f["axis"]))
                for f in features if f["kind"] == "pit" and f["axis"] is not None]
        score = inside.sum() + (float(np.mean(into)) if into else 0.0)
        if score > best_score:
            best, best_score = i, score
    return best
