"""Score one mesh: the whole `neus-l0 eval` pipeline as a function returning the report.

`score_mesh(mesh, ScoreSpec(...))` runs five stages: load the ground truth (first, so that
a bad path fails before the slow part), load and optionally cull the mesh, sample and thin
it, score it with the ground truth's protocol, and optionally write error maps. The
protocol and the report's fields are documented in docs/EVALUATION.md.

Every setting is checked before any file is read (`ScoreSpec.check`: finite, in range, a
colormap matplotlib knows), and the number of points the sampling will make (the mesh's
area / density^2, `pointcloud.expected_samples`) is checked against the memory available
before sampling. The report holds no NaN or infinity (they become null), so that the JSON
written is valid.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from neus_l0.errors import NeusL0Error
from neus_l0.evaluation import dtu, synthetic
from neus_l0.evaluation.chamfer import ChamferResult, nearest_distances
from neus_l0.evaluation.cull import cull_mesh
from neus_l0.evaluation.dtu import DTU_DENSITY, DTU_MARGIN_HIGH, DTU_MARGIN_LOW, DTU_MAX_DIST
from neus_l0.evaluation.io import load_mesh, load_points
from neus_l0.evaluation.pointcloud import (
    expected_samples,
    sample_mesh,
    sampling_bytes,
    thin_points,
)
from neus_l0.evaluation.synthetic import DEPTH_TOL, SyntheticGT

#: Expected sampled points from which `score_mesh` logs its steps and shows progress bars.
PROGRESS_POINTS = 2_000_000


@dataclasses.dataclass(frozen=True)
class ScoreSpec:
    """How to score a mesh (the flags of `neus-l0 eval`; the defaults are DTU's).

    Attributes:
        scene: synthetic scene folder (gt_points.ply, gt_depth.npz, cameras_sphere.npz);
            give this or `dtu_dir`.
        dtu_dir: DTU evaluation folder (Points/stl, ObsMask); needs `scan`.
        scan: DTU scan number.
        cull: scene folder whose dilated masks cull the mesh first (NeuS's no-mask protocol).
        cull_dilate: mask dilation in pixels (None: round(24 * width / 1600)).
        error_maps: folder for accuracy.ply / completeness.ply coloured by distance (None:
            no maps).
        vmax: top of the error maps' colour scale (None: `max_dist`).
        cmap: matplotlib colormap of the error maps.
        density: sampling density and thinning radius (world units).
        max_dist: distances >= this are left out of both means.
        margin_low, margin_high: evaluation box margins below / above the GT box.
        depth_tol: synthetic visibility tolerance (world units behind the true surface).
        seed: seed of the thinning order (>= 0).
        workers: kd-tree threads (-1: all cores, else >= 1).
    """

    scene: str | Path | None = None
    dtu_dir: str | Path | None = None
    scan: int | None = None
    cull: str | Path | None = None
    cull_dilate: int | None = None
    error_maps: str | Path | None = None
    vmax: float | None = None
    cmap: str = "jet"
    density: float = DTU_DENSITY
    max_dist: float = DTU_MAX_DIST
    margin_low: float = DTU_MARGIN_LOW
    margin_high: float = DTU_MARGIN_HIGH
    depth_tol: float = DEPTH_TOL
    seed: int = 0
    workers: int = -1

    def check(self) -> None:
        """Raise `NeusL0Error` (one line, in the flags' words) on inconsistent or out-of-range
        settings: every number finite and in range, the colormap known to matplotlib."""
        from neus_l0.evaluation.error_maps import check_cmap

        if (self.scene is None) == (self.dtu_dir is None):
            raise NeusL0Error("give exactly one ground truth: a synthetic scene or a DTU folder")
        if self.dtu_dir is not None and self.scan is None:
            raise NeusL0Error("--dtu needs --scan (the DTU scan number)")
        positive = [("density", self.density), ("max-dist", self.max_dist)]
        if self.vmax is not None:
            positive.append(("vmax", self.vmax))
        for name, value in positive:
            if not (math.isfinite(value) and value > 0):
                raise NeusL0Error(f"--{name} {value}: must be a positive finite number")
        for name, value in (("margin-low", self.margin_low), ("margin-high", self.margin_high),
                            ("depth-tol", self.depth_tol)):
            if not (math.isfinite(value) and value >= 0):
                raise NeusL0Error(f"--{name} {value}: must be a finite number >= 0")
        for name, value in (("scan", self.scan), ("cull-dilate", self.cull_dilate),
                            ("seed", self.seed)):
            if value is not None and value < 0:
                raise NeusL0Error(f"--{name} {value}: must be >= 0")
        if self.workers == 0 or self.workers < -1:
            raise NeusL0Error(f"--workers {self.workers}: give -1 (all cores) or a number of "
                              "threads >= 1")
        check_cmap(self.cmap)

    @property
    def margins(self) -> dict[str, float]:
        """The box margins as keyword arguments of the protocols' functions."""
        return {"margin_low": self.margin_low, "margin_high": self.margin_high}


@dataclasses.dataclass
class GroundTruth:
    """The loaded ground truth of one protocol, with the protocol's scoring functions.

    Attributes:
        protocol: "dtu" or "synthetic".
        points: (M, 3) float64 GT points (DTU: the STL points; synthetic: gt_points.ply).
        info: what the report records about it (paths, scan).
        obs, plane: DTU's ObsMask and (4,) plane (None for a synthetic scene).
        scene_gt: the synthetic scene's ground truth (None for DTU).
    """

    protocol: str
    points: np.ndarray
    info: dict
    obs: dtu.ObsMask | None = None
    plane: np.ndarray | None = None
    scene_gt: SyntheticGT | None = None

    def evaluate(self, pred: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                 spec: ScoreSpec) -> tuple[ChamferResult, dict[str, np.ndarray]]:
        """Chamfer of thinned points (N, 3) from the mesh (vertices (V, 3), faces (F, 3)).

        Returns:
            (result, masks) of `dtu.evaluate_dtu` / `synthetic.evaluate_synthetic`.
        """
        if self.protocol == "dtu":
            return dtu.evaluate_dtu(pred, self.points, self.obs, self.plane, spec.max_dist,
                                    workers=spec.workers, **spec.margins)
        return synthetic.evaluate_synthetic(pred, self.scene_gt, spec.max_dist,
                                            depth_tol=spec.depth_tol, workers=spec.workers,
                                            pred_mesh=(vertices, faces), **spec.margins)

    def scored(self, vertices: np.ndarray, spec: ScoreSpec) -> np.ndarray:
        """(V,) bool: which of (V, 3) points the accuracy side would score."""
        if self.protocol == "dtu":
            return dtu.evaluation_region(vertices, self.obs, **spec.margins)[1]
        return synthetic.evaluation_region(vertices, self.scene_gt, depth_tol=spec.depth_tol,
                                           **spec.margins)[1]

    def distance(self, vertices: np.ndarray, top: float, workers: int) -> np.ndarray:
        """(V,) accuracy distance of (V, 3) points (`inf` at or above `top`)."""
        if self.protocol == "dtu":
            return nearest_distances(vertices, self.points, upper_bound=top, workers=workers)
        # the same distance as accuracy (point-to-mesh with gt_mesh.ply)
        return self.scene_gt.distance_to_gt(vertices, top, workers=workers)


def load_ground_truth(spec: ScoreSpec) -> GroundTruth:
    """Read the ground truth `spec` names (DTU files or a synthetic scene).

    Raises:
        NeusL0Error: a missing folder or a missing / malformed file.
    """
    if spec.dtu_dir is None:
        gt = synthetic.load_synthetic_gt(spec.scene)
        return GroundTruth("synthetic", gt.points, {"scene": str(spec.scene)}, scene_gt=gt)
    if not Path(spec.dtu_dir).is_dir():
        raise NeusL0Error(f"{spec.dtu_dir}: DTU evaluation folder not found")
    paths = dtu.dtu_paths(spec.dtu_dir, spec.scan)
    obs = dtu.load_obs_mask(paths["obs_mask"])
    plane = dtu.load_plane(paths["plane"])
    info = {"dtu_dir": str(spec.dtu_dir), "scan": spec.scan,
            **{k: str(v) for k, v in paths.items()}}
    return GroundTruth("dtu", load_points(paths["stl"]), info, obs=obs, plane=plane)


def load_culled_mesh(mesh: Path, spec: ScoreSpec,
                     counts: dict) -> tuple[np.ndarray, np.ndarray, dict | None]:
    """Read the mesh and, with `spec.cull`, cull it with that scene's dilated masks.

    Args:
        mesh: mesh file; spec: the settings; counts: report counts, updated in place.

    Returns:
        vertices (V, 3), faces (F, 3) and the culling info (None without `cull`).
    """
    vertices, faces = load_mesh(mesh)
    counts.update(mesh_vertices=len(vertices), mesh_faces=len(faces))
    if spec.cull is None:
        return vertices, faces, None
    vertices, faces, cull_info = cull_mesh(vertices, faces, spec.cull, spec.cull_dilate)
    if len(faces) == 0:
        raise NeusL0Error(f"{mesh}: no faces left after culling with {spec.cull}/mask")
    counts.update(culled_vertices=len(vertices), culled_faces=len(faces))
    return vertices, faces, cull_info


def check_sampling(vertices: np.ndarray, faces: np.ndarray, density: float,
                   available: int | None) -> float:
    """Refuse a density whose sampling would not fit in memory, before sampling.

    Args:
        vertices (V, 3), faces (F, 3): the mesh to sample; density: `--density`;
        available: bytes of memory available (None: unknown, no check).

    Returns:
        The expected number of sampled points (`pointcloud.expected_samples`).

    Raises:
        NeusL0Error: one line with the point count, the memory it needs, the memory
            available and the smallest density that fits.
    """
    n = expected_samples(vertices, faces, density)
    if available is None or sampling_bytes(n) <= available:
        return n
    area = (n - len(vertices)) * density**2
    per_point = sampling_bytes(1.0) - sampling_bytes(0.0)
    room = (available - sampling_bytes(0.0)) / per_point - len(vertices)  # grid points
    if room <= 0 or area <= 0:
        fit = "not even the mesh's vertices fit; free some memory"
    else:
        smallest = math.sqrt(area / room)
        fit = f"the smallest density that fits is about {_round_up(smallest)}"
    raise NeusL0Error(f"--density {density}: sampling the mesh (area {area:.4g}) would make "
                      f"about {n:.3g} points, needing about {_gib(sampling_bytes(n))} of "
                      f"memory, {_gib(available)} is available; {fit}")


def _round_up(x: float) -> str:
    """`x` rounded up to two significant digits, as text."""
    scale = 10.0 ** (math.floor(math.log10(x)) - 1)
    return f"{math.ceil(x / scale - 1e-9) * scale:.2g}"


def _gib(n: float) -> str:
    """Bytes as GiB, or TiB / PiB where large."""
    for unit, scale in (("PiB", 2**50), ("TiB", 2**40)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n / 2**30:.3g} GiB"


def sample_prediction(vertices: np.ndarray, faces: np.ndarray, spec: ScoreSpec,
                      counts: dict, bars: bool = False) -> np.ndarray:
    """DTU-style sampling of the mesh at `spec.density`, then thinning to that radius.

    Args:
        vertices (V, 3), faces (F, 3): the mesh; spec: the settings; counts: report counts,
        updated in place; bars: show tqdm progress bars (stderr) for both steps.

    Returns:
        (N, 3) thinned points; `counts` gets pred_sampled and pred_thinned.
    """
    from tqdm import tqdm

    expected = int(expected_samples(vertices, faces, spec.density))
    with tqdm(total=expected, desc="eval: sample", unit="pt", unit_scale=True,
              disable=not bars, leave=False) as bar:
        sampled = sample_mesh(vertices, faces, spec.density, progress=bar.update)
    counts["pred_sampled"] = len(sampled)
    with tqdm(total=len(sampled), desc="eval: thin", unit="pt", unit_scale=True,
              disable=not bars, leave=False) as bar:
        pred = thin_points(sampled, spec.density, seed=spec.seed, progress=bar.update)
    counts["pred_thinned"] = len(pred)
    return pred


def write_maps(truth: GroundTruth, vertices: np.ndarray, faces: np.ndarray,
               res: ChamferResult, masks: dict, spec: ScoreSpec) -> dict:
    """Write accuracy.ply / completeness.ply into `spec.error_maps`.

    Args:
        truth: the ground truth; vertices (V, 3), faces (F, 3): the scored mesh;
        res, masks: what `GroundTruth.evaluate` returned; spec: the settings.

    Returns:
        The report's ``error_maps`` entry: vmax, cmap and the paths written.
    """
    from neus_l0.evaluation.error_maps import write_error_maps

    top = spec.vmax if spec.vmax is not None else spec.max_dist
    v_scored = truth.scored(vertices, spec)
    v_dist = truth.distance(vertices, top, spec.workers)
    gt_dist = np.full(len(truth.points), np.inf)
    gt_dist[masks["gt_used"]] = res.dist_gt
    written = write_error_maps(spec.error_maps, vertices, faces, v_dist, v_scored,
                               truth.points, gt_dist, masks["gt_used"], top, spec.cmap)
    return {"vmax": top, "cmap": spec.cmap, **{k: str(v) for k, v in written.items()}}


def score_features(scene: str | Path, pred: np.ndarray, res: ChamferResult, gt: np.ndarray,
                   max_dist: float) -> dict | None:
    """The report's ``features`` entry on a synthetic scene with features (None: none).

    Args:
        scene: the scene folder (its ``features.json``); pred: (N, 3) the points scored for
        accuracy, res: their result (``dist_pred`` (N,), ``dist_gt`` (M,)); gt: (M, 3) the
        ground-truth points scored for completeness; max_dist: the truncation.

    Returns:
        ``{"each": [per feature], "by_kind": {kind: pooled}}``
        (`neus_l0.evaluation.features`).
    """
    from neus_l0.evaluation.features import feature_errors, kind_errors, load_features

    if not (Path(scene) / "features.json").is_file():
        return None
    feats = load_features(scene)
    if not feats:
        return None
    args = (pred, res.dist_pred, gt, res.dist_gt, feats, max_dist)
    return {"each": feature_errors(*args), "by_kind": kind_errors(*args)}


def _num(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def finite_json(obj):
    """`obj` with every non-finite float (NaN, infinity) replaced by None, recursively, so
    that ``json.dumps(..., allow_nan=False)`` accepts it."""
    if isinstance(obj, dict):
        return {k: finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def score_mesh(mesh: str | Path, spec: ScoreSpec | None = None, *,
               log: Callable[[str], None] = _stderr, memory: int | None = None,
               progress: bool = False, **fields) -> dict:
    """Chamfer distance of a mesh (world units) to a synthetic scene's or DTU's ground truth.

    Args:
        mesh: predicted mesh file (PLY/OBJ), world units.
        spec: the settings (`ScoreSpec`); None: the defaults.
        log: progress messages.
        memory: bytes of memory available (None: no check); a density whose sampling
            would need more (`check_sampling`) is refused before sampling.
        progress: show tqdm bars (stderr) while sampling and thinning, when at least
            `PROGRESS_POINTS` points are expected.
        **fields: `ScoreSpec` fields that replace the spec's (``scene=..., density=...``),
            so that short calls stay short.

    Returns:
        The report (see docs/EVALUATION.md): accuracy, completeness, overall, counts,
        settings, ...

    Raises:
        NeusL0Error: bad settings or unreadable / malformed files.
    """
    from neus_l0 import __version__

    spec = dataclasses.replace(spec or ScoreSpec(), **fields)
    spec.check()
    mesh = Path(mesh)
    t0 = time.perf_counter()
    truth = load_ground_truth(spec)  # first: a bad GT path fails before the slow part
    counts: dict = {}
    vertices, faces, cull_info = load_culled_mesh(mesh, spec, counts)
    expected = check_sampling(vertices, faces, spec.density, memory)
    if expected >= PROGRESS_POINTS:
        log(f"eval: sampling about {expected:.3g} points at density {spec.density}")
    pred = sample_prediction(vertices, faces, spec, counts,
                             bars=progress and expected >= PROGRESS_POINTS)
    log(f"eval: {counts['pred_sampled']} points sampled, {len(pred)} after thinning "
        f"({time.perf_counter() - t0:.1f} s)")
    if len(pred) >= PROGRESS_POINTS:
        log(f"eval: scoring {len(pred)} points against {len(truth.points)} ground-truth "
            "points")
    res, masks = truth.evaluate(pred, vertices, faces, spec)
    counts.update(res.counts)
    maps = None if spec.error_maps is None else write_maps(truth, vertices, faces, res,
                                                           masks, spec)
    settings = {"protocol": truth.protocol, "density": spec.density,
                "thin_radius": spec.density, "max_dist": spec.max_dist, **spec.margins,
                "seed": spec.seed, "distance": res.distance, "cull": cull_info}
    feats = None
    if truth.protocol == "synthetic":
        settings["depth_tol"] = spec.depth_tol
        feats = score_features(spec.scene, pred[masks["pred_kept"]], res,
                               truth.points[masks["gt_used"]], spec.max_dist)
    return finite_json({
        "protocol": truth.protocol,
        "mesh": str(mesh),
        "gt": truth.info,
        "accuracy": _num(res.accuracy),
        "completeness": _num(res.completeness),
        "overall": _num(res.overall),
        "counts": {k: int(v) for k, v in counts.items()},
        "settings": settings,
        "error_maps": maps,
        **({"features": feats} if feats else {}),
        "seconds": round(time.perf_counter() - t0, 3),
        "version": __version__,
    })
