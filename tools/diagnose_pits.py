"""Where the deep pit's error can come from, measured outside training (issue #35).

Usage:
    python tools/diagnose_pits.py SCENE [--conf demo] [--rays 96] [--budgets 16+16,32+32]
                                  [--out diag.json] [--train-seconds S --fraction F
                                  --tile T --signal colour|depth|depth_mask --warmup W
                                  --set KEY=VALUE ...] [--features [--feature-tol 6]]

SCENE is a `pits-deep` folder (``neus-l0 synth pits-deep SCENE``). Every pixel's first true
hit (``gt_depth.npz``) is labelled by the exact geometry of the deep pit
(`neus_l0.synthetic.shapes.DEEP_PIT`): pit floor, pit wall, rods standing in the pit, open
surface (everything else the object shows), or nothing. With ``--features`` SCENE is any
synthetic scene with a ``features.json`` and each feature is a label (`feature_label`: a
thin feature's axis segment widened by ``--feature-tol``, any other feature's ball). Per
label it prints:

- the share of the training pixel pool (`neus_l0.bounds.pixel_pool.reachable_pixels` under
  the config's static bounds, as a run builds it) and, times ``train.batch_size``, the rays
  a step draws there (uniform draws over the pool, `neus_l0.train.step.draw_step_inputs`);
- how many views see it (at least one pixel; at least 20 pixels) and its pixels per view;
- where NeuS's fine samples land on up to `--rays` pool rays of that label, per sampler
  (hvs, l0) and budget: the up-sampling run on the exact SDF at NeuS's fixed sharpness
  (`neus_l0.experiments.oracle`, training-like: the rays' own spans), scored against the
  exact first hit: the share within 0.003 and 0.01 (normalised units) of it, the share of
  rays with none within 0.01, and the share of samples that sit on the surface (|SDF| <
  0.01) before the hit: rays grazing the rim or a rod on their way to the floor.

With ``--train-seconds S`` it also trains the config for S seconds (one thread, eager unless
``--set train.compile=true``) with ``train.error_map.fraction`` `--fraction`, tiles of
`--tile` pixels, the map's signal `--signal` (``train.error_map.signal``) and warm-up
`--warmup`, and prints at each
log step the rays a step draws per label under the map's table and the mean running error
of the label's pixels: whether the map finds the pit.

With ``--hash 15,19`` it also counts, for the SDF's hash grid at each table size
(``model.sdf.encoding.log2_hashmap_size``), how much of the surface ray traffic on a label's
table entries is the label's own: every pool pixel's first hit spreads its trilinear weights
over the 8 corners of its cell at each level; an entry's traffic is the sum over all hits,
and a label's own share at a level is the mean, over its hits' corner weights, of (the
label's traffic on the entry) / (the entry's traffic). 1: the entries are the label's
alone; 0.05: 95 % of the gradient that reaches them comes from surface elsewhere (a hashed
level's collisions, or a coarse cell shared with the open surface). With ``--hash-free K``
the samples along the rays count too: K uniform samples in each of ``--hash-rays`` random
pool rays' spans (a step's coarse samples, scaled to the whole pool) enter every entry's
traffic and no label's own, and each hit counts K (its fine samples, near the surface).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neus_l0.atomic import atomic_write_json
from neus_l0.bounds.pixel_pool import reachable_pixels
from neus_l0.bounds.sphere import near_far_from_sphere
from neus_l0.bounds.static import static_bounds
from neus_l0.config.load import load_config
from neus_l0.config.schema import SamplerConfig
from neus_l0.data.rays import rays_at
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.features import feature_label, load_features
from neus_l0.evaluation.synthetic import first_hits
from neus_l0.experiments.oracle import first_hit
from neus_l0.formats.neus import load_scene
from neus_l0.render.volume import coarse_z_vals
from neus_l0.sampling.upsample import build_sampler, up_sample
from neus_l0.synthetic.scene import WORLD_OFFSET
from neus_l0.synthetic.shapes import (
    BUILTIN_SHAPES,
    DEEP_PIT,
    DEEP_PIT_RODS,
    Translated,
    builtin_shape,
)
from neus_l0.train.callbacks import TrainingCallback
from neus_l0.train.loop import train

LABELS = ("nothing", "open surface", "pit wall", "pit floor", "rods")
#: World-unit tolerance of the labels (about a pixel's footprint at 400x300).
TOL = 1.0
SAMPLERS = {"hvs": SamplerConfig(name="hvs"), "l0": SamplerConfig(name="l0")}


def label(pts: np.ndarray) -> np.ndarray:
    """(...,) int labels (`LABELS` indices) of (..., 3) world points (NaN: nothing)."""
    (px, py), r, depth = DEEP_PIT
    ox, oy, oz = WORLD_OFFSET
    top, floor = 25.0 + oz, 25.0 + oz - depth
    x, y, z = pts[..., 0] - px - ox, pts[..., 1] - py - oy, pts[..., 2]
    rho = np.hypot(x, y)
    out = np.where(np.isnan(z), 0, 1)
    inside = (rho < r + TOL) & (z < top - TOL) & (z > floor - TOL)
    out = np.where(inside & (np.abs(rho - r) <= TOL), 2, out)
    out = np.where(inside & (np.abs(z - floor) <= TOL) & (rho < r - TOL), 3, out)
    for (dx, dy), rr, h in DEEP_PIT_RODS:
        on_rod = (np.hypot(x - dx, y - dy) <= rr + TOL) & (z > floor + TOL) & (z <= floor + h
                                                                                + TOL)
        out = np.where(on_rod, 4, out)
    return out


def view_table(labels: np.ndarray, pool_labels: np.ndarray, batch: int,
               names: tuple[str, ...] = LABELS) -> list[dict]:
    """Per label: pool share, rays a step, views seeing it, pixels per seeing view."""
    rows = []
    for k, name in enumerate(names):
        per_view = (labels == k).reshape(labels.shape[0], -1).sum(-1)
        share = float((pool_labels == k).mean())
        seen = per_view[per_view > 0]
        rows.append({"feature": name, "pool_share": share, "rays_per_step": share * batch,
                     "views_1px": int((per_view > 0).sum()),
                     "views_20px": int((per_view >= 20).sum()),
                     "px_per_seeing_view": float(np.median(seen)) if len(seen) else 0.0})
    return rows


class NormalisedSdf:
    """The scene's exact SDF in NeuS's normalised frame: ``f(S x + c) / s``."""

    def __init__(self, scale_mat: np.ndarray, shape_name: str = "pits-deep"):
        shape = builtin_shape(shape_name)
        self.sdf = Translated(shape.sdf, WORLD_OFFSET)
        self.s = float(scale_mat[0, 0])
        self.c = torch.as_tensor(scale_mat[:3, 3], dtype=torch.float64)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return self.sdf(x.double() * self.s + self.c) / self.s


def fine_sample_row(sdf, rays: dict, span: torch.Tensor, hit: torch.Tensor,
                    budget: tuple[int, int, int], cfg: SamplerConfig) -> dict:
    """Where one sampler's fine samples land on (B,) rays with exact first hits `hit`."""
    n_samples, n_importance, rounds = budget
    o, d = rays["origins"].float(), rays["dirs"].float()
    g = torch.Generator().manual_seed(0)
    z = coarse_z_vals(span[:, :1], span[:, 1:2], n_samples, perturb=True, generator=g)
    _, z_new = up_sample(sdf, o, d, z, build_sampler(cfg), n_importance, rounds)
    dist = (z_new.double() - hit[:, None]).abs()  # (B, n_importance)
    pts = o.double()[:, None] + d.double()[:, None] * z_new.double()[..., None]
    f = sdf(pts.reshape(-1, 3)).reshape(z_new.shape).abs()
    before = (z_new.double() < hit[:, None] - 0.01) & (f < 0.01)
    return {"within_0.003": float((dist <= 0.003).double().mean()),
            "within_0.01": float((dist <= 0.01).double().mean()),
            "rays_missed": float((dist > 0.01).all(-1).double().mean()),
            "on_surface_before_hit": float(before.double().mean())}


