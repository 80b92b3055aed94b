"""The optional mesh steps' flags, shared by `neus-l0 mesh` and `neus-l0 bench`
(`neus_l0.mesh.from_run.MeshSteps`)."""

from __future__ import annotations

import argparse


def add_mesh_step_flags(p: argparse.ArgumentParser) -> None:
    """--close-underside, --drop-outside-masks, --fill-missed, --photo-carve and --inset K
    (all off by default)."""
    p.add_argument("--close-underside", action="store_true",
                   help="close the side no training view sees flat, under the lowest point "
                        "they see in their masks (needs the scene's masks; extracts twice)")
    p.add_argument("--drop-outside-masks", action="store_true",
                   help="drop connected pieces that a training view sees outside its mask "
                        "(over half their vertices off the mask dilated by 2 px)")
    p.add_argument("--fill-missed", action="store_true",
                   help="fill thin parts the masks see and the mesh misses: the visual hull's "
                        "points on mask pixels the mesh's silhouette misses in 2 views or more "
                        "(needs the scene's masks; extracts twice)")
    p.add_argument("--photo-carve", action="store_true",
                   help="carve free space behind the mesh in its concavities (a deep pit's "
                        "raised floor) where the plane sweeps of the training images agree "
                        "across a neighbourhood of rays and in 2 views or more (needs the "
                        "scene's images and masks; extracts twice)")
    p.add_argument("--inset", type=float, default=0.0, metavar="K",
                   help="extract the SDF's level -K/s, s NeuS's learned sharpness (a zero level "
                        "trained with NeuS's colour composite over black sits 0.1-0.9 of 1/s "
                        "outside the true surface; train.hit_color_floor removes most of it; "
                        "default 0)")
