"""`neus-l0 colmap PHOTOS OUT`: turn a folder of photos into a NeuS-format scene with pycolmap.

Stages: check the photos -> SfM (feature extraction, matching, incremental mapping; or an
existing COLMAP model with ``--sparse``) -> the object sphere (automatic or ``--center`` /
``--radius``) -> undistortion to a pinhole camera and the NeuS-format scene -> a preview PNG
and a summary. See docs/PHOTOS.md.
"""

from __future__ import annotations

import argparse

from neus_l0.errors import NeusL0Error

CAMERA_MODEL_CHOICES = ("simple-pinhole", "pinhole", "simple-radial", "radial", "opencv",
                        "full-opencv", "simple-radial-fisheye", "radial-fisheye",
                        "opencv-fisheye")
#: Default longest side of the images features are extracted from and the scene is written at.
DEFAULT_MAX_SIZE = 1600
#: Views shown in sphere_preview.png.
PREVIEW_VIEWS = 4


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(
        name, help="turn a folder of photos into a NeuS-format scene with pycolmap",
        description="Recover the cameras of the photos in PHOTOS with COLMAP (pycolmap, CPU): "
                    "SIFT features, matching, incremental mapping; or read an existing "
                    "COLMAP sparse model with --sparse. Undistort to a pinhole camera, choose "
                    "the object sphere, and write OUT in NeuS format (image/, mask/ with "
                    "--masks, cameras_sphere.npz) plus sources.txt, unregistered.txt, "
                    "sphere_preview.png and colmap_summary.json. See docs/PHOTOS.md.")
    p.add_argument("photos", help="folder of photos (one size, one camera)")
    p.add_argument("out", help="output scene folder")
    p.add_argument("--masks", metavar="DIR",
                   help="foreground masks (white = object), one per photo, same stem")
    p.add_argument("--matcher", choices=("auto", "exhaustive", "sequential"), default="auto",
                   help="feature matcher (default auto: exhaustive up to 100 photos, "
                        "sequential beyond; sequential expects photos in shooting order)")
    p.add_argument("--camera-model", choices=CAMERA_MODEL_CHOICES, default=None,
                   help="COLMAP camera model shared by all photos (default simple-radial)")
    p.add_argument("--max-size", type=int, default=DEFAULT_MAX_SIZE, metavar="N",
                   help=f"longest image side for features and the written scene "
                        f"(default {DEFAULT_MAX_SIZE}; -1 keeps full size)")
    p.add_argument("--max-features", type=int, default=None, metavar="N",
                   help="SIFT features per photo (default 8192)")
    p.add_argument("--refine-principal-point", action="store_true",
                   help="let bundle adjustment move the principal point (off by default)")
    p.add_argument("--sparse", metavar="MODEL_DIR",
                   help="use this COLMAP sparse model (cameras/images/points3D .txt or .bin) "
                        "instead of running SfM")
    p.add_argument("--center", metavar="X,Y,Z",
                   help="object-sphere centre in the model's world frame (with --radius)")
    p.add_argument("--radius", type=float, metavar="R",
                   help="object-sphere radius (with --center)")
    p.add_argument("--threads", type=int, default=-1, help="CPU threads (default: all)")
    p.add_argument("--seed", type=int, default=0, help="random seed of COLMAP (default 0)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    return p


def _parse_sphere(args: argparse.Namespace):
    if (args.center is None) != (args.radius is None):
        raise NeusL0Error("--center and --radius go together")
    if args.center is None:
        return None
    try:
        c = [float(v) for v in args.center.split(",")]
    except ValueError:
        c = []
    if len(c) != 3:
        raise NeusL0Error(f"--center '{args.center}': expected three numbers X,Y,Z")
    if not args.radius > 0:
        raise NeusL0Error(f"--radius {args.radius}: must be > 0")
    return c, float(args.radius)


def run(args: argparse.Namespace) -> int:
    import json
    import time
    from pathlib import Path

    import cv2
    import numpy as np

    from neus_l0.atomic import atomic_write_text
    from neus_l0.commands._paths import check_output_dir
    from neus_l0.photos import sfm, sparse_io
    from neus_l0.photos.export import export_scene, find_masks
    from neus_l0.photos.preview import write_preview
    from neus_l0.photos.sphere import choose_sphere, user_sphere

    t_start = time.perf_counter()
    sphere_arg = _parse_sphere(args)
    photo_dir, out = Path(args.photos), check_output_dir(args.out, "OUT")
    if args.sparse and (args.camera_model or args.max_features):
        raise NeusL0Error("--camera-model and --max-features apply to SfM, not to --sparse")
    if args.masks and not Path(args.masks).is_dir():
        raise NeusL0Error(f"{args.masks}: mask folder not found")
    progress = not args.no_progress
    print(f"checking photos in {photo_dir}")
    paths, sizes = sfm.list_photos(photo_dir, same_size=not args.sparse)
    names = [p.name for p in paths]
    print(f"      {len(names)} photos")

    timings: dict = {}
    if args.sparse:
        print(f"reading the sparse model {args.sparse}")
        model = sparse_io.read_model(args.sparse)
        for name, cid in zip(model.names, model.camera_ids, strict=True):
            if name not in sizes:
                raise NeusL0Error(f"{args.sparse}: image '{name}' of the model is not in "
                                  f"{photo_dir}")
            cam = model.cameras[int(cid)]
            if sizes[name] != (cam.width, cam.height):
                raise NeusL0Error(f"{photo_dir / name}: size {sizes[name][0]}x{sizes[name][1]} "
                                  f"differs from its camera's {cam.width}x{cam.height} in "
                                  f"{args.sparse}")
        model = sfm.check_models([model], len(names), photo_dir)
    else:
        opts = sfm.SfmOptions(camera_model=args.camera_model or sfm.DEFAULT_CAMERA_MODEL,
                              matcher=args.matcher, max_size=args.max_size,
                              max_features=args.max_features or sfm.DEFAULT_MAX_FEATURES,
                              threads=args.threads, seed=args.seed,
                              refine_principal_point=args.refine_principal_point)
        models, timings = sfm.run_sfm(photo_dir, names, out / "colmap", opts,
                                      progress=progress)
        model = sfm.check_models(models, len(names), photo_dir)

    registered = set(model.names)
    missing = [n for n in names if n not in registered]
    atomic_write_text(out / "unregistered.txt", "".join(f"{n}\n" for n in missing))

    if sphere_arg is not None:
        sphere = user_sphere(np.array(sphere_arg[0]), sphere_arg[1], model.centres, model.axes)
    else:
        sphere = choose_sphere(model.points, model.track_len, model.centres, model.axes)

    masks = find_masks(args.masks, model.names) if args.masks else None
    print(f"writing the NeuS scene to {out}")
    info = export_scene(out, model, photo_dir, sphere.center, sphere.radius, masks=masks,
                        max_size=args.max_size, progress=progress)

    picks = np.unique(np.linspace(0, model.n_views - 1, min(PREVIEW_VIEWS, model.n_views))
                      .round().astype(int))
    images = [cv2.cvtColor(cv2.imread(str(out / "image" / f"{i:03d}.png")), cv2.COLOR_BGR2RGB)
              for i in picks]
    write_preview(out / "sphere_preview.png", images, [info["world_mats"][i] for i in picks],
                  model.points, sphere.center, sphere.radius,
                  titles=[model.names[i] for i in picks])

    summary = {
        "photos": len(names), "registered": model.n_views, "unregistered": missing,
        "points3D": int(len(model.points)), "size": list(info["size"]),
        "source": "sparse model " + str(args.sparse) if args.sparse else "pycolmap SfM",
        "timings_s": {k: (round(v, 2) if isinstance(v, float) else v)
                      for k, v in timings.items()},
        "sphere": {"center": [float(v) for v in sphere.center], "radius": sphere.radius,
                   "source": sphere.source, "convergence": [float(v) for v in
                                                            sphere.convergence],
                   "points_used": sphere.n_points, "capped": sphere.capped},
        "masks": masks is not None,
        "seconds": round(time.perf_counter() - t_start, 2),
    }
    atomic_write_text(out / "colmap_summary.json", json.dumps(summary, indent=2) + "\n")
    print(f"registered   {model.n_views} of {len(names)} photos, {len(model.points)} sparse "
          f"points, images {info['size'][0]} x {info['size'][1]}")
    if missing:
        print(f"unregistered {len(missing)}: {', '.join(missing)} (listed in "
              f"{out / 'unregistered.txt'}; not written to the scene)")
    print(sphere.explain())
    print(f"check it     {out / 'sphere_preview.png'} (override with --center X,Y,Z "
          "--radius R)")
    print(f"next         neus-l0 train {out} --conf "
          f"{'wmask' if masks is not None else 'womask'} sampler=l0 --out RUN; "
          "then neus-l0 mesh RUN")
    return 0
