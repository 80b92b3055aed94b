"""Which plane-sweep rays to trust: a neighbourhood's consensus (`neus-l0 mesh --photo-carve`).

A single ray's sweep is as often wrong as the mesh away from a pit's floor (issue #35,
session 22: ray by ray, 36 % of the cup's carving rays ended more than a unit inside the
true surface). Where the mesh sits raised over a floor, every ray through that patch of
mesh finds the floor the same distance behind it; where a sweep is fooled, its neighbours
disagree. So each ray's displacement along the mesh normal,
``h = (best depth - mesh depth) |ray . n|``, is pooled with the rays whose mesh point lies
in the same cell and whose normal shares its dominant signed axis (`cell_keys`,
`consensus`); a ray counts only when its cell agrees and it agrees with its cell
(`agreeing`). A planar patch swept across a convex part (a handle, a rod) ends inside it, so
rays whose mesh is convex around them are left out (`local_convexity`). Measured outside
training (session 23, `tools/carve_consensus.py`): 7-8 % of the carving rays ended more than
a unit inside the truth on the cup, pits-deep and the well.

The two passes (`consensus_rays`): pass 1 sweeps every `STRIDE`-th row and column of every
`EVERY`-th view's concave pixels (`neus_l0.mesh.plane_sweep.concave_pixels`) and pools their
displacements in cells of `CELL_PX` footprints; pass 2 sweeps every concave pixel of every
view in the cells where pass 1's rays agree on a displacement behind the mesh
(`MIN_RAYS_FIRST` rays, `MIN_SHARE` of them within `AGREE_PX` of a median of `MARGIN_PX` or
more). A pass-2 ray carves when its cell agrees (`MIN_RAYS`, the same share and median), it
agrees with its cell, its cost is below `MAX_COST`, and `local_convexity` (radius
`CONVEX_PX` footprints) is at least `CONVEX` around it.

Pure functions of arrays.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from scipy.spatial import cKDTree

from neus_l0.errors import NeusL0Error
from neus_l0.mesh.plane_sweep import INVALID, sweep_depths

MARGIN_PX = 2.0
"""A cell whose median displacement behind the mesh is this many footprints or more carves."""
MAX_COST = 0.15
"""A ray carves only when its best depth's cost (1 - NCC) / 2 is below this."""
STRIDE = 3
"""Pass 1 sweeps every STRIDE-th row and column ..."""
EVERY = 3
"""... of every EVERY-th view."""
CELL_PX = 14.0
"""Side of the cells whose rays are pooled, in footprints (10 world units on the cup, where
session 23 measured the rule)."""
AGREE_PX = 2.0
"""Rays within this many footprints of their cell's median displacement agree with it."""
MIN_RAYS_FIRST = 3
"""Pass 1 flags a cell that holds this many rays (from 2 views or more) ..."""
MIN_RAYS = 8
"""... and pass 2 carves from a cell that holds this many."""
MIN_SHARE = 0.3
"""The share of a cell's rays that must agree with its median."""
CONVEX_PX = 6.0
"""The radius of `local_convexity`, in footprints (4 world units on the cup)."""
CONVEX = -0.05
"""Rays whose mesh point's local convexity is below this do not carve (on the cup, planar
patches ended inside the thin handle on 87 % of its agreeing rays)."""


def cell_keys(points: np.ndarray, normals: np.ndarray, cell: float) -> np.ndarray:
    """(N, 4) int keys: the cell of side `cell` that holds each point (N, 3), and the
    dominant axis of its normal (N, 3) with its sign, as 0-5 (``2 * axis + (n_axis > 0)``)."""
    axis = np.argmax(np.abs(normals), 1)
    sign = normals[np.arange(len(normals)), axis] > 0
    return np.column_stack([np.floor(points / cell).astype(np.int64), axis * 2 + sign])


