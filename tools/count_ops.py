"""Count the aten ops that one training step dispatches (forward, backward and optimiser).

Usage:
    python tools/count_ops.py [--conf demo] [--views 4] [--width 40] [--height 30]
                              [--warm 3] [--iteration ITER] [--top 25] [override ...]

Builds the built-in ``demo`` scene (small, `neus_l0.data.synthetic.make_scene`), the config's
model and optimiser, runs ``--warm`` untimed steps (lazy state: Adam's moments, the first
occupancy update), then runs ONE `neus_l0.train.train_step` under a `TorchDispatchMode` that
counts every aten op reaching the dispatcher below autograd: the ops a kernel launch (or a
CPU kernel call) is made for, plus views and metadata ops, which cost host time too. The step
is taken at ``--iteration`` (default: the last warm step + 1), so schedules that depend on
the iteration (progressive hash levels, occupancy updates) are those of that iteration.

Prints the total and the ``--top`` most frequent ops with their share. Compare configs or
overrides run against run, e.g. ``--conf fast model.sdf.gradient=analytic``.
"""

from __future__ import annotations

import argparse
import collections
import tempfile
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from neus_l0.config import load_config
from neus_l0.data.scene import load_scene
from neus_l0.data.synthetic import make_scene
from neus_l0.train import make_model, make_occupancy, make_optimizer, make_scaler, train_step


class OpCounter(TorchDispatchMode):
    """Counts aten ops by overload packet name (e.g. ``aten.mm``)."""

    def __init__(self) -> None:
        super().__init__()
        self.counts: collections.Counter[str] = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.counts[str(func.overloadpacket)] += 1
        return func(*args, **(kwargs or {}))


def count_step_ops(conf: str, overrides: list[str], views: int = 4, width: int = 40,
                   height: int = 30, warm: int = 3,
                   iteration: int | None = None) -> collections.Counter[str]:
    """Aten ops of one training step of config `conf` (with `overrides`) on the demo scene.

    Returns:
        counts of each op name over the step (forward, backward, optimiser step).
    """
    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as tmp:
        root = make_scene("demo", Path(tmp) / "demo", views=views, width=width,
                          height=height, seed=0, gt_voxel=4.0, point_spacing=2.0,
                          progress=False)
        scene = load_scene(root, device="cpu")
    cfg = load_config(conf, overrides)
    model = make_model(cfg, "cpu")
    opt = make_optimizer(model, cfg)
    grid = make_occupancy(cfg, "cpu")
    scaler = make_scaler(cfg, "cpu")
    gen = torch.Generator().manual_seed(0)
    for it in range(warm):
        train_step(model, opt, scene, cfg, it, gen, occupancy=grid, scaler=scaler)
    it = warm if iteration is None else iteration
    counter = OpCounter()
    with counter:
        train_step(model, opt, scene, cfg, it, gen, occupancy=grid, scaler=scaler)
    return counter.counts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--conf", default="demo", help="built-in config name or YAML path")
    ap.add_argument("--views", type=int, default=4, help="views of the synthetic scene")
    ap.add_argument("--width", type=int, default=40, help="image width of the scene")
    ap.add_argument("--height", type=int, default=30, help="image height of the scene")
    ap.add_argument("--warm", type=int, default=3, help="untimed steps before the count")
    ap.add_argument("--iteration", type=int, default=None,
                    help="iteration number of the counted step (default: --warm)")
    ap.add_argument("--top", type=int, default=25, help="how many op names to list")
    ap.add_argument("overrides", nargs="*", help="dotted key=value config overrides")
    args = ap.parse_args()
    torch.set_num_threads(1)
    counts = count_step_ops(args.conf, args.overrides, args.views, args.width, args.height,
                            args.warm, args.iteration)
    total = sum(counts.values())
    print(f"# conf {args.conf} {' '.join(args.overrides)}: {total} aten ops in one step "
          f"(torch {torch.__version__})")
    print("| op | count | share |")
    print("|---|---:|---:|")
    for name, n in counts.most_common(args.top):
        print(f"| {name} | {n} | {n / total:.1%} |")


if __name__ == "__main__":
    main()
