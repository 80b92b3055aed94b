"""Dataclass configs, read from `confs/*.yaml` with dotted `key=value` overrides.

One dataclass per component, each field documented where it is declared. A config file is a
nested YAML mapping whose keys mirror the dataclass fields; every key is optional (missing
keys keep the defaults below, which are NeuS's `wmask` settings). Overrides on the command
line use dotted keys, e.g. ``sampler=hvs train.iters=2000 model.sdf.hidden=64``; their values
are parsed as YAML. Unknown keys and values of the wrong type raise `ConfigError` naming the
key.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from neus_l0.errors import ConfigError
from neus_l0.samplers import L0_KINDS, PAD_MODES, PLACEMENTS, SAMPLERS


def _find_confs_dir() -> Path:
    """The folder of the built-in configs.

    The YAMLs live in the repository's top-level ``confs/``; a wheel ships them inside the
    package as ``neus_l0/confs/`` (the build-time mapping in setup.py). So: the checkout's
    ``confs/`` beside ``pyproject.toml`` (a source tree or an editable install), else the
    installed package's own ``confs/``.
    """
    here = Path(__file__).resolve().parent
    checkout = here.parent / "confs"
    if (here.parent / "pyproject.toml").is_file() and checkout.is_dir():
        return checkout
    return here / "confs"


#: Folder holding the built-in configs (`wmask`, `womask`, `demo`, ...).
CONFS_DIR = _find_confs_dir()

#: Folder prefixes under which a config is also looked up by name in `CONFS_DIR`, so that
#: ``--conf confs/demo.yaml`` and ``--conf ./confs/demo.yaml`` work from any directory.
_CONF_PREFIXES = (Path("."), Path("confs"), Path("neus_l0") / "confs")

#: Old `render.*` sampler keys and the `sampler.*` keys they now mean (`_legacy_sampler`).
LEGACY_SAMPLER_KEYS: dict[str, str] = {
    "point_weights": "placement",
    "weights_as_density": "as_density",
    "l0_pad": "pad",
    "compile_sampler": "compile",
}


@dataclass
class EncodingConfig:
    """An input encoding (see `neus_l0.fields.encodings.build_encoding`)."""

    kind: str = "frequency"
    """Encoding kind: `frequency` (NeRF positional encoding), `identity` or `hashgrid`
    (Instant-NGP multiresolution hash grid; 3-D inputs only, used for the SDF network)."""
    n_freqs: int = 6
    """Number of octaves 2^0 .. 2^(n_freqs-1) of the frequency encoding (0: input only).
    For `hashgrid`: frequency bands added between the raw input and the grid features."""
    include_input: bool = True
    """Whether the raw input is concatenated in front of the sines and cosines (or of the
    grid features)."""
    n_levels: int = 16
    """`hashgrid`: number of resolution levels."""
    n_features: int = 2
    """`hashgrid`: features per level."""
    log2_hashmap_size: int = 19
    """`hashgrid`: log2 of the entries of each hashed level's table."""
    base_resolution: int = 16
    """`hashgrid`: cells per axis of the coarsest level."""
    per_level_scale: float = 0.0
    """`hashgrid`: resolution growth factor between levels (0: derive it from
    `finest_resolution`)."""
    finest_resolution: int = 2048
    """`hashgrid`: cells per axis of the finest level, when `per_level_scale` is 0."""
    bound: float = 1.0
    """`hashgrid`: the grid covers [-bound, bound]^3 (the unit sphere's box)."""
    init_scale: float = 1e-4
    """`hashgrid`: table entries start uniform in [-init_scale, init_scale]."""
    lr_scale: float = 1.0
    """`hashgrid`: the table learns at `train.lr * lr_scale` (with Adam)."""
    start_level: int | None = None
    """`hashgrid`: progressive levels: active levels at the start (None: all, always)."""
    update_steps: int = 1000
    """`hashgrid`: training iterations between activating one more level."""


