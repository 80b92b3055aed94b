"""`neus-l0 render`: novel views of a trained run (orbit video, training or held-out views)."""

from __future__ import annotations

import argparse

from neus_l0.commands._threads import add_threads_flag


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="render novel views of a trained run (frames, videos, PSNR)",
                       description="Render colour, normals (camera frame) and depth "
                                   "(camera z, colour-mapped) of a trained run inside its "
                                   "visual hull: a turntable orbit at the training cameras' "
                                   "mean distance and elevation (default), the training "
                                   "views, or held-out views. Writes DIR/{color,normal,depth}/"
                                   "NNNN.png and DIR/{color,normal,depth}.mp4; on training or "
                                   "held-out views also PSNR and SSIM per view and their mean "
                                   "(DIR/metrics.json). Prints one JSON line.")
    p.add_argument("run", metavar="RUN", help="run folder written by `neus-l0 train`")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="output folder (default RUN/render/VIEWS)")
    p.add_argument("--views", default="orbit", choices=["orbit", "train", "test"],
                   help="orbit: turntable around the object (default); train: the training "
                        "cameras; test: the views the run held out (train --holdout K)")
    p.add_argument("--frames", type=int, default=60, help="orbit frames (60)")
    p.add_argument("--elevation", type=float, default=None, metavar="DEG",
                   help="orbit elevation in degrees (default the training cameras' mean)")
    p.add_argument("--width", type=int, default=None, metavar="W",
                   help="output width (alone: the height keeps the training aspect)")
    p.add_argument("--height", type=int, default=None, metavar="H",
                   help="output height (alone: the width keeps the training aspect)")
    p.add_argument("--downscale", type=float, default=None, metavar="S",
                   help="output = training image size / S (instead of --width/--height; "
                        "default: the training size)")
    p.add_argument("--test-views", default=None, metavar="I,J,...",
                   help="views to render as test views, e.g. 0,8,16 (default: the run's "
                        "held-out views; views it trained on are labelled train views)")
    p.add_argument("--holdout", type=int, default=0, metavar="K",
                   help="test views: every K-th (views 0, K, 2K, ...; as `train --holdout`; "
                        "default: the run's own)")
    p.add_argument("--scene", default=None, metavar="DIR",
                   help="scene folder (default the one RUN/run.json names)")
    p.add_argument("--checkpoint", default=None,
                   help="a specific checkpoint (default the newest that loads)")
    p.add_argument("--device", default=None, choices=["cpu", "cuda"])
    add_threads_flag(p)
    p.add_argument("--fps", type=float, default=24.0, help="video frame rate (24)")
    p.add_argument("--no-video", dest="video", action="store_false",
                   help="write the PNG frames only")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _test_views(text: str | None) -> tuple[int, ...] | None:
    """``"0,8,16"`` -> (0, 8, 16).

    Raises:
        NeusL0Error: anything but comma-separated integers.
    """
    from neus_l0.errors import NeusL0Error

    if text is None:
        return None
    try:
        views = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise NeusL0Error(f"--test-views {text!r}: give comma-separated view indices, "
                          "e.g. 0,8,16") from None
    if not views:
        raise NeusL0Error(f"--test-views {text!r}: no view index given")
    return views


def run(args: argparse.Namespace) -> int:
    import json
    import sys

    from neus_l0.commands._paths import check_not_input, check_output_dir
    from neus_l0.commands._threads import use_threads
    from neus_l0.device import pick_device
    from neus_l0.pipelines.render_run import RENDER_NAMES, RenderOptions, render_run

    options = RenderOptions(
        views=args.views, frames=args.frames, elevation=args.elevation, width=args.width,
        height=args.height, downscale=args.downscale, fps=args.fps, video=args.video,
        test_views=_test_views(args.test_views), holdout=args.holdout, scene=args.scene,
        checkpoint=args.checkpoint)
    options.check()
    out = None
    if args.out:
        check_not_input(args.out, "--out", [args.run, args.scene, args.checkpoint])
        out = check_output_dir(args.out, "--out", ("metrics.json",), RENDER_NAMES,
                               "a render folder")
    device = pick_device(args.device)
    use_threads(args.threads, device)
    result = render_run(args.run, out, options, device, progress=not args.quiet)
    if result.metrics and result.metrics["trained_on"]:
        views = ", ".join(map(str, result.metrics["trained_on"]))
        print(f"neus-l0 render: views {views} were trained on: their metrics are train views, "
              "not held-out (train with --holdout K for held-out views)", file=sys.stderr)
    H, W = result.size
    print(f"neus-l0 render: {result.frames} frames of {W}x{H} in {result.seconds:.1f} s "
          f"({result.seconds / max(result.frames, 1):.2f} s/frame) -> {result.out}",
          file=sys.stderr)
    print(json.dumps(result.summary()), flush=True)
    return 0
