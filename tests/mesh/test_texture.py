"""Textured meshes: the atlas rasteriser against brute force, baked colours reproduce the colour
function, the OBJ + MTL + PNG load back, and `mesh --texture`."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from neus_l0.errors import NeusL0Error
from neus_l0.mesh.texture import bake_texture, dilate_texture, rasterize_atlas, write_textured_obj


def colour_of(points):
    """A smooth colour field: f(x) in [0, 1]^3."""
    return 0.5 + 0.5 * np.stack([np.sin(2 * points[:, 0]), np.cos(3 * points[:, 1]),
                                 points[:, 2] / 1.5], -1)


def _brute_force(uvs, face_uvs, H, W):
    """Per texel, per triangle, float64 barycentrics: {texel: set of covering triangles}."""
    cover = {}
    for r in range(H):
        for c in range(W):
            q = np.array([(c + 0.5) / W, 1 - (r + 0.5) / H])
            for f, (a, b, d) in enumerate(uvs[face_uvs].astype(np.float64)):
                m = np.array([b - a, d - a]).T
                if abs(np.linalg.det(m)) < 1e-15:
                    continue
                l1, l2 = np.linalg.solve(m, q - a)
                if min(l1, l2, 1 - l1 - l2) >= -1e-9:
                    cover.setdefault(r * W + c, set()).add(f)
    return cover


def test_rasterizer_matches_brute_force():
    rng = np.random.default_rng(0)
    uvs = rng.uniform(0.02, 0.98, (30, 2)).astype(np.float32)
    face_uvs = rng.integers(0, 30, (12, 3))
    H, W = 23, 31
    texels, faces, bary = rasterize_atlas(uvs, face_uvs, H, W, chunk=50)  # many batches
    ref = _brute_force(uvs, face_uvs, H, W)
    got = dict(zip(texels.tolist(), faces.tolist(), strict=True))
    assert len(texels) == len(set(texels.tolist()))
    # every texel the reference covers is covered by one of its triangles, and no other
    assert set(got) == set(ref)
    for t, f in got.items():
        assert f in ref[t]
    # the barycentrics give back the texel centre
    q = np.einsum("kc,kcd->kd", bary, uvs[face_uvs[faces]].astype(np.float64))
    rows, cols = texels // W, texels % W
    centre = np.stack([(cols + 0.5) / W, 1 - (rows + 0.5) / H], -1)
    assert np.abs(q - centre).max() < 1e-6
    assert np.allclose(bary.sum(1), 1.0) and bary.min() >= 0


def test_dilation_fills_the_gutter_from_the_nearest_texel():
    img = np.zeros((5, 7, 3), np.uint8)
    covered = np.zeros((5, 7), bool)
    covered[2, 1], covered[2, 5] = True, True
    img[2, 1], img[2, 5] = (10, 20, 30), (200, 100, 50)
    out = dilate_texture(img, covered, 1)
    assert tuple(out[2, 0]) == (10, 20, 30) and tuple(out[1, 5]) == (200, 100, 50)
    assert tuple(out[0, 3]) == (0, 0, 0)  # 2 texels from both: left alone
    assert tuple(out[2, 1]) == (10, 20, 30)


@pytest.fixture(scope="module")
def baked():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    return mesh, bake_texture(mesh.vertices, mesh.faces, colour_of, size=256)


def test_baked_texels_reproduce_the_colour_function(baked):
    mesh, tex = baked
    assert np.array_equal(tex.vertices, mesh.vertices)
    assert tex.faces.shape == tex.face_uvs.shape == mesh.faces.shape
    # the same triangles, corner by corner (xatlas keeps the face order)
    assert np.array_equal(tex.faces, mesh.faces)
    H, W = tex.image.shape[:2]
    assert 0.7 * 256 < max(H, W) < 1.5 * 256
    rng = np.random.default_rng(1)
    fi = rng.integers(0, len(tex.faces), 3000)
    b = rng.dirichlet([2.0, 2.0, 2.0], 3000)  # away from the chart borders
    uv = np.einsum("kc,kcd->kd", b, tex.uvs[tex.face_uvs[fi]].astype(np.float64))
    pts = np.einsum("kc,kcd->kd", b, tex.vertices[tex.faces[fi]])
    col = np.clip((uv[:, 0] * W).astype(int), 0, W - 1)
    row = np.clip(H - 1 - (uv[:, 1] * H).astype(int), 0, H - 1)
    err = np.abs(tex.image[row, col] / 255.0 - colour_of(pts))
    # within half a texel of the sample (the field's slope is <= 3 per unit, a texel is
    # about 2 / 256 units on this sphere) plus 8-bit rounding
    assert err.max() < 0.03 and err.mean() < 0.005


def test_textured_obj_loads_back(baked, tmp_path):
    mesh, tex = baked
    paths = write_textured_obj(tex, tmp_path / "out" / "m.obj")
    assert [p.name for p in paths] == ["m.obj", "m.mtl", "m.png"]
    assert "map_Kd m.png" in paths[1].read_text()
    back = trimesh.load(paths[0], force="mesh", process=False)
    assert isinstance(back.visual, trimesh.visual.TextureVisuals)
    assert back.visual.uv is not None and len(back.visual.uv) == len(back.vertices)
    image = np.asarray(back.visual.material.image.convert("RGB"))
    assert np.array_equal(image, tex.image)
    assert len(back.faces) == len(mesh.faces)
    # colours looked up through the loaded UVs match the colour function at the vertices
    uv = back.visual.uv
    H, W = image.shape[:2]
    col = np.clip((uv[:, 0] * W).astype(int), 0, W - 1)
    row = np.clip(H - 1 - (uv[:, 1] * H).astype(int), 0, H - 1)
    assert np.abs(image[row, col] / 255.0 - colour_of(back.vertices)).mean() < 0.02
    merged = trimesh.load(paths[0], force="mesh")
    merged.merge_vertices(merge_tex=True)
    assert merged.is_watertight  # the seams do not open the surface
    with pytest.raises(NeusL0Error, match=".obj"):
        write_textured_obj(tex, tmp_path / "m.ply")


def test_mesh_command_texture(tmp_path, capsys, monkeypatch):
    import torch

    import neus_l0.mesh.from_run
    from neus_l0.cli import main
    from neus_l0.synthetic.shapes import Sphere

    class _Sdf(torch.nn.Module):
        def sdf(self, p):
            return Sphere((0.0, 0.0, 0.0), 0.5)(p)

        def forward(self, p):  # (P, 3) -> (P, 1 + 3): the SDF and a feature
            return torch.cat([self.sdf(p).reshape(-1, 1), p], -1)

    class _Model:
        sdf = _Sdf()

        @staticmethod
        def color(x, grad, view, feat):  # colour = f(position), seen along -normal
            assert torch.allclose(view, -torch.nn.functional.normalize(x, dim=-1), atol=1e-5)
            return torch.as_tensor(colour_of(x.detach().double().numpy()), dtype=x.dtype)

    def fake_load(run, device, checkpoint=None):
        return _Model(), None, {"scale_mat": np.eye(4), "path": tmp_path / "ckpt.pt",
                                "iteration": 7}

    monkeypatch.setattr(neus_l0.mesh.from_run, "load_trained_model", fake_load)
    out = tmp_path / "t.obj"
    assert main(["mesh", str(tmp_path), "--resolution", "40", "--texture", "--texture-size",
                 "128", "--simplify", "800", "--out", str(out)]) == 0
    assert "texture:" in capsys.readouterr().out
    back = trimesh.load(out, force="mesh")
    assert len(back.faces) <= 800 and back.visual.uv is not None
    image = np.asarray(back.visual.material.image.convert("RGB"))
    uv = back.visual.uv
    H, W = image.shape[:2]
    col = np.clip((uv[:, 0] * W).astype(int), 0, W - 1)
    row = np.clip(H - 1 - (uv[:, 1] * H).astype(int), 0, H - 1)
    assert np.abs(image[row, col] / 255.0 - colour_of(back.vertices)).mean() < 0.03
    assert main(["mesh", str(tmp_path), "--texture", "--out", str(tmp_path / "t.ply")]) == 2
    assert "must end in .obj" in capsys.readouterr().err