@dataclass
class SDFConfig:
    """NeuS's SDF network (IDR's MLP with a skip connection and geometric initialisation)."""

    hidden: int = 256
    """Width of the hidden layers."""
    layers: int = 8
    """Number of hidden layers."""
    skip: list[int] = field(default_factory=lambda: [4])
    """Indices of the linear layers whose input is re-concatenated with the encoded input."""
    encoding: EncodingConfig = field(default_factory=lambda: EncodingConfig(n_freqs=6))
    """Encoding of the 3-D point."""
    feature_dim: int = 256
    """Length of the feature vector handed to the colour network."""
    geometric_init: bool = True
    """Initialise the SDF to a sphere of radius `bias` (SAL / IDR geometric init)."""
    bias: float = 0.5
    """Radius of the initial sphere."""
    scale: float = 1.0
    """Input scale: the network sees `x * scale` and returns `sdf / scale`."""
    softplus_beta: float = 100.0
    """Sharpness of the softplus activation."""
    weight_norm: bool = True
    """Weight normalisation on every linear layer."""
    gradient: str = "autograd"
    """How the SDF's spatial gradient (the Eikonal term's and the colour network's normal)
    is computed (`neus_l0.fields.sdf`): `autograd` (torch.autograd.grad; in training a
    double backward), `analytic` (the hash grid's / frequency encoding's derivative in
    closed form carried forward through the MLP: one ordinary backward, same values) or
    `finite-difference` (central differences with one batched 7-point pass; the step is
    half a cell of the hash grid's finest active level, or 1e-3 without a hash grid)."""


@dataclass
class ColorConfig:
    """NeuS's colour (rendering) network."""

    hidden: int = 256
    """Width of the hidden layers."""
    layers: int = 4
    """Number of hidden layers."""
    mode: str = "idr"
    """Inputs: `idr` (point, view dir, normal, feature), `no_view_dir` or `no_normal`."""
    view_encoding: EncodingConfig = field(default_factory=lambda: EncodingConfig(n_freqs=4))
    """Encoding of the view direction."""
    weight_norm: bool = True
    """Weight normalisation on every linear layer."""


@dataclass
class VarianceConfig:
    """NeuS's single learned variance: s = exp(10 * variance)."""

    init: float = 0.3
    """Initial value of `variance` (s starts at exp(3) ~ 20)."""


@dataclass
class BackgroundConfig:
    """NeRF++ background model for the space outside the unit sphere (no-mask setting)."""

    hidden: int = 256
    """Width of the hidden layers."""
    layers: int = 8
    """Number of hidden layers."""
    skip: list[int] = field(default_factory=lambda: [4])
    """Layers after which the encoded input is re-concatenated."""
    encoding: EncodingConfig = field(default_factory=lambda: EncodingConfig(n_freqs=10))
    """Encoding of the inverse-sphere point (x/r, 1/r), 4-D."""
    view_encoding: EncodingConfig = field(default_factory=lambda: EncodingConfig(n_freqs=4))
    """Encoding of the view direction."""


@dataclass
class ModelConfig:
    """All networks."""

    sdf: SDFConfig = field(default_factory=SDFConfig)
    """The SDF network."""
    color: ColorConfig = field(default_factory=ColorConfig)
    """The colour network."""
    variance: VarianceConfig = field(default_factory=VarianceConfig)
    """The single variance."""
    background: BackgroundConfig = field(default_factory=BackgroundConfig)
    """The background model, built only when `render.n_outside > 0`."""


