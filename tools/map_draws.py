"""Where a finished run's error map draws its rays, per feature of a synthetic scene (#35).

A run trained with ``train.error_map.fraction > 0`` keeps its map in every checkpoint. This
rebuilds the run's pixel pool (its training views, its hull, its config), loads the newest
checkpoint's map into it and labels each pool pixel by the feature its first true hit lies
on (`neus_l0.evaluation.features.feature_label`), so that no training is needed to see:

- per feature: its pool pixels, the rays a step draws there against a uniform draw
  (``draw / uniform``) and its tiles' mean error against the pool's;
- how concentrated the map is (the share of the error in its top 1 % and 10 % of tiles, the
  Gini coefficient);
- at other shares f of the draw: the effective share of the batch that importance weights
  leave (``1 / E[w^2]``), the largest weight ``1 / (1 - f)`` and each floor's draw.

    python tools/map_draws.py RUN [RUN ...] [--fractions 0.3,0.5,0.8] [--json OUT]

RUN is a training run folder (``neus-l0 train``, or ``runs/NAME`` inside a ``bench`` folder)
of a synthetic scene (``features.json`` and the exact first hits).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

from neus_l0.atomic import atomic_write_json
from neus_l0.bounds.error_map import draw_probabilities, restore_map
from neus_l0.bounds.pixel_pool import reachable_pixels, with_error_map
from neus_l0.bounds.static import static_bounds
from neus_l0.config.load import load_config
from neus_l0.data.split import subset_scene
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.features import feature_label, load_features
from neus_l0.evaluation.synthetic import first_hits
from neus_l0.formats.neus import load_scene
from neus_l0.mesh.from_run import run_scene
from neus_l0.run.checkpoints import latest_checkpoint, load_checkpoint


def concentration(error: np.ndarray) -> dict:
    """How concentrated (K,) tile errors >= 0 are: the share of their sum in the top 1 %
    and 10 % of tiles, and the Gini coefficient (0: all equal, -> 1: one tile holds all)."""
    e = np.sort(np.clip(error.astype(np.float64), 0, None))[::-1]
    n, total = e.size, e.sum()
    if total <= 0:
        return {"top1": 0.0, "top10": 0.0, "gini": 0.0}
    cum = np.cumsum(e[::-1])
    return {"top1": float(e[:max(1, n // 100)].sum() / total),
            "top10": float(e[:max(1, n // 10)].sum() / total),
            "gini": float(1 - 2 * cum.sum() / (n * total) + 1 / n)}


def effective_share(prob: np.ndarray) -> float:
    """``1 / E[w^2]`` for draws from (P,) probabilities with weights ``w = 1 / (P p)``: the
    share of a batch whose plain mean would be as noisy as the weighted one (1: uniform)."""
    p = prob.astype(np.float64)
    return float(p.size ** 2 / (1.0 / p).sum())


def feature_rows(prob: np.ndarray, error: np.ndarray, labels: np.ndarray,
                 names: tuple[str, ...], min_pixels: int = 20) -> list[dict]:
    """Per label with at least `min_pixels` pool pixels: (P,) draw probabilities and
    per-pixel errors summed over its (P,) labels, against a uniform draw and the mean."""
    n, mean = prob.size, max(float(error.mean()), 1e-30)
    rows = []
    for k, name in enumerate(names):
        on = labels == k
        if on.sum() < min_pixels:
            continue
        rows.append({"feature": name, "pixels": int(on.sum()),
                     "draw_vs_uniform": float(prob[on].sum() / (on.sum() / n)),
                     "error_vs_mean": float(error[on].mean() / mean)})
    return rows


def run_map(run_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, Path,
                                     list[int] | None]:
    """A run's error map on its pool: (P,) draw probabilities, (P,) each pixel's tile error,
    (P,) flat pixel indices into the run's training views, the map's share, the scene and
    the run's training views (None: every view).

    Raises:
        NeusL0Error: no config, checkpoint or map, or a map of another pool.
    """
    scene_dir, train = run_scene(run_dir)
    ckpt = latest_checkpoint(run_dir)
    if ckpt is None or not (run_dir / "config.yaml").is_file():
        raise NeusL0Error(f"{run_dir}: no config.yaml or checkpoint (not a training run?)")
    cfg = load_config(str(run_dir / "config.yaml"))
    full = load_scene(scene_dir)
    scene = subset_scene(full, train) if train else full
    with tempfile.TemporaryDirectory() as tmp:  # the run's hull, never rewritten
        hull = Path(tmp) / "hull.pt"
        if (run_dir / "hull.pt").is_file():
            hull.write_bytes((run_dir / "hull.pt").read_bytes())
        bounds = static_bounds(scene, cfg, hull, reuse=True)
    pool = with_error_map(reachable_pixels(scene, cfg.render, bounds,
                                           background=cfg.render.n_outside > 0), scene, cfg)
    state = load_checkpoint(ckpt).get("error_map")
    if pool is None or pool.error_map is None or not isinstance(state, dict):
        raise NeusL0Error(f"{ckpt}: no error map (train.error_map.fraction was 0)")
    if not restore_map(pool.error_map, state):
        raise NeusL0Error(f"{ckpt}: its error map has other tiles than the run's pool")
    em = pool.error_map
    return (em.prob.double().numpy(), em.table_error[em.tile].numpy(), pool.pixels.numpy(),
            em.fraction, scene_dir, train)


def report(run_dir: Path, fractions: list[float]) -> dict:
    """The tables of one run (`feature_rows`, `concentration`, and per share f the
    `effective_share`, the largest weight and the floors' draw)."""
    prob, error, pixels, share, scene_dir, train = run_map(run_dir)
    hits, _, _ = first_hits(scene_dir)
    hits = hits[train] if train else hits
    labels, names = feature_label(hits, load_features(scene_dir))
    lab = labels.reshape(-1)[pixels]
    floors = [k for k, n in enumerate(names) if "floor" in n]
    at = []
    for f in fractions:
        p = draw_probabilities(torch.from_numpy(error), f).numpy()
        at.append({"fraction": f, "effective_share": effective_share(p),
                   "largest_weight": float(1.0 / (p.size * p.min())),
                   **{f"{names[k]} draw_vs_uniform": float(p[lab == k].sum()
                                                           / max((lab == k).mean(), 1e-30))
                      for k in floors}})
    return {"run": str(run_dir), "fraction": share, "concentration": concentration(error),
            "effective_share": effective_share(prob),
            "features": feature_rows(prob, error, lab, names), "at_fractions": at}


def _print(rep: dict) -> None:
    c = rep["concentration"]
    print(f"{rep['run']}: share {rep['fraction']:.2f}, effective share "
          f"{rep['effective_share']:.3f}; top 1 % of tiles {c['top1']:.3f} of the error, "
          f"top 10 % {c['top10']:.3f}, Gini {c['gini']:.3f}")
    print("| feature | pool pixels | draw / uniform | error / mean |\n|---|---:|---:|---:|")
    for r in rep["features"]:
        print(f"| {r['feature']} | {r['pixels']} | {r['draw_vs_uniform']:.2f} | "
              f"{r['error_vs_mean']:.2f} |")
    for a in rep["at_fractions"]:
        rest = ", ".join(f"{k.split(' draw')[0]} {v:.2f}x" for k, v in a.items()
                         if k.endswith("draw_vs_uniform"))
        print(f"  at f {a['fraction']}: effective share {a['effective_share']:.3f}, largest "
              f"weight {a['largest_weight']:.2f}{', ' + rest if rest else ''}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", type=Path, nargs="+", help="training run folders")
    ap.add_argument("--fractions", default="0.3,0.5,0.8",
                    help="shares of the draw to price the map at (comma-separated)")
    ap.add_argument("--json", type=Path, default=None, help="also write the tables as JSON")
    args = ap.parse_args()
    try:
        fractions = [float(x) for x in args.fractions.split(",") if x]
    except ValueError:
        ap.error(f"--fractions: numbers, got {args.fractions!r}")
    if not all(0.0 <= f < 1.0 for f in fractions):
        ap.error(f"--fractions: each in [0, 1), got {args.fractions!r}")
    torch.set_num_threads(1)
    reports = []
    for run in args.runs:
        try:
            reports.append(report(run, fractions))
        except NeusL0Error as exc:
            print(f"map_draws: {exc}")
            return 2
        _print(reports[-1])
    if args.json:
        atomic_write_json(args.json, {"runs": reports})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
