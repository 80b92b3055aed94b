"""`train.compile: auto`: compile the training step when the run is long enough to repay it.

The compiled step (`neus_l0.train.compile`) is faster than the eager one, but compiling
costs tens of seconds with an empty inductor cache and seconds with a warm one, which a short
run does not win back (docs/BENCHMARKS.md, "When does the step compile, and what does a cold
compile cost?"). `auto` weighs the two:

    saving  = min(iterations left x eager step, train.max_seconds) x (1 - compiled fraction)
    compile = the expected compile time (warm when this step was compiled here before),
              scaled on the CPU by how much slower than the cost model the eager step ran
              (`machine_speed`)

and compiles when the saving is larger. The eager step time is measured: a few timed eager
steps on the run itself, undone after (`neus_l0.train.probe`), noted in a small record in
the user's cache (`compile_record_path`) so that the next run of the setting reads it. A
cost model (seconds per ray sample on the CPU, a launch-bound constant on CUDA) only
decides whether measuring is worth it: when even a step `UNSEEN_FACTOR` times slower than
it would not repay a warm compile, the run stays eager unmeasured. The compile time comes
from the same record, which every compile updates. Compiling
needs an SDF gradient without double backward: `auto` takes ``model.sdf.gradient=analytic``
(equal to autograd's to float rounding, `neus_l0.fields.sdf`) in place of ``autograd``.

The inductor cache lives under the same cache folder (`neus_l0.train.cache_folder`), so the
second run of a config pays the warm time, also after /tmp is cleared.

A run's ``config.yaml`` records the resolved choice (``train.compile: true`` or ``false``), so
a resume computes what the run computed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from neus_l0.atomic import atomic_write_json
from neus_l0.config.load import load_config, non_default, to_dict
from neus_l0.config.schema import Config
from neus_l0.errors import NeusL0Error
from neus_l0.run.resumes import recorded_overrides
from neus_l0.train.cache_folder import compile_record_path

#: Seconds per ray sample of an eager CPU step on one thread, from `demo`'s eager step
#: (docs/BENCHMARKS.md, "How fast is a training step").
EAGER_CPU_S_PER_SAMPLE = 9.1e-6
#: An eager CUDA step is launch-bound (its kernel launches, not its arithmetic, set the
#: time), so one constant stands for it (docs/benchmarks/training-step.md, "Numbers moved
#: from code comments").
EAGER_CUDA_STEP_S = 0.04
#: Compiled step time / eager step time, measured and rounded up: the CPU's from `demo`
#: (docs/BENCHMARKS.md, "How fast is a training step"), CUDA's from `fast` at 4096 rays on
#: an H100 (25.7 it/s eager, 66.8 compiled: 0.385; docs/BENCHMARKS.md, "GPU").
COMPILED_FRACTION = {"cpu": 0.45, "cuda": 0.4}
#: Expected compile seconds with an empty inductor cache: the CPU's is the slow case (one
#: thread, another process running), so that `auto` does not compile on a hope
#: (docs/BENCHMARKS.md, "When does the step compile, and what does a cold compile cost?");
#: on an H100 `fast` compiled in 54 s and NeuS's `wmask` in 103 s.
COLD_COMPILE_S = {"cpu": 45.0, "cuda": 90.0}
#: Expected compile seconds when this step compiled here before, above the measured warm
#: compile (docs/BENCHMARKS.md, "When does the step compile, and what does a cold compile
#: cost?"); once the record holds a warm compile, its time replaces this.
WARM_COMPILE_S = {"cpu": 12.0, "cuda": 20.0}
#: The most a measured eager step may scale the expected compile (`machine_speed`).
MAX_SLOWDOWN = 8.0
#: How far the cost model may be off for a setting never measured here (it said 0.6 s for
#: a `wmask` step that took 14-20 s on a 2-core CPU).
UNSEEN_FACTOR = 30.0
#: Config sections that do not change the compiled graph (the optimiser and the schedule run
#: outside it); everything else in the config is part of the record's key.
_NOT_IN_GRAPH = ("iters", "lr", "lr_alpha", "lr_decay_iters", "warm_up", "seed", "log_every",
                 "val_every", "val_downscale", "save_every", "keep_checkpoints", "max_seconds",
                 "compile", "tensorboard", "threads", "budget", "budget_up_to_iters",
                 "early_stop")


def step_key(cfg: Config, device: str) -> str:
    """A short hash of what shapes the compiled step: torch's version, the device type, on
    the CPU the torch thread count (inductor's C++ kernels are built for it: a cache warmed
    at 2 threads recompiles at 1), and the config's keys that differ from the schema's
    defaults, but the schedule and logging (`_NOT_IN_GRAPH`). Keyed on the differences, a
    key added to the schema at its default leaves every record's key as it was (the record
    is a hint for `auto`; inductor's own cache is keyed on the graph)."""
    d = non_default(to_dict(cfg), to_dict(Config()))
    d["train"] = {k: v for k, v in d.get("train", {}).items() if k not in _NOT_IN_GRAPH}
    threads = torch.get_num_threads() if device == "cpu" else None
    text = json.dumps([torch.__version__, device, threads, d], sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def read_record(path: Path | None = None) -> dict:
    """The compile record (``{key: {"compiles": n, "seconds": s}}``); empty when missing or
    unreadable (it is a hint, never a reason to fail)."""
    path = path or compile_record_path()
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def note_compile(key: str, seconds: float, path: Path | None = None) -> None:
    """Add one measured compile to the record (silently skipped when the cache is not
    writable)."""
    path = path or compile_record_path()
    record = read_record(path)
    entry = record.get(key) if isinstance(record.get(key), dict) else {}
    record[key] = {"compiles": int(entry.get("compiles", 0)) + 1, "seconds": round(seconds, 2)}
    try:
        atomic_write_json(path, record)
    except OSError:
        pass


def eager_key(cfg: Config, device: str) -> str:
    """The record's key of `cfg`'s measured eager step."""
    return "eager:" + step_key(cfg, device)


def note_eager(key: str, seconds: float, path: Path | None = None) -> None:
    """Record a measured eager step (`eager_key`; silently skipped when not writable)."""
    path = path or compile_record_path()
    record = read_record(path)
    record[key] = {"eager_s": round(seconds, 4)}
    try:
        atomic_write_json(path, record)
    except OSError:
        pass


def recorded_eager(record: dict, key: str) -> float | None:
    """The eager step the record holds for `key`, if any."""
    entry = record.get(key)
    value = entry.get("eager_s") if isinstance(entry, dict) else None
    return float(value) if isinstance(value, (int, float)) and value > 0 else None


@dataclass(frozen=True)
class CompileChoice:
    """What `choose_compile` decided and from which estimates (seconds)."""

    compile: bool
    eager_step_s: float
    saving_s: float
    compile_s: float
    warm: bool
    measured: bool = False

    def line(self, why: str = "") -> str:
        """One line saying what was chosen and why."""
        cache = "warm cache" if self.warm else "empty cache"
        how = "measured" if self.measured else "estimated"
        if self.compile:
            return (f"train.compile=auto: compiling the step (it should save "
                    f"~{self.saving_s:.0f} s of eager steps at "
                    f"~{1000 * self.eager_step_s:.0f} ms, {how}; compiling costs "
                    f"~{self.compile_s:.0f} s, {cache}){why}")
        return (f"train.compile=auto: eager (compiling would cost ~{self.compile_s:.0f} s, "
                f"{cache}, to save ~{self.saving_s:.0f} s of eager steps at "
                f"~{1000 * self.eager_step_s:.0f} ms, {how}){why}")


def eager_step_seconds(cfg: Config, device: str) -> float:
    """The cost model's eager step time: samples per step x seconds per sample on the CPU
    (divided by the threads, which scale about 1.4x at 2), a constant on CUDA."""
    if device == "cuda":
        return EAGER_CUDA_STEP_S
    r = cfg.render
    samples = cfg.train.batch_size * (r.n_samples + r.n_importance + r.n_outside)
    threads = max(1, torch.get_num_threads())
    return EAGER_CPU_S_PER_SAMPLE * samples / threads ** 0.5


def machine_speed(measured_s: float | None, modelled_s: float) -> float:
    """How many times slower than the cost model's machine this one runs the step: the
    measured eager step over the modelled one, in [1, `MAX_SLOWDOWN`] (1 unmeasured).

    The expected compile times are a faster machine's; compiling (tracing, then g++ on each
    kernel) slows down with the machine as the eager step does. On a VM where the eager
    `demo` step took 2-4x the model's, a cold compile took 70-170 s against the 45 s
    expected, and the demo's first run, compiling, trained one iteration in its 124 s.
    """
    if not measured_s or modelled_s <= 0:
        return 1.0
    return min(MAX_SLOWDOWN, max(1.0, measured_s / modelled_s))


def _steps_time(cfg: Config, start_iteration: int, step: float) -> float:
    """Seconds of eager steps the run would take (a budget fills its time with steps)."""
    left = max(0, cfg.train.iters - start_iteration) * step
    if cfg.train.budget > 0:
        return min(cfg.train.budget, left) if cfg.train.budget_up_to_iters else cfg.train.budget
    return min(left, cfg.train.max_seconds) if cfg.train.max_seconds > 0 else left


def worth_measuring(cfg: Config, device: str, start_iteration: int = 0) -> bool:
    """Whether compiling could repay a warm compile if the eager step were `UNSEEN_FACTOR`
    times the cost model's (else the run stays eager without measuring)."""
    kind = "cuda" if device == "cuda" else "cpu"
    step = UNSEEN_FACTOR * eager_step_seconds(cfg, kind)
    saving = _steps_time(cfg, start_iteration, step) * (1.0 - COMPILED_FRACTION[kind])
    return saving > WARM_COMPILE_S[kind]


def choose_compile(cfg: Config, device: str, start_iteration: int = 0,
                   record: dict | None = None, eager_s: float | None = None) -> CompileChoice:
    """Whether `auto` compiles a run of `cfg` on `device` from `start_iteration` (pure but
    for the thread count the cost model reads).

    Args:
        record: the compile record (`read_record`); its entry for `step_key` means a warm
            cache, its `eager_key` entry a measured eager step.
        eager_s: a measured eager step (else the record's, else the cost model's).
    """
    kind = "cuda" if device == "cuda" else "cpu"
    measured = eager_s or recorded_eager(record or {}, eager_key(cfg, kind))
    modelled = eager_step_seconds(cfg, kind)
    step = measured or modelled
    saving = _steps_time(cfg, start_iteration, step) * (1.0 - COMPILED_FRACTION[kind])
    entry = (record or {}).get(step_key(as_compiled(cfg), kind))
    warm = isinstance(entry, dict) and entry.get("compiles", 0) > 0
    slower = machine_speed(measured, modelled) if kind == "cpu" else 1.0
    expected = COLD_COMPILE_S[kind] * slower
    if warm:
        expected = WARM_COMPILE_S[kind] * slower
        if entry.get("compiles", 0) > 1:  # its last compile was itself a warm one
            expected = max(1.0, float(entry.get("seconds", expected)))
    # A budget run plans its iterations after the compile, from the time it took: a warm
    # cache that missed costs iterations, never the budget, so a budget counts the warm
    # compile as any run does (counting a cold one left 60 s budgets eager at twice the
    # step time, docs/BENCHMARKS.md "What does a --budget buy").
    return CompileChoice(compile=saving > expected, eager_step_s=step, saving_s=saving,
                         compile_s=expected, warm=warm, measured=measured is not None)


def _measured_eager(cfg: Config, device: str, start_iteration: int,
                    measure: Callable[[], float] | None) -> float | None:
    """`measure()` when the record has no eager step for `cfg` and measuring is worth it
    (noted in the record), else None."""
    kind = "cuda" if device == "cuda" else "cpu"
    key = eager_key(cfg, kind)
    if measure is None or recorded_eager(read_record(), key) is not None \
            or not worth_measuring(cfg, kind, start_iteration):
        return None
    seconds = measure()
    note_eager(key, seconds)
    return seconds


def _run_choice(run_dir: Path | None) -> bool | None:
    """The compile choice a run folder recorded (``config.yaml`` with its resumes' overrides,
    as a resume reads it: `neus_l0.run.resumes.recorded_overrides`), if any."""
    if run_dir is None or not (run_dir / "config.yaml").is_file():
        return None
    try:
        value = load_config(run_dir / "config.yaml", recorded_overrides(run_dir)).train.compile
    except NeusL0Error:
        return None
    return value if isinstance(value, bool) else None


def as_compiled(cfg: Config) -> Config:
    """`cfg` as `auto` compiles it: ``train.compile=true`` and ``model.sdf.gradient=analytic``
    in place of ``autograd`` (the step the compile record keys on)."""
    model = cfg.model
    if model.sdf.gradient == "autograd":
        model = dataclasses.replace(model, sdf=dataclasses.replace(model.sdf,
                                                                   gradient="analytic"))
    return dataclasses.replace(cfg, model=model,
                               train=dataclasses.replace(cfg.train, compile=True))


def resolve_compile(cfg: Config, device: str, start_iteration: int = 0,
                    run_dir: Path | None = None,
                    measure: Callable[[], float] | None = None) -> tuple[Config, str | None]:
    """`cfg` with ``train.compile`` a bool, and the line to print (None when it was one).

    ``auto`` keeps the choice a resumed run recorded in its ``config.yaml``; otherwise
    `choose_compile` decides, on the eager step `measure()` times (called when the record
    has none and `worth_measuring`; noted in the record). Compiling with
    ``model.sdf.gradient=autograd`` switches the gradient to ``analytic``.
    """
    if cfg.train.compile != "auto":
        return cfg, None
    recorded = _run_choice(run_dir) if start_iteration > 0 else None
    if recorded is not None:
        on, line = recorded, (f"train.compile=auto: {'compiled' if recorded else 'eager'}, as "
                              "the run started")
    else:
        choice = choose_compile(cfg, device, start_iteration, read_record(),
                                _measured_eager(cfg, device, start_iteration, measure))
        on, line = choice.compile, choice.line()
    if not on:
        return dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, compile=False)), line
    if cfg.model.sdf.gradient == "autograd":
        line += "; model.sdf.gradient=analytic (autograd's double backward cannot compile)"
    return as_compiled(cfg), line
