"""pymeshlab clean-up: face bound, shape kept, specks removed, holes closed; the mesh flags."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from neus_l0.errors import NeusL0Error
from neus_l0.mesh.cleanup import CleanupOptions, clean_up


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(subdivisions=5, radius=1.0)  # 20480 faces


@pytest.mark.parametrize("faces", [4, 100, 1000, 5000])
def test_simplify_respects_the_face_bound(sphere, faces):
    out = clean_up(sphere, CleanupOptions(simplify=faces))
    assert len(out.faces) <= faces
    assert len(out.faces) >= 0.9 * faces  # it does not throw away more than asked


def test_simplify_keeps_a_sphere_a_sphere(sphere):
    out = clean_up(sphere, CleanupOptions(simplify=1000))
    r = np.linalg.norm(out.vertices, axis=1)
    assert np.abs(r - 1.0).max() < 0.01
    assert out.is_watertight
    # the surface between vertices: sample it, distance to the true sphere
    pts, _ = trimesh.sample.sample_surface(out, 5000, seed=0)
    assert np.abs(np.linalg.norm(pts, axis=1) - 1.0).max() < 0.02
    assert abs(out.volume / (4 / 3 * np.pi) - 1) < 0.02


def test_simplify_above_the_face_count_is_a_no_op(sphere):
    out = clean_up(sphere, CleanupOptions(simplify=10**6))
    assert len(out.faces) == len(sphere.faces)


def test_taubin_smoothing_removes_noise_without_shrinking(sphere):
    rng = np.random.default_rng(0)
    noisy = sphere.copy()
    noisy.vertices = noisy.vertices + rng.normal(0.0, 0.01, noisy.vertices.shape)
    out = clean_up(noisy, CleanupOptions(smooth=10))
    r_in = np.linalg.norm(noisy.vertices, axis=1)
    r_out = np.linalg.norm(out.vertices, axis=1)
    assert r_out.std() < 0.5 * r_in.std()
    assert abs(r_out.mean() - 1.0) < 0.005  # Taubin does not shrink (Laplacian would)
    assert len(out.faces) == len(sphere.faces)


def test_small_components_are_removed(sphere):
    speck = trimesh.creation.icosphere(subdivisions=2, radius=0.02)
    speck.apply_translation([2.0, 0.0, 0.0])
    rod = trimesh.creation.box(extents=[0.5, 0.05, 0.05])
    rod.apply_translation([0.0, 2.0, 0.0])
    both = trimesh.util.concatenate([sphere, speck, rod])
    out = clean_up(both, CleanupOptions(min_component=0.05))
    parts = out.split(only_watertight=False)
    # the speck (diagonal 0.07 < 5 % of ~3.6) goes; the rod (0.5) stays
    assert sorted(len(p.faces) for p in parts) == [12, len(sphere.faces)]
    far = speck.copy()
    far.apply_translation([-4.0, 0.0, 0.0])
    with pytest.raises(NeusL0Error, match="no face is left"):  # each is tiny next to both
        clean_up(trimesh.util.concatenate([speck, far]), CleanupOptions(min_component=0.5))


def test_small_holes_are_closed(sphere):
    holed = sphere.copy()
    # a hole of 6 boundary edges: drop the faces around one vertex
    ring = np.flatnonzero((holed.faces == 0).any(axis=1))
    keep = np.ones(len(holed.faces), bool)
    keep[ring] = False
    holed.update_faces(keep)
    holed.remove_unreferenced_vertices()
    assert not holed.is_watertight
    assert not clean_up(holed, CleanupOptions(close_holes=4)).is_watertight  # too big a hole
    out = clean_up(holed, CleanupOptions(close_holes=30))
    assert out.is_watertight
    assert len(out.faces) == len(holed.faces) + len(ring) - 2  # a 6-gon takes 4 triangles


def test_options_are_checked():
    for bad in (CleanupOptions(simplify=2), CleanupOptions(smooth=-1),
                CleanupOptions(min_component=1.0), CleanupOptions(close_holes=-3)):
        with pytest.raises(NeusL0Error):
            clean_up(trimesh.creation.box(), bad)
    box = trimesh.creation.box()
    assert clean_up(box, CleanupOptions()) is box


def test_mesh_command_flags(tmp_path, capsys, monkeypatch):
    import neus_l0.mesh.from_run
    from neus_l0.cli import main
    from neus_l0.synthetic.shapes import Sphere

    class _Sdf(__import__("torch").nn.Module):
        def sdf(self, p):
            return Sphere((0.0, 0.0, 0.0), 0.5)(p)

    class _Model:
        sdf = _Sdf()

    scale = np.diag([2.0, 2.0, 2.0, 1.0])
    scale[:3, 3] = [1.0, -2.0, 0.5]

    def fake_load(run, device, checkpoint=None):
        return _Model(), None, {"scale_mat": scale, "path": tmp_path / "ckpt.pt",
                                "iteration": 7}

    monkeypatch.setattr(neus_l0.mesh.from_run, "load_trained_model", fake_load)
    out = tmp_path / "m.ply"
    assert main(["mesh", str(tmp_path), "--resolution", "64", "--out", str(out),
                 "--simplify", "500", "--smooth", "3", "--min-component", "0.05",
                 "--close-holes", "50"]) == 0
    mesh = trimesh.load(out, force="mesh")
    assert len(mesh.faces) <= 500 and mesh.is_watertight
    r = np.linalg.norm(mesh.vertices - scale[:3, 3], axis=1)  # world radius 1.0
    assert np.abs(r - 1.0).max() < 0.03
    assert "clean-up:" in capsys.readouterr().out
    assert main(["mesh", str(tmp_path), "--simplify", "1"]) == 2
    assert "--simplify 1" in capsys.readouterr().err
