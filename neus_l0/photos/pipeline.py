"""Own photos -> a NeuS-format scene, the whole chain behind `neus-l0 colmap`.

Stages: check the photos -> SfM (feature extraction, matching, incremental mapping; or an
existing COLMAP model) -> the object sphere (automatic or given) -> undistortion to a pinhole
camera and the NeuS-format scene -> a preview PNG and ``colmap_summary.json``. See
docs/PHOTOS.md.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from neus_l0.data.image_io import imread_bytes
from neus_l0.errors import NeusL0Error

#: What `neus-l0 colmap` writes at the top of its scene folder (its own, for --out checks).
PHOTO_SCENE_NAMES = ("image", "mask", "cameras_sphere.npz", "sources.txt", "unregistered.txt",
                     "colmap_summary.json", "sphere_preview.png", "colmap", "sparse_points.npz")
#: Views shown in sphere_preview.png.
PREVIEW_VIEWS = 4


@dataclasses.dataclass
class PhotoOptions:
    """What `neus-l0 colmap` was asked for.

    Attributes:
        photos: the folder of photos; out: the scene folder to write.
        masks: a folder of foreground masks (same stems), or None.
        sparse: an existing COLMAP sparse model to use instead of SfM, or None.
        sfm: the SfM settings (`neus_l0.photos.sfm.SfmOptions`; unused with `sparse`).
        max_size: longest side of the written images (-1: full size).
        sphere: ``(centre (3,), radius)`` given by the user, or None to choose one.
        progress: show progress bars.
    """

    photos: Path
    out: Path
    sfm: object
    masks: Path | None = None
    sparse: Path | None = None
    max_size: int = 1600
    sphere: tuple[list[float], float] | None = None
    progress: bool = True


def photos_to_scene(opts: PhotoOptions) -> dict:
    """Run the chain (module docstring) and return the summary (also written as
    ``OUT/colmap_summary.json``), with ``explain`` (how the sphere was chosen) and
    ``unregistered_file`` added for the command to print.

    Raises:
        NeusL0Error: a missing mask folder, a model that does not match the photos, SfM
            that registers too few photos (each names the file or folder).
    """
    from neus_l0.atomic import atomic_write_text
    from neus_l0.photos import sfm
    from neus_l0.photos.export import export_scene, find_masks

    t_start = time.perf_counter()
    if opts.masks is not None and not Path(opts.masks).is_dir():
        raise NeusL0Error(f"{opts.masks}: mask folder not found")
    print(f"checking photos in {opts.photos}")
    paths, sizes = sfm.list_photos(opts.photos, same_size=opts.sparse is None)
    names = [p.name for p in paths]
    print(f"      {len(names)} photos")
    model, timings = _cameras(opts, names, sizes)
    registered = set(model.names)
    missing = [n for n in names if n not in registered]
    atomic_write_text(opts.out / "unregistered.txt", "".join(f"{n}\n" for n in missing))
    sphere = _sphere(opts, model)
    masks = find_masks(opts.masks, model.names) if opts.masks is not None else None
    print(f"writing the NeuS scene to {opts.out}")
    info = export_scene(opts.out, model, opts.photos, sphere.center, sphere.radius, masks=masks,
                        max_size=opts.max_size, progress=opts.progress)
    _preview(opts.out, model, info, sphere)
    summary = {
        "photos": len(names), "registered": model.n_views, "unregistered": missing,
        "points3D": int(len(model.points)), "size": list(info["size"]),
        "source": "sparse model " + str(opts.sparse) if opts.sparse else "pycolmap SfM",
        "timings_s": {k: (round(v, 2) if isinstance(v, float) else v)
                      for k, v in timings.items()},
        "sphere": {"center": [float(v) for v in sphere.center], "radius": sphere.radius,
                   "source": sphere.source, "convergence": [float(v) for v in
                                                            sphere.convergence],
                   "points_used": sphere.n_points, "capped": sphere.capped},
        "masks": masks is not None,
        "seconds": round(time.perf_counter() - t_start, 2),
    }
    atomic_write_text(opts.out / "colmap_summary.json", json.dumps(summary, indent=2) + "\n")
    return {**summary, "explain": sphere.explain(),
            "unregistered_file": str(opts.out / "unregistered.txt")}


def _cameras(opts: PhotoOptions, names: list[str], sizes: dict):
    """The sparse model: read from ``opts.sparse`` (checked against the photos) or made by
    SfM. Returns the model and SfM's timings."""
    from neus_l0.photos import sfm, sparse_io

    if opts.sparse is None:
        models, timings = sfm.run_sfm(opts.photos, names, opts.out / "colmap", opts.sfm,
                                      progress=opts.progress)
        return sfm.check_models(models, len(names), opts.photos), timings
    print(f"reading the sparse model {opts.sparse}")
    model = sparse_io.read_model(opts.sparse)
    for name, cid in zip(model.names, model.camera_ids, strict=True):
        if name not in sizes:
            raise NeusL0Error(f"{opts.sparse}: image '{name}' of the model is not in "
                              f"{opts.photos}")
        cam = model.cameras[int(cid)]
        if sizes[name] != (cam.width, cam.height):
            raise NeusL0Error(f"{opts.photos / name}: size {sizes[name][0]}x{sizes[name][1]} "
                              f"differs from its camera's {cam.width}x{cam.height} in "
                              f"{opts.sparse}")
    return sfm.check_models([model], len(names), opts.photos), {}


def _sphere(opts: PhotoOptions, model):
    """The object sphere: the user's, or chosen from the sparse points."""
    from neus_l0.formats.sphere import choose_sphere, given_sphere

    if opts.sphere is not None:
        center, radius = opts.sphere
        return given_sphere(np.array(center), radius, model.centres, model.axes)
    return choose_sphere(model.points, model.track_len, model.centres, model.axes)


def _preview(out: Path, model, info: dict, sphere) -> None:
    """``OUT/sphere_preview.png``: the sphere drawn over `PREVIEW_VIEWS` of the views."""
    import cv2

    from neus_l0.formats.preview import write_preview

    picks = np.unique(np.linspace(0, model.n_views - 1, min(PREVIEW_VIEWS, model.n_views))
                      .round().astype(int))
    images = [cv2.cvtColor(imread_bytes(out / "image" / f"{i:03d}.png", cv2.IMREAD_COLOR),
                           cv2.COLOR_BGR2RGB) for i in picks]
    write_preview(out / "sphere_preview.png", images, [info["world_mats"][i] for i in picks],
                  model.points, sphere.center, sphere.radius,
                  titles=[model.names[i] for i in picks])
