"""Time the training step with and without each work-skipping switch, side by side.

Usage:
    python tools/bench_train_step.py [--conf demo] [--views 8] [--width 100] [--height 75]
                                     [--warm 150] [--steps 20] [--rounds 3] [--threads 1]
                                     [--device cpu|cuda] [--compile] [--only VARIANT ...]
                                     [override ...]

Builds the built-in ``demo`` scene (`neus_l0.synthetic.scene.make_scene`), trains the config
for ``--warm`` iterations (the baseline, so the shape has moved away from the initial
sphere and s has grown), then copies that state into one model per variant and times
``--steps`` training steps of each, interleaved over ``--rounds`` rounds (so load on a
shared machine hits every variant alike). Reported per variant: the best round's
iterations/s and its ratio to the baseline, the SDF points evaluated per iteration
(up-sampling, the rendering pass and the amortised grid updates, counted by a wrapper of
the SDF network), the fraction of rays that got samples, the samples per such
ray, and the loss over the timed steps (a sanity check: variants should stay close).

Variants: ``baseline`` (NeuS), ``sphere`` (`render.cull_outside_sphere`), ``grid``
(`render.occupancy.enabled`), ``grid+eik0.25`` (also `train.eikonal_fraction=0.25`),
``eik0.25`` alone, and on CUDA ``amp-bf16`` / ``amp-fp16`` and ``grid+amp-bf16``. With
``--compile`` a ``compile-color`` variant runs the colour network through `torch.compile`,
and ``compile-step`` the whole
render and loss (`train.compile`, with the analytic SDF gradient, whose eager cost is the
``analytic`` variant; ``finite-difference`` is the other double-backward-free gradient).
"""

from __future__ import annotations

import argparse
import copy
import datetime
import os
import platform
import statistics
import tempfile
import time

import torch
from _common import add_scene_args, device_sync, small_demo_scene

from neus_l0.config.load import load_config
from neus_l0.fields.model import make_model
from neus_l0.sampling.upsample import build_sampler
from neus_l0.train.compile import compiled_step
from neus_l0.train.step import (
    StepSetup,
    make_occupancy,
    make_optimizer,
    make_scaler,
    render_and_loss,
    train_step,
)


