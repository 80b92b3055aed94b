"""What a cold `train.compile` costs, under inductor settings, each from an empty cache.

Usage (from the repository root):
    python tools/bench_cold_compile.py [--settings default,warm,cpp_wrapper,no_vec,one_worker]
                                       [--conf demo] [override ...]

Each setting runs in a fresh process with its own empty ``TORCHINDUCTOR_CACHE_DIR`` (``warm``
re-runs ``default``'s cache): `demo`'s step (``model.sdf.gradient=analytic``) on the small
built-in scene (6 views, 80x60, one torch thread), the first (compiling) step timed, then 10
steps. Prints one row per setting: first step, 10 steps, the process's wall time and how many
C++ kernel files inductor wrote, and the phase times of `torch._dynamo.utils.compile_times`
with ``--phases``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: Environment of each setting (on top of an empty cache folder).
SETTINGS = {
    "default": {},
    "warm": {},
    "cpp_wrapper": {"TORCHINDUCTOR_CPP_WRAPPER": "1"},
    "no_vec": {"TORCHINDUCTOR_VEC_ISA_OK": "0"},
    "one_worker": {"TORCHINDUCTOR_COMPILE_THREADS": "1"},
}


def child(conf: str, overrides: list[str], phases: bool) -> None:
    """The measured process: one compiling step, then 10 steps; prints a JSON line."""
    import torch
    from _common import small_demo_scene

    from neus_l0.config.load import load_config
    from neus_l0.fields.model import make_model
    from neus_l0.train.compile import CompiledStep
    from neus_l0.train.step import StepSetup, make_optimizer, render_and_loss, train_step

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        scene = small_demo_scene(tmp, views=6, width=80, height=60)
    cfg = load_config(conf, ["model.sdf.gradient=analytic", "train.warm_up=0",
                             "train.compile=true", *overrides])
    model = make_model(cfg)
    opt = make_optimizer(model, cfg)
    g = torch.Generator().manual_seed(0)
    setup = StepSetup(compiled=CompiledStep(render_and_loss, torch.device("cpu")))
    t0 = time.perf_counter()
    train_step(model, opt, scene, cfg, 0, g, setup=setup)[0].item()
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    for it in range(1, 11):
        train_step(model, opt, scene, cfg, it, g, setup=setup)[0].item()
    out = {"first_s": first, "ten_steps_s": time.perf_counter() - t0}
    if phases:
        out["phases"] = torch._dynamo.utils.compile_times()
    print("RESULT " + json.dumps(out), flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--settings", default="default,warm,cpp_wrapper,no_vec,one_worker")
    p.add_argument("--conf", default="demo")
    p.add_argument("--phases", action="store_true", help="print compile_times() per setting")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("overrides", nargs="*")
    args = p.parse_args()
    if args.child:
        child(args.conf, args.overrides, args.phases)
        return
    root = Path(tempfile.mkdtemp(prefix="cold_compile_"))
    print(f"{'setting':<12} {'first step':>11} {'10 steps':>9} {'process':>8} {'kernels':>8}")
    for name in args.settings.split(","):
        cache = root / ("default" if name == "warm" else name)
        env = {**os.environ, **SETTINGS[name], "TORCHINDUCTOR_CACHE_DIR": str(cache)}
        cmd = [sys.executable, __file__, "--child", "--conf", args.conf, *args.overrides]
        if args.phases:
            cmd.insert(2, "--phases")
        t0 = time.perf_counter()
        run = subprocess.run(cmd, env=env, capture_output=True, text=True,
                             cwd=Path(__file__).parent)
        wall = time.perf_counter() - t0
        line = [ln for ln in run.stdout.splitlines() if ln.startswith("RESULT ")]
        if run.returncode or not line:
            print(f"{name:<12} failed: {run.stderr.strip().splitlines()[-1:]}")
            continue
        r = json.loads(line[0][7:])
        kernels = len(list(cache.rglob("*.cpp")))
        print(f"{name:<12} {r['first_s']:>10.1f}s {r['ten_steps_s']:>8.2f}s {wall:>7.1f}s "
              f"{kernels:>8}", flush=True)
        if args.phases:
            print(r["phases"])


if __name__ == "__main__":
    main()
