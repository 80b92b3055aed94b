"""What `train --viewer` costs a training step on the CPU: the demo config with and without
the live viewer (`neus_l0.viewer.live.LiveViewer`), runs alternated, one JSON line each.

    python tools/bench_viewer_cost.py --out /tmp/viewer_cost [--iters 300] [--reps 2]

The demo scene at its default size; ``--threads 1``; ``train.val_every=100`` so that a
300-iteration run builds three coarse meshes (5x the demo config's rate); no compile, no
checkpoints but the last. ``ms_per_step`` is the training clock over the iterations
(validation renders and logging included, in both arms).
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import torch

from neus_l0.config.load import load_config
from neus_l0.formats.open import open_scene
from neus_l0.synthetic.scene import make_scene
from neus_l0.train.loop import train
from neus_l0.viewer.live import LiveViewer


def main() -> None:
    """Parse the flags, run the pairs, print one JSON line a run."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="work folder (scene and runs)")
    p.add_argument("--iters", type=int, default=300)
    p.add_argument("--reps", type=int, default=2)
    p.add_argument("--val-every", type=int, default=100)
    args = p.parse_args()
    torch.set_num_threads(1)
    out = Path(args.out)
    root = out / "scene" / "demo"
    if not (root / "cameras_sphere.npz").is_file():
        make_scene("demo", root, seed=0, progress=False)
    scene = open_scene(root, preview=False, log=lambda _line: None)
    cfg = load_config("demo", [f"train.iters={args.iters}", f"train.val_every={args.val_every}",
                               "train.compile=false", "train.max_seconds=0",
                               "train.save_every=0"])
    for rep in range(args.reps):
        for viewer in (False, True):
            run = out / f"run_{'viewer' if viewer else 'plain'}_{rep}"
            shutil.rmtree(run, ignore_errors=True)
            res = train(scene, cfg, run, progress=False,
                        callbacks=[LiveViewer(0)] if viewer else [])
            print(json.dumps({"viewer": viewer, "rep": rep, "seconds": round(res.seconds, 2),
                              "ms_per_step": round(1000 * res.seconds / args.iters, 2)}),
                  flush=True)


if __name__ == "__main__":
    main()