def consensus(keys: np.ndarray, h: np.ndarray, views: np.ndarray, tol: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per ray, its cell's median displacement, the share of the cell's rays within `tol`
    of that median, and the cell's ray count (0 when they come from fewer than 2 views).

    Args:
        keys: (N, k) int cell keys (`cell_keys`); h: (N,) displacements; views: (N,) the
            rays' views; tol: the agreement's half width, in the units of `h`.

    Returns:
        (N,) float median, (N,) float share in [0, 1], (N,) int count.
    """
    n = len(h)
    med, share, count = np.zeros(n), np.zeros(n), np.zeros(n, np.int64)
    if n == 0:
        return med, share, count
    _, cell = np.unique(keys, axis=0, return_inverse=True)
    order = np.argsort(cell.reshape(-1), kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(cell.reshape(-1)[order]) != 0])
    for idx in np.split(order, starts[1:]):
        m = np.median(h[idx])
        med[idx] = m
        share[idx] = np.mean(np.abs(h[idx] - m) <= tol)
        count[idx] = len(idx) if len(np.unique(views[idx])) >= 2 else 0
    return med, share, count


def agreeing(h: np.ndarray, med: np.ndarray, share: np.ndarray, count: np.ndarray,
             min_rays: int, min_share: float, margin: float, tol: float) -> np.ndarray:
    """(N,) bool the rays whose cell agrees on a displacement behind the mesh and that agree
    with it: the cell holds `min_rays` or more (from 2 views), `min_share` of them lie within
    `tol` of its median, the median is `margin` or more, and the ray lies within `tol` of it.

    Args:
        h: (N,) the rays' displacements; med, share, count: (N,) `consensus` of their cells.
    """
    return ((count >= min_rays) & (share >= min_share) & (med >= margin)
            & (np.abs(h - med) <= tol))


def local_convexity(samples: np.ndarray, points: np.ndarray, normals: np.ndarray,
                    radius: float) -> np.ndarray:
    """(N,) how the surface (its dense samples (n, 3)) curves around each point (N, 3) with
    its normal (N, 3), turned towards the viewer: the mean height of the samples within
    `radius` over the tangent plane, divided by `radius`. 0 on a plane, -radius / (4 rho) on
    a sphere of radius rho seen from outside (convex: a rod, a handle), positive in a
    concavity; NaN where no sample is that near."""
    out = np.full(len(points), np.nan)
    if not len(points) or not len(samples):
        return out
    tree = cKDTree(samples)
    for i, near in enumerate(tree.query_ball_point(points, radius)):
        if near:
            out[i] = np.mean((samples[near] - points[i]) @ normals[i]) / radius
    return out


def _encode(keys: np.ndarray) -> np.ndarray:
    """(N,) int64 codes of `cell_keys` rows: 20 bits per cell index, 3 for the axis.

    Raises:
        NeusL0Error: a cell index beyond +-2^19 (a mesh over half a million cells across).
    """
    k = keys.astype(np.int64)
    if len(k) and np.abs(k[:, :3]).max() >= 2**19:
        raise NeusL0Error(f"--photo-carve: the mesh spans over 2^19 cells of {CELL_PX:g} pixel "
                          "footprints; its views' footprints are too small for its size")
    return (((k[:, 0] + 2**19) << 43) | ((k[:, 1] + 2**19) << 23) | ((k[:, 2] + 2**19) << 3)
            | k[:, 3])


def _sweep_rows(found: Sequence[tuple | None], pick, gray: torch.Tensor,
                projections: np.ndarray, offsets: np.ndarray) -> dict[str, np.ndarray]:
    """Sweep the pixels ``pick(v, found[v])`` ((N_v,) bool, or None for none) of each view;
    per swept ray: ``view``, ``pix`` (2), ``point`` (the mesh's, 3), ``normal`` (3), ``z0``,
    ``z_best``, ``cost`` and the displacement ``h`` along the normal (rays whose best views
    cannot score a patch are left out)."""
    out: dict[str, list] = {k: [] for k in ("view", "pix", "point", "normal", "z0", "z_best",
                                            "cost", "h")}
    for v, f in enumerate(found):
        sel = None if f is None else pick(v, f)
        if sel is None or not sel.any():
            continue
        centre = f[1]
        pix, rays, z0, n = (a[sel] for a in (f[0], *f[2:]))
        z_best, cost, _ = sweep_depths(gray, projections, v, pix, n, z0, offsets)
        ok = cost < INVALID
        for k, a in (("view", np.full(len(z0), v)), ("pix", pix), ("normal", n), ("z0", z0),
                     ("point", centre + rays * z0[:, None]), ("z_best", z_best), ("cost", cost),
                     ("h", (z_best - z0) * np.abs((rays * n).sum(1)))):
            out[k].append(a[ok])
    if not out["view"]:
        return {"view": np.zeros(0, np.int64), "pix": np.zeros((0, 2), np.int64),
                "point": np.zeros((0, 3)), "normal": np.zeros((0, 3)),
                **{k: np.zeros(0) for k in ("z0", "z_best", "cost", "h")}}
    return {k: np.concatenate(a) for k, a in out.items()}


def consensus_rays(found: Sequence[tuple | None], gray: torch.Tensor, projections: np.ndarray,
                   offsets: np.ndarray, foot: float, samples: np.ndarray
                   ) -> tuple[dict[str, np.ndarray], np.ndarray, dict]:
    """The two passes of the module docstring.

    Args:
        found: per view, `concave_pixels` at stride 1 (None: none).
        gray: (V, H, W) grey images; projections: (V, 3, 4); offsets: (T,) the sweep's
            depths around the mesh's; foot: a pixel's footprint, world units;
            samples: (n, 3) the mesh's dense surface samples.

    Returns:
        pass 2's rays (`_sweep_rows`), (N,) bool those that carve, and a report:
        ``swept`` (rays, both passes), ``cells`` (flagged by pass 1), ``agreeing``
        (pass-2 rays that agree with their cell), ``carving``.
    """
    cell, tol, margin = CELL_PX * foot, AGREE_PX * foot, MARGIN_PX * foot
    first = _sweep_rows(found, lambda v, f: None if v % EVERY else
                        (f[0][:, 0] % STRIDE == 0) & (f[0][:, 1] % STRIDE == 0),
                        gray, projections, offsets)
    keys = cell_keys(first["point"], first["normal"], cell)
    med, share, count = consensus(keys, first["h"], first["view"], tol)
    flagged = np.unique(_encode(keys[(count >= MIN_RAYS_FIRST) & (med >= margin)
                                     & (share >= MIN_SHARE)]))

    def in_flagged(v, f):
        centre, rays, z0, n = f[1:]
        return np.isin(_encode(cell_keys(centre + rays * z0[:, None], n, cell)), flagged)

    dense = _sweep_rows(found, in_flagged if len(flagged) else lambda v, f: None, gray,
                        projections, offsets)
    med, share, count = consensus(cell_keys(dense["point"], dense["normal"], cell), dense["h"],
                                  dense["view"], tol)
    agree = agreeing(dense["h"], med, share, count, MIN_RAYS, MIN_SHARE, margin, tol) \
        & (dense["cost"] < MAX_COST)
    convexity = np.full(len(agree), np.nan)
    convexity[agree] = local_convexity(samples, dense["point"][agree], dense["normal"][agree],
                                       CONVEX_PX * foot)
    with np.errstate(invalid="ignore"):
        carve = agree & ~(convexity < CONVEX)
    report = {"swept": len(first["h"]) + len(dense["h"]), "cells": len(flagged),
              "agreeing": int(agree.sum()), "carving": int(carve.sum())}
    return dense, carve, report
