"""Training-step cost of configs side by side (interleaved rounds in one process).

Usage: python tools/bench_demo_configs.py --scene DIR --conf demo --conf path/old.yaml \
    [--threads 1] [--rounds 5] [--steps 10]

Builds each config's networks and optimiser on the scene (made with `neus-l0 demo`'s scene
settings if DIR does not exist), runs a few warm-up steps, then `--rounds` rounds in which
every config runs `--steps` training steps in turn; prints the minimum and median seconds
per iteration of each config and its ratio to the first one. Interleaving makes the ratios
fair on a shared machine whose load changes while it runs.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", required=True)
    p.add_argument("--conf", action="append", required=True)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--steps", type=int, default=10)
    args = p.parse_args()
    torch.set_num_threads(args.threads)

    from neus_l0.config.load import load_config
    from neus_l0.fields.model import make_model
    from neus_l0.formats.neus import load_scene
    from neus_l0.pipelines.demo import DEMO_SCENE
    from neus_l0.synthetic.scene import make_scene
    from neus_l0.train.step import make_optimizer, train_step

    if not (Path(args.scene) / "scene.json").is_file():
        make_scene("demo", args.scene, seed=0, progress=False, **DEMO_SCENE)
    runs = []
    for conf in args.conf:
        cfg = load_config(conf)
        scene = load_scene(args.scene, downscale=cfg.data.downscale)
        model = make_model(cfg)
        model.train()
        opt = make_optimizer(model, cfg)
        gen = torch.Generator().manual_seed(0)
        for i in range(3):
            train_step(model, opt, scene, cfg, i, gen)
        runs.append({"conf": conf, "cfg": cfg, "scene": scene, "model": model, "opt": opt,
                     "gen": gen, "it": 3, "times": []})
    for _ in range(args.rounds):
        for r in runs:
            t0 = time.perf_counter()
            for _ in range(args.steps):
                train_step(r["model"], r["opt"], r["scene"], r["cfg"], r["it"], r["gen"])
                r["it"] += 1
            r["times"].append((time.perf_counter() - t0) / args.steps)
    base = min(runs[0]["times"])
    print(f"threads={args.threads} rounds={args.rounds} steps={args.steps}")
    print("| config | rays | samples | min s/it | median s/it | it/s (min) | x first (min) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for r in runs:
        c = r["cfg"]
        m, med = min(r["times"]), statistics.median(r["times"])
        print(f"| {r['conf']} | {c.train.batch_size} | {c.render.n_samples}+"
              f"{c.render.n_importance} | {m:.4f} | {med:.4f} | {1 / m:.1f} | {m / base:.2f} |")


if __name__ == "__main__":
    main()
