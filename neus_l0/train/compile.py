"""`train.compile`: the training step's render and loss through `torch.compile`.

What is compiled is `neus_l0.train.step.render_and_loss` (rendering, the up-sampling draw, the
networks with their SDF gradient, every loss term); AOT autograd compiles its backward
with it, and the optimiser's update stays eager (fused Adam on CUDA). The step is written
for it: fixed shapes, no host synchronisation, no generator inside (the random numbers
are drawn before, `neus_l0.train.step.draw_step_inputs`), and the SDF gradient without double
backward (``model.sdf.gradient`` `analytic` or `finite-difference`; `autograd` cannot be
compiled, since AOT autograd does not support ``create_graph``).

On CUDA the first choice is ``mode="reduce-overhead"`` (CUDA graphs); if compiling or the
first step fails there, a one-line warning says so and the default mode is used; if that
fails too, the step runs eagerly, again with one line. The compile time (the first step's)
is reported once, and noted in the user's compile record, which `train.compile: auto` reads
(`neus_l0.train.compile_auto`); inductor's cache lives in the user's cache folder.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

import torch

from neus_l0.errors import ConfigError
from neus_l0.train.cache_folder import use_persistent_cache
from neus_l0.train.compile_auto import note_compile, step_key


def _warn(msg: str) -> None:
    print(f"neus-l0: {msg}", file=sys.stderr, flush=True)


class CompiledStep:
    """A compiled `render_and_loss` with its fallbacks (see the module docstring).

    Call it as `render_and_loss` is called. Attributes after the first call:
    ``mode`` (the mode that works, or ``"eager"``) and ``compile_seconds``. With a `key`
    (`neus_l0.train.compile_auto.step_key`), the compile time joins the user's record.
    """

    def __init__(self, fn: Callable, device: torch.device, key: str | None = None) -> None:
        self.fn = fn
        self.key = key
        self.modes = ["reduce-overhead", "default"] if device.type == "cuda" else ["default"]
        self.mode: str | None = None
        self.compiled: Callable | None = None
        self.compile_seconds: float | None = None

    def __call__(self, *args, **kwargs):
        if self.compiled is not None:
            return self.compiled(*args, **kwargs)
        use_persistent_cache()
        t0 = time.monotonic()
        for mode in self.modes:
            candidate = torch.compile(self.fn, mode=mode, fullgraph=True, dynamic=False)
            try:
                out = candidate(*args, **kwargs)
            except Exception as exc:  # noqa: BLE001 - any compiler failure falls back
                reason = str(exc).strip().splitlines()[0][:160] if str(exc).strip() else ""
                _warn(f"torch.compile(mode={mode!r}) failed ({type(exc).__name__}: "
                      f"{reason}); falling back")
                continue
            self.compiled, self.mode = candidate, mode
            self.compile_seconds = time.monotonic() - t0
            _warn(f"compiled the training step (mode={mode!r}) in "
                  f"{self.compile_seconds:.1f} s")
            if self.key is not None:
                note_compile(self.key, self.compile_seconds)
            return out
        self.compiled, self.mode = self.fn, "eager"
        _warn("train.compile: no mode compiled; the step runs eagerly")
        return self.fn(*args, **kwargs)


def compiled_step(fn: Callable, cfg, device: torch.device) -> CompiledStep | None:
    """`CompiledStep(fn)` when ``train.compile`` is true, else None (resolve ``auto`` first:
    `neus_l0.train.compile_auto.resolve_compile`).

    Raises:
        ConfigError: ``train.compile`` with ``model.sdf.gradient=autograd``, or still ``auto``.
    """
    if cfg.train.compile == "auto":
        raise ConfigError("train.compile=auto must be resolved before the run is built "
                          "(neus_l0.train.compile_auto.resolve_compile)")
    if not cfg.train.compile:
        return None
    if cfg.model.sdf.gradient == "autograd":
        raise ConfigError("train.compile=true needs model.sdf.gradient=analytic or "
                          "finite-difference (autograd's double backward cannot be compiled)")
    device = torch.device(device)
    return CompiledStep(fn, device, key=step_key(cfg, device.type))
