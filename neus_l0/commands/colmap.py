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
    from pathlib import Path

    from neus_l0.commands._paths import check_not_input, check_output_dir
    from neus_l0.photos import sfm
    from neus_l0.photos.pipeline import PHOTO_SCENE_NAMES, PhotoOptions, photos_to_scene

    sphere = _parse_sphere(args)
    check_not_input(args.out, "OUT", [args.photos, args.masks, args.sparse])
    out = check_output_dir(args.out, "OUT", ("colmap_summary.json",), PHOTO_SCENE_NAMES,
                           "a scene made from photos")
    if args.sparse and (args.camera_model or args.max_features):
        raise NeusL0Error("--camera-model and --max-features apply to SfM, not to --sparse")
    sfm_opts = sfm.SfmOptions(camera_model=args.camera_model or sfm.DEFAULT_CAMERA_MODEL,
                              matcher=args.matcher, max_size=args.max_size,
                              max_features=args.max_features or sfm.DEFAULT_MAX_FEATURES,
                              threads=args.threads, seed=args.seed,
                              refine_principal_point=args.refine_principal_point)
    s = photos_to_scene(PhotoOptions(
        photos=Path(args.photos), out=out, sfm=sfm_opts,
        masks=Path(args.masks) if args.masks else None,
        sparse=Path(args.sparse) if args.sparse else None, max_size=args.max_size,
        sphere=sphere, progress=not args.no_progress))
    print(f"registered   {s['registered']} of {s['photos']} photos, {s['points3D']} sparse "
          f"points, images {s['size'][0]} x {s['size'][1]}")
    if s["unregistered"]:
        print(f"unregistered {len(s['unregistered'])}: {', '.join(s['unregistered'])} (listed "
              f"in {s['unregistered_file']}; not written to the scene)")
    print(s["explain"])
    print(f"check it     {out / 'sphere_preview.png'} (override with --center X,Y,Z "
          "--radius R)")
    print(f"next         neus-l0 train {out} --conf "
          f"{'wmask' if s['masks'] else 'womask'} sampler=l0 --out RUN; "
          "then neus-l0 mesh RUN")
    return 0