def variants(device: str, compile_: bool) -> dict[str, list[str]]:
    v = {
        "baseline": [],
        "sphere": ["render.cull_outside_sphere=true"],
        "grid": ["render.occupancy.enabled=true"],
        "eik0.25": ["train.eikonal_fraction=0.25"],
        "analytic": ["model.sdf.gradient=analytic"],
        "finite-difference": ["model.sdf.gradient=finite-difference"],
        "grid+eik0.25": ["render.occupancy.enabled=true", "train.eikonal_fraction=0.25"],
    }
    if device == "cuda":
        v["amp-bf16"] = ["train.amp=bf16"]
        v["amp-fp16"] = ["train.amp=fp16"]
        v["grid+amp-bf16"] = ["render.occupancy.enabled=true", "train.amp=bf16"]
    if compile_:
        v["compile-color"] = []
        v["compile-step"] = ["train.compile=true", "model.sdf.gradient=analytic"]
    return v


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--conf", default="demo")
    add_scene_args(ap, views=8, width=100, height=75)
    ap.add_argument("--warm", type=int, default=150)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--compile", action="store_true")
    ap.add_argument("--only", nargs="+", default=None, metavar="VARIANT",
                    help="time only these variants (baseline is always kept)")
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    sync = device_sync(device)

    with tempfile.TemporaryDirectory() as tmp:
        scene = small_demo_scene(tmp, args.views, args.width, args.height, device)

    base_cfg = load_config(args.conf, args.overrides)
    # Warm-up: train the baseline so that the measured state is not the initial sphere.
    model = make_model(base_cfg, device)
    opt = make_optimizer(model, base_cfg)
    gen = torch.Generator(device=device).manual_seed(0)
    t0 = time.perf_counter()
    for it in range(args.warm):
        train_step(model, opt, scene, base_cfg, it, gen)
    sync()
    warm_s = time.perf_counter() - t0
    state = copy.deepcopy(model.state_dict())

    runs = {}
    chosen = variants(device.type, args.compile)
    if args.only:
        unknown = set(args.only) - set(chosen)
        if unknown:
            ap.error(f"--only: unknown variants {sorted(unknown)} (have {sorted(chosen)})")
        chosen = {k: v for k, v in chosen.items() if k == "baseline" or k in args.only}
    for name, extra in chosen.items():
        cfg = load_config(args.conf, ["train.compile=false", *args.overrides, *extra])
        m = make_model(cfg, device)
        m.load_state_dict(state)
        if name == "compile-color":
            m.color = torch.compile(m.color)
        o = make_optimizer(m, cfg)
        counter = {"points": 0}

        def count(mod, inp, c=counter):
            c["points"] += inp[0].shape[0]

        m.sdf.register_forward_pre_hook(count)  # the rendering pass (module call)
        plain_sdf = m.sdf.sdf  # up-sampling and grid updates call .sdf() directly

        def counted_sdf(x, f=plain_sdf, c=counter):
            c["points"] += x.shape[0]
            return f(x)

        m.sdf.sdf = counted_sdf
        setup = StepSetup(sampler=build_sampler(cfg.sampler),
                          compiled=compiled_step(render_and_loss, cfg, device))
        runs[name] = {"cfg": cfg, "model": m, "opt": o, "scaler": make_scaler(cfg, device),
                      "setup": setup,
                      "grid": make_occupancy(cfg, device), "counter": counter,
                      "gen": torch.Generator(device=device).manual_seed(1),
                      "its": [], "points": 0, "losses": [], "active": [], "it": args.warm}
        # one untimed step (grid update at the first step, compilation, allocator warm-up)
        r = runs[name]
        train_step(m, o, scene, cfg, args.warm - args.warm % cfg.render.occupancy.update_every,
                   r["gen"], occupancy=r["grid"], scaler=r["scaler"], setup=setup)
    for _ in range(args.rounds):
        for r in runs.values():
            cfg, m = r["cfg"], r["model"]
            r["counter"]["points"] = 0
            losses = []
            sync()
            t0 = time.perf_counter()
            for _ in range(args.steps):
                losses.append(train_step(m, r["opt"], scene, cfg, r["it"], r["gen"],
                                         occupancy=r["grid"], scaler=r["scaler"],
                                         setup=r["setup"]))
                r["it"] += 1
            sync()
            r["its"].append(args.steps / (time.perf_counter() - t0))
            r["points"] = r["counter"]["points"] / args.steps
            r["losses"].append(torch.stack(losses)[:, 0].mean().item())
    # Active rays and samples per active ray, on one batch per variant (outside the timing).
    from neus_l0.data.rays import random_rays
    from neus_l0.render.volume import render_rays

    for r in runs.values():
        cfg = r["cfg"]
        b = random_rays(scene, cfg.train.batch_size, torch.Generator(device=device)
                        .manual_seed(2))
        with torch.no_grad():
            grid = (r["grid"],) if r["grid"] is not None else ()
            out = render_rays(r["model"], b["origins"], b["dirs"], cfg.render,
                              build_sampler(cfg.sampler),
                              bounds=grid)
        r["active"] = out.active.float().mean().item()
        r["per_ray"] = out.t.shape[1]
        r["occ"] = r["grid"].fraction_occupied().item() if r["grid"] is not None else 1.0

    base = max(runs["baseline"]["its"])
    c = base_cfg
    print(f"# {datetime.date.today()} {platform.processor() or platform.machine()} "
          f"torch {torch.__version__} device {device} threads {args.threads} "
          f"cpus {os.cpu_count()} load {os.getloadavg()[0]:.1f}")
    print(f"# conf {args.conf} {' '.join(args.overrides)}: batch {c.train.batch_size}, "
          f"samples {c.render.n_samples}+{c.render.n_importance}, sampler {c.sampler.name}, "
          f"sdf {c.model.sdf.layers}x{c.model.sdf.hidden}; scene demo {args.views} views "
          f"{args.width}x{args.height}; warm-up {args.warm} its ({warm_s:.0f} s); "
          f"{args.rounds} rounds x {args.steps} steps")
    print("| variant | it/s (best) | x baseline | SDF points / it | active rays | "
          "samples / active ray | occupied cells | loss |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, r in runs.items():
        best = max(r["its"])
        print(f"| {name} | {best:.2f} | {best / base:.2f} | {r['points']:.0f} | "
              f"{r['active']:.2f} | {r['per_ray']} | {r['occ']:.3f} | "
              f"{statistics.mean(r['losses']):.4f} |")


if __name__ == "__main__":
    main()
