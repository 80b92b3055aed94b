"""Sparse mesh extraction: agreement with the dense reference, the block rule, memory."""

import subprocess
import sys
import tracemalloc

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from neus_l0.data.cameras import to_world
from neus_l0.errors import NeusL0Error
from neus_l0.mesh.extract import (
    SPARSE_ABOVE,
    extract_mesh,
    keep_blocks,
    marching_cubes,
    sdf_grid,
    sparse_marching_cubes,
)
from neus_l0.synthetic.shapes import Box, CappedCone, Difference, Sphere, Union, builtin_shape


def canonical(V, F, step):
    """Snap vertices within float32 rounding of a grid node onto it, merge vertices with
    identical coordinates, drop degenerate faces.

    Marching cubes puts a vertex at a node where the SDF is exactly 0 there, once per edge,
    and float32 rounding can leave those copies an ulp apart (in either path).
    """
    g = (V + 1.0) / step  # grid units
    r = np.round(g)
    g = np.where(np.abs(g - r) < 1e-4, r, g)
    u, inv = np.unique(g, axis=0, return_inverse=True)
    F = inv.reshape(-1)[F]
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    return u * step - 1.0, F


def face_set(F):
    """Faces as a set of index triples rotated to start at their smallest index (winding kept)."""
    k = np.argmin(F, axis=1)
    rolled = np.stack([F[np.arange(len(F)), (k + i) % 3] for i in range(3)], axis=1)
    return set(map(tuple, rolled.tolist()))


def assert_same_mesh(sdf, R, **kw):
    """Sparse == dense: same vertices (to float32 rounding of grid units) and same faces."""
    step = 2.0 / (R - 1)
    Vd, Fd = canonical(*marching_cubes(sdf_grid(sdf, R)), step)
    Vs0, Fs0, stats = sparse_marching_cubes(sdf, R, **kw)
    assert len(np.unique(Vs0, axis=0)) == len(Vs0)  # the sparse mesh has no duplicate vertices
    Vs, Fs = canonical(Vs0, Fs0, step)
    dist, nn = cKDTree(Vd).query(Vs)
    assert len(Vs) == len(Vd)
    assert dist.max() < 1e-4 * step
    assert len(np.unique(nn)) == len(Vd)  # a bijection
    assert face_set(nn[Fs]) == face_set(Fd)
    return Vs0, Fs0, stats


SPHERE = Sphere((0.1, -0.05, 0.02), 0.55)
BOX = Box((0.03, -0.02, 0.01), (0.5, 0.3, 0.4))
# a slab with a pit (radius 2.5 voxels at R = 64) and rods thinner than a voxel
ROD_AND_PIT = Union((
    Difference(Box((0.0, 0.0, -0.2), (0.7, 0.6, 0.2), rounding=0.02),
               (CappedCone((0.2, 0.1, -0.3), (0.2, 0.1, 0.5), 0.08, 0.08),)),
    CappedCone((-0.3, -0.2, -0.1), (-0.3, -0.2, 0.7), 0.012, 0.012),
    CappedCone((-0.1, 0.3, -0.1), (0.05, 0.35, 0.6), 0.03, 0.03),
))


@pytest.mark.parametrize("R", [9, 33, 50, 97])
def test_sparse_equals_dense_sphere(R):
    assert_same_mesh(SPHERE, R)


@pytest.mark.parametrize("R,block", [(41, 8), (57, 5), (70, 16)])
def test_sparse_equals_dense_box_and_csg(R, block):
    assert_same_mesh(BOX, R, block=block)
    assert_same_mesh(ROD_AND_PIT, R, block=block)


def test_sparse_equals_dense_builtin_pits_and_thin():
    shape = builtin_shape("pits-and-thin")  # world units, about 200 across

    def sdf(p):
        return shape.sdf(p * 120.0) / 120.0

    _, _, stats = assert_same_mesh(sdf, 61)
    assert stats.blocks_surface < stats.blocks_kept < stats.blocks


