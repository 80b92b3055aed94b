"""Range rules of the config: one rule per key, and the few rules that tie keys together.

Types and choices are checked while loading (`neus_l0.config.load`, the schema's types and
`Literal` choice lists); these rules catch numbers whose type is right but whose value
cannot work (``render.chunk=0``, ``train.lr=.nan``, ``train.lr_alpha=-1``), before any work
starts. Every float must be finite. A broken rule raises `ConfigError` naming the dotted
key, the value and the range.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

from neus_l0.config.schema import (
    L0_KINDS,
    BackgroundConfig,
    ColorConfig,
    DataConfig,
    EncodingConfig,
    ErrorMapConfig,
    HullConfig,
    L0Config,
    OccupancyConfig,
    PhotoConfig,
    PointBoundConfig,
    RenderConfig,
    SamplerConfig,
    SDFConfig,
    TrainConfig,
    VarianceConfig,
)
from neus_l0.errors import ConfigError


@dataclasses.dataclass(frozen=True)
class Range:
    """A closed or open interval a number must lie in (None: unbounded on that side)."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    note: str = ""

    def holds(self, v: float) -> bool:
        if self.lo is not None and not (v > self.lo if self.lo_open else v >= self.lo):
            return False
        return self.hi is None or (v < self.hi if self.hi_open else v <= self.hi)

    def describe(self) -> str:
        if self.hi is None:
            text = f"must be {'>' if self.lo_open else '>='} {self.lo:g}"
        elif self.lo is None:
            text = f"must be {'<' if self.hi_open else '<='} {self.hi:g}"
        else:
            text = (f"must be in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}"
                    f"{')' if self.hi_open else ']'}")
        return text + (f" ({self.note})" if self.note else "")


def at_least(lo: float, note: str = "") -> Range:
    return Range(lo=lo, note=note)


def positive(note: str = "") -> Range:
    return Range(lo=0.0, lo_open=True, note=note)


