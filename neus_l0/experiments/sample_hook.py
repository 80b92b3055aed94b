"""The training hook that logs how far the fine samples land from the true surface
(``sample_dist``), for the benchmark runs and the fork study.

The measurement itself is `neus_l0.evaluation.sample_distance`: fixed rays that hit the
object, their fine samples in world units, the exact distance to the ground-truth mesh.
"""

from __future__ import annotations

import math

import numpy as np
from torch import Tensor

from neus_l0.data.scene import Scene
from neus_l0.evaluation.sample_distance import SurfaceDistance, fine_points_world, object_rays


class SampleDistanceHook:
    """Training hook logging ``sample_dist``: the mean world distance of the fine samples.

    Called as ``hook(iteration, model, scene, cfg) -> {"sample_dist": float}`` (see
    `neus_l0.train.loop.train`) at every log step; it measures only at geometrically spaced
    iterations (the first call, then once the iteration has grown by the factor `growth`),
    since each measurement costs seconds of exact point-to-mesh distances and a run that
    measured at every log step spent longer measuring than training. Its time never counts
    against the training budget, but it does lengthen a sweep. Called with ``force=True``
    (after training) it always measures.

    Args:
        surface: the true surface.
        n_rays: rays rendered per call (chosen once, on the first call, by `object_rays`).
        seed: seed of the ray choice.
        growth: iteration factor between two measurements (1: every call).
    """

    def __init__(self, surface: SurfaceDistance, n_rays: int = 256, seed: int = 0,
                 growth: float = 1.5):
        if growth < 1.0:
            raise ValueError(f"growth must be >= 1, got {growth}")
        self.surface = surface
        self.n_rays = n_rays
        self.seed = seed
        self.growth = growth
        self._next = 0
        self._rays: tuple[Tensor, Tensor] | None = None

    def due(self, iteration: int) -> bool:
        """Whether a training-time call at `iteration` measures (and, if so, when next)."""
        if iteration < self._next:
            return False
        self._next = max(iteration + 1, math.ceil(iteration * self.growth))
        return True

    def rays(self, scene: Scene) -> tuple[Tensor, Tensor]:
        """The fixed rays (chosen on the first call, then reused)."""
        if self._rays is None or self._rays[0].device != scene.device:
            self._rays = object_rays(scene, self.n_rays, self.seed)
        return self._rays

    def __call__(self, iteration: int, model, scene: Scene, cfg, force: bool = False) -> dict:
        from neus_l0.render.volume import render_rays
        from neus_l0.sampling.upsample import build_sampler
        from neus_l0.train.schedule import cos_anneal_ratio

        if not force and not self.due(iteration):
            return {}
        o, d = self.rays(scene)
        if len(o) == 0 or cfg.render.n_importance == 0:
            return {"sample_dist": None}
        out = render_rays(model, o, d, cfg.render, build_sampler(cfg.sampler),
                          cos_anneal_ratio=cos_anneal_ratio(iteration, cfg.train.anneal_end))
        dist = self.surface(fine_points_world(o, d, out.t_fine, scene.scale_mat))
        value = float(np.mean(dist))
        return {"sample_dist": value if math.isfinite(value) else None}