def sample_table(scene, pool, pool_labels: np.ndarray, n_rays: int,
                 budgets: list[tuple[int, int, int]],
                 names: tuple[str, ...] = LABELS, shape_name: str = "pits-deep"
                 ) -> list[dict]:
    """`fine_sample_row` per label (not `nothing`), budget and sampler, on the built-in
    shape `shape_name`'s exact SDF."""
    sdf = NormalisedSdf(np.asarray(scene.scale_mat), shape_name)
    rng = np.random.default_rng(0)
    rows = []
    for k, name in enumerate(names[1:], start=1):
        idx = np.nonzero(pool_labels == k)[0]
        idx = torch.as_tensor(rng.choice(idx, min(n_rays, len(idx)), replace=False))
        if len(idx) == 0:
            continue
        rays = rays_at(scene, pool.pixels[idx])
        if pool.spans is not None:
            span = pool.spans[idx]
        else:
            span = torch.cat(near_far_from_sphere(rays["origins"], rays["dirs"]), -1)
        hit = first_hit(sdf, rays["origins"].double(), rays["dirs"].double(), n=4001)
        ok = torch.isfinite(hit)
        rays = {key: v[ok] for key, v in rays.items()}
        for budget in budgets:
            for sname, cfg in SAMPLERS.items():
                row = {"feature": name, "rays": int(ok.sum()),
                       "budget": f"{budget[0]}+{budget[1]}", "sampler": sname}
                row.update(fine_sample_row(sdf, rays, span[ok], hit[ok], budget, cfg))
                rows.append(row)
    return rows