#: The range of each numeric key, by (config class, field). Floats not named here must
#: only be finite.
RULES: dict[tuple[type, str], Range] = {
    (L0Config, "pad"): at_least(0),
    (SamplerConfig, "base_inv_s"): positive(),
    (DataConfig, "downscale"): at_least(1),
    (EncodingConfig, "n_freqs"): at_least(0),
    (EncodingConfig, "n_levels"): at_least(1),
    (EncodingConfig, "n_features"): at_least(1),
    (EncodingConfig, "log2_hashmap_size"): Range(4, 30),
    (EncodingConfig, "base_resolution"): at_least(1),
    (EncodingConfig, "finest_resolution"): at_least(1),
    (EncodingConfig, "bound"): positive(),
    (EncodingConfig, "init_scale"): positive(),
    (EncodingConfig, "lr_scale"): positive(),
    (EncodingConfig, "start_level"): at_least(0, "or null: all levels"),
    (EncodingConfig, "update_steps"): at_least(1),
    (SDFConfig, "hidden"): at_least(1),
    (SDFConfig, "layers"): at_least(1),
    (SDFConfig, "feature_dim"): at_least(0),
    (SDFConfig, "scale"): positive(),
    (SDFConfig, "softplus_beta"): positive(),
    (ColorConfig, "hidden"): at_least(1),
    (ColorConfig, "layers"): at_least(1),
    (BackgroundConfig, "hidden"): at_least(1),
    (BackgroundConfig, "layers"): at_least(1),
    (RenderConfig, "n_samples"): at_least(2),
    (RenderConfig, "n_importance"): at_least(0),
    (RenderConfig, "up_sample_steps"): at_least(0),
    (RenderConfig, "n_outside"): at_least(0),
    (RenderConfig, "chunk"): at_least(1, "rays per rendering chunk"),
    (OccupancyConfig, "resolution"): at_least(1),
    (OccupancyConfig, "update_every"): at_least(1),
    (OccupancyConfig, "start"): at_least(0),
    (OccupancyConfig, "margin"): at_least(1),
    (OccupancyConfig, "widths"): at_least(0),
    (OccupancyConfig, "hold"): at_least(0),
    (OccupancyConfig, "block"): at_least(1),
    (HullConfig, "resolution"): at_least(8, "cells per axis"),
    (HullConfig, "margin_px"): at_least(0, "pixels"),
    (PointBoundConfig, "margin"): at_least(0),
    (PointBoundConfig, "min_views"): at_least(2),
    (VarianceConfig, "init"): Range(-1.38, 1.38, note="s = exp(10 init) must stay inside "
                                    "NeuS's clamp [1e-6, 1e6]"),
    (TrainConfig, "iters"): at_least(1),
    (TrainConfig, "batch_size"): at_least(1),
    (TrainConfig, "sample_budget"): at_least(0, "0: off"),
    (TrainConfig, "lr"): positive(),
    (TrainConfig, "lr_alpha"): Range(0, 1, note="the final fraction of the learning rate"),
    (TrainConfig, "lr_decay_iters"): at_least(0, "0: train.iters"),
    (TrainConfig, "warm_up"): at_least(0),
    (TrainConfig, "anneal_end"): at_least(0),
    (TrainConfig, "igr_weight"): at_least(0),
    (TrainConfig, "mask_weight"): at_least(0),
    (TrainConfig, "carve_weight"): at_least(0, "0: off"),
    (TrainConfig, "fill_weight"): at_least(0, "0: off"),
    (TrainConfig, "fill_margin"): Range(-5, 10, note="in 1/s; 0: until the ray hits"),
    (TrainConfig, "fill_span"): Range(0, 2, note="0: every ray"),
    (TrainConfig, "hit_color_floor"): Range(0, 1, note="0: off (NeuS's composite over black)"),
    (TrainConfig, "seed"): at_least(0),
    (TrainConfig, "log_every"): at_least(1),
    (TrainConfig, "val_every"): at_least(0, "0: never"),
    (TrainConfig, "val_downscale"): at_least(1),
    (TrainConfig, "holdout"): at_least(0, "0: train on every view"),
    (TrainConfig, "save_every"): at_least(0, "0: only at the end"),
    (TrainConfig, "keep_checkpoints"): at_least(0, "0: keep all"),
    (TrainConfig, "max_seconds"): at_least(0, "0: no time limit"),
    (TrainConfig, "threads"): at_least(0, "0: the free cores"),
    (TrainConfig, "eikonal_fraction"): Range(0, 1, lo_open=True),
    (TrainConfig, "curvature_weight"): at_least(0, "0: off"),
    (TrainConfig, "curvature_fraction"): Range(0, 1, lo_open=True),
    (ColorConfig, "view_warmup"): Range(0, 1),
    (ErrorMapConfig, "fraction"): Range(0, 1, hi_open=True),
    (ErrorMapConfig, "warmup"): Range(0, 1),
    (ErrorMapConfig, "decay"): Range(0, 1, lo_open=True),
    (ErrorMapConfig, "tile"): at_least(1),
    (PhotoConfig, "weight"): at_least(0, "0: off"),
    (PhotoConfig, "sources"): at_least(1),
    (PhotoConfig, "best"): at_least(1),
    (PhotoConfig, "normal_sources"): at_least(0, "0: none"),
    (PhotoConfig, "patch"): at_least(1),
    (PhotoConfig, "stride"): at_least(1),
    (PhotoConfig, "max_sdf"): positive(),
    (PhotoConfig, "occlusion_samples"): at_least(0, "0: no occlusion test"),
    (PhotoConfig, "planar_sdf"): at_least(0, "0: no test"),
    (PhotoConfig, "wide_sources"): at_least(0, "0: never wider"),
    (PhotoConfig, "wide_after"): Range(0, 1),
}


