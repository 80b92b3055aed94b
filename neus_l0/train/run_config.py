"""The config `neus-l0 train` runs: a new run's (its `--conf`, or the device's setting sized
for its budget) or a resumed run's (what its folder recorded), and the process's own clock
that a budget counts from."""

from __future__ import annotations


def resumed_config(run_dir, overrides: list[str], change: bool):
    """The resumed run's config: ``config.yaml``, the overrides earlier resumes recorded, then
    these `overrides` (training records what they change: `neus_l0.run.resumes`).

    Raises:
        ConfigError: overrides that change what is learnt without ``--change-config``.
    """
    from neus_l0.config.load import load_config
    from neus_l0.errors import ConfigError
    from neus_l0.run.resumes import changed_keys, guarded_keys, recorded_overrides

    base = run_dir / "config.yaml"
    prior = recorded_overrides(run_dir)
    before = load_config(base, prior)
    cfg = load_config(base, prior + list(overrides))
    changed = changed_keys(before, cfg)
    guarded = guarded_keys(changed)
    if guarded and not change:
        raise ConfigError(f"{run_dir}: resuming with {', '.join(guarded)} changed would train "
                          "a different run; add --change-config to do it on purpose (recorded "
                          "in resumes.jsonl; config.yaml keeps the original)")
    return cfg


def fresh_config(conf: str | None, overrides: list[str], device: str, budget: float):
    """The config of a new run: `conf` (or the device's default setting with its capacity
    for `budget`, `neus_l0.train.budget.default_setting`), the overrides, then `budget`."""
    import sys

    from neus_l0.config.load import load_config
    from neus_l0.train.budget import default_setting

    ladder: tuple[str, ...] = ()
    chosen = conf is None
    if chosen:
        conf, ladder = default_setting(device, budget)
    cfg = load_config(conf, [*ladder, *overrides])
    if chosen:
        print(f"neus-l0 train: no --conf: {conf}, the {device} setting"
              + (f" with {' '.join(ladder)} for this budget" if ladder else "")
              + " (--conf wmask for NeuS's own)", file=sys.stderr, flush=True)
    return with_budget(cfg, budget) if budget else cfg


def with_budget(cfg, seconds: float):
    """`cfg` with ``train.budget`` set to `seconds`."""
    import dataclasses

    return dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, budget=seconds))


def process_seconds() -> float:
    """Seconds since this process started (Linux: /proc; elsewhere since the import)."""
    import os
    import time
    from pathlib import Path

    try:
        stat = Path("/proc/self/stat").read_text(encoding="ascii")
        started = int(stat.rsplit(")", 1)[1].split()[19]) / os.sysconf("SC_CLK_TCK")
        uptime = float(Path("/proc/uptime").read_text(encoding="ascii").split()[0])
        return max(0.0, uptime - started)
    except (OSError, ValueError, IndexError):
        return time.monotonic() - _IMPORTED


_IMPORTED = __import__("time").monotonic()


def run_files(run_dir) -> list[str]:
    """What the run folder holds, as the end-of-training line lists it."""
    names = ["config.yaml", "metrics.jsonl"]
    if any((run_dir / "validation").glob("*.png")):
        names.append("validation/")
    names.append("checkpoints/")
    if any(run_dir.glob("events.out.tfevents.*")):
        names.append(f"TensorBoard events: tensorboard --logdir {run_dir}")
    return names