class _RaysWhereTheMapDraws(TrainingCallback):
    """At each log step: the rays a step draws per label under the error map's table, and
    the mean running error of the label's pixels (their tiles')."""

    def __init__(self, labels: np.ndarray, batch: int, names: tuple[str, ...] = LABELS):
        self.labels, self.batch, self.names, self.rows = labels, batch, names, []

    def on_log(self, run, metrics: dict) -> None:
        pool = run.setup.pool
        prob = pool.error_map.prob.double().cpu().numpy()
        lab = self.labels[pool.pixels.cpu().numpy()]
        row = {"iteration": run.iteration, "loss": metrics.get("loss", float("nan"))}
        row.update({name: float(prob[lab == k].sum()) * self.batch
                    for k, name in enumerate(self.names)})
        err = pool.error_map.error[pool.error_map.tile].cpu().numpy()
        row.update({f"err {name}": float(err[lab == k].mean()) if (lab == k).any() else 0.0
                    for k, name in enumerate(self.names)})
        self.rows.append(row)


def error_map_run(scene, conf: str, labels: np.ndarray, seconds: float,
                  overrides: list[str], names: tuple[str, ...] = LABELS) -> list[dict]:
    """Train config `conf` with the error map's `overrides` (``train.error_map.*=...``, and
    any other) for `seconds` (one thread; eager unless the overrides say otherwise) and
    return the rays a step draws per label at each log step (under the table the draw uses
    then: `refresh_interval`)."""
    cfg = load_config(conf, [f"train.max_seconds={seconds}", "train.compile=false",
                             "train.threads=1", "train.val_every=0", "train.save_every=0",
                             "train.tensorboard=false", "train.log_every=100", *overrides])
    cb = _RaysWhereTheMapDraws(labels.reshape(-1), cfg.train.batch_size, names)
    with tempfile.TemporaryDirectory() as tmp:
        train(scene, cfg, Path(tmp) / "run", progress=False, callbacks=[cb])
    return cb.rows