def test_surface_on_block_boundaries():
    # R = 65, block 8: coarse samples every 1/4; the box faces +-0.5 lie exactly on block
    # faces and on grid nodes (sdf == 0 there), the sphere crosses block faces everywhere.
    box = Box((0.0, 0.0, 0.0), (0.5, 0.5, 0.25))
    axis = torch.linspace(-1, 1, 65)
    assert axis[16] == -0.5 and axis[48] == 0.5  # the faces are on grid nodes
    for sdf in (box, Sphere((0.0, 0.0, 0.0), 0.5)):
        V, F, _ = assert_same_mesh(sdf, 65, block=8)
        mesh = trimesh.Trimesh(V, F, process=False)
        assert mesh.is_watertight and mesh.volume > 0


def test_sparse_mesh_is_watertight_and_closed():
    V, F, stats = sparse_marching_cubes(ROD_AND_PIT, 110)
    mesh = trimesh.Trimesh(V, F, process=False)
    assert mesh.is_watertight and mesh.volume > 0
    # every connected piece (slab with its pit, rods) is closed
    assert all(p.is_watertight for p in mesh.split(only_watertight=False))
    assert stats.sdf_evals < 0.75 * stats.dense_evals  # a large surface at a low R


class _Model(torch.nn.Module):
    """Stand-in of NeuSModel for `extract_mesh`: `model.sdf.sdf(p)` -> (P, 1)."""

    def __init__(self, sdf):
        super().__init__()

        class Sdf(torch.nn.Module):
            def sdf(self, p):
                return sdf(p)[:, None]

        self.sdf = Sdf()


def test_extract_mesh_sparse_in_world_units():
    c = np.cos(0.4)
    s = np.sin(0.4)
    scale_mat = np.array([[3.0 * c, -3.0 * s, 0.0, 10.0],
                          [3.0 * s, 3.0 * c, 0.0, -20.0],
                          [0.0, 0.0, 3.0, 5.0],
                          [0.0, 0.0, 0.0, 1.0]])
    centre, radius = (0.1, -0.2, 0.05), 0.5
    mesh = extract_mesh(_Model(Sphere(centre, radius)), scale_mat, resolution=SPARSE_ABOVE + 32)
    st = mesh.metadata["extraction"]
    assert st["method"] == "sparse" and st["sdf_evals"] < st["dense_evals"] / 2
    c_world = to_world(np.array([centre]), scale_mat)[0]
    r = np.linalg.norm(mesh.vertices - c_world, axis=1)
    assert abs(r.mean() - 3.0 * radius) < 0.002 * 3.0
    assert r.std() < 0.003
    assert np.allclose(mesh.vertices.mean(0), c_world, atol=0.01)
    assert mesh.is_watertight and mesh.volume > 0
    small = extract_mesh(_Model(Sphere(centre, radius)), scale_mat, resolution=40)
    assert small.metadata["extraction"]["method"] == "dense"
    with pytest.raises(NeusL0Error, match="method"):
        extract_mesh(_Model(SPHERE), scale_mat, resolution=40, method="fast")


def test_sparse_without_surface_is_a_clear_error():
    with pytest.raises(NeusL0Error, match="no surface"):
        sparse_marching_cubes(lambda p: p.norm(dim=-1) + 0.1, 40)


# --- the block rule -------------------------------------------------------------------------

def test_keep_blocks_rule():
    d = 1.0  # block diagonal
    coarse = np.full((3, 3, 3), 5.0, np.float32)  # 2x2x2 blocks, all far outside
    assert not keep_blocks(coarse, d, lipschitz=1.0, dilate=0).any()
    # all 8 corners of block (0, 0, 0) within L*d: kept; raising one of them drops it
    coarse[:2, :2, :2] = 0.9
    assert keep_blocks(coarse, d, lipschitz=1.0, dilate=0)[0, 0, 0]
    coarse[0, 0, 0] = 1.1
    assert not keep_blocks(coarse, d, lipschitz=1.0, dilate=0).any()
    assert keep_blocks(coarse, d, lipschitz=1.5, dilate=0)[0, 0, 0]
    # a sign change among the corners keeps the block whatever the values, and its
    # neighbours with dilate=1
    coarse = np.full((3, 3, 3), 5.0, np.float32)
    coarse[0, 0, 0] = -5.0
    k = keep_blocks(coarse, d, lipschitz=1.0, dilate=0)
    assert k[0, 0, 0] and k.sum() == 1
    assert keep_blocks(coarse, d, lipschitz=1.0, dilate=1).all()
    # the sign test follows marching cubes: value <= level counts as inside
    coarse = np.full((3, 3, 3), 5.0, np.float32)
    coarse[2, 2, 2] = 0.0
    assert keep_blocks(coarse, d, lipschitz=0.0, dilate=0)[1, 1, 1]
    # non-finite corners keep their blocks
    coarse = np.full((3, 3, 3), 5.0, np.float32)
    coarse[1, 1, 1] = np.nan
    assert keep_blocks(coarse, d, lipschitz=1.0, dilate=0).all()


