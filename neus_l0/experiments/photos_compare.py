"""Compare a scene written by `neus-l0 colmap` with the true cameras of a synthetic scene.

Used by the tests and by docs/PHOTOS.md's measurements: views are paired through
``sources.txt`` (file names), the recovered camera centres are aligned to the true ones by
a similarity (`photos_align.umeyama`), and the errors are reported relative to the
object's size.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from neus_l0.experiments.photos_align import pose_errors


def world_c2w(scene) -> np.ndarray:
    """(N, 4, 4) float64 camera-to-world poses of a loaded `Scene` in world units."""
    c2w = scene.c2w.double().numpy().copy()
    sm = scene.scale_mat
    c2w[:, :3, 3] = c2w[:, :3, 3] @ sm[:3, :3].T + sm[:3, 3]
    return c2w


def compare_to_truth(est_dir: str | Path, true_dir: str | Path) -> dict:
    """Pose errors of the scene in `est_dir` against the true scene in `true_dir`.

    Args:
        est_dir: a scene written by `neus-l0 colmap` (with ``sources.txt``).
        true_dir: the synthetic scene whose ``image/`` photos were given to it.

    Returns:
        `photos_align.pose_errors`'s dict plus ``object_size`` (the true object's
        diameter: ``2 x scale_mat radius / 1.1``, the synthetic sphere's margin),
        ``sphere_center`` (3,) and ``sphere_radius`` of the chosen sphere mapped into the
        true world frame, ``gt_inside`` (fraction of ``gt_points.ply`` inside that sphere,
        when the file exists) and ``views`` (true view indices compared).
    """
    from neus_l0.formats.neus import load_scene

    est_dir, true_dir = Path(est_dir), Path(true_dir)
    est, true = load_scene(est_dir), load_scene(true_dir)
    sources = (est_dir / "sources.txt").read_text(encoding="utf-8").split("\n")
    index = {n: i for i, n in enumerate(true.image_names)}
    views = np.array([index[Path(s).name] for s in sources if s])
    c2w_true = world_c2w(true)[views]
    object_size = 2.0 * float(true.scale_mat[0, 0]) / 1.1
    errs = pose_errors(world_c2w(est), c2w_true, object_size)
    s, R, t = errs["scale"], errs["R"], errs["t"]
    center = s * R @ est.scale_mat[:3, 3] + t
    radius = s * float(est.scale_mat[0, 0])
    errs.update(object_size=object_size, sphere_center=center, sphere_radius=radius,
                views=views)
    gt = true_dir / "gt_points.ply"
    if gt.is_file():
        import trimesh

        pts = np.asarray(trimesh.load(gt, process=False).vertices, dtype=np.float64)
        errs["gt_inside"] = float((np.linalg.norm(pts - center, axis=-1) <= radius).mean())
    return errs
