"""Eager against compiled (`train.compile`) training steps, side by side in one process.

Usage (from the repository root):
    python tools/bench_compile_step.py [CONF] [override ...]     # default CONF: demo

Renders the small built-in `demo` scene (6 views, 80x60; `_common.small_demo_scene`), then
for eager and compiled in turn: the model and optimiser of CONF with
``model.sdf.gradient=analytic``, one first step (timed: the compiled one compiles), then 29
timed steps with one torch thread. Prints the first step's seconds, the median step in ms,
and the largest difference of the two loss curves.
"""

from __future__ import annotations

import sys
import tempfile
import time

import torch
from _common import small_demo_scene

from neus_l0.config.load import load_config
from neus_l0.fields.model import make_model
from neus_l0.train.compile import CompiledStep
from neus_l0.train.step import StepSetup, make_optimizer, render_and_loss, train_step


def main() -> None:
    torch.set_num_threads(1)
    conf = sys.argv[1] if len(sys.argv) > 1 else "demo"
    overrides = sys.argv[2:]
    with tempfile.TemporaryDirectory() as tmp:
        scene = small_demo_scene(tmp, views=6, width=80, height=60)
    curves = {}
    for compiled in (False, True):
        cfg = load_config(conf, ["model.sdf.gradient=analytic", "train.warm_up=0"] + overrides)
        model = make_model(cfg)
        opt = make_optimizer(model, cfg)
        g = torch.Generator().manual_seed(0)
        step = CompiledStep(render_and_loss, torch.device("cpu")) if compiled else None
        setup = StepSetup(compiled=step)
        t0 = time.time()
        losses = [train_step(model, opt, scene, cfg, 0, g, setup=setup)[0].item()]
        first = time.time() - t0
        times = []
        for it in range(1, 30):
            a = time.perf_counter()
            losses.append(train_step(model, opt, scene, cfg, it, g, setup=setup)[0].item())
            times.append(time.perf_counter() - a)
        times.sort()
        curves[compiled] = losses
        print(f"{'compiled' if compiled else 'eager'}: first step {first:.2f} s, median step "
              f"{1000 * times[len(times) // 2]:.1f} ms")
    print("largest loss difference", max(abs(a - b) for a, b in zip(curves[False],
                                                                   curves[True])))


if __name__ == "__main__":
    main()
