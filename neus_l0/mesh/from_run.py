"""The mesh of a run folder: its trained networks, inside its visual hull, in world units.

The one path from a checkpoint to a mesh that `neus-l0 mesh`, the demo, the bench and the
tools share, so none of them can forget the hull or the run's ``scale_mat``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch
import trimesh

from neus_l0.bounds.hull import load_run_hull
from neus_l0.config.schema import Config
from neus_l0.fields.model import NeuSModel
from neus_l0.mesh.extract import extract_mesh, progress_bars
from neus_l0.run.checkpoints import load_trained_model


@dataclasses.dataclass
class RunMesh:
    """A run's mesh and what it was made from.

    Attributes:
        mesh: world units; ``mesh.metadata["extraction"]`` has the extraction's numbers.
        model: the networks (eval mode), for colours and textures.
        cfg: the run's config.
        info: the checkpoint's light fields (``iteration``, ``scale_mat``, ``path``, ...).
    """

    mesh: trimesh.Trimesh
    model: NeuSModel
    cfg: Config
    info: dict

    @property
    def scale_mat(self) -> np.ndarray:
        """(4, 4) float64 normalised -> world of the run's scene."""
        return np.asarray(self.info["scale_mat"], dtype=np.float64)


def mesh_from_run(run_dir: str | Path, resolution: int, device: str | torch.device = "cpu",
                  checkpoint: str | Path | None = None, clean: bool = True,
                  method: str = "auto", progress: bool = False) -> RunMesh:
    """Marching cubes of a run's SDF at `resolution`^3, restricted to the run's visual hull
    (``RUN/hull.pt``, when it has one).

    Args:
        run_dir: the run folder.
        resolution: grid cells per axis over the unit sphere's box.
        device: where the networks run.
        checkpoint: a specific checkpoint file; default the newest that loads.
        clean: drop floating specks (see `extract_mesh`).
        method: ``auto``, ``dense`` or ``sparse`` (see `extract_mesh`).
        progress: a tqdm bar on stderr while the SDF is evaluated (`progress_bars`).

    Raises:
        NeusL0Error: no usable checkpoint, or no surface in the field.
    """
    model, cfg, info = load_trained_model(run_dir, device, checkpoint)
    with progress_bars(progress):
        mesh = extract_mesh(model, np.asarray(info["scale_mat"]), resolution=resolution,
                            clean=clean, device=device, method=method,
                            hull=load_run_hull(run_dir, device))
    return RunMesh(mesh, model, cfg, info)
