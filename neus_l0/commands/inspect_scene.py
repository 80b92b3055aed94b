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
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from neus_l0.data.scene import validate_scene

    info = validate_scene(args.data)
    print(json.dumps(info, indent=2) if args.json else format_summary(info))
    return 0