@dataclass
class OccupancyConfig:
    """Occupancy grid that keeps coarse samples out of empty space (`neus_l0.occupancy`).

    Off in `wmask` / `womask` (which reproduce NeuS). When on, rays that miss the unit
    sphere or cross no occupied cell get zero opacity, and the coarse samples of the others
    lie in the span [first occupied, last occupied] along the ray. Measured on the CPU
    without masks (docs/BENCHMARKS.md, "Bounds without masks"): 32^3 updated every 128
    steps costs under 1 % of a step, but batches keep their shape, so it saves no network
    work, and it moved only 1.07x the coarse samples toward the surface; early in training
    it left out a few % of the true surface (it follows the network's SDF)."""

    enabled: bool = False
    """Use the grid in training and rendering."""
    resolution: int = 32
    """Cells per axis over [-1, 1]^3 (a multiple of `block`). 32 (was 64): an update costs
    a tenth, and early in training it left out less of the true surface (BENCHMARKS.md)."""
    update_every: int = 128
    """Training iterations between grid updates (the first at iteration `start`)."""
    start: int = 0
    """No update before this iteration: until then every cell is occupied (nothing is
    emptied before the SDF has been trained a while)."""
    margin: float = 1.5
    """Slack on the 1-Lipschitz bound: a cell is occupied when |sdf(centre)| <=
    margin * half-diagonal + widths / s."""
    widths: float = 6.0
    """Logistic widths 1 / s (s: the current sharpness) added to the bound."""
    hold: int = 2
    """Updates a cell stays occupied after it last passed the test."""
    block: int = 4
    """Cells per axis of the blocks tested first in an update (1: test every cell)."""
    compact: bool = True
    """Kept so that older configs load; it no longer changes anything: training keeps every
    batch's shape (rays that cross nothing are masked, and rays are drawn from pixels that
    can reach the surface, `neus_l0.pixel_pool`), and `render_image` always skips rays that
    cross nothing."""


@dataclass
class HullConfig:
    """The visual hull carved from the masks (`neus_l0.hull`): rays get samples only where
    they cross it. Scenes without masks have none (nothing is carved where nothing is
    known)."""

    enabled: bool = True
    """Carve and use the hull when the scene has masks (saved as ``RUN/hull.pt``, so a
    resume and ``neus-l0 mesh`` use the same one)."""
    resolution: int = 128
    """Cells per axis over the unit sphere's box (128: 7-8 s on 49 views of 1600x1200)."""
    margin_px: float = 2.0
    """Mask dilation in pixels for mask and calibration error (1 px is the least that kept
    every true surface point with masks eroded by 2 px; 2 leaves one to spare)."""


@dataclass
class PointBoundConfig:
    """The oriented box around a `neus-l0 colmap` scene's SfM points (`neus_l0.point_bound`),
    for scenes without a visual hull. Off by default: on the synthetic scenes exported
    through pycolmap a margin below 0.2 cut thin parts the SfM points miss, and at 0.2 the
    box keeps 70-94 % of the sphere (docs/BENCHMARKS.md, "Bounds without masks")."""

    enabled: bool = False
    """Narrow the rays to the box when the scene folder holds ``sparse_points.npz`` and the
    run has no visual hull."""
    margin: float = 0.2
    """Widening of every face of the points' box, as a fraction of its diagonal."""
    min_views: int = 2
    """Least number of views that see a point for it to count."""


@dataclass
class RenderConfig:
    """Sampling along rays and compositing (NeuS's `neus_renderer` block)."""

    n_samples: int = 64
    """Coarse samples, uniform in [near, far] of the unit sphere."""
    n_importance: int = 64
    """Fine samples in total, drawn in `up_sample_steps` equal rounds."""
    up_sample_steps: int = 4
    """Rounds of up-sampling; round i uses the fixed inv_s = 64 * 2^i."""
    n_outside: int = 0
    """Samples of the background model outside the unit sphere (0: no background model)."""
    perturb: bool = True
    """Jitter the coarse samples (one random shift per ray) during training."""
    white_background: bool = False
    """Composite over white instead of black (no background model)."""
    chunk: int = 1024
    """Rays per chunk when rendering whole images (validation)."""
    cull_outside_sphere: bool = False
    """Rays that miss the unit sphere get no samples and no SDF work (zero opacity, or the
    background model alone), and the coarse samples of the others lie on the sphere's chord
    instead of NeuS's [mid - 1, mid + 1]. Implied by `occupancy.enabled`."""
    occupancy: OccupancyConfig = field(default_factory=OccupancyConfig)
    """The occupancy grid (off by default)."""
    hull: HullConfig = field(default_factory=HullConfig)
    """The visual hull (on when the scene has masks)."""
    point_bound: PointBoundConfig = field(default_factory=PointBoundConfig)
    """The SfM points' box of a colmap scene without a hull (off by default)."""


