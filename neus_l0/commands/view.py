"""`neus-l0 view`: a web page of a run (mesh, cameras, curves, validation images)."""

from __future__ import annotations

import argparse


def add_parser(sub: argparse._SubParsersAction, name: str) -> argparse.ArgumentParser:
    p = sub.add_parser(name, help="watch a run in the browser (mesh, cameras, curves)",
                       description="Serve a page of a run folder on this machine: the newest "
                                   "mesh with its vertex colours (or its normals), the "
                                   "training cameras (click one for its image), the curves "
                                   "of metrics.jsonl (loss, PSNR, sharpness inv_s, learning "
                                   "rate), the validation images and a slider over the "
                                   "checkpoints. The page follows a run that is still "
                                   "training. Its web client ships with viser: nothing is "
                                   "loaded from the internet. --screenshot FILE saves a "
                                   "picture of the page through headless Chromium instead.")
    p.add_argument("run", metavar="RUN", help="run folder written by `neus-l0 train`")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this machine only; "
                        "0.0.0.0 opens the page to every machine that reaches this one)")
    p.add_argument("--port", type=int, default=8080, help="port (8080; 0: a free one)")
    p.add_argument("--resolution", type=int, default=128,
                   help="marching-cubes cells per axis of the meshes shown (128)")
    p.add_argument("--screenshot", default=None, metavar="PNG",
                   help="save a screenshot of the page (headless Chromium) and exit")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    return p


def run(args: argparse.Namespace) -> int:
    import sys

    from neus_l0.device import use_cpu_threads
    from neus_l0.errors import NeusL0Error
    from neus_l0.viewer.page import reach_line

    if not 0 <= args.port < 65536:
        raise NeusL0Error(f"--port {args.port}: must be 0..65535")
    if args.resolution < 16:
        raise NeusL0Error(f"--resolution {args.resolution}: must be at least 16")
    use_cpu_threads(args.threads, "cpu")
    if args.screenshot:
        from neus_l0.viewer.browser import screenshot_run

        shot = screenshot_run(args.run, args.screenshot, resolution=args.resolution)
        print(f"neus-l0 view: screenshot -> {shot.path} ({len(shot.requests)} requests, "
              f"{len(shot.outside)} off the loopback)")
        return 0
    from neus_l0.viewer.serve import serve_run

    def ready(page) -> None:
        print(reach_line(args.host, page.port), file=sys.stderr, flush=True)

    serve_run(args.run, args.host, args.port, args.resolution, ready=ready)
    return 0
