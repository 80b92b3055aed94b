"""Time a training step with the `l0` draw against one with `hvs`, side by side.

Usage (from the repository root):
    python tools/bench_sampler_step.py [--confs demo,fast] [--rounds 7] [--steps 3]
                                       [--warm 3] [--views 4] [--width 40] [--height 30]
                                       [override ...]

For each config: the built-in ``demo`` scene (small; as `tools/count_ops.py` builds it),
two models from the same initialisation, one trained with ``sampler=l0`` and one with
``sampler=hvs``, ``--warm`` untimed steps each, then ``--rounds`` rounds of ``--steps``
timed steps of each, the order alternating from round to round so that load on a shared
machine hits both alike. Prints the median over rounds of the per-round time ratio
l0 / hvs (and each round's), with one torch thread.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time

import torch
from _common import add_scene_args, small_demo_scene

from neus_l0.config.load import load_config
from neus_l0.fields.model import make_model
from neus_l0.sampling.upsample import build_sampler
from neus_l0.train.step import StepSetup, make_optimizer, train_step


def _arm(conf: str, sampler: str, overrides: list[str]):
    cfg = load_config(conf, [f"sampler={sampler}"] + overrides)
    model = make_model(cfg)
    return {"cfg": cfg, "model": model, "opt": make_optimizer(model, cfg),
            "gen": torch.Generator().manual_seed(0), "it": 0,
            "setup": StepSetup(sampler=build_sampler(cfg.sampler))}


def _steps(arm: dict, scene, n: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        train_step(arm["model"], arm["opt"], scene, arm["cfg"], arm["it"], arm["gen"],
                   setup=arm["setup"])
        arm["it"] += 1
    return (time.perf_counter() - t0) / n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--confs", default="demo,fast")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--warm", type=int, default=3)
    add_scene_args(ap, views=4, width=40, height=30)
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        scene = small_demo_scene(tmp, args.views, args.width, args.height)
    for conf in args.confs.split(","):
        arms = {s: _arm(conf, s, args.overrides) for s in ("l0", "hvs")}
        for arm in arms.values():
            _steps(arm, scene, args.warm)
        ratios, per = [], {"l0": [], "hvs": []}
        for r in range(args.rounds):
            order = ("l0", "hvs") if r % 2 == 0 else ("hvs", "l0")
            t = {s: _steps(arms[s], scene, args.steps) for s in order}
            per["l0"].append(t["l0"])
            per["hvs"].append(t["hvs"])
            ratios.append(t["l0"] / t["hvs"])
        print(f"{conf}: l0/hvs median ratio {statistics.median(ratios):.3f} over "
              f"{args.rounds} rounds (rounds: {', '.join(f'{x:.2f}' for x in ratios)}); "
              f"median step l0 {1000 * statistics.median(per['l0']):.0f} ms, hvs "
              f"{1000 * statistics.median(per['hvs']):.0f} ms")


if __name__ == "__main__":
    main()