@dataclass(eq=False)
class SamplerConfig:
    """The fine-sample draw of NeuS's up-sampling (`neus_l0.samplers.build_sampler`).

    In YAML and on the command line a bare name stands for the block with that name and
    the defaults (``sampler: l0``, ``sampler=hvs``); ``sampler.pad=0.01`` sets one field. The
    old keys ``render.point_weights``, ``render.weights_as_density``, ``render.l0_pad`` and
    ``render.compile_sampler`` are still read, as ``sampler.placement``, ``as_density``, ``pad``
    and ``compile`` (`LEGACY_SAMPLER_KEYS`). A `SamplerConfig` compares equal to its name and
    prints as it, so code that expected the old string keeps working.
    """

    name: str = "l0"
    """`hvs` (NeuS's piecewise constant), `l0` (L0 exponential, the default), `l0-inverse`,
    `l0-linear` or `neus-exact` (the exact CDF of NeuS's opacity inside each section)."""
    kind: str = ""
    """L0 interpolation kind, `exp`, `inverse` or `linear` ("": the name's, e.g. `l0-linear`
    -> `linear`); only the L0 samplers have one."""
    pad: float = 0.0
    """Pad of the L0 samplers' point weights (maxblur's, or added directly without blur; see
    `pad_mode`). The authors' code uses 0.001, the paper 0.01. Default 0: in the oracle study
    (docs/BENCHMARKS.md) every pad only moved fine samples away from the surface."""
    pad_mode: str = "relative"
    """How `pad` scales: `absolute` (added to the point weights as they are: NeuS's section
    weights sum to at most 1, so its share of the draw grows as a ray's weight shrinks),
    `relative` (times the ray's mean point weight: at most pad / (1 + pad) of the draw,
    whatever the weights) or `none` (no pad)."""
    blur: bool = False
    """Apply the L0-Sampler's maxblur (paper eq. 10) to the point weights. Off by default:
    in the oracle study maxblur, not the pad, is what put fewer fine samples near the surface
    than `hvs` (0.68x within 0.01 at 16+16; without it 1.12x); `render.l0_pad` in an old
    config or checkpoint turns it back on (with an absolute pad), as the old code ran."""
    placement: str = "midpoint"
    """How NeuS's section weights become point weights for the L0 samplers: `midpoint`
    (weights at section midpoints) or `endpoint` (average of the two adjacent sections at
    each sample). Was `render.point_weights`."""
    as_density: bool = True
    """Divide each section weight by its length (times the mean length) before the L0
    interpolation, so that point values are densities even when sections are uneven. Was
    `render.weights_as_density`."""
    masses: str = "sections"
    """Where the L0 samplers' section shares come from: `sections` (the default: each of
    NeuS's sections keeps its own weight's share, as `hvs` draws, and the L0 interpolant of
    the section densities only places the samples inside it:
    `neus_l0.sampling.sample_l0_sections`; blur, pad, placement and as_density do not apply)
    or `interpolant` (the paper's draw: the interpolant's own mass over each stretch decides
    its share, after maxblur and pad). In the oracle study (docs/BENCHMARKS.md) `sections`
    put more fine samples near the surface than `hvs` and than `interpolant`."""
    base_inv_s: float = 64.0
    """NeuS's fixed sharpness of the first up-sampling round; round i uses base * 2^i."""
    compile: bool = False
    """Deprecated, no effect (a one-line warning): `train.compile=true` compiles the whole
    training step, the draw included. Kept so that configs and checkpoints that set it (or
    the older `render.compile_sampler`) still load."""

    def l0_kind(self) -> str:
        """The L0 interpolation kind in effect (`kind`, else the name's)."""
        return self.kind or L0_KINDS.get(self.name, "exp")

    def __str__(self) -> str:
        return self.name

    def __eq__(self, other: object) -> bool:
        if isinstance(other, str):
            return self.name == other
        if isinstance(other, SamplerConfig):
            return dataclasses.astuple(self) == dataclasses.astuple(other)
        return NotImplemented

    def __hash__(self) -> int:  # equal to its name, so it hashes like it
        return hash(self.name)


