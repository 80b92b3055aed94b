"""Count the aten ops that one training step dispatches (forward, backward and optimiser).

Usage:
    python tools/count_ops.py [--conf demo] [--views 4] [--width 40] [--height 30]
                              [--warm 3] [--iteration ITER] [--top 25] [--phases]
                              [--run-setup] [override ...]

Builds the built-in ``demo`` scene (small, `neus_l0.synthetic.scene.make_scene`), the config's
model and optimiser, runs ``--warm`` untimed steps (lazy state: Adam's moments, the first
occupancy update), then runs ONE `neus_l0.train.step.train_step` under a `TorchDispatchMode` that
counts every aten op reaching the dispatcher below autograd: the ops a kernel launch (or a
CPU kernel call) is made for, plus views and metadata ops, which cost host time too. The step
is taken at ``--iteration`` (default: the last warm step + 1), so schedules that depend on
the iteration (progressive hash levels, occupancy updates) are those of that iteration.

Prints the total and the ``--top`` most frequent ops with their share. Compare configs or
overrides run against run, e.g. ``--conf fast model.sdf.gradient=analytic``.

``--phases`` also breaks the count down by phase of the step: each forward op is
attributed to the chain of known functions on its Python stack (`PHASES`: inputs,
up-sampling with its SDF passes, section weights, draws and merges, the SDF network with
its gradient, the colour network, compositing, losses, optimiser), and each backward op to
the phase of the forward op whose autograd node runs it (``backward/<phase>``; the nodes'
forward stacks are kept by anomaly mode without its NaN checks, which would add ops).
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import re
import sys
import tempfile
from pathlib import Path

import torch
from _common import add_scene_args, small_demo_scene
from torch.utils._python_dispatch import TorchDispatchMode

from neus_l0.bounds.pixel_pool import reachable_pixels
from neus_l0.bounds.static import static_bounds
from neus_l0.config.load import load_config
from neus_l0.fields.model import make_model
from neus_l0.sampling.upsample import build_sampler
from neus_l0.train.step import StepSetup, make_occupancy, make_optimizer, make_scaler, train_step

#: "module file stem:function name" -> phase label, for `--phases`; nested matches join
#: with "/" (outermost first).
PHASES = {
    "step:draw_step_inputs": "inputs",
    "step:update_occupancy": "occupancy",
    "volume:render_rays": "render",
    "spans:ray_bounds": "bounds",
    "spans:_ray_bounds": "bounds",
    "volume:coarse_z_vals": "coarse",
    "upsample:up_sample": "up_sample",
    "upsample:sdf_at": "sdf",
    "upsample:upsample_section_weights": "sections",
    "upsample:draw": "draw",
    "sdf:sdf_and_gradient": "sdf+grad",
    "encodings:forward_jacobian": "hashgrid",
    "encodings:forward": "hashgrid",
    "color:forward": "color",
    "volume:section_alpha": "alpha",
    "losses:neus_loss": "loss",
    "optimizer:zero_grad": "zero_grad",
    "adam:step": "optimizer",
    "linear:clear_weight_cache": "cache",
}
_FRAME = re.compile(r'File "(?:[^"]*/)?([^"/]*?)(?:\.py)?", line \d+, in (\S+)')


def _phase_of_names(names: list[str]) -> str:
    """Outermost-first "stem:function" names -> the phase path (unknown frames skipped)."""
    parts = [PHASES[n] for n in names if n in PHASES]
    return "/".join(parts) if parts else "other"


def _python_phase() -> str:
    """The phase of the calling Python stack."""
    names = []
    frame = sys._getframe(2)
    while frame is not None:
        code = frame.f_code
        stem = code.co_filename.rsplit("/", 1)[-1].removesuffix(".py")
        names.append(f"{stem}:{code.co_name}")
        frame = frame.f_back
    return _phase_of_names(names[::-1])


class OpCounter(TorchDispatchMode):
    """Counts aten ops by overload packet name (e.g. ``aten.mm``), and by phase when
    `phases` (see the module docstring)."""

    def __init__(self, phases: bool = False) -> None:
        super().__init__()
        self.counts: collections.Counter[str] = collections.Counter()
        self.phases: collections.Counter[str] | None = collections.Counter() if phases else None
        self._node_phase: dict[int, str] = {}

    def _phase(self) -> str:
        node = torch._C._current_autograd_node()
        if node is None:
            return _python_phase()
        key = id(node)
        if key not in self._node_phase:
            stack = node.metadata.get("traceback_") or []
            names = [f"{m.group(1)}:{m.group(2)}" for line in stack
                     for m in [_FRAME.search(line)] if m]
            self._node_phase[key] = "backward/" + _phase_of_names(names).replace(
                "backward/", "")
        return self._node_phase[key]

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.counts[str(func.overloadpacket)] += 1
        if self.phases is not None:
            self.phases[self._phase()] += 1
        return func(*args, **(kwargs or {}))


def count_step_ops(conf: str, overrides: list[str], views: int = 4, width: int = 40,
                   height: int = 30, warm: int = 3,
                   iteration: int | None = None, phases: bool = False,
                   run_setup: bool = False
                   ) -> collections.Counter[str] | tuple[collections.Counter[str],
                                                          collections.Counter[str]]:
    """Aten ops of one training step of config `conf` (with `overrides`) on the demo scene.

    With `run_setup` the step gets what `neus_l0.train` gives a run's steps: the built
    sampler, the visual hull (the demo scene has masks) and the pixel pool; without, the
    bare `train_step` (no hull, rays from every pixel).

    Returns:
        counts of each op name over the step (forward, backward, optimiser step); with
        `phases`, also the counts of each phase (see the module docstring).
    """
    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as tmp:
        scene = small_demo_scene(tmp, views, width, height)
        cfg = load_config(conf, overrides)
        model = make_model(cfg, "cpu")
        setup = None
        if run_setup:
            setup = StepSetup(sampler=build_sampler(cfg.sampler))
            setup.bounds = static_bounds(scene, cfg, Path(tmp) / "hull.pt")
            setup.pool = reachable_pixels(scene, cfg.render, setup.bounds,
                                          background=model.background is not None)
    opt = make_optimizer(model, cfg)
    grid = make_occupancy(cfg, "cpu")
    scaler = make_scaler(cfg, "cpu")
    gen = torch.Generator().manual_seed(0)
    for it in range(warm):
        train_step(model, opt, scene, cfg, it, gen, occupancy=grid, scaler=scaler, setup=setup)
    it = warm if iteration is None else iteration
    counter = OpCounter(phases)
    anomaly = (torch.autograd.set_detect_anomaly(True, check_nan=False) if phases
               else contextlib.nullcontext())
    with anomaly, counter:
        train_step(model, opt, scene, cfg, it, gen, occupancy=grid, scaler=scaler, setup=setup)
    return (counter.counts, counter.phases) if phases else counter.counts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--conf", default="demo", help="built-in config name or YAML path")
    add_scene_args(ap, views=4, width=40, height=30)
    ap.add_argument("--warm", type=int, default=3, help="untimed steps before the count")
    ap.add_argument("--iteration", type=int, default=None,
                    help="iteration number of the counted step (default: --warm)")
    ap.add_argument("--top", type=int, default=25, help="how many op names to list")
    ap.add_argument("--phases", action="store_true",
                    help="also count the ops of each phase of the step")
    ap.add_argument("--run-setup", action="store_true",
                    help="count the step a run takes: with its visual hull and pixel pool")
    ap.add_argument("--json", action="store_true",
                    help="print one JSON object {total, torch, ops, phases} instead of tables")
    ap.add_argument("overrides", nargs="*", help="dotted key=value config overrides")
    args = ap.parse_args()
    torch.set_num_threads(1)
    result = count_step_ops(args.conf, args.overrides, args.views, args.width, args.height,
                            args.warm, args.iteration, args.phases, args.run_setup)
    counts, phases = result if args.phases else (result, None)
    total = sum(counts.values())
    if args.json:
        print(json.dumps({"total": total, "torch": torch.__version__, "ops": dict(counts),
                          "phases": dict(phases) if phases is not None else None}))
        return
    setup = " (run setup: hull, pixel pool)" if args.run_setup else ""
    print(f"# conf {args.conf} {' '.join(args.overrides)}{setup}: {total} aten ops in one "
          f"step (torch {torch.__version__})")
    print("| op | count | share |")
    print("|---|---:|---:|")
    for name, n in counts.most_common(args.top):
        print(f"| {name} | {n} | {n / total:.1%} |")
    if phases is not None:
        print("\n| phase | ops |")
        print("|---|---:|")
        for name, n in sorted(phases.items()):
            print(f"| {name} | {n} |")


if __name__ == "__main__":
    main()
