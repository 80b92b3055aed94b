"""The training step on a GPU: it/s eager and compiled, GPU busy fraction, kernel launches,
peak memory, at several batch sizes (issue #16's measurement, one command).

Usage (on a CUDA machine; also runs on the CPU, where "busy" is the CPU kernels' share):
    python tools/bench_gpu_step.py [--conf fast] [--rays 1024,4096] [--views 49]
                                   [--width 400] [--height 300] [--warm 30] [--steps 50]
                                   [--modes eager,compiled] [override ...]

Builds the built-in ``demo`` scene at the given size (`make_scene`, cached in a temporary
folder), then per (rays, mode): the model and optimiser of the config, ``--warm`` untimed
steps (compilation included for ``compiled``, whose compile time is printed), ``--steps``
timed steps (it/s after `torch.cuda.synchronize`), and one profiled step (torch.profiler):
the number of device kernels launched and the device time over the step's wall time.
``compiled`` sets ``train.compile=true`` (CUDA graphs first, see `neus_l0.train.compile`).
Prints a Markdown table for docs/BENCHMARKS.md. The time to reach a fixed Chamfer is measured
by `tools/bench_fast_vs_neus.py` (Chamfer against wall-clock from snapshot checkpoints).
"""

from __future__ import annotations

import argparse
import datetime
import tempfile
import time
from pathlib import Path

import torch
from _common import add_scene_args, small_demo_scene

from neus_l0.config.load import load_config
from neus_l0.train.loop import build_run_state
from neus_l0.train.step import train_step


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _profile(step, device: torch.device) -> tuple[int, float, float]:
    """Kernels launched, device busy time (s) and wall time (s) of one step."""
    from torch.profiler import ProfilerActivity, profile

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    _sync(device)
    t0 = time.perf_counter()
    with profile(activities=acts) as prof:
        step()
        _sync(device)
    wall = time.perf_counter() - t0
    events = [e for e in prof.events() if e.device_type.name == ("CUDA" if device.type == "cuda"
                                                                 else "CPU")]
    if device.type == "cuda":
        kernels = [e for e in events if e.device_time > 0]
        busy = sum(e.device_time for e in kernels) / 1e6
    else:
        kernels = [e for e in events if e.name.startswith("aten::") and not e.cpu_parent]
        busy = sum(e.cpu_time for e in kernels) / 1e6
    return len(kernels), busy, wall


def run(scene, conf: str, overrides: list[str], rays: int, mode: str, args,
        tmp: Path) -> str:
    extra = [f"train.batch_size={rays}", "train.tensorboard=false", "train.warm_up=0"]
    # `auto` would compile a long config's "eager" arm too: each mode says what it is
    extra += ["train.compile=true" if mode == "compiled" else "train.compile=false"]
    cfg = load_config(conf, overrides + extra)
    run = build_run_state(scene, cfg, tmp / f"{rays}_{mode}", scene.device, resume=False)
    setup = run.setup  # the hull bounds, sampler, pixel pool and (compiled) step
    it = [0]

    def step():
        train_step(run.model, run.optimizer, run.scene, cfg, it[0], run.generator,
                   occupancy=run.occupancy, scaler=run.scaler, setup=setup)
        it[0] += 1

    if scene.device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    for _ in range(args.warm):
        step()
    _sync(scene.device)
    warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(args.steps):
        step()
    _sync(scene.device)
    its = args.steps / (time.perf_counter() - t0)
    kernels, busy, wall = _profile(step, scene.device)
    peak = (torch.cuda.max_memory_allocated() / 2**30 if scene.device.type == "cuda"
            else float("nan"))
    return (f"| {conf} | {rays} | {mode} | {its:.1f} | {busy / wall:.0%} | {kernels} | "
            f"{peak:.2f} | {warm:.1f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--conf", default="fast")
    ap.add_argument("--rays", default="1024,4096")
    add_scene_args(ap, views=49, width=400, height=300)
    ap.add_argument("--warm", type=int, default=30)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--modes", default="eager,compiled")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args()
    device = torch.device(args.device)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        scene = small_demo_scene(tmp, args.views, args.width, args.height, device)
        name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
        print(f"# {datetime.date.today()} {name}, torch {torch.__version__}; scene demo "
              f"{args.views} views {args.width}x{args.height}; {args.warm} warm + "
              f"{args.steps} timed steps")
        print("| conf | rays | mode | it/s | busy | kernels / step | peak GiB | warm-up s |")
        print("|---|---:|---|---:|---:|---:|---:|---:|")
        for rays in (int(r) for r in args.rays.split(",")):
            for mode in args.modes.split(","):
                print(run(scene, args.conf, args.overrides, rays, mode, args, tmp), flush=True)


if __name__ == "__main__":
    main()