def _check_numbers(obj: Any, bad: Callable[[str, str], ConfigError]) -> None:
    """Every number of `obj` finite and in its `RULES` range; list entries too."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        values = value if isinstance(value, list) else [value]
        for v in values:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                continue
            if not math.isfinite(v):
                raise bad(f.name, f"{v!r} is not a finite number")
            rule = RULES.get((type(obj), f.name))
            if rule is not None and not rule.holds(v):
                raise bad(f.name, f"{v!r}: {rule.describe()}")


def _check_encoding(obj: EncodingConfig, bad: Callable[[str, str], ConfigError]) -> None:
    if obj.per_level_scale != 0 and obj.per_level_scale < 1:
        raise bad("per_level_scale", "must be >= 1 (or 0: from finest_resolution)")
    if obj.kind == "hashgrid" and obj.per_level_scale == 0 and \
            obj.finest_resolution < obj.base_resolution:
        raise bad("finest_resolution", "must be >= base_resolution")


def _check_skips(obj: SDFConfig | BackgroundConfig, bad: Callable[[str, str], ConfigError]
                 ) -> None:
    # the SDF concatenates the input before its linear layer i (1 .. layers), the background
    # after its layer i (0 .. layers - 2). The default skip past a smaller `layers` is no skip
    # at all (the networks ignore it), so lowering `layers` need not touch `skip`; any other
    # index past the last would be silently ignored, and one below the first fails to build
    wrong = [i for i in obj.skip if i < 0]
    if wrong:
        raise bad("skip", f"{wrong}: layer indices must be >= 0")
    lo, hi = (1, obj.layers) if isinstance(obj, SDFConfig) else (0, obj.layers - 2)
    default = list(obj.skip) == type(obj)().skip
    wrong = [i for i in obj.skip if i < lo or (i > hi and not default)]
    if wrong:
        span = f"indices {lo} .. {hi}, or [] for none" if hi >= lo else "use []"
        raise bad("skip", f"{wrong}: no such layer in a network of {obj.layers} layers "
                  f"({span})")


def _check_render(obj: RenderConfig, bad: Callable[[str, str], ConfigError]) -> None:
    if obj.up_sample_steps and obj.n_importance % obj.up_sample_steps:
        raise bad("n_importance", f"{obj.n_importance} is not a multiple of "
                  f"up_sample_steps={obj.up_sample_steps}")


def _check_occupancy(obj: OccupancyConfig, bad: Callable[[str, str], ConfigError]) -> None:
    if obj.resolution % obj.block:
        raise bad("resolution", f"{obj.resolution} must be a positive multiple of "
                  f"block={obj.block}")


def _check_sampler(obj: SamplerConfig, bad: Callable[[str, str], ConfigError]) -> None:
    o = obj.l0
    if o.kind:
        if obj.name not in L0_KINDS:
            raise bad("l0.kind", f"sampler {obj.name} has no interpolation kind (only "
                      f"{', '.join(L0_KINDS)} do)")
        if obj.name != "l0" and o.kind != L0_KINDS[obj.name]:
            raise bad("l0.kind", f"{o.kind} contradicts sampler {obj.name} (set name: l0 and "
                      f"the kind, or the name alone)")
    if o.masses == "sections" and obj.name in L0_KINDS:
        for key, unused in (("blur", o.blur), ("pad", o.pad > 0),
                            ("placement", o.placement != "midpoint"),
                            ("as_density", not o.as_density)):
            if unused:
                raise bad(f"l0.{key}", "applies only to the interpolant's draw; add "
                          "sampler.l0.masses=interpolant")


def _check_photo(obj: PhotoConfig, bad: Callable[[str, str], ConfigError]) -> None:
    if obj.patch % 2 == 0:
        raise bad("patch", f"{obj.patch}: must be odd (the patch is centred on the ray's pixel)")
    if obj.best > obj.sources:
        raise bad("best", f"{obj.best}: at most train.photo.sources ({obj.sources})")
    if 0 < obj.wide_sources <= obj.sources:
        raise bad("wide_sources", f"{obj.wide_sources}: more than train.photo.sources "
                  f"({obj.sources}), or 0 (never wider)")
    if obj.normal_sources > 0 and obj.occlusion_samples <= 0:
        raise bad("normal_sources", f"{obj.normal_sources}: the normal's sources stand in "
                  "when the SDF blocks the nearest; it needs train.photo.occlusion_samples > 0")


def _check_train(obj: TrainConfig, bad: Callable[[str, str], ConfigError]) -> None:
    if obj.carve_weight > 0 and obj.mask_weight <= 0:
        raise bad("carve_weight", f"{obj.carve_weight}: carving reads the masks; it needs "
                  "train.mask_weight > 0")
    if obj.fill_weight > 0 and obj.mask_weight <= 0:
        raise bad("fill_weight", f"{obj.fill_weight}: filling reads the masks; it needs "
                  "train.mask_weight > 0")
    if obj.fill_silhouettes and obj.fill_weight <= 0:
        raise bad("fill_silhouettes", "true: it narrows silhouette filling; it needs "
                  "train.fill_weight > 0")
    if (obj.fill_span > 0 or obj.fill_middle) and not obj.fill_silhouettes:
        raise bad("fill_span" if obj.fill_span > 0 else "fill_middle",
                  "it reads the samples inside every mask; it needs "
                  "train.fill_silhouettes=true")


#: The rules that tie several keys of one config class together.
JOINT_RULES: dict[type, Callable[[Any, Callable[[str, str], ConfigError]], None]] = {
    EncodingConfig: _check_encoding,
    SDFConfig: _check_skips,
    BackgroundConfig: _check_skips,
    RenderConfig: _check_render,
    OccupancyConfig: _check_occupancy,
    SamplerConfig: _check_sampler,
    PhotoConfig: _check_photo,
    TrainConfig: _check_train,
}


def validate(obj: Any, prefix: str) -> None:
    """Check one config dataclass (its nested ones are checked as they are built).

    Raises:
        ConfigError: ``PREFIX.key: value: why``.
    """
    def bad(name: str, why: str) -> ConfigError:
        return ConfigError(f"{prefix}{name}: {why}")

    _check_numbers(obj, bad)
    joint = JOINT_RULES.get(type(obj))
    if joint is not None:
        joint(obj, bad)
