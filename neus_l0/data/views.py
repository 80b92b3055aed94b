"""Which file is which view: images, masks and cameras paired by the number in their names.

A NeuS-format folder names its views by number: ``image/000.png`` goes with
``mask/000.png`` and with ``world_mat_0`` / ``scale_mat_0`` in ``cameras_sphere.npz``.
Pairing by sorted position instead breaks on names people's own scripts write (``0.png ...
11.png`` sorts as 0, 1, 10, 11, 2, ...) and on a deleted view (every later view would take
its neighbour's camera), silently. So the view index is the last integer in a file's name
(`view_index`), and images, masks and cameras pair by it (`pair_views`). DTU's
``000000.png`` images with ``000.png`` masks pair as views 0 too.

Pure file-system and NumPy-free code; `neus_l0.data.scene` (the loader) and
`neus_l0.data.cameras` (the light readers evaluation uses) both pair through it.
"""

from __future__ import annotations

import dataclasses
import re
import sys
from collections.abc import Iterable
from pathlib import Path

from neus_l0.errors import SceneError

#: Image files a view folder may hold.
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")

#: How views pair, in one line (`neus-l0 inspect` prints it).
PAIRING_RULE = ("views pair by the last number in each file name: image/N.*, mask/N.* and "
                "world_mat_N / scale_mat_N")

_LAST_INT = re.compile(r"(\d+)(?!.*\d)")


def view_index(path: str | Path) -> int | None:
    """The last integer in a file's stem (``image_12.jpg`` -> 12, ``000.png`` -> 0), or
    None when the stem has no digit."""
    m = _LAST_INT.search(Path(path).stem)
    return int(m.group(1)) if m else None


def _names(paths: Iterable[Path], limit: int = 5) -> str:
    paths = list(paths)
    shown = ", ".join(p.name for p in paths[:limit])
    return shown + (f", ... ({len(paths)} in all)" if len(paths) > limit else "")


def indexed_files(folder: Path) -> dict[int, Path]:
    """The view files of `folder` by their index, in index order.

    Hidden files (``.DS_Store``, macOS's ``._000.png`` resource forks) are not views.

    Raises:
        SceneError: a file with no number in its name, or two files with one number.
    """
    files = sorted(p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
                   and not p.name.startswith("."))
    out: dict[int, Path] = {}
    for p in files:
        i = view_index(p)
        if i is None:
            raise SceneError(f"{p}: no view number in the file name ({PAIRING_RULE})")
        if i in out:
            raise SceneError(f"{folder}: {out[i].name} and {p.name} are both view {i} "
                             f"({PAIRING_RULE})")
        out[i] = p
    return dict(sorted(out.items()))


@dataclasses.dataclass
class ViewPairing:
    """The views a folder holds, paired by index.

    Attributes:
        indices: the view indices used, ascending.
        images: the image of each, in that order.
        masks: the mask of each, or None without a ``mask/`` folder.
        unused_cameras: camera indices with no image (left out of training).
        unused_masks: masks with no image (ignored).
    """

    indices: list[int]
    images: list[Path]
    masks: list[Path] | None
    unused_cameras: list[int] = dataclasses.field(default_factory=list)
    unused_masks: list[Path] = dataclasses.field(default_factory=list)


def pair_views(images: dict[int, Path], masks: dict[int, Path] | None,
               cameras: Iterable[int], camera_file: Path) -> ViewPairing:
    """Pair images, masks and cameras by view index (module docstring).

    Args:
        images, masks: `indexed_files` of ``image/`` and ``mask/`` (None: no mask folder).
        cameras: the indices i of the camera file's ``world_mat_i``.
        camera_file: named in errors.

    Raises:
        SceneError: an image without its camera, or without its mask when there are masks.
    """
    cams = set(cameras)
    no_camera = [i for i in images if i not in cams]
    if no_camera:
        shown = ", ".join(f"world_mat_{i} ({images[i].name})" for i in no_camera[:5])
        more = f", ... ({len(no_camera)} in all)" if len(no_camera) > 5 else ""
        raise SceneError(f"{camera_file}: missing {shown}{more} ({PAIRING_RULE})")
    if masks is not None:
        no_mask = [p for i, p in images.items() if i not in masks]
        if no_mask:
            folder = next(iter(masks.values())).parent if masks else "mask/"
            raise SceneError(f"{folder}: no mask for {_names(no_mask)} ({PAIRING_RULE})")
    idx = list(images)
    return ViewPairing(
        indices=idx, images=[images[i] for i in idx],
        masks=[masks[i] for i in idx] if masks is not None else None,
        unused_cameras=sorted(cams - set(images)),
        unused_masks=[p for i, p in (masks or {}).items() if i not in images])


def warn_unused(pairing: ViewPairing, camera_file: Path) -> None:
    """One line on stderr for cameras without an image and masks without an image."""
    if pairing.unused_cameras:
        shown = ", ".join(f"world_mat_{i}" for i in pairing.unused_cameras[:8])
        more = ", ..." if len(pairing.unused_cameras) > 8 else ""
        print(f"neus-l0: warning: {camera_file}: {len(pairing.unused_cameras)} camera(s) have "
              f"no image ({shown}{more}); training uses the {len(pairing.indices)} views that "
              "have both", file=sys.stderr, flush=True)
    if pairing.unused_masks:
        print(f"neus-l0: warning: {pairing.unused_masks[0].parent}: masks with no image are "
              f"ignored: {_names(pairing.unused_masks)}", file=sys.stderr, flush=True)
