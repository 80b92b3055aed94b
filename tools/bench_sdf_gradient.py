"""Time one training step with each way of computing the SDF's gradient, side by side.

Usage:
    PYTHONPATH=. python tools/bench_sdf_gradient.py [--conf demo] [--views 8] [--width 100]
        [--height 75] [--warm 150] [--steps 20] [--rounds 3] [--threads 1]
        [--device cpu|cuda] [--methods autograd analytic finite-difference] [override ...]

Builds the built-in ``demo`` scene, trains the config (with ``model.sdf.gradient=autograd``)
for ``--warm`` iterations so the measured state is not the initial sphere, copies that state
into one model per method (`model.sdf.gradient`), and times ``--steps`` calls of
`neus_l0.train.step.train_step` per method, interleaved over ``--rounds`` rounds (load on a shared
machine hits every method alike). Prints per method the best round's it/s and its ratio to
autograd, the aten ops of one step (`tools/count_ops.py`'s counter) and the mean loss of
the timed steps (a sanity check).
"""

from __future__ import annotations

import argparse
import copy
import datetime
import os
import tempfile
import time

import torch
from _common import add_scene_args, device_sync, small_demo_scene
from count_ops import OpCounter

from neus_l0.config.load import load_config
from neus_l0.fields.model import make_model
from neus_l0.train.step import make_occupancy, make_optimizer, make_scaler, train_step


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--conf", default="demo", help="built-in config name or YAML path")
    add_scene_args(ap, views=8, width=100, height=75)
    ap.add_argument("--warm", type=int, default=150, help="training steps before timing")
    ap.add_argument("--steps", type=int, default=20, help="timed steps per round and method")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--methods", nargs="+",
                    default=["autograd", "analytic", "finite-difference"],
                    help="values of model.sdf.gradient to compare")
    ap.add_argument("overrides", nargs="*", help="dotted key=value config overrides")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    sync = device_sync(device)
    with tempfile.TemporaryDirectory() as tmp:
        scene = small_demo_scene(tmp, args.views, args.width, args.height, device)

    base = load_config(args.conf, args.overrides + ["model.sdf.gradient=autograd"])
    model = make_model(base, device)
    opt = make_optimizer(model, base)
    gen = torch.Generator(device=device).manual_seed(0)
    for it in range(args.warm):
        train_step(model, opt, scene, base, it, gen)
    state = copy.deepcopy(model.state_dict())
    opt_state = copy.deepcopy(opt.state_dict())

    runs = {}
    for name in args.methods:
        cfg = load_config(args.conf, args.overrides + [f"model.sdf.gradient={name}"])
        m = make_model(cfg, device)
        m.load_state_dict(state)
        o = make_optimizer(m, cfg)
        o.load_state_dict(opt_state)
        r = {"cfg": cfg, "model": m, "opt": o, "grid": make_occupancy(cfg, device),
             "scaler": make_scaler(cfg, device), "it": args.warm, "its": [], "losses": [],
             "gen": torch.Generator(device=device).manual_seed(1)}
        counter = OpCounter()
        with counter:  # one untimed, counted step (allocator warm-up, grid update)
            train_step(m, o, scene, cfg, r["it"], r["gen"], occupancy=r["grid"],
                       scaler=r["scaler"])
        r["ops"] = sum(counter.counts.values())
        r["it"] += 1
        runs[name] = r
    for _ in range(args.rounds):
        for r in runs.values():
            losses = []
            sync()
            t0 = time.perf_counter()
            for _ in range(args.steps):
                losses.append(train_step(r["model"], r["opt"], scene, r["cfg"], r["it"],
                                         r["gen"], occupancy=r["grid"], scaler=r["scaler"]))
                r["it"] += 1
            sync()
            r["its"].append(args.steps / (time.perf_counter() - t0))
            r["losses"].append(torch.stack(losses)[:, 0].mean().item())
    ref = max(next(iter(runs.values()))["its"])
    print(f"# {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, torch "
          f"{torch.__version__}, device {device}, threads {args.threads}, cpus "
          f"{os.cpu_count()}, load {os.getloadavg()[0]:.1f}; conf {args.conf} "
          f"{' '.join(args.overrides)}; scene demo {args.views} views {args.width}x"
          f"{args.height}; warm-up {args.warm} its; {args.rounds} rounds x {args.steps} steps")
    print(f"| model.sdf.gradient | it/s (best) | x {args.methods[0]} | aten ops / step | loss |")
    print("|---|---:|---:|---:|---:|")
    for name, r in runs.items():
        best = max(r["its"])
        print(f"| {name} | {best:.2f} | {best / ref:.2f} | {r['ops']} | "
              f"{sum(r['losses']) / len(r['losses']):.4f} |")


if __name__ == "__main__":
    main()
