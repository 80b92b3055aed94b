"""`neus-l0 inspect DATA`: validate a scene (NeuS format or transforms.json) and print a
summary."""

from __future__ import annotations

import argparse
import json


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(
        name, help="validate a scene and print a summary",
        description="Check a scene folder, NeuS format (image/, mask/, cameras_sphere.npz) or "
                    "transforms.json (NeRF-synthetic, instant-ngp, nerfstudio): every image "
                    "and mask readable and the same size, one camera per image, finite and "
                    "non-singular cameras. Prints the format, views, resolution, where the "
                    "masks come from and their coverage, the object sphere (world units; for "
                    "transforms.json, how it was found, with sphere_preview.png) and the "
                    "camera distances (normalised units, where the object sphere is the unit "
                    "sphere), and what `train` would refuse or warn of (the object cut by its "
                    "sphere, judged from the visual hull training carves; cameras inside the "
                    "sphere).")
    p.add_argument("data", help="scene folder (or a transforms JSON file)")
    p.add_argument("--split", choices=("train", "val", "test"), default="train",
                   help="the split of a transforms.json scene (default train)")
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
    fmt = info.get("format", "neus")
    source = {"mask/": "mask/", "alpha": "images' alpha", "mask_path": "mask_path files"}.get(
        info.get("mask_source", "mask/"), info.get("mask_source", "mask/"))
    split = f", {info['split']} split" if info.get("split") else ""
    lines = [
        f"scene        {info['root']}",
        f"format       {'NeuS' if fmt == 'neus' else fmt + ' transforms.json'}",
        f"views        {info['views']}  ({info['camera_file']}{split})",
        f"resolution   {info['width']} x {info['height']}",
        ("masks        foreground {:.1%} mean ({:.1%} .. {:.1%}), from {}".format(
            cov["mean"], cov["min"], cov["max"], source) if info["has_masks"]
         else "masks        none (all pixels count as foreground)"),
        f"object       sphere radius {info['sphere_radius']:.4g} world units, "
        f"centre ({c[0]:.4g}, {c[1]:.4g}, {c[2]:.4g})",
        f"cameras      distance {dist['mean']:.3f} mean ({dist['min']:.3f} .. {dist['max']:.3f}) "
        f"sphere radii; focal {info['focal']['min']:.1f} .. {info['focal']['max']:.1f} px",
    ]
    if info.get("pairing"):
        idx = info.get("view_indices") or []
        span = f"views {idx[0]} .. {idx[-1]}" if idx else "no views"
        unused = info.get("unused_cameras") or []
        lines.append(f"pairing      {info['pairing']} ({span}"
                     + (f"; cameras without an image: {unused}" if unused else "") + ")")
    if "sphere_method" in info:
        lines.append(f"sphere from  {info['sphere_method']}: {info['sphere_detail']}")
    if info.get("preview"):
        lines.append(f"preview      {info['preview']}")
    if info.get("undistorted"):
        lines.append(f"cameras      {info['undistorted']}")
    lines += [f"warning      {w}" for w in info["warnings"]]
    lines += _train_lines(info.get("train"))
    if "hull" in info:
        h = info["hull"]
        n_carve = sum(s in ("ok", "full") for s in h["status"])
        lines.append(f"visual hull  keeps {h['fraction_kept']:.1%} of the bounding sphere "
                     f"({h['resolution']}^3, margin {h['margin_px']:g} px, {n_carve} of "
                     f"{len(h['status'])} views carve, {h['seconds']:.1f} s) -> {h['mesh']}")
        lines += [f"warning      {w}" for w in h["warnings"]]
    return "\n".join(lines)


def _train_lines(verdict: dict | None) -> list[str]:
    """The summary's lines for `neus_l0.bounds.static.train_verdict`."""
    if verdict is None:
        return []
    if verdict["refuses"]:
        return [f"warning      train would refuse this scene: {verdict['refuses']}"]
    lines = [f"warning      train would warn: {w}" for w in verdict["warnings"]]
    if verdict["shell"] is not None:
        lines.append(f"train        the object fits its unit sphere (the visual hull fills "
                     f"{verdict['shell']:.1%} of the sphere's outer shell)")
    return lines


def _train_check(args: argparse.Namespace, scene, hull) -> dict:
    """`train_verdict` with the hull training would carve (the one --hull carved when it used
    the same settings)."""
    from neus_l0.bounds.hull import hull_from_scene
    from neus_l0.bounds.static import train_verdict
    from neus_l0.config.schema import HullConfig

    h = HullConfig()
    if scene.has_masks and (hull is None or (hull.resolution, hull.margin_px)
                            != (h.resolution, h.margin_px)):
        hull = hull_from_scene(scene, h.resolution, h.margin_px)
    return train_verdict(scene, hull if scene.has_masks else None)


def _hull(args: argparse.Namespace, scene) -> dict:
    """Carve the scene's visual hull, write its mesh, return the report as a dict."""
    from neus_l0.bounds.hull import DEFAULT_MARGIN_PX, DEFAULT_RESOLUTION, hull_from_scene
    from neus_l0.errors import NeusL0Error
    from neus_l0.mesh.extract import export_mesh

    R = DEFAULT_RESOLUTION if args.hull_resolution is None else args.hull_resolution
    margin = DEFAULT_MARGIN_PX if args.hull_margin is None else args.hull_margin
    if not 4 <= R <= 1024:
        raise NeusL0Error(f"--hull-resolution {R}: use 4 .. 1024")
    if not scene.has_masks:
        raise NeusL0Error(f"{args.data}: no masks (no 'mask/' folder, mask_path or alpha), so "
                          f"there is no visual hull")
    hull = hull_from_scene(scene, resolution=R, margin_px=margin)
    export_mesh(hull.to_mesh(scene.scale_mat), args.hull)
    return dict(hull.report.to_dict(), mesh=str(args.hull), resolution=R, margin_px=margin,
                carved=hull)


def run(args: argparse.Namespace) -> int:
    from neus_l0.formats.open import open_scene, summarise

    if args.hull is None and (args.hull_resolution is not None or args.hull_margin is not None):
        from neus_l0.errors import NeusL0Error

        raise NeusL0Error("--hull-resolution and --hull-margin need --hull OUT.ply")
    scene = open_scene(args.data, split=args.split)
    info = summarise(scene)
    carved = None
    if args.hull is not None:
        info["hull"] = _hull(args, scene)
        carved = info["hull"].pop("carved")
    info["train"] = _train_check(args, scene, carved)
    print(json.dumps(info, indent=2) if args.json else format_summary(info))
    return 0