@dataclass
class TrainConfig:
    """Optimisation, losses, logging and checkpoints."""

    iters: int = 300000
    """Total iterations (NeuS's `end_iter`); the cosine schedule ends here."""
    batch_size: int = 512
    """Rays per iteration (the starting number when `sample_budget` is set)."""
    sample_budget: int = 0
    """Foreground samples per iteration to aim for (0: off, every iteration draws
    `batch_size` rays). Rays that miss the unit sphere (`render.cull_outside_sphere`) or the
    occupancy grid get no samples, so a fixed batch evaluates fewer samples than the device
    could; with a budget the number of rays is re-set at every log step (the loop's host
    read-back) to ``rays * sample_budget / samples of that step``, kept within
    [batch_size / 8, 8 * batch_size] (instant-nsr-pl's dynamic ray count). The current
    number is saved in checkpoints (resume stays exact) and logged as ``rays``."""
    lr: float = 5e-4
    """Peak learning rate of Adam."""
    lr_alpha: float = 0.05
    """Final learning rate as a fraction of `lr` (cosine decay)."""
    warm_up: int = 5000
    """Iterations of linear learning-rate warm-up."""
    anneal_end: int = 0
    """Iteration where the cos-annealing ratio reaches 1 (0: 1 from the start)."""
    igr_weight: float = 0.1
    """Weight of the Eikonal loss."""
    mask_weight: float = 0.1
    """Weight of the mask BCE loss (0: masks unused)."""
    seed: int = 0
    """Seed of the network initialisation and of the ray / sample generator."""
    log_every: int = 100
    """Iterations between metric log lines (and the only host syncs of the loop)."""
    val_every: int = 2500
    """Iterations between validation renders (0: never)."""
    val_downscale: int = 4
    """Downscale factor of the validation renders."""
    save_every: int = 10000
    """Iterations between checkpoints (a final one is always written)."""
    keep_checkpoints: int = 3
    """How many of the newest checkpoints to keep."""
    max_seconds: float = 0.0
    """Wall-clock budget of the training loop (steps, logging, validation, checkpoints; not
    the setup before it nor the time of training hooks): stop and checkpoint after this many
    seconds (0: no budget)."""
    amp: str = "off"
    """Mixed precision of the networks on CUDA: `off`, `bf16` or `fp16` (with a gradient
    scaler and fused Adam); ignored on the CPU."""
    compile: bool = False
    """Compile the training step's render and loss with `torch.compile`
    (`neus_l0.compile_step`; needs `model.sdf.gradient` analytic or finite-difference;
    CUDA graphs on CUDA where they work)."""
    tensorboard: bool = True
    """Write TensorBoard events into the run folder (`tensorboard --logdir RUN`)."""
    eikonal_fraction: float = 1.0
    """Fraction of the samples (drawn at random each step) that the Eikonal term averages
    over; 1: all samples within radius 1.2 (NeuS)."""


@dataclass
class DataConfig:
    """How the scene is loaded."""

    downscale: int = 1
    """Integer image downscale at load time."""


