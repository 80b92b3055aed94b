"""Dense against sparse mesh extraction: time, SDF evaluations, peak memory.

Usage:
    python tools/bench_mesh.py [--resolutions 128 256 512] [--sparse-only 1024]
                               [--sdf analytic mlp] [--device cpu|cuda] [--threads 1]

Two SDFs: ``analytic`` (a sphere of radius 0.5, exact and cheap: the cost is the grid and
marching cubes) and ``mlp`` (a small random MLP, 3 -> 64 -> 64 -> 1 softplus, plus the
sphere, so its zero set is a bumpy closed surface: the cost is dominated by SDF
evaluations, as with a trained network). Each case runs in a fresh subprocess so that its
peak resident memory (``ru_maxrss``, including torch) is its own; numpy's peak is also read
with tracemalloc. The dense path is `sdf_grid` + `marching_cubes`, the sparse path
`sparse_marching_cubes` with its defaults.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time

CASE = r"""
import json, resource, sys, time, tracemalloc
import torch
from neus_l0.synthetic.shapes import Sphere
from neus_l0.mesh.extract import marching_cubes, sdf_grid, sparse_marching_cubes

method, kind, device = sys.argv[1], sys.argv[2], sys.argv[4]
R, threads = int(sys.argv[3]), int(sys.argv[5])
torch.set_num_threads(threads)
sphere = Sphere((0.0, 0.0, 0.0), 0.5)
if kind == "analytic":
    sdf = sphere
else:
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(3, 64), torch.nn.Softplus(beta=100),
                              torch.nn.Linear(64, 64), torch.nn.Softplus(beta=100),
                              torch.nn.Linear(64, 1)).to(device)
    with torch.no_grad():
        net[-1].weight.mul_(0.02)
        net[-1].bias.zero_()
    def sdf(p):
        return sphere(p) + net(p)[:, 0]
sdf(torch.zeros(4, 3, device=device))
tracemalloc.start()
t0 = time.perf_counter()
if method == "dense":
    V, F = marching_cubes(sdf_grid(sdf, R, device=device))
    evals = R ** 3
else:
    V, F, st = sparse_marching_cubes(sdf, R, device=device)
    evals = st.sdf_evals
if device == "cuda":
    torch.cuda.synchronize()
seconds = time.perf_counter() - t0
_, peak = tracemalloc.get_traced_memory()
print(json.dumps({"seconds": seconds, "evals": evals, "numpy_peak_mb": peak / 2**20,
                  "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "vertices": len(V), "faces": len(F)}))
"""


def run_case(method: str, kind: str, R: int, device: str, threads: int) -> dict:
    """One extraction in a fresh interpreter; its JSON report."""
    out = subprocess.run([sys.executable, "-c", CASE, method, kind, str(R), device, str(threads)],
                         capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolutions", type=int, nargs="+", default=[128, 256, 512])
    ap.add_argument("--sparse-only", type=int, nargs="*", default=[1024])
    ap.add_argument("--sdf", nargs="+", default=["analytic", "mlp"], choices=["analytic", "mlp"])
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()

    print(f"# {platform.processor() or platform.machine()}, python {platform.python_version()}, "
          f"device {args.device}, {args.threads} torch thread(s), {time.strftime('%Y-%m-%d')}")
    print("| SDF | R | dense s | sparse s | speed-up | dense evals | sparse evals | evals saved "
          "| dense peak MB (rss / numpy) | sparse peak MB (rss / numpy) | faces |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for kind in args.sdf:
        for R in list(args.resolutions) + list(args.sparse_only):
            s = run_case("sparse", kind, R, args.device, args.threads)
            if R in args.resolutions:
                d = run_case("dense", kind, R, args.device, args.threads)
                dense = (f"{d['seconds']:.2f}", f"{d['seconds'] / s['seconds']:.1f}x",
                         f"{d['evals']:,}",
                         f"{d['maxrss_mb']:.0f} / {d['numpy_peak_mb']:.0f}")
            else:
                dense = ("-", "-", f"({R**3:,})", "-")
            print(f"| {kind} | {R} | {dense[0]} | {s['seconds']:.2f} | {dense[1]} | {dense[2]} "
                  f"| {s['evals']:,} | {1 - s['evals'] / R**3:.1%} | {dense[3]} "
                  f"| {s['maxrss_mb']:.0f} / {s['numpy_peak_mb']:.0f} | {s['faces']:,} |",
                  flush=True)


if __name__ == "__main__":
    main()
