"""Error on a synthetic scene's features (pits, thin parts): the Chamfer sides inside each
feature's ball.

A synthetic scene's ``features.json`` (world units) lists ``kind`` (pit | thin), ``name``,
``center`` (3,), ``radius`` (the ball that encloses the feature: a pit and its rim, a rod
along its length) and ``axis`` (3,) or null. The figures crop these balls; the scores here
are the numbers behind those crops: of the points the Chamfer protocol scored, the
predicted points inside a ball give its accuracy and the ground-truth points inside it
its completeness, each the mean of the distances below the protocol's ``max_dist``.
`near_axis` and `feature_label` say which points lie on which feature (a rod by its axis),
for the tools that count rays and score rods in their tubes.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from neus_l0.errors import NeusL0Error

#: The feature kinds `kind_errors` pools.
KINDS = ("pit", "thin")


def load_features(scene_dir: str | Path) -> list[dict]:
    """The features of a synthetic scene (``features.json``), in world units.

    Raises:
        NeusL0Error: the file is missing or malformed.
    """
    path = Path(scene_dir) / "features.json"
    if not path.is_file():
        raise NeusL0Error(f"{path}: missing (a synthetic scene's features)")
    try:
        feats = json.loads(path.read_text())["features"]
        for f in feats:
            f["center"] = np.asarray(f["center"], dtype=np.float64).reshape(3)
            f["radius"] = float(f["radius"])
            f["axis"] = None if f.get("axis") is None else np.asarray(f["axis"], np.float64)
            if f["axis"] is not None and not (f["axis"].shape == (3,)
                                              and np.isfinite(f["axis"]).all()
                                              and np.linalg.norm(f["axis"]) > 0):
                raise ValueError(f"feature {f.get('name')!r}: axis not 3 finite numbers "
                                 "of non-zero length")
            if not (np.isfinite(f["center"]).all() and f["radius"] > 0):
                raise ValueError(f"feature {f.get('name')!r}: centre or radius not finite "
                                 "and positive")
    except (KeyError, ValueError, TypeError) as exc:
        raise NeusL0Error(f"{path}: malformed ({exc})") from exc
    return feats


def near_axis(points: np.ndarray, feature: dict, tube: float) -> np.ndarray:
    """(N,) which of (N, 3) points lie within `tube` world units of a thin feature's axis
    segment, ``center +- radius * axis``: the rod itself and a margin, without the ball's
    surroundings (a cavity's floor, a seat above a leg).

    Raises:
        ValueError: the feature has no axis, or one of zero or non-finite length.
    """
    if feature.get("axis") is None:
        raise ValueError(f"feature {feature.get('name')!r} has no axis")
    axis = np.asarray(feature["axis"], dtype=np.float64)
    length = float(np.linalg.norm(axis))
    if not (np.isfinite(length) and length > 0):
        raise ValueError(f"feature {feature.get('name')!r}: axis of length {length}")
    axis = axis / length
    d = np.asarray(points, dtype=np.float64) - feature["center"]
    along = np.clip(d @ axis, -feature["radius"], feature["radius"])
    return np.linalg.norm(d - along[:, None] * axis, axis=1) <= tube


def feature_label(pts: np.ndarray, features: list[dict], tol: float = 6.0
                  ) -> tuple[np.ndarray, tuple[str, ...]]:
    """Label (..., 3) world points by a scene's features (``features.json``, any scene).

    A thin feature with an axis is the segment ``center +- radius * axis``: a point within
    `tol` world units of it is on the feature (a rod's radius plus a pixel or two). Any other
    feature is its ball (the crop the scores use). Where features overlap, the smaller one
    (by radius) wins.

    Returns:
        (...,) int labels (NaN points: 0, points on no feature: 1, feature i: i + 2) and the
        names: ``("nothing", "open surface", *feature names)``.
    """
    out = np.where(np.isnan(pts[..., 2]), 0, 1)
    flat = pts.reshape(-1, 3)
    for i in sorted(range(len(features)), key=lambda i: -features[i]["radius"]):
        f = features[i]
        if f["kind"] == "thin" and f.get("axis") is not None:
            on = near_axis(flat, f, tol).reshape(out.shape)
        else:
            on = np.linalg.norm(pts - f["center"], axis=-1) <= f["radius"]
        out = np.where(on, i + 2, out)
    return out, ("nothing", "open surface", *(f["name"] for f in features))


def _mean_below(d: np.ndarray, max_dist: float) -> float:
    d = d[d < max_dist]
    return float(d.mean()) if len(d) else math.nan


def feature_errors(pred: np.ndarray, dist_pred: np.ndarray, gt: np.ndarray,
                   dist_gt: np.ndarray, features: list[dict], max_dist: float) -> list[dict]:
    """Accuracy and completeness inside each feature's ball.

    Args:
        pred: (N, 3) the predicted points scored for accuracy; dist_pred: (N,) their
            distances to the ground truth (`inf` beyond max_dist).
        gt: (M, 3) the ground-truth points scored for completeness; dist_gt: (M,) their
            distances to the prediction.
        features: `load_features` entries.
        max_dist: distances at or above it are left out of the means (as the protocol's).

    Returns:
        One dict per feature: name, kind, accuracy, completeness, overall (their mean; NaN
        where a side has no point below max_dist), n_pred, n_gt (points inside the ball).
    """
    out = []
    for f in features:
        in_pred = np.linalg.norm(pred - f["center"], axis=1) <= f["radius"]
        in_gt = np.linalg.norm(gt - f["center"], axis=1) <= f["radius"]
        acc = _mean_below(dist_pred[in_pred], max_dist)
        comp = _mean_below(dist_gt[in_gt], max_dist)
        out.append({"name": f["name"], "kind": f["kind"], "accuracy": acc,
                    "completeness": comp, "overall": (acc + comp) / 2,
                    "n_pred": int(in_pred.sum()), "n_gt": int(in_gt.sum())})
    return out


def kind_errors(pred: np.ndarray, dist_pred: np.ndarray, gt: np.ndarray, dist_gt: np.ndarray,
                features: list[dict], max_dist: float) -> dict[str, dict]:
    """The same scores pooled over every ball of a kind (a point counts once).

    Args and units: as `feature_errors`.

    Returns:
        {kind: {accuracy, completeness, overall, n_pred, n_gt}} for the kinds present.
    """
    out = {}
    for kind in KINDS:
        balls = [f for f in features if f["kind"] == kind]
        if not balls:
            continue
        in_pred = np.zeros(len(pred), dtype=bool)
        in_gt = np.zeros(len(gt), dtype=bool)
        for f in balls:
            in_pred |= np.linalg.norm(pred - f["center"], axis=1) <= f["radius"]
            in_gt |= np.linalg.norm(gt - f["center"], axis=1) <= f["radius"]
        acc = _mean_below(dist_pred[in_pred], max_dist)
        comp = _mean_below(dist_gt[in_gt], max_dist)
        out[kind] = {"accuracy": acc, "completeness": comp, "overall": (acc + comp) / 2,
                     "n_pred": int(in_pred.sum()), "n_gt": int(in_gt.sum())}
    return out


def kind_overall(report: dict | None, kind: str) -> float | None:
    """The Chamfer distance over a score report's features of `kind` ("pit", "thin"; its
    ``features.by_kind``, `neus_l0.evaluation.score.score_mesh`), None without any."""
    entry = (((report or {}).get("features") or {}).get("by_kind") or {}).get(kind)
    return None if entry is None else entry.get("overall")