def _corner_weights(enc, x: Tensor) -> tuple[Tensor, Tensor]:
    """(n, L, 8) table rows and float64 trilinear weights of (n, 3) normalised points."""
    _, _, frac, idx = enc._cells(x)  # (n, L, 3), (n, L, 8)
    c = enc.corners.bool()  # (8, 3)
    w = torch.prod(torch.where(c, frac[:, :, None, :], 1 - frac[:, :, None, :]), -1)
    return idx, w.double()


#: Points per chunk of the hash-share count.
HASH_CHUNK = 1 << 18


def _entry_traffic(enc, x: Tensor, lab: Tensor, xf: Tensor, hit_weight: float,
                   free_weight: float, n_labels: int) -> Tensor:
    """(n_labels, table rows) float64: each label's traffic on every entry (label 0's row
    also takes the free samples `xf`)."""
    traffic = torch.zeros(n_labels, enc.table.shape[0], dtype=torch.float64)
    for i in range(0, len(xf), HASH_CHUNK):
        idx, w = _corner_weights(enc, xf[i:i + HASH_CHUNK])
        traffic[0].index_add_(0, idx.reshape(-1), w.reshape(-1) * free_weight)
    rows = traffic.shape[1]
    for i in range(0, len(x), HASH_CHUNK):
        idx, w = _corner_weights(enc, x[i:i + HASH_CHUNK])
        key = lab[i:i + HASH_CHUNK, None, None] * rows + idx  # (n, L, 8)
        traffic.view(-1).index_add_(0, key.reshape(-1), w.reshape(-1) * hit_weight)
    return traffic


def hash_share_table(points: np.ndarray, labels: np.ndarray, scale_mat: np.ndarray,
                     conf: str, log2_sizes: list[int], free: np.ndarray | None = None,
                     weights: tuple[float, float] = (1.0, 1.0),
                     names: tuple[str, ...] = LABELS) -> list[dict]:
    """Per (table size, label): the label's own share of the traffic on its entries, per
    level of the SDF's hash grid (see the module docstring).

    Args:
        points: (N, 3) world first hits of the pool's pixels (labels > 0 only).
        labels: (N,) int indices into `names` of `points`.
        scale_mat: (4, 4) the scene's normalised -> world matrix (``scale_mat_0``).
        conf: the config whose ``model.sdf.encoding`` is counted.
        log2_sizes: table sizes (log2) to count.
        free: (M, 3) world sample points along the rays (the coarse samples), counted in
            every entry's traffic but no label's own; None: surface hits only.
        weights: (hit, free) the traffic of one hit and of one free point.
        names: the labels' names (`LABELS`, or `feature_label`'s).
    """
    from neus_l0.data.cameras import to_normalised
    from neus_l0.fields.encodings import HashGridEncoding

    x = torch.as_tensor(to_normalised(points, scale_mat), dtype=torch.float32)
    xf = (torch.as_tensor(to_normalised(free, scale_mat), dtype=torch.float32)
          if free is not None else torch.zeros(0, 3))
    lab = torch.as_tensor(labels, dtype=torch.int64)
    rows = []
    for log2 in log2_sizes:
        cfg = load_config(conf, [f"model.sdf.encoding.log2_hashmap_size={log2}"])
        enc = HashGridEncoding(cfg.model.sdf.encoding)
        traffic = _entry_traffic(enc, x, lab, xf, *weights, len(names))
        total = traffic.sum(0).clamp_min(1e-30)  # (table rows,)
        own = torch.zeros(len(names), enc.n_levels, dtype=torch.float64)
        mass = torch.zeros_like(own)
        for i in range(0, len(x), HASH_CHUNK):  # recomputed: no per-hit tensors kept
            idx, w = _corner_weights(enc, x[i:i + HASH_CHUNK])
            lab_c = lab[i:i + HASH_CHUNK]
            share = traffic[lab_c[:, None, None], idx] / total[idx]
            own.index_add_(0, lab_c, (w * share).sum(-1))
            mass.index_add_(0, lab_c, w.sum(-1))
        for k, name in enumerate(names):
            if k == 0 or mass[k, 0] == 0:
                continue
            row = {"log2 table": log2, "hashed levels": f"L{enc.n_direct}+",
                   "label": name, "hits": int((lab == k).sum())}
            for lv, res in enumerate(enc.resolutions):
                row[f"L{lv} ({res} cells)"] = float(own[k, lv] / mass[k, lv])
            rows.append(row)
    return rows