@dataclass
class Config:
    """A complete run configuration."""

    sampler: SamplerConfig = field(default_factory=SamplerConfig)
    """The up-sampling draw and its settings; a bare name (`sampler: hvs`) sets the name."""
    data: DataConfig = field(default_factory=DataConfig)
    """Scene loading."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """Networks."""
    render: RenderConfig = field(default_factory=RenderConfig)
    """Sampling and compositing."""
    train: TrainConfig = field(default_factory=TrainConfig)
    """Optimisation."""

    def __post_init__(self) -> None:
        if isinstance(self.sampler, str):
            self.sampler = SamplerConfig(name=self.sampler)


# ------------------------------------------------------------------------------------------
# Building dataclasses from plain data, with type checks.


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Return `value` converted to the annotated type `tp`, or raise `ConfigError`."""
    origin = typing.get_origin(tp)
    if tp is SamplerConfig and isinstance(value, str):
        value = {"name": value}  # `sampler: hvs` is short for `sampler: {name: hvs}`
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a mapping, got {value!r}")
        return from_dict(tp, value, prefix=key + ".")
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, key)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{key}: bad value {value!r}")
    if origin is list:
        (item_tp,) = typing.get_args(tp)
        if isinstance(value, tuple):
            value = list(value)
        if not isinstance(value, list):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        return [_coerce(v, item_tp, f"{key}[{i}]") for i, v in enumerate(value)]
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{key}: expected true or false, got {value!r}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise ConfigError(f"{key}: expected an integer, got {value!r}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):  # PyYAML reads "5e-4" (no dot) as a string
            try:
                return float(value)
            except ValueError:
                pass
        raise ConfigError(f"{key}: expected a number, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{key}: expected a string, got {value!r}")
    raise ConfigError(f"{key}: unsupported type {_type_name(tp)}")  # pragma: no cover


def from_dict(cls: type, data: dict, prefix: str = "") -> Any:
    """Build dataclass `cls` from a nested mapping; unknown keys raise `ConfigError`."""
    if cls is Config:
        data = _legacy_sampler(data)
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = [k for k in data if k not in names]
    if unknown:
        raise ConfigError(f"unknown config key '{prefix}{unknown[0]}' "
                          f"(known under '{prefix or '.'}': {', '.join(sorted(names))})")
    base = cls()
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name in data:
            kwargs[f.name] = _coerce(data[f.name], hints[f.name], prefix + f.name)
        else:
            kwargs[f.name] = getattr(base, f.name)
    obj = cls(**kwargs)
    _validate(obj, prefix)
    return obj


#: The fields of a sampler block dumped before `masses` existed (session 3's `SamplerConfig`).
_DUMPED_SAMPLER_KEYS = frozenset({"name", "kind", "pad", "pad_mode", "blur", "placement",
                                  "as_density", "base_inv_s"})


def _legacy_sampler(data: dict) -> dict:
    """Move the old `render.*` sampler keys (`LEGACY_SAMPLER_KEYS`) into the sampler block.

    The one place where old configs and checkpoints are read: ``render.l0_pad`` becomes
    ``sampler.pad`` and so on; a bare ``sampler: NAME`` becomes ``{name: NAME}``. Where both
    spellings are given, the new ``sampler.*`` key wins. ``render.l0_pad`` also sets
    ``blur: true`` and ``pad_mode: absolute`` (unless given), which is what the old code ran,
    so old configs and checkpoints keep their meaning; so does a whole sampler block dumped
    before ``masses`` existed (every field of that time, `_DUMPED_SAMPLER_KEYS`, and no
    ``masses``: it gets ``masses: interpolant``). A hand-written block (``{name: hvs,
    base_inv_s: 128}``) is not a dump and keeps the default.
    """
    stored = data.get("sampler")
    if (isinstance(stored, dict) and _DUMPED_SAMPLER_KEYS <= stored.keys()
            and "masses" not in stored):
        # a whole block dumped before `masses` existed: those runs drew from the interpolant
        data = {**data, "sampler": {**stored, "masses": "interpolant"}}
    render = data.get("render")
    if not isinstance(render, dict) or not any(k in render for k in LEGACY_SAMPLER_KEYS):
        return data
    sampler = data.get("sampler", {})
    sampler = {"name": sampler} if isinstance(sampler, str) else dict(sampler or {})
    render = dict(render)
    for old, new in LEGACY_SAMPLER_KEYS.items():
        if old in render:
            sampler.setdefault(new, render.pop(old))
            if old == "l0_pad":  # the old code always blurred, with an absolute pad
                sampler.setdefault("blur", True)
                sampler.setdefault("pad_mode", "absolute")
    if sampler.get("name", "l0") in L0_KINDS:  # the old code drew from the interpolant
        sampler.setdefault("masses", "interpolant")
    return {**data, "render": render, "sampler": sampler}


def to_dict(cfg: Any) -> dict:
    """Plain nested dict of a config dataclass (for YAML and checkpoints)."""
    return dataclasses.asdict(cfg)


def _validate(obj: Any, prefix: str) -> None:
    """Range checks of values whose types are right but whose meaning is not."""
    def bad(name: str, why: str) -> ConfigError:
        return ConfigError(f"{prefix}{name}: {why}")

    if isinstance(obj, SamplerConfig):
        _validate_sampler(obj, bad)
    if isinstance(obj, EncodingConfig):
        if obj.kind not in ("frequency", "identity", "hashgrid"):
            raise bad("kind", f"unknown encoding {obj.kind!r} (frequency, identity, hashgrid)")
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
    if isinstance(obj, SDFConfig) and obj.gradient not in (
            "autograd", "analytic", "finite-difference"):
        raise bad("gradient", f"unknown method {obj.gradient!r} (autograd, analytic, "
                  "finite-difference)")
    if isinstance(obj, ColorConfig) and obj.mode not in ("idr", "no_view_dir", "no_normal"):
        raise bad("mode", f"unknown mode {obj.mode!r} (idr, no_view_dir, no_normal)")
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
        if obj.amp not in ("off", "bf16", "fp16"):
            raise bad("amp", f"unknown choice {obj.amp!r} (off, bf16, fp16)")
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
    """Range checks of a `SamplerConfig` (names from the one registry, `samplers.SAMPLERS`)."""
    if obj.name not in SAMPLERS:
        raise bad("name", f"unknown sampler {obj.name!r} (choose from {', '.join(SAMPLERS)})")
    if obj.kind:
        if obj.name not in L0_KINDS:
            raise bad("kind", f"sampler {obj.name} has no interpolation kind (only "
                      f"{', '.join(L0_KINDS)} do)")
        if obj.kind not in ("exp", "inverse", "linear"):
            raise bad("kind", f"unknown kind {obj.kind!r} (exp, inverse, linear)")
        if obj.name != "l0" and obj.kind != L0_KINDS[obj.name]:
            raise bad("kind", f"{obj.kind} contradicts sampler {obj.name} (set name: l0 and "
                      f"the kind, or the name alone)")
    if obj.pad_mode not in PAD_MODES:
        raise bad("pad_mode", f"unknown choice {obj.pad_mode!r} ({', '.join(PAD_MODES)})")
    if obj.masses not in ("interpolant", "sections"):
        raise bad("masses", f"unknown choice {obj.masses!r} (interpolant, sections)")
    if obj.masses == "sections" and obj.name in L0_KINDS:
        for key, unused in (("blur", obj.blur), ("pad", obj.pad > 0),
                            ("placement", obj.placement != "midpoint"),
                            ("as_density", not obj.as_density)):
            if unused:
                raise bad(key, "applies only to the interpolant's draw; add "
                          "sampler.masses=interpolant")
    if obj.placement not in PLACEMENTS:
        raise bad("placement", f"unknown choice {obj.placement!r} ({', '.join(PLACEMENTS)}; "
                  "formerly render.point_weights)")
    if not obj.pad >= 0.0:
        raise bad("pad", "must be >= 0")
    if not obj.base_inv_s > 0.0:
        raise bad("base_inv_s", "must be > 0")


# ------------------------------------------------------------------------------------------
# Files and overrides.


def resolve_conf_path(conf: str | Path) -> Path:
    """Find a config: an existing path, else a built-in one in `CONFS_DIR`.

    A built-in config is named ``NAME``, ``NAME.yaml``, ``confs/NAME.yaml`` or
    ``./confs/NAME.yaml`` (``neus_l0/confs/NAME.yaml``, the old place, too), whatever the
    working directory.
    """
    path = Path(conf)
    if path.is_file():
        return path
    name = path.name if path.suffix in (".yaml", ".yml") else path.name + ".yaml"
    candidate = CONFS_DIR / name
    if path.parent in _CONF_PREFIXES and candidate.is_file():
        return candidate
    known = ", ".join(sorted(p.stem for p in CONFS_DIR.glob("*.yaml")))
    raise ConfigError(f"{conf}: no such config file (built-in configs: {known})")


def parse_overrides(items: list[str]) -> dict:
    """Turn ``["a.b=1", "c=x"]`` into the nested dict ``{"a": {"b": 1}, "c": "x"}``.

    Values are parsed as YAML (so `1e-4`, `true`, `[4]` work); a malformed item raises
    `ConfigError`.
    """
    out: dict = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"override '{item}' is not of the form key=value")
        key, text = item.split("=", 1)
        key = key.strip()
        if not key or any(not part for part in key.split(".")):
            raise ConfigError(f"override '{item}' has an empty key")
        try:
            value = yaml.safe_load(text) if text.strip() else ""
        except yaml.YAMLError as exc:
            raise ConfigError(f"override '{item}': value is not valid YAML ({exc})") from None
        node = out
        parts = key.split(".")
        for part in parts[:-1]:
            if node is out and isinstance(node.get(part), str):
                node[part] = _shorthand(part, node[part])  # sampler=l0 sampler.pad=0.1
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override '{item}' conflicts with another override")
        if node is out and isinstance(node.get(parts[-1]), dict):
            value = _merge(node[parts[-1]], {"name": value}) if _is_name(parts[-1], value) \
                else value
        node[parts[-1]] = value
    return out


