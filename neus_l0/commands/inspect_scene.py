"""`neus-l0 inspect DATA`: validate a NeuS-format scene and print a summary."""

from __future__ import annotations

import argparse
import json


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(
        name, help="validate a NeuS-format scene and print a summary",
        description="Check a NeuS-format scene folder (image/, mask/, cameras_sphere.npz): "
                    "every image and mask readable and the same size, one camera per image, "
                    "finite and non-singular projections. Prints views, resolution, mask "
                    "coverage, the object sphere (world units) and the camera distances "
                    "(normalised units, where the object sphere is the unit sphere).")
    p.add_argument("data", help="scene folder")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--hull", metavar="OUT.ply", default=None,
                   help="carve the visual hull from the masks and write it as a watertight "
                        "mesh in world units (.ply or .obj); prints the fraction of the "
                        "bounding sphere it keeps and a warning for each suspicious mask")
    p.add_argument("--hull-resolution", type=int, default=None, metavar="R",
                   help="cells per axis of the hull grid over the unit sphere's cube "
                        "(default 128)")
    p.add_argument("--hull-margin", type=float, default=None, metavar="PX",
                   help="mask dilation in pixels for mask and calibration error (default 2)")
    return p


def format_summary(info: dict) -> str:
    """Human-readable lines for the dict `validate_scene` returns."""
    cov = info["mask_coverage"]
    dist = info["camera_distance"]
    c = info["sphere_center"]
    lines = [
        f"scene        {info['root']}",
        f"views        {info['views']}  ({info['camera_file']})",
        f"resolution   {info['width']} x {info['height']}",
        ("masks        foreground {:.1%} mean ({:.1%} .. {:.1%})".format(
            cov["mean"], cov["min"], cov["max"]) if info["has_masks"]
         else "masks        none (all pixels count as foreground)"),
        f"object       sphere radius {info['sphere_radius']:.4g} world units, "
        f"centre ({c[0]:.4g}, {c[1]:.4g}, {c[2]:.4g})",
        f"cameras      distance {dist['mean']:.3f} mean ({dist['min']:.3f} .. {dist['max']:.3f}) "
        f"sphere radii; focal {info['focal']['min']:.1f} .. {info['focal']['max']:.1f} px",
    ]
    lines += [f"warning      {w}" for w in info["warnings"]]
    if "hull" in info:
        h = info["hull"]
        n_carve = sum(s in ("ok", "full") for s in h["status"])
        lines.append(f"visual hull  keeps {h['fraction_kept']:.1%} of the bounding sphere "
                     f"({h['resolution']}^3, margin {h['margin_px']:g} px, {n_carve} of "
                     f"{len(h['status'])} views carve, {h['seconds']:.1f} s) -> {h['mesh']}")
        lines += [f"warning      {w}" for w in h["warnings"]]
    return "\n".join(lines)


def _hull(args: argparse.Namespace) -> dict:
    """Carve the scene's visual hull, write its mesh, return the report as a dict."""
    from neus_l0.bounds.hull import DEFAULT_MARGIN_PX, DEFAULT_RESOLUTION, hull_from_scene
    from neus_l0.data.scene import load_scene
    from neus_l0.errors import NeusL0Error
    from neus_l0.mesh.extract import export_mesh

    R = DEFAULT_RESOLUTION if args.hull_resolution is None else args.hull_resolution
    margin = DEFAULT_MARGIN_PX if args.hull_margin is None else args.hull_margin
    if not 4 <= R <= 1024:
        raise NeusL0Error(f"--hull-resolution {R}: use 4 .. 1024")
    scene = load_scene(args.data)
    if not scene.has_masks:
        raise NeusL0Error(f"{args.data}: no 'mask/' folder, so there is no visual hull")
    hull = hull_from_scene(scene, resolution=R, margin_px=margin)
    export_mesh(hull.to_mesh(scene.scale_mat), args.hull)
    return dict(hull.report.to_dict(), mesh=str(args.hull), resolution=R, margin_px=margin)


def run(args: argparse.Namespace) -> int:
    from neus_l0.data.scene import validate_scene

    if args.hull is None and (args.hull_resolution is not None or args.hull_margin is not None):
        from neus_l0.errors import NeusL0Error

        raise NeusL0Error("--hull-resolution and --hull-margin need --hull OUT.ply")
    info = validate_scene(args.data)
    if args.hull is not None:
        info["hull"] = _hull(args)
    print(json.dumps(info, indent=2) if args.json else format_summary(info))
    return 0