def free_samples(scene, pool, bounds, render_cfg, n_rays: int, per_ray: int,
                 seed: int = 0) -> tuple[np.ndarray, float]:
    """(M, 3) world points: `per_ray` uniform samples in the span of `n_rays` random pool
    rays (as a step's coarse samples lie), and the traffic weight that scales them to the
    whole pool (pool pixels / rays)."""
    from neus_l0.bounds.spans import packed_spans
    from neus_l0.data.cameras import to_world

    g = torch.Generator().manual_seed(seed)
    pick = pool.pixels[torch.randperm(pool.pixels.numel(), generator=g)[:n_rays]]
    rays = rays_at(scene, pick)
    span, active = packed_spans(rays["origins"], rays["dirs"], render_cfg, bounds)
    t = torch.rand(len(pick), per_ray, generator=g)
    z = span[:, :1] + (span[:, 1:2] - span[:, :1]) * t  # (R, K)
    pts = rays["origins"][:, None, :] + rays["dirs"][:, None, :] * z[..., None]
    pts = pts[active].reshape(-1, 3).double().numpy()
    return to_world(pts, scene.scale_mat), pool.pixels.numel() / max(1, int(active.sum()))


def _log2_list(text: str) -> list[int]:
    """``--hash``'s value: comma-separated table sizes (log2), each in 4..30."""
    try:
        sizes = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give integers, e.g. 15,19") from None
    if any(not 4 <= v <= 30 for v in sizes):
        raise argparse.ArgumentTypeError(f"{text!r}: table sizes are log2 values in 4..30")
    return sizes


def _markdown(rows: list[dict]) -> str:
    keys = list(rows[0])

    def fmt(v):
        return f"{v:.3g}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(fmt(r[k]) for k in keys) + " |" for r in rows]
    return "\n".join(lines)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--conf", default="demo")
    ap.add_argument("--rays", type=int, default=96, help="rays per feature for the samples")
    ap.add_argument("--budgets", default="16+16,32+32")
    ap.add_argument("--out", type=Path, default=None, help="write the tables as JSON")
    ap.add_argument("--train-seconds", type=float, default=0.0,
                    help="also train this long with the error map on and report where it "
                         "draws (0: no training)")
    ap.add_argument("--fraction", type=float, default=0.5, help="train.error_map.fraction")
    ap.add_argument("--tile", type=int, default=8, help="train.error_map.tile")
    ap.add_argument("--signal", default="colour", choices=["colour", "depth", "depth_mask"],
                    help="train.error_map.signal")
    ap.add_argument("--warmup", type=float, default=0.0, help="train.error_map.warmup")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="more config overrides for the --train-seconds run")
    ap.add_argument("--features", action="store_true",
                    help="label by the scene's features.json (any synthetic scene: each "
                         "feature a label) instead of the pits-deep geometry")
    ap.add_argument("--feature-tol", type=float, default=6.0,
                    help="with --features: world units from a thin feature's axis segment "
                         "that count as on it")
    ap.add_argument("--hash", type=_log2_list, default=[],
                    help="table sizes (log2, comma-separated) whose entries' own share of "
                         "surface traffic to count per label, e.g. 15,19 (empty: none)")
    ap.add_argument("--hash-free", type=int, default=0,
                    help="with --hash: also count K uniform samples per ray in its span (a "
                         "step's coarse samples; each hit then counts K, its fine samples)")
    ap.add_argument("--hash-rays", type=int, default=100000,
                    help="pool rays whose span samples --hash-free counts")
    return ap


