"""Range checks of config values whose types are right but whose meaning is not.

One rule per key, raising `ConfigError` that names the dotted key.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from neus_l0.config.schema import (
    L0_KINDS,
    BackgroundConfig,
    ColorConfig,
    EncodingConfig,
    HullConfig,
    OccupancyConfig,
    PointBoundConfig,
    RenderConfig,
    SamplerConfig,
    SDFConfig,
    TrainConfig,
)
from neus_l0.errors import ConfigError


def validate(obj: Any, prefix: str) -> None:
    """Range checks of values whose types are right but whose meaning is not."""
    def bad(name: str, why: str) -> ConfigError:
        return ConfigError(f"{prefix}{name}: {why}")

    if isinstance(obj, SamplerConfig):
        _validate_sampler(obj, bad)
    if isinstance(obj, EncodingConfig):
        if obj.n_freqs < 0:
            raise bad("n_freqs", "must be >= 0")
        if obj.kind == "hashgrid":
            for name in ("n_levels", "n_features", "base_resolution", "update_steps"):
                if getattr(obj, name) < 1:
                    raise bad(name, "must be >= 1")
            if not 4 <= obj.log2_hashmap_size <= 30:
                raise bad("log2_hashmap_size", "must be in 4 .. 30")
            if obj.per_level_scale < 0 or 0 < obj.per_level_scale < 1:
                raise bad("per_level_scale", "must be >= 1 (or 0: from finest_resolution)")
            if obj.per_level_scale == 0 and obj.finest_resolution < obj.base_resolution:
                raise bad("finest_resolution", "must be >= base_resolution")
            for name in ("bound", "init_scale", "lr_scale"):
                if not getattr(obj, name) > 0:
                    raise bad(name, "must be > 0")
            if obj.start_level is not None and obj.start_level < 0:
                raise bad("start_level", "must be >= 0 (or null: all levels)")
    if isinstance(obj, PointBoundConfig) and not (obj.margin >= 0 and obj.min_views >= 2):
        raise bad("margin", "margin must be >= 0 and min_views >= 2")
    if isinstance(obj, HullConfig):
        if obj.resolution < 8:
            raise bad("resolution", "must be >= 8 cells per axis")
        if not obj.margin_px >= 0:
            raise bad("margin_px", "must be >= 0 pixels")
    if isinstance(obj, RenderConfig):
        if obj.n_samples < 2:
            raise bad("n_samples", "must be >= 2")
        if obj.up_sample_steps < 0 or obj.n_importance < 0:
            raise bad("n_importance", "must be >= 0")
        if obj.up_sample_steps and obj.n_importance % obj.up_sample_steps:
            raise bad("n_importance", f"{obj.n_importance} is not a multiple of "
                      f"up_sample_steps={obj.up_sample_steps}")
    if isinstance(obj, OccupancyConfig):
        if obj.block < 1 or obj.resolution < 1 or obj.resolution % obj.block:
            raise bad("resolution", f"{obj.resolution} must be a positive multiple of "
                      f"block={obj.block}")
        if obj.update_every < 1 or obj.hold < 0 or obj.start < 0:
            raise bad("update_every", "update_every must be >= 1, hold and start >= 0")
        if obj.margin < 1.0 or obj.widths < 0.0:
            raise bad("margin", "margin must be >= 1 and widths >= 0")
    if isinstance(obj, TrainConfig):
        if not 0.0 < obj.eikonal_fraction <= 1.0:
            raise bad("eikonal_fraction", "must be in (0, 1]")
        for name in ("iters", "batch_size", "log_every"):
            if getattr(obj, name) < 1:
                raise bad(name, "must be >= 1")
        if obj.sample_budget < 0:
            raise bad("sample_budget", "must be >= 0 (0: off)")
        if obj.lr <= 0:
            raise bad("lr", "must be > 0")
    if isinstance(obj, (SDFConfig, ColorConfig, BackgroundConfig)):
        if obj.hidden < 1 or obj.layers < 1:
            raise bad("hidden", "hidden and layers must be >= 1")


def _validate_sampler(obj: SamplerConfig, bad: Callable[[str, str], ConfigError]) -> None:
    """Range checks of a `SamplerConfig` (its choices are checked by their `Literal` types)."""
    if obj.kind:
        if obj.name not in L0_KINDS:
            raise bad("kind", f"sampler {obj.name} has no interpolation kind (only "
                      f"{', '.join(L0_KINDS)} do)")
        if obj.name != "l0" and obj.kind != L0_KINDS[obj.name]:
            raise bad("kind", f"{obj.kind} contradicts sampler {obj.name} (set name: l0 and "
                      f"the kind, or the name alone)")
    if obj.masses == "sections" and obj.name in L0_KINDS:
        for key, unused in (("blur", obj.blur), ("pad", obj.pad > 0),
                            ("placement", obj.placement != "midpoint"),
                            ("as_density", not obj.as_density)):
            if unused:
                raise bad(key, "applies only to the interpolant's draw; add "
                          "sampler.masses=interpolant")
    if not obj.pad >= 0.0:
        raise bad("pad", "must be >= 0")
    if not obj.base_inv_s > 0.0:
        raise bad("base_inv_s", "must be > 0")