def _shorthand(key: str, value: Any) -> Any:
    """``sampler: NAME`` as the block ``{name: NAME}`` (other keys and values unchanged)."""
    return {"name": value} if _is_name(key, value) else value


def _is_name(key: str, value: Any) -> bool:
    return key == "sampler" and isinstance(value, str)


def _merge(base: dict, extra: dict) -> dict:
    """`extra` over `base`, recursively. A bare sampler name over a sampler block changes its
    name only (``sampler=hvs`` keeps the file's ``sampler.pad``), and a block over a bare name
    keeps that name."""
    out = dict(base)
    for k, v in extra.items():
        if _is_name(k, v) and isinstance(out.get(k), dict):
            v = {"name": v}
        if isinstance(v, dict):  # a block merged into a shorthand: expand the shorthand
            out[k] = _shorthand(k, out.get(k))
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def read_yaml(path: Path) -> dict:
    """Read a YAML mapping (empty file: {}), raising `ConfigError` on malformed files."""
    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read config ({exc})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config file must be a mapping of keys to values")
    return data


def load_config(conf: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Read a config file (see `resolve_conf_path`) and apply dotted overrides.

    Args:
        conf: a path, `confs/NAME.yaml` or a bare `NAME`; None for the defaults (wmask).
        overrides: ``key=value`` strings applied after the file.

    Raises:
        ConfigError: naming the file or the key that is wrong.
    """
    data: dict = {}
    source = "defaults"
    if conf is not None:
        path = resolve_conf_path(conf)
        data = read_yaml(path)
        source = str(path)
    if overrides:
        data = _merge(data, parse_overrides(overrides))
    try:
        return from_dict(Config, data)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def config_from_dict(data: dict) -> Config:
    """Rebuild a `Config` from `to_dict` output (e.g. a checkpoint's)."""
    return from_dict(Config, data)


def dump_config(cfg: Config) -> str:
    """The config as YAML text (every key, so the file documents the run)."""
    return yaml.safe_dump(to_dict(cfg), sort_keys=False)
