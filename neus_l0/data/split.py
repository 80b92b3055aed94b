"""Held-out views: which views a benchmark run trains on, and a `Scene` restricted to them.

View ``i`` is held out when ``i % every == 0`` (views 0, K, 2K, ...: the usual "every K-th
view" split of NeRF benchmarks); ``every = 0`` holds out nothing.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch

from neus_l0.data.scene import Scene
from neus_l0.errors import NeusL0Error


def split_views(n_views: int, every: int) -> tuple[list[int], list[int]]:
    """Split view indices ``0 .. n_views-1`` into (training, held-out).

    Args:
        n_views: number of views of the scene.
        every: hold out view ``i`` when ``i % every == 0``; 0 holds out none.

    Returns:
        (train, heldout): sorted index lists that partition ``range(n_views)``.

    Raises:
        NeusL0Error: a negative `every`, or a split that leaves no training view.
    """
    if every < 0:
        raise NeusL0Error(f"--holdout {every}: must be 0 (none) or a positive K")
    if every == 0:
        return list(range(n_views)), []
    heldout = [i for i in range(n_views) if i % every == 0]
    train = [i for i in range(n_views) if i % every != 0]
    if not train:
        raise NeusL0Error(f"--holdout {every}: holds out all {n_views} views (use K >= 2)")
    return train, heldout


def holdout_split(scene: Scene, every: int) -> tuple[Scene, Scene | None, dict]:
    """The views a run trains on and those it holds out (`split_views`).

    Args:
        scene: the full scene; every: hold out every `every`-th view (0: none).

    Returns:
        (training scene, held-out scene or None, record): the record, as ``run.json`` keeps
        it, is ``{"holdout": every, "n_views": N, "train": [...], "heldout": [...]}`` with
        indices into the full scene.
    """
    train, held = split_views(scene.n_views, every)
    record = {"holdout": int(every), "n_views": scene.n_views, "train": train, "heldout": held}
    if not held:
        return scene, None, record
    return subset_scene(scene, train), subset_scene(scene, held), record


def subset_scene(scene: Scene, views: Sequence[int]) -> Scene:
    """The scene with only `views` (in the given order); shares nothing mutable with `scene`.

    Args:
        scene: the full scene.
        views: view indices into `scene` (each in ``0 .. n_views-1``).

    Returns:
        a `Scene` whose images, masks, intrinsics, c2w and image names are those of `views`
        (same root, scale_mat and device).

    Raises:
        NeusL0Error: an empty selection or an index out of range.
    """
    views = [int(v) for v in views]
    if not views:
        raise NeusL0Error(f"{scene.root}: empty view subset")
    bad = [v for v in views if not 0 <= v < scene.n_views]
    if bad:
        raise NeusL0Error(f"{scene.root}: view indices {bad} out of range 0..{scene.n_views - 1}")
    idx = torch.tensor(views, dtype=torch.long, device=scene.device)
    return dataclasses.replace(
        scene,
        images=scene.images.index_select(0, idx),
        masks=scene.masks.index_select(0, idx),
        intrinsics=scene.intrinsics.index_select(0, idx),
        c2w=scene.c2w.index_select(0, idx),
        scale_mat=scene.scale_mat.copy(),
        image_names=[scene.image_names[v] for v in views],
    )