def _shape_source(scene_dir: Path) -> str | None:
    """The built-in shape a synthetic scene was rendered from (``scene.json``'s ``source``),
    None for a mesh file's scene or a scene without a readable ``scene.json``."""
    try:
        source = json.loads((scene_dir / "scene.json").read_text()).get("source")
    except (OSError, ValueError, AttributeError):
        return None
    return source if source in BUILTIN_SHAPES else None


def _hash_rows(args, scene, pool, bounds, cfg, flat_hits: np.ndarray,
               pool_labels: np.ndarray, names: tuple[str, ...]) -> list[dict]:
    """`hash_share_table` for ``--hash`` (and ``--hash-free``), printed."""
    hit = pool_labels > 0
    free, free_w = (free_samples(scene, pool, bounds, cfg.render, args.hash_rays,
                                 args.hash_free) if args.hash_free else (None, 1.0))
    shares = hash_share_table(flat_hits[hit], pool_labels[hit], scene.scale_mat, args.conf,
                              args.hash, free, (max(1, args.hash_free), free_w), names)
    what = f"surface and {args.hash_free} span samples a ray" if args.hash_free else "surface"
    print(f"\nown share of the {what} traffic on each label's table entries\n"
          f"{_markdown(shares)}")
    return shares


def main() -> int:
    args = _parser().parse_args()
    torch.set_num_threads(1)
    cfg = load_config(args.conf)
    try:
        scene = load_scene(args.scene)
        pts, _, _ = first_hits(args.scene)
        feats = load_features(args.scene) if args.features else None
    except NeusL0Error as exc:
        print(f"diagnose_pits: {exc}")
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        bounds = static_bounds(scene, cfg, Path(tmp) / "hull.pt")
    pool = reachable_pixels(scene, cfg.render, bounds)
    if feats is not None:
        labels, names = feature_label(pts, feats, args.feature_tol)
    else:
        labels, names = label(pts), LABELS  # (V, H, W)
    pool_labels = labels.reshape(-1)[pool.pixels.numpy()]
    views = view_table(labels, pool_labels, cfg.train.batch_size, names)
    print(f"pool: {pool.pixels.numel()} pixels ({pool.fraction:.3f} of all), batch "
          f"{cfg.train.batch_size}\n{_markdown(views)}\n")
    budgets = [(int(a), int(b), 2) for a, b in (s.split("+") for s in args.budgets.split(",")
                                                 if s)]
    source = _shape_source(args.scene)
    if budgets and source is None:
        print(f"{args.scene}: not rendered from a built-in shape: no exact SDF, so no "
              "fine-sample table")
        budgets = []
    samples = (sample_table(scene, pool, pool_labels, args.rays, budgets, names, source)
               if budgets else [])
    if samples:
        print(_markdown(samples))
    shares = (_hash_rows(args, scene, pool, bounds, cfg, pts.reshape(-1, 3)[pool.pixels.numpy()],
                         pool_labels, names) if args.hash else [])
    drawn = []
    if args.train_seconds > 0:
        emap = [f"train.error_map.fraction={args.fraction}",
                f"train.error_map.tile={args.tile}", f"train.error_map.signal={args.signal}",
                f"train.error_map.warmup={args.warmup}"]
        drawn = error_map_run(scene, args.conf, labels, args.train_seconds,
                              [*emap, *args.set], names)
        print(f"\nrays a step draws per feature, {' '.join([*emap, *args.set])}\n"
              f"{_markdown(drawn)}")
    if args.out:
        atomic_write_json(args.out, {"views": views, "samples": samples, "error_map": drawn,
                                     "hash_share": shares})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
