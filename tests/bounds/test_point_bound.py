"""The SfM-point box: contains the true surface, never cuts a ray's hit, exact slab test."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neus_l0.bounds.points import MIN_POINTS, PointBound
from neus_l0.bounds.sphere import sphere_chord
from neus_l0.config.load import load_config
from neus_l0.data.points import POINTS_FILE, read_points, write_points


def _rotation(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q


def _ellipsoid_surface(n: int, seed: int, radii=(0.7, 0.4, 0.2)) -> np.ndarray:
    """(n, 3) points on a rotated, shifted ellipsoid inside the unit sphere."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    return (u * np.asarray(radii)) @ _rotation(seed).T + np.array([0.1, -0.05, 0.08])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_box_of_sparse_noisy_points_holds_the_whole_surface(seed):
    rng = np.random.default_rng(seed)
    surface = _ellipsoid_surface(20000, seed)
    sfm = surface[rng.choice(len(surface), 300, replace=False)]
    sfm = sfm + rng.normal(scale=0.01, size=sfm.shape)  # triangulation noise
    outliers = rng.uniform(-0.6, 0.6, size=(15, 3))  # stray matches inside the sphere
    far_away = rng.normal(size=(10, 3)) * 5.0 + 8.0  # background: outside the sphere
    pts = np.concatenate([sfm, outliers, far_away])
    box = PointBound.from_points(pts, np.full(len(pts), 3), margin=0.2)
    assert box.n_points == 315  # the far background is ignored
    assert bool(box.contains(torch.as_tensor(surface, dtype=torch.float32)).all())
    # stray points inside the sphere only widen it; without them, oriented along the
    # points, the box keeps much less than the sphere of a flat object
    clean = PointBound.from_points(sfm, margin=0.2)
    assert bool(clean.contains(torch.as_tensor(surface, dtype=torch.float32)).all())
    assert clean.fraction_of_sphere() < 0.75 and box.fraction_of_sphere() >= \
        clean.fraction_of_sphere() - 0.01


def test_rays_through_surface_points_keep_them_inside_their_bounds():
    surface = _ellipsoid_surface(5000, 3)
    box = PointBound.from_points(surface[::10], margin=0.05)
    rng = np.random.default_rng(0)
    eye = rng.normal(size=(5000, 3))
    eye = 3.0 * eye / np.linalg.norm(eye, axis=-1, keepdims=True)  # cameras outside
    target = surface[rng.integers(0, len(surface), 5000)]
    inside = box.contains(torch.as_tensor(target, dtype=torch.float32)).numpy()
    d = target - eye
    t_true = np.linalg.norm(d, axis=-1)
    o = torch.as_tensor(eye, dtype=torch.float32)
    d = torch.as_tensor(d / t_true[:, None], dtype=torch.float32)
    near, far, hit_sphere = sphere_chord(o, d)
    lo, hi, hits = box.ray_bounds(o, d, near, far)
    t = torch.as_tensor(t_true, dtype=torch.float32)
    sel = torch.as_tensor(inside)
    assert bool(hits[sel].all()) and bool(hit_sphere[sel].all())
    assert bool((lo[sel, 0] <= t[sel] + 1e-5).all() and (t[sel] <= hi[sel, 0] + 1e-5).all())
    assert bool(((near <= lo) & (lo <= hi) & (hi <= far)).all())


def test_ray_bounds_match_brute_force_sampling():
    box = PointBound.from_points(_ellipsoid_surface(400, 4), margin=0.1)
    g = torch.Generator().manual_seed(0)
    o = torch.randn(500, 3, generator=g) * 2.0
    d = torch.nn.functional.normalize(torch.randn(500, 3, generator=g), dim=-1)
    d[:20, 1:] = 0.0  # axis-parallel directions (zero slab components)
    d[:20, 0] = 1.0
    near, far, _ = sphere_chord(o, d)
    lo, hi, hits = box.ray_bounds(o, d, near, far)
    s = torch.linspace(0, 1, 4001)
    t = near + (far - near) * s  # (B, 4001)
    inside = box.contains(o[:, None] + d[:, None] * t[..., None])  # (B, 4001)
    step = float((far - near).max()) / 4000
    assert torch.equal(inside.any(-1), hits) or (inside.any(-1) ^ hits).sum() <= 2
    first = torch.where(inside, t, torch.inf).amin(-1)
    last = torch.where(inside, t, -torch.inf).amax(-1)
    ok = inside.any(-1) & hits
    assert bool((lo[ok, 0] <= first[ok] + 1e-5).all() and (last[ok] <= hi[ok, 0] + 1e-5).all())
    assert bool((first[ok] - lo[ok, 0] <= step + 1e-4).all())  # tight, not only safe


def test_points_file_round_trip_and_too_few_points(tmp_path):
    sm = np.diag([2.0, 2.0, 2.0, 1.0])
    sm[:3, 3] = [1.0, -2.0, 0.5]
    unit = _ellipsoid_surface(50, 5)
    write_points(tmp_path / POINTS_FILE, unit * 2.0 + sm[:3, 3], np.arange(50))
    pts, track = read_points(tmp_path / POINTS_FILE, sm)
    np.testing.assert_allclose(pts, unit, atol=1e-12)
    assert track.tolist() == list(range(50))
    assert PointBound.from_points(unit[:MIN_POINTS - 1]) is None
    # min_views drops short tracks
    assert PointBound.from_points(unit, track, min_views=40) is None


def test_run_uses_the_box_only_when_asked_and_without_masks(tmp_path):
    from types import SimpleNamespace

    from neus_l0.bounds.static import static_bounds

    sm = np.diag([2.0, 2.0, 2.0, 1.0])
    sm[:3, 3] = [1.0, -2.0, 0.5]
    scene = SimpleNamespace(root=tmp_path / "s", has_masks=False, scale_mat=sm,
                            device=torch.device("cpu"))
    scene.root.mkdir(parents=True)
    unit = _ellipsoid_surface(200, 6, radii=(0.5, 0.5, 0.5))
    write_points(scene.root / POINTS_FILE, unit * sm[0, 0] + sm[:3, 3], np.full(200, 3))
    assert static_bounds(scene, load_config("womask"), tmp_path / "run" / "hull.pt") == ()
    on = load_config("womask", ["render.point_bound.enabled=true"])
    (box,) = static_bounds(scene, on, tmp_path / "run" / "hull.pt")
    assert isinstance(box, PointBound) and box.n_points == 200
    assert not (tmp_path / "run" / "hull.pt").exists()


def test_a_damaged_points_file_is_a_clear_error(tmp_path):
    import numpy as np
    import pytest

    from neus_l0.data.points import read_points
    from neus_l0.errors import SceneError

    bad = tmp_path / "sparse_points.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(SceneError, match="sparse_points.npz"):
        read_points(bad, np.eye(4))
    np.savez(bad, points_world=np.array([[0.0, np.nan, 0.0]]), track_len=np.array([3]))
    with pytest.raises(SceneError, match="finite"):
        read_points(bad, np.eye(4))
