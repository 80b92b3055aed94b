"""Smaller, cleaner meshes through pymeshlab: specks, holes, smoothing, simplification.

`clean_up` runs, in this order, the steps whose option is set:

1. **small components** removed: those whose bounding-box diagonal is below
   `min_component` times the whole mesh's (MeshLab's "remove isolated pieces (wrt
   diameter)"); marching cubes of a trained SDF leaves floating specks;
2. **holes closed** that have at most `close_holes` boundary edges (MeshLab's "close
   holes"): the cut a clipping bound leaves, or tiny gaps;
3. **Taubin smoothing** (lambda 0.5, mu -0.53, `smooth` iterations): removes the
   staircase of marching cubes without the shrinking of Laplacian smoothing;
4. **quadric edge collapse** to at most `simplify` faces (Garland-Heckbert, optimal
   vertex placement, normals and topology preserved, planar quadrics so flat parts do
   not sliver); last, so that the face bound holds for the final mesh.

Every step keeps the frame and units of the input. Vertex colours are not carried (the
`mesh` command computes them, or the texture, on the cleaned mesh).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh

from neus_l0.errors import NeusL0Error

TAUBIN_LAMBDA, TAUBIN_MU = 0.5, -0.53
"""Taubin's pass-band parameters (MeshLab's defaults; mu < -lambda keeps the volume)."""


@dataclasses.dataclass
class CleanupOptions:
    """What `clean_up` does; the defaults do nothing.

    Attributes:
        simplify: the most faces of the result (quadric edge collapse); None = keep all.
        smooth: Taubin smoothing iterations (0 = none).
        min_component: drop components whose bounding-box diagonal is below this fraction
            of the mesh's (0 = keep all).
        close_holes: close holes of at most this many boundary edges (0 = none).
    """

    simplify: int | None = None
    smooth: int = 0
    min_component: float = 0.0
    close_holes: int = 0

    def any(self) -> bool:
        """Whether any step is on."""
        return bool(self.simplify is not None or self.smooth > 0 or self.min_component > 0
                    or self.close_holes > 0)

    def check(self) -> None:
        """Raise `NeusL0Error` naming the flag of an out-of-range value."""
        if self.simplify is not None and self.simplify < 4:
            raise NeusL0Error(f"--simplify {self.simplify}: give at least 4 faces")
        if self.smooth < 0:
            raise NeusL0Error(f"--smooth {self.smooth}: iterations must be >= 0")
        if not 0.0 <= self.min_component < 1.0:
            raise NeusL0Error(f"--min-component {self.min_component}: a fraction in [0, 1)")
        if self.close_holes < 0:
            raise NeusL0Error(f"--close-holes {self.close_holes}: edges must be >= 0")


def _to_meshset(mesh: trimesh.Trimesh):
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(mesh.vertices, np.float64),
                               face_matrix=np.asarray(mesh.faces, np.int32)))
    return ms


def _from_meshset(ms) -> trimesh.Trimesh:
    m = ms.current_mesh()
    return trimesh.Trimesh(m.vertex_matrix().copy(), m.face_matrix().astype(np.int64),
                           process=False)


def clean_up(mesh: trimesh.Trimesh, options: CleanupOptions) -> trimesh.Trimesh:
    """Apply the steps of `options` (see the module docstring) with pymeshlab.

    Args:
        mesh: the input mesh (not modified).
        options: which steps, with which parameters.

    Returns:
        a new mesh (the input itself when no step is on); with ``options.simplify`` set it
        has at most that many faces.

    Raises:
        NeusL0Error: an option out of range, or nothing left after removing components.
    """
    options.check()
    if not options.any():
        return mesh
    import pymeshlab

    ms = _to_meshset(mesh)
    if options.min_component > 0:
        ms.meshing_remove_connected_component_by_diameter(
            mincomponentdiag=pymeshlab.PercentageValue(100.0 * options.min_component),
            removeunref=True)
        if ms.current_mesh().face_number() == 0:
            raise NeusL0Error(f"--min-component {options.min_component}: no face is left")
    if options.close_holes > 0:
        ms.meshing_close_holes(maxholesize=int(options.close_holes), newfaceselected=False,
                               selfintersection=True)
    if options.smooth > 0:
        ms.apply_coord_taubin_smoothing(lambda_=TAUBIN_LAMBDA, mu=TAUBIN_MU,
                                        stepsmoothnum=int(options.smooth))
    if options.simplify is not None:
        _simplify(ms, int(options.simplify))
    return _from_meshset(ms)


def _simplify(ms, faces: int, tries: int = 4) -> None:
    """Quadric edge collapse until at most `faces` faces remain.

    The collapse can stop a little above its target (collapses refused to keep the
    topology or the normals); the target is then lowered by the excess and the collapse
    repeated, and a last pass without those guards enforces the bound.
    """
    target = faces
    for attempt in range(tries + 1):
        n = ms.current_mesh().face_number()
        if n <= faces:
            return
        guard = attempt < tries
        ms.meshing_decimation_quadric_edge_collapse(
            targetfacenum=max(target, 1), qualitythr=0.3, preserveboundary=guard,
            preservenormal=guard, preservetopology=guard, optimalplacement=True,
            planarquadric=True, autoclean=True)
        target -= max(ms.current_mesh().face_number() - faces, 0)
    if ms.current_mesh().face_number() > faces:
        raise NeusL0Error(f"--simplify {faces}: the collapse stopped at "
                          f"{ms.current_mesh().face_number()} faces")
