"""Mesh extraction: marching cubes of analytic SDFs in world units, clean-up, export."""

import numpy as np
import pytest
import torch
import trimesh

from neus_l0.data.cameras import to_world
from neus_l0.errors import NeusL0Error
from neus_l0.mesh.extract import (
    clean_mesh,
    export_mesh,
    extract_mesh,
    marching_cubes,
    sdf_grid,
)

SCALE = np.array([[2.5, 0.0, 0.0, 10.0],
                  [0.0, 2.5, 0.0, -20.0],
                  [0.0, 0.0, 2.5, 5.0],
                  [0.0, 0.0, 0.0, 1.0]])


def sphere_sdf(centre, radius):
    c = torch.tensor(centre, dtype=torch.float32)
    return lambda p: (p - c).norm(dim=-1) - radius


def test_sdf_grid_matches_dense_evaluation_and_is_chunked():
    calls = []

    def f(p):
        calls.append(len(p))
        return p[:, 0] + 2 * p[:, 1] - p[:, 2]

    vol = sdf_grid(f, 17, bound=1.0, chunk=100)
    ax = np.linspace(-1, 1, 17)
    X, Y, Z = np.meshgrid(ax, ax, ax, indexing="ij")
    assert np.allclose(vol, X + 2 * Y - Z, atol=1e-6)
    assert max(calls) <= 100 and sum(calls) == 17**3


def test_marching_cubes_sphere_in_world_units():
    centre, radius = (0.1, -0.2, 0.05), 0.5
    vol = sdf_grid(sphere_sdf(centre, radius), 96)
    v, f = marching_cubes(vol)
    mesh = trimesh.Trimesh(to_world(v, SCALE), f)
    c_world = to_world(np.array([centre]), SCALE)[0]
    r = np.linalg.norm(mesh.vertices - c_world, axis=1)
    assert abs(r.mean() - radius * 2.5) < 0.01 * 2.5
    assert r.std() < 0.01
    assert np.allclose(mesh.vertices.mean(0), c_world, atol=0.02)
    assert mesh.is_watertight and mesh.volume > 0  # outward normals
    assert abs(mesh.volume - 4 / 3 * np.pi * (radius * 2.5) ** 3) / mesh.volume < 0.02


def test_marching_cubes_without_surface_is_a_clear_error():
    with pytest.raises(NeusL0Error, match="no surface"):
        marching_cubes(np.ones((8, 8, 8), np.float32))


def test_clean_drops_specks_and_keeps_cut_off_thin_parts():
    """A speck goes; a long thin rod the grid cut off from the body stays (its diagonal is
    most of the body's, though it has few faces); the fraction sets the line."""
    body = trimesh.creation.icosphere(subdivisions=4, radius=1.0)  # 5120 faces
    speck = trimesh.creation.icosphere(subdivisions=1, radius=0.03)  # 3 % of the body
    speck.apply_translation([3.0, 0, 0])
    rod = trimesh.creation.cylinder(radius=0.02, height=1.5, sections=6)
    rod.apply_translation([0, 0, 2.0])
    assert len(rod.faces) < 0.01 * len(body.faces)  # a face-count rule would drop it
    everything = trimesh.util.concatenate([body, speck, rod])
    kept = clean_mesh(everything)
    assert len(kept.faces) == len(body.faces) + len(rod.faces)
    assert kept.bounds[1][2] == pytest.approx(2.75)  # the rod's top
    assert len(clean_mesh(everything, min_diagonal=0.0).faces) == len(everything.faces)
    assert len(clean_mesh(everything, min_diagonal=1.0).faces) == len(body.faces)
    assert clean_mesh(body) is body
    # the main piece is the one with the most faces (here the speck), kept whatever the
    # fraction, and the line is drawn at its diagonal: the longer rod stays, a smaller speck goes
    shrunk = trimesh.creation.icosphere(subdivisions=0, radius=0.005)  # 20 faces
    shrunk.apply_translation([0.0, 0.0, -2.0])
    pieces = trimesh.util.concatenate([speck, rod, shrunk])
    assert len(clean_mesh(pieces, min_diagonal=1.0).faces) == len(speck.faces) + len(rod.faces)



class _Model(torch.nn.Module):
    """Minimal stand-in of NeuSModel for `extract_mesh`: an analytic SDF and constant colour."""

    def __init__(self):
        super().__init__()
        f = sphere_sdf((0.0, 0.0, 0.0), 0.4)

        class Sdf(torch.nn.Module):
            def forward(self, p):
                return torch.cat([f(p)[:, None], torch.zeros(len(p), 2)], -1)

            def sdf(self, p):
                return self.forward(p)[:, :1]

        class Color(torch.nn.Module):
            def forward(self, x, n, v, feat):
                assert torch.allclose(v, -torch.nn.functional.normalize(n, dim=-1))
                return torch.full_like(x, 0.25)

        self.sdf, self.color = Sdf(), Color()


def test_extract_mesh_with_colours_and_export(tmp_path):
    mesh = extract_mesh(_Model(), SCALE, resolution=48, clean=True, colors=True)
    r = np.linalg.norm(mesh.vertices - SCALE[:3, 3], axis=1)
    assert abs(r.mean() - 1.0) < 0.02  # 0.4 * 2.5
    assert mesh.visual.vertex_colors.shape == (len(mesh.vertices), 4)
    assert (mesh.visual.vertex_colors[:, 0] == 64).all()
    for name in ("m.ply", "m.obj"):
        p = export_mesh(mesh, tmp_path / name)
        back = trimesh.load(p, force="mesh")
        assert len(back.faces) == len(mesh.faces)
    with pytest.raises(NeusL0Error, match="unsupported"):
        export_mesh(mesh, tmp_path / "m.fbx")
    assert sorted(x.name for x in tmp_path.iterdir()) == ["m.obj", "m.ply"]  # no temp files