def test_small_components_between_coarse_samples_need_the_lipschitz_clause():
    # spheres 1.3 voxels in radius inside blocks, far from every coarse sample: no coarse
    # sign change, so only the Lipschitz clause finds them
    R, B = 65, 8
    step = 2.0 / (R - 1)
    centres = [(-1 + (8 * i + 3.6) * step, -1 + (8 * j + 4.3) * step, -1 + (8 * k + 4.1) * step)
               for i, j, k in [(1, 2, 3), (5, 5, 1), (3, 6, 6)]]
    blobs = Union(tuple(Sphere(c, 1.3 * step) for c in centres))
    V, F, stats = assert_same_mesh(blobs, R, block=B, lipschitz=1.0, dilate=0)
    assert len(trimesh.Trimesh(V, F, process=False).split(only_watertight=False)) == 3
    assert stats.blocks_kept < stats.blocks / 10
    # too small a Lipschitz bound loses them: the clause is what makes the rule safe
    with pytest.raises(NeusL0Error, match="no surface"):
        sparse_marching_cubes(blobs, R, block=B, lipschitz=0.2, dilate=1)


def test_steeper_than_assumed_sdf_is_still_extracted_through_sign_changes():
    # 3 x a sphere's SDF (3-Lipschitz): the sign-change clause and its dilation catch it
    def steep(p):
        return 3.0 * SPHERE(p)

    assert_same_mesh(steep, 81, lipschitz=1.5, dilate=1)


# --- memory -----------------------------------------------------------------------------------

def test_sparse_memory_is_far_below_the_dense_volume():
    R = 257
    tracemalloc.start()
    try:
        V, F, stats = sparse_marching_cubes(SPHERE, R)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    mesh_bytes = V.nbytes + F.nbytes
    assert peak < 3 * mesh_bytes + 16 * 2**20
    assert peak < 0.5 * 4 * R**3  # the float32 dense volume alone
    assert stats.sdf_evals < 0.25 * stats.dense_evals


@pytest.mark.slow
def test_sparse_1024_sphere_fits_in_memory():
    code = (
        "import resource, torch, trimesh\n"
        "from neus_l0.synthetic.shapes import Sphere\n"
        "from neus_l0.mesh.extract import sparse_marching_cubes\n"
        "V, F, st = sparse_marching_cubes(Sphere((0.0, 0.0, 0.0), 0.5), 1024)\n"
        "m = trimesh.Trimesh(V, F, process=False)\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, st.sdf_evals, "
        "st.dense_evals, len(V), m.is_watertight)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    maxrss_kib, evals, dense, n_verts, watertight = out
    assert int(maxrss_kib) * 1024 < 1.5 * 2**30  # the dense float32 volume is 4 GiB
    assert int(evals) < 0.05 * int(dense)
    assert int(n_verts) > 10**6 and watertight == "True"


# --- the command ----------------------------------------------------------------------------

def test_mesh_command_reports_sparse_extraction(tmp_path, monkeypatch, capsys):
    import neus_l0.mesh.from_run
    from neus_l0.cli import main

    def fake_load(run, device, checkpoint=None):
        return (_Model(Sphere((0.0, 0.0, 0.0), 0.5)), None,
                {"scale_mat": np.eye(4), "path": tmp_path / "ckpt.pt", "iteration": 7})

    monkeypatch.setattr(neus_l0.mesh.from_run, "load_trained_model", fake_load)
    assert main(["mesh", str(tmp_path), "--resolution", "160"]) == 0
    out = capsys.readouterr().out
    assert "sparse extraction at 160^3" in out and "SDF evaluations" in out
    assert (tmp_path / "mesh.ply").is_file()
