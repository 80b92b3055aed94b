"""The config schema: one dataclass per component, each field documented where it is
declared, and the choice lists the rest of the package checks names against.

Every key is optional; the defaults are NeuS's `wmask` settings. Loading, overrides and
type checks are in `neus_l0.config.load`, range checks in `neus_l0.config.checks`, the keys
old runs used in `neus_l0.config.legacy`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, NewType, get_args

# The choice lists: each field with a fixed set of values is typed with one of these, and
# `neus_l0.config.load` refuses any other value, naming the key and the choices.

#: Sampler names, in the order `--help` and errors list them (the registry in
#: `neus_l0.sampling.upsample` checks at import that it builds exactly these).
SamplerName = Literal["hvs", "l0", "l0-inverse", "l0-linear", "neus-exact"]
SAMPLERS: tuple[str, ...] = get_args(SamplerName)
#: The L0 interpolation kinds ("" in a config: the sampler name's kind).
L0Kind = Literal["", "exp", "inverse", "linear"]
#: The L0 sampler names and the interpolation kind each uses by default.
L0_KINDS: dict[str, str] = {"l0": "exp", "l0-inverse": "inverse", "l0-linear": "linear"}
#: How the maxblur pad of the L0 samplers is scaled (see `L0Sampler`).
PadMode = Literal["absolute", "relative", "none"]
PAD_MODES: tuple[str, ...] = get_args(PadMode)
#: Where section weights are placed as point weights (see `section_to_point_weights`).
Placement = Literal["midpoint", "endpoint"]
PLACEMENTS: tuple[str, ...] = get_args(Placement)
#: What a ray writes into the pool's error map (see `ErrorMapConfig.signal`).
ErrorSignal = Literal["colour", "depth", "depth_mask"]
#: Where the L0 samplers' section shares come from (see `L0Sampler`).
Masses = Literal["interpolant", "sections"]
MASSES: tuple[str, ...] = get_args(Masses)
#: Input encodings (`neus_l0.fields.encodings`).
EncodingKind = Literal["frequency", "identity", "hashgrid"]
#: How the SDF's spatial gradient is computed (`neus_l0.fields.sdf`).
GradientMethod = Literal["autograd", "analytic", "finite-difference"]
#: The colour network's inputs.
ColorMode = Literal["idr", "no_view_dir", "no_normal"]
#: Mixed precision of the networks.
AmpMode = Literal["off", "bf16", "fp16"]
#: A duration in seconds, written as a number or with a unit (``90s``, ``10m``, ``1h``;
#: `neus_l0.config.duration.parse_seconds`).
Seconds = NewType("Seconds", float)


@dataclass
class EncodingConfig:
    """An input encoding (see `neus_l0.fields.encodings.build_encoding`)."""

    kind: EncodingKind = "frequency"
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
    gradient: GradientMethod = "autograd"
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
    mode: ColorMode = "idr"
    """Inputs: `idr` (point, view dir, normal, feature), `no_view_dir` or `no_normal`."""
    view_encoding: EncodingConfig = field(default_factory=lambda: EncodingConfig(n_freqs=4))
    """Encoding of the view direction."""
    weight_norm: bool = True
    """Weight normalisation on every linear layer."""
    view_warmup: float = 0.0
    """Fraction of the schedule (``train.iters``, or ``train.lr_decay_iters`` when set) over
    which the view direction's encoding fades in, linearly from 0 (a colour that cannot vary
    with the view, so that it cannot fake geometry with shading) to 1; 0: the whole
    encoding from the start (NeuS)."""


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
    """Occupancy grid that keeps coarse samples out of empty space (`neus_l0.bounds.occupancy`).

    Off in `wmask` / `womask` (which reproduce NeuS). When on, rays that miss the unit
    sphere or cross no occupied cell get zero opacity, and the coarse samples of the others
    lie in the span [first occupied, last occupied] along the ray. Off by default because
    on the CPU path it cannot pay: batches keep their shape, so it saves no network work and
    only moves where the coarse samples lie; and since it follows the network's SDF, early
    in training it can leave out some of the true surface (docs/BENCHMARKS.md, "Without
    masks")."""

    enabled: bool = False
    """Use the grid in training and rendering."""
    resolution: int = 32
    """Cells per axis over [-1, 1]^3 (a multiple of `block`). 32 (was 64): fewer cells make
    an update cheaper, and larger cells leave out less of the true surface early in training
    (docs/benchmarks/bounds.md, "The occupancy grid on the CPU without masks")."""
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
    can reach the surface, `neus_l0.bounds.pixel_pool`), and `render_image` always skips rays that
    cross nothing."""


@dataclass
class HullConfig:
    """The visual hull carved from the masks (`neus_l0.bounds.hull`): rays get samples only where
    they cross it. Scenes without masks have none (nothing is carved where nothing is
    known)."""

    enabled: bool = True
    """Carve and use the hull when the scene has masks (saved as ``RUN/hull.pt``, so a
    resume and ``neus-l0 mesh`` use the same one)."""
    resolution: int = 128
    """Cells per axis over the unit sphere's box. At 128 the build takes seconds, and a finer
    hull keeps little less of the sphere (docs/BENCHMARKS.md, "What does the visual hull
    cost and buy?")."""
    margin_px: float = 2.0
    """Mask dilation in pixels for mask and calibration error (1 px is the least that kept
    every true surface point with masks eroded by 2 px; 2 leaves one to spare)."""


@dataclass
class PointBoundConfig:
    """The oriented box around a `neus-l0 colmap` scene's SfM points (`neus_l0.bounds.points`),
    for scenes without a visual hull. Off by default: the SfM points miss thin parts, so a
    margin below 0.2 cuts them, and a box that wide keeps most of the sphere, which narrows
    the rays little (docs/BENCHMARKS.md, "Without masks")."""

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


@dataclass
class L0Config:
    """The options of the L0 samplers (`l0`, `l0-inverse`, `l0-linear`): the interpolation
    kind and how NeuS's section weights become the draw (`neus_l0.sampling.upsample.L0Sampler`).
    """

    masses: Masses = "sections"
    """Where the L0 samplers' section shares come from: `sections` (the default: each of
    NeuS's sections keeps its own weight's share, as `hvs` draws, and the L0 interpolant of
    the section densities only places the samples inside it:
    `neus_l0.sampling.kernels.sample_l0_sections`; blur, pad, placement and as_density do not apply)
    or `interpolant` (the paper's draw: the interpolant's own mass over each stretch decides
    its share, after maxblur and pad). `sections` is the default because it keeps `hvs`'s
    shares and only refines where the samples lie inside each section, so it lands fine
    samples at least as near the surface as either (docs/BENCHMARKS.md, "Where do fine
    samples land on exact SDFs?")."""
    kind: L0Kind = ""
    """L0 interpolation kind, `exp`, `inverse` or `linear` ("": the name's, e.g. `l0-linear`
    -> `linear`); only the L0 samplers have one."""
    pad: float = 0.0
    """Pad of the L0 samplers' point weights (maxblur's, or added directly without blur; see
    `pad_mode`). The authors' code uses 0.001, the paper 0.01. Default 0: a pad puts weight
    where the section weights see no surface, so it can only draw fine samples away from it
    (docs/BENCHMARKS.md, "Where do fine samples land on exact SDFs?")."""
    pad_mode: PadMode = "relative"
    """How `pad` scales: `absolute` (added to the point weights as they are: NeuS's section
    weights sum to at most 1, so its share of the draw grows as a ray's weight shrinks),
    `relative` (times the ray's mean point weight: at most pad / (1 + pad) of the draw,
    whatever the weights) or `none` (no pad)."""
    blur: bool = False
    """Apply the L0-Sampler's maxblur (paper eq. 10) to the point weights. Off by default:
    maxblur widens a peak that NeuS's weights put in one section into a plateau over three,
    which spreads the fine samples away from the surface; it, not the pad, is what put the
    paper's draw behind `hvs` (docs/BENCHMARKS.md, "Where do fine samples land on exact
    SDFs?"). `render.l0_pad` in an old config or checkpoint turns it back on (with an
    absolute pad), as the old code ran."""
    placement: Placement = "midpoint"
    """How NeuS's section weights become point weights for the L0 samplers: `midpoint`
    (weights at section midpoints) or `endpoint` (average of the two adjacent sections at
    each sample). Was `render.point_weights`."""
    as_density: bool = True
    """Divide each section weight by its length (times the mean length) before the L0
    interpolation, so that point values are densities even when sections are uneven. Was
    `render.weights_as_density`."""


@dataclass
class SamplerConfig:
    """The fine-sample draw of NeuS's up-sampling (`neus_l0.sampling.upsample.build_sampler`).

    What every sampler shares sits here; each sampler's own options sit in its block (the
    L0 samplers': ``l0``; `hvs` and `neus-exact` have none). In YAML and on the command line
    a bare name stands for the block with that name and the defaults (``sampler: l0``,
    ``sampler=hvs``); ``sampler.l0.pad=0.01`` sets one option. The keys older configs,
    checkpoints and command lines used (``sampler.pad``, ``render.l0_pad``, ...) are read by
    `neus_l0.config.legacy`.
    """

    name: SamplerName = "l0"
    """`hvs` (NeuS's piecewise constant), `l0` (L0 exponential, the default), `l0-inverse`,
    `l0-linear` or `neus-exact` (the exact CDF of NeuS's opacity inside each section)."""
    base_inv_s: float = 64.0
    """NeuS's fixed sharpness of the first up-sampling round; round i uses base * 2^i."""

    l0: L0Config = field(default_factory=L0Config)
    """The L0 samplers' options (unused by `hvs` and `neus-exact`)."""

    def l0_kind(self) -> str:
        """The L0 interpolation kind in effect (`l0.kind`, else the name's)."""
        return self.l0.kind or L0_KINDS.get(self.name, "exp")


@dataclass
class ErrorMapConfig:
    """Error-map ray sampling (instant-ngp style; `neus_l0.bounds.error_map`): part of each
    batch is drawn from a running per-tile error map of the pixel pool, the rest uniformly,
    and each ray's colour and mask terms are weighted by 1 / (P p) so that the loss's
    expectation is the whole pool's. Off by default."""

    fraction: float = 0.0
    """Share of the draw that follows the error map, in [0, 1) (0: off, uniform draws)."""
    warmup: float = 0.0
    """Share of the schedule over which the map's share rises linearly from 0 to
    `fraction`, in [0, 1] (0: `fraction` from the start): the early rays stay uniform, to
    carve the hull's slack before the map draws them to the deep pixels."""
    decay: float = 0.3
    """Weight of a ray's new error in its tile's running error, in (0, 1]."""
    tile: int = 8
    """Side of the map's tiles in pixels (1: a tile per pixel); every pool pixel of a tile
    takes the tile's error."""
    signal: ErrorSignal = "colour"
    """What a ray writes into the map: ``colour`` (its colour L1 inside the mask, plus
    |opacity - mask| with masks) or ``depth`` (how far its rendered surface lies behind the
    ray's entry into the visual hull, in the unit sphere's units: a pit's floor, a rod
    inside a cavity; a ray off the mask takes its batch's mean over the rays on it, so that
    the map leaves the rays that carve the hull's slack their uniform share) or
    ``depth_mask`` (``depth`` plus each ray's mask error |opacity - mask|: the rays that
    still see surface outside the silhouette, or miss inside it, are drawn more, where
    ``depth`` alone starved them and left slack under an object)."""
    weigh_all: bool = False
    """The Eikonal and photometric terms weigh the map's rays by their importance weights
    too (a self-normalised mean), so that every term estimates the pool's own mean, as
    under uniform draws, and the map changes only which rays a step sees; off: only the
    colour, mask, carve and fill terms are weighted, and the Eikonal and photometric terms
    lean to the map's rays."""


@dataclass
class PhotoConfig:
    """Multi-view photometric consistency of the rendered surface (`neus_l0.train.photometric`):
    a patch around each ray's pixel, carried by the plane of its rendered surface into the
    nearest training views, scored by normalised cross-correlation (Geo-NeuS's term). Off by
    default."""

    weight: float = 0.0
    """Weight of the term, (1 - NCC) / 2 averaged over each ray's `best` sources (0: off)."""
    sources: int = 4
    """Source views per view: the nearest by the angle seen from the object's centre."""
    best: int = 2
    """How many of a ray's sources count: those that agree best (the others may not see
    the point)."""
    normal_sources: int = 0
    """Per ray, this many stand-in sources: the views that look most squarely at its
    surface point (by its normal), which count only when the SDF blocks every one of its
    `sources` nearest (`occlusion_samples` > 0 decides; 0: none). The nearest views of a
    camera that sees a cavity's floor at a slant mostly see the wall instead."""
    patch: int = 3
    """Side of the square patch in samples (odd; 3 measured best at 400x300 on pits-deep
    against 5 and 7, which straddle narrow pits' rims)."""
    stride: int = 1
    """Pixels between the patch's samples."""
    max_sdf: float = 0.02
    """Rays whose rendered point lies farther than this from the zero level (normalised
    frame) do not count: their depth mixes two surfaces."""
    occlusion_samples: int = 0
    """SDF samples on the segment from a ray's surface point to each source camera; a
    source the SDF blocks does not count (0: no test; a cavity's floor is seen by few
    views, and its nearest sources often look at the wall instead)."""
    planar_sdf: float = 0.0
    """With > 0, a ray whose patch's points on the plane of its surface lie farther than
    this from the zero level (normalised frame) does not count: its patch straddles a rim
    (a narrow pit's opening), where the plane the patch is carried by is not there
    (0: no test)."""
    wide_sources: int = 0
    """With more than `sources`: this many nearest sources once the schedule reaches
    `wide_after` (the nearest `sources` before). A cavity's floor is seen by few views and
    its 4 nearest sources mostly see the wall: 8 give the floor's cost a minimum at the
    truth, but from the start they unsettle training while the geometry is a blob
    (0: never wider)."""
    wide_after: float = 0.5
    """Share of the schedule after which `wide_sources` count, in [0, 1]."""


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
    lr_decay_iters: int = 0
    """Length of the cosine decay in iterations (0: `iters`); set longer than `iters`, the
    run stops part-way down the curve (a budget scales it with the schedule)."""
    warm_up: int = 5000
    """Iterations of linear learning-rate warm-up."""
    anneal_end: int = 0
    """Iteration where the cos-annealing ratio reaches 1 (0: 1 from the start)."""
    igr_weight: float = 0.1
    """Weight of the Eikonal loss."""
    mask_weight: float = 0.1
    """Weight of the mask BCE loss (0: masks unused)."""
    hit_color_floor: float = 0.0
    """With masks: the colour term compares the colour of the surface a ray hits,
    ``color / max(opacity, hit_color_floor)``, instead of NeuS's composite over black (0: off,
    NeuS). The composite makes a ray inside a mask that grazes the surface render dark, so
    the colour term pulls every silhouette outward (on an exact sphere the colour and mask
    terms together are lowest with the surface 3.2-4.3 / s outside, normalised within 0.3 / s);
    normalised, the mask term alone sets the opacity. Below the floor the colour still pulls
    the opacity up (at 0.5: only rays that render as outside their mask are pulled)."""
    carve_weight: float = 0.0
    """Weight of silhouette carving (`neus_l0.train.losses.free_space`): on the rays whose
    mask is 0, how far the deepest sample lies inside the surface (0: off; needs the
    masks, `mask_weight` > 0). It removes what the mask BCE leaves a pixel or two outside
    the silhouettes, such as a skirt under an object that no camera sees from below. Off:
    at 100 it lowered the demo scene's accuracy (200x150 views) to 0.65x; at 10 on 400x300
    views the accuracy to 0.90x but not the pits (docs/BENCHMARKS.md, "Where does the error
    live")."""
    fill_weight: float = 0.0
    """Weight of silhouette filling (`neus_l0.train.losses.missed_rays`): on the rays whose
    mask is 1 but that render below 0.5 opacity, how far outside the surface the shallowest
    sample stays (0: off; needs the masks, `mask_weight` > 0). The mask BCE gives such a ray
    no gradient once it passes a few 1/s from every surface (its clip at 1e-3), so a thin
    part that did not form early never forms; this term's gradient does not fade. It lets go
    at `fill_margin` / s."""
    fill_margin: float = 3.0
    """Silhouette filling lets go of a ray once its shallowest counted sample lies within
    this many 1/s of the surface (3: where the mask BCE's gradient is alive again and takes
    over; 0: only once the ray crosses the surface)."""
    fill_silhouettes: bool = False
    """Silhouette filling counts only the samples inside every view's mask (the visual hull
    at pixel resolution, `neus_l0.bounds.silhouettes`, widened by `hull.margin_px`), so it
    pushes at the thin part a ray sees instead of the nearest other surface along it. Off:
    with `fill_margin` 0 it formed the r1 rod of `pits-deep` in 3 of 8 pairs, but lowered the
    pits in none and grows the unseen cone under the base (docs/BENCHMARKS.md, "Where does
    the error live")."""
    fill_span: float = 0.0
    """With `fill_silhouettes`: push only the rays whose samples inside every view's mask lie
    within this length of each other (normalised units; the object fits the unit sphere):
    a ray that sees a thin part against the background crosses the masks' intersection in a
    short segment, one into a pit or along a wall in a long one (0: every ray)."""
    fill_middle: bool = False
    """With `fill_silhouettes`: push the sample nearest the middle of a ray's samples inside
    every mask instead of the shallowest of them (which lies next to the surface that is
    already there: beside a plate, the masks' intersection is a wedge around it)."""
    seed: int = 0
    """Seed of the network initialisation and of the ray / sample generator."""
    log_every: int = 100
    """Iterations between metric log lines (and the only host syncs of the loop)."""
    val_every: int = 2500
    """Iterations between validation renders (0: never)."""
    val_downscale: int = 4
    """Downscale factor of the validation renders."""
    holdout: int = 0
    """Keep every K-th view (views 0, K, 2K, ...: `neus_l0.data.split.split_views`) out of
    training (0: train on every view). The run records which views in ``run.json``
    (``views``); validation then renders the held-out views, and `neus-l0 render --views
    test` renders exactly those."""
    save_every: int = 10000
    """Iterations between checkpoints (a final one is always written)."""
    keep_checkpoints: int = 3
    """How many of the newest checkpoints to keep."""
    max_seconds: float = 0.0
    """Wall-clock budget of the training loop (steps, logging, validation, checkpoints; not
    the setup before it nor the time of training hooks): stop and checkpoint after this many
    seconds (0: no budget)."""
    budget: Seconds = Seconds(0.0)
    """Time for the whole run, end to end (start-up, compile, steps, the final checkpoint):
    seconds, or ``90s``, ``10m``, ``1h`` (0: off, `iters` decides). The step rate is
    measured after the compile on a few steps that are then undone; `iters` is set from it
    and the schedule's landmarks (`warm_up`, `anneal_end`, `lr_decay_iters`, the hash grid's
    `update_steps`, `val_every`, `save_every`) keep their fraction of it
    (`neus_l0.train.budget.planned_config`). The run's
    config.yaml records the plan with ``budget: 0``, so a resume or a re-run of it trains
    the same schedule; ``RUN/budget.json`` records the budget and the measurements. If the
    step rate drifts later, the rest of the schedule is compressed (or stretched) to end in
    time. Without ``--conf``, `neus-l0 train` takes the device's setting and its capacity
    for the budget (`neus_l0.train.budget.LADDER`)."""
    budget_up_to_iters: bool = False
    """With `budget`: plan at most `iters` iterations. Where the config's schedule fits, the
    run trains it as is and ends early; where it does not, it is compressed to the budget
    (`neus-l0 demo`: at most 3500 iterations within its 150 s)."""
    early_stop: bool = False
    """Stop when the surface stops moving: an SDF probe on points near the surface
    (`neus_l0.train.early_stop`); off by default (not yet measured to pay)."""
    amp: AmpMode = "off"
    """Mixed precision of the networks on CUDA: `off`, `bf16` or `fp16` (with a gradient
    scaler and fused Adam); ignored on the CPU."""
    compile: bool | Literal["auto"] = "auto"
    """Compile the training step's render and loss with `torch.compile`
    (`neus_l0.train.compile`; needs `model.sdf.gradient` analytic or finite-difference;
    CUDA graphs on CUDA where they work). `auto`: compile when the run is long enough to
    repay the compile time, taking `model.sdf.gradient=analytic` then
    (`neus_l0.train.compile_auto`); the run's config.yaml records the choice."""
    tensorboard: bool = True
    """Write TensorBoard events into the run folder (`tensorboard --logdir RUN`)."""
    threads: int = 0
    """Torch CPU threads on the CPU (0: the cores free when the run starts, from the load
    average; `neus-l0 train --threads N` overrides it). Ignored on CUDA."""
    error_map: ErrorMapConfig = field(default_factory=ErrorMapConfig)
    """Error-map ray sampling (off by default); its draw table is rebuilt every
    `log_every` iterations."""
    photo: PhotoConfig = field(default_factory=PhotoConfig)
    """Multi-view photometric consistency (off by default)."""
    eikonal_fraction: float = 1.0
    """Fraction of the samples (drawn at random each step) that the Eikonal term averages
    over; 1: all samples within radius 1.2 (NeuS)."""
    curvature_weight: float = 0.0
    """Weight of Neuralangelo's curvature term: the mean |Laplacian| of the SDF at a random
    `curvature_fraction` of the step's samples, by central differences with the step of
    `model.sdf.gradient=finite-difference` (half a cell of the hash grid's finest active
    level, so it shrinks as levels switch on); 0: off. It smooths bumps the hash grid leaves
    on flat faces; each point costs 7 SDF evaluations."""
    curvature_fraction: float = 0.125
    """Fraction of the samples the curvature term averages over (with `curvature_weight`)."""


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
