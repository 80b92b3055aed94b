"""Connected pieces of a mesh that a training view sees outside its mask, dropped
(`neus-l0 mesh --drop-outside-masks`).

Marching cubes runs a little beyond the visual hull (`VisualHull.for_grid` dilates it so
that the grid sees the SDF's own values), and the trained SDF can leave small closed
surfaces there: floaters a few pixels outside the silhouettes. `--clean` keeps every piece
over 5 % of the main piece's diagonal, so that a thin part the grid cut off stays, and such
a floater can be larger than that.

The images settle it. A piece is an outlier when, in some training view, more than `share`
of its vertices fall on pixels outside the view's mask dilated by `dilate_px` pixels (the
visual hull's own margin for mask and calibration error). The object's pieces, thin ones
included, lie inside every mask up to that margin; a floater next to the object is seen
against the background. A piece hidden inside the object projects inside the masks and
stays.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import trimesh

from neus_l0.data.cameras import depth_projection, pixel_indices
from neus_l0.errors import NeusL0Error
from neus_l0.evaluation.cull import dilate_mask

DILATE_PX = 2
"""Mask dilation of the test, in pixels (the visual hull's default margin)."""
SHARE = 0.5
"""A piece is dropped when more than this share of its vertices is outside a view's mask."""


def outside_share(vertices: np.ndarray, projections: np.ndarray,
                  masks: Sequence[np.ndarray]) -> np.ndarray:
    """(V,) for each view, the share of `vertices` (N, 3) world units that land inside its
    image on pixels where `masks` (V (H, W) bool, already dilated) is False (0 for a view
    the vertices all miss)."""
    P_n = depth_projection(np.asarray(projections, dtype=np.float64))
    out = np.zeros(len(masks))
    for v, mask in enumerate(masks):
        col, row, _ = pixel_indices(P_n[v], vertices, *mask.shape)
        ok = col >= 0
        if ok.any():
            out[v] = float((~mask[row[ok], col[ok]]).mean())
    return out


def mask_outliers(mesh: trimesh.Trimesh, projections: np.ndarray,
                  masks: Sequence[np.ndarray], dilate_px: int = DILATE_PX,
                  share: float = SHARE) -> tuple[trimesh.Trimesh, list[dict]]:
    """The mesh without its mask outliers, and what was dropped.

    Args:
        mesh: the mesh (world units).
        projections: (V, 3, 4) world -> pixel of the training views.
        masks: V (H, W) bool foreground masks.
        dilate_px: mask dilation in pixels.
        share: the largest share of a piece's vertices outside a view's dilated mask.

    Returns:
        the kept pieces, joined (the input itself when nothing is dropped), and one dict per
        dropped piece: ``faces``, ``diagonal`` (world units), ``views`` (how many views see
        it outside their mask).

    Raises:
        NeusL0Error: every piece is an outlier (the masks do not fit the cameras).
    """
    dilated = [dilate_mask(m, dilate_px) for m in masks]  # a disk, as `eval --cull` does
    pieces = mesh.split(only_watertight=False)
    if len(pieces) <= 1:
        return mesh, []
    kept, dropped = [], []
    for piece in pieces:
        outside = outside_share(np.asarray(piece.vertices), projections, dilated)
        if outside.max() > share:
            dropped.append({"faces": len(piece.faces),
                            "diagonal": float(np.linalg.norm(np.ptp(piece.vertices, axis=0))),
                            "views": int((outside > share).sum())})
        else:
            kept.append(piece)
    if not dropped:
        return mesh, []
    if not kept:
        raise NeusL0Error("--drop-outside-masks: every piece of the mesh lies outside some "
                          "training view's mask (do the masks match the cameras?)")
    return trimesh.util.concatenate(kept), dropped
