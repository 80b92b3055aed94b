"""Time the L0-Sampler (each kind) against NeRF's sample_pdf on the same rays.

Usage:
    python tools/bench_sampler.py [--rays 4096] [--points 128] [--samples 64] [--repeat 50]
                                  [--device cpu|cuda|all] [--dtype float32|float64]
                                  [--compile] [--count-ops]

`sample_l0_sections` (the default `l0` draw) and `sample_neus_sections` (`neus-exact`) get the
section weights as `sample_pdf` does. All samplers get the same NeuS-like rays: N sorted
positions with a sharp surface peak.
``sample_pdf`` gets the N-1 section weights (bins = the N positions), ``sample_l0`` the N
point weights, so both draw from the same coarse information. Prints the minimum and median
time per call and the ratio of minima to ``sample_pdf``, measured side by side, interleaved,
in one process. Every draw is timed with ``check=False``, as the up-sampling calls it (the
positions' check, one pass and a host synchronisation, is left out). With ``--compile`` the
exp draw and ``sample_pdf`` also run through `torch.compile` (``dynamic=True``,
``det=True``, as `render.compile_sampler` uses it; compiled in the warm-up), beside their
eager ``det=True`` calls.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import torch

from neus_l0.sampling.kernels import sample_l0, sample_l0_sections, sample_neus_sections, sample_pdf


def make_rays(n_rays: int, n_points: int, device: str, dtype: torch.dtype,
              seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """NeuS-like rays: positions (R, N) in [near, far], point weights (R, N), sections (R, N-1)."""
    g = torch.Generator().manual_seed(seed)
    near = 0.5 + torch.rand(n_rays, 1, generator=g)
    t = near + 2.0 * torch.linspace(0, 1, n_points).expand(n_rays, -1)
    t = t + torch.rand(n_rays, n_points, generator=g) * (2.0 / n_points) * 0.5
    t, _ = torch.sort(t, dim=-1)
    surf = near + 0.3 + 1.4 * torch.rand(n_rays, 1, generator=g)
    width = 0.005 + 0.05 * torch.rand(n_rays, 1, generator=g)
    w = torch.exp(-0.5 * ((t - surf) / width) ** 2)
    w_sec = 0.5 * (w[:, 1:] + w[:, :-1])
    return (t.to(device=device, dtype=dtype), w.to(device=device, dtype=dtype),
            w_sec.to(device=device, dtype=dtype))


def time_fn(fn, device: str, repeat: int, warmup: int = 5) -> list[float]:
    """Wall times of ``repeat`` calls of fn() in milliseconds (synchronising CUDA)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        if device == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device == "cuda":
            torch.cuda.synchronize()
        times.append((time.perf_counter() - t0) * 1e3)
    return times


def count_ops(fn) -> int:
    """aten ops one call of fn() dispatches (a `TorchDispatchMode` counter)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class _Count(TorchDispatchMode):
        n = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            _Count.n += 1
            return func(*args, **(kwargs or {}))

    with _Count():
        fn()
    return _Count.n


def bench(device: str, args: argparse.Namespace) -> list[tuple[str, float, float, float]]:
    """(name, min ms, median ms, ratio of minima to sample_pdf) per sampler on one device.

    Rounds are interleaved so that drifting machine load hits every sampler alike; the
    minimum over calls is the least disturbed estimate on a shared machine.
    """
    dtype = getattr(torch, args.dtype)
    t, w, w_sec = make_rays(args.rays, args.points, device, dtype)
    sdf = 1.2 - t  # a plane's SDF for neus-exact's estimates (its cost does not depend on them)
    n = args.samples
    fns = {
        "sample_pdf (HVS)": lambda: sample_pdf(t, w_sec, n, det=False, check=False),
        "sample_l0 exp": lambda: sample_l0(t, w, n, kind="exp", det=False, check=False),
        "sample_l0 inverse": lambda: sample_l0(t, w, n, kind="inverse", det=False, check=False),
        "sample_l0 linear": lambda: sample_l0(t, w, n, kind="linear", det=False, check=False),
        "l0 sections (exp)": lambda: sample_l0_sections(t, w_sec, n, det=False, check=False),
        "neus-exact": lambda: sample_neus_sections(t, w_sec, sdf[:, :-1], sdf[:, 1:], 256.0,
                                                   n, det=False, check=False),
    }
    if args.compile:
        c_l0 = torch.compile(sample_l0, dynamic=True)
        c_pdf = torch.compile(sample_pdf, dynamic=True)
        # det=True, as the up-sampling draws (dynamo cannot trace torch.rand with symbolic
        # shapes); the eager det=True draws are timed beside them.
        fns["pdf det"] = lambda: sample_pdf(t, w_sec, n, det=True, check=False)
        fns["compiled pdf det"] = lambda: c_pdf(t, w_sec, n, det=True, check=False)
        fns["l0 exp det"] = lambda: sample_l0(t, w, n, kind="exp", det=True, check=False)
        fns["compiled l0 exp det"] = lambda: c_l0(t, w, n, kind="exp", det=True, check=False)
    if args.count_ops:
        return [(k, float(count_ops(fn)), float("nan"), float("nan")) for k, fn in fns.items()]
    per: dict[str, list[float]] = {k: [] for k in fns}
    rounds = 10
    for _ in range(rounds):
        for k, fn in fns.items():
            per[k] += time_fn(fn, device, max(args.repeat // rounds, 1), warmup=1)
    base = min(per["sample_pdf (HVS)"])
    return [(k, min(v), statistics.median(v), min(v) / base) for k, v in per.items()]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rays", type=int, default=4096)
    p.add_argument("--points", type=int, default=128)
    p.add_argument("--samples", type=int, default=64)
    p.add_argument("--repeat", type=int, default=50)
    p.add_argument("--device", default="all", choices=["cpu", "cuda", "all"])
    p.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: default)")
    p.add_argument("--count-ops", action="store_true",
                   help="print the aten ops one call of each sampler dispatches (no timing)")
    p.add_argument("--compile", action="store_true",
                   help="also time torch.compile'd sample_l0 (exp) and sample_pdf")
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    devices = ["cpu", "cuda"] if args.device == "all" else [args.device]
    devices = [d for d in devices if d == "cpu" or torch.cuda.is_available()]
    print(f"torch {torch.__version__}, {platform.processor() or platform.machine()}, "
          f"{torch.get_num_threads()} threads; {args.rays} rays x {args.points} points -> "
          f"{args.samples} samples, {args.dtype}, det=False")
    for dev in devices:
        name = torch.cuda.get_device_name() if dev == "cuda" else "cpu"
        print(f"\n{dev} ({name})")
        rows = bench(dev, args)
        if args.count_ops:
            print(f"{'sampler':<20} {'aten ops':>9}")
            for k, n, _, _ in rows:
                print(f"{k:<20} {int(n):>9}")
            continue
        print(f"{'sampler':<20} {'min ms':>9} {'median ms':>10} {'x sample_pdf (min)':>19}")
        for k, lo, med, ratio in rows:
            print(f"{k:<20} {lo:>9.3f} {med:>10.3f} {ratio:>19.2f}")


if __name__ == "__main__":
    main()
