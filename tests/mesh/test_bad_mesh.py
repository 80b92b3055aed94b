"""`neus-l0 mesh`'s bad inputs (issues #27 and #18): a coarse resolution no longer dilates the
hull for minutes, numbers are checked before any work, long evaluations show progress.
"""

from __future__ import annotations

import numpy as np
import pytest

from neus_l0.cli import main
from neus_l0.formats.neus import load_scene


def _ball_hull(R: int = 128, radius: float = 0.3):
    """A hull like a run's: 128 cells a side, a carved ball dilated by one cell."""
    from neus_l0.bounds.grid import cell_axis, dilate
    from neus_l0.bounds.hull import VisualHull

    c = cell_axis(R)
    r2 = c[:, None, None] ** 2 + c[None, :, None] ** 2 + c[None, None, :] ** 2
    return VisualHull(dilate(r2 <= radius ** 2))


@pytest.fixture
def pool_kernels(monkeypatch):
    """The kernel sizes of every max-pool (the old dilation) called while the test runs."""
    import torch.nn.functional as F

    seen: list[int] = []
    real = F.max_pool3d

    def spy(x, kernel_size, *args, **kw):
        seen.append(int(np.max(kernel_size)))
        return real(x, kernel_size, *args, **kw)

    monkeypatch.setattr(F, "max_pool3d", spy)
    return seen


@pytest.mark.parametrize("resolution, radius", [(8, 0.9), (9, 0.6), (16, 0.6)])
def test_coarse_extraction_does_not_grow_the_dilation(sphere_model, pool_kernels, resolution,
                                                      radius):
    from neus_l0.mesh.extract import extract_mesh

    hull = _ball_hull(radius=radius)  # holds the model's sphere of radius 0.5
    region = hull.for_grid(2.0 / (resolution - 1))
    assert max(pool_kernels, default=1) <= 3  # no kernel of (2n + 1)^3 cells, n ~ 15-32
    if radius == 0.9:
        assert bool(region.occupancy.all())  # the hull's region covers the whole grid
    model = sphere_model()
    inside = extract_mesh(model, np.eye(4), resolution=resolution, clean=False, hull=hull)
    plain = extract_mesh(model, np.eye(4), resolution=resolution, clean=False)
    assert max(pool_kernels, default=1) <= 3
    # inside the carved hull the mesh is the one without a hull
    assert len(plain.faces) > 0
    assert np.array_equal(np.asarray(inside.vertices), np.asarray(plain.vertices))
    assert np.array_equal(np.asarray(inside.faces), np.asarray(plain.faces))


@pytest.fixture(scope="module")
def tiny_run(tiny_scene, small_overrides, tmp_path_factory):
    """A run of 4 iterations on the tiny scene (with its hull.pt)."""
    from neus_l0.config.load import load_config
    from neus_l0.train.loop import train

    run = tmp_path_factory.mktemp("mesh") / "run"
    cfg = load_config("demo", [*small_overrides, "train.iters=4", "train.tensorboard=false"])
    train(load_scene(tiny_scene), cfg, run, progress=False)
    assert (run / "hull.pt").is_file()
    return run


@pytest.mark.parametrize("resolution", ["8", "9", "16"])
def test_mesh_command_at_a_coarse_resolution(tiny_run, tmp_path, capsys, pool_kernels,
                                             resolution):
    out = tmp_path / "m.ply"
    assert main(["mesh", str(tiny_run), "--resolution", resolution, "--out", str(out)]) == 0
    assert out.is_file() and max(pool_kernels, default=1) <= 3
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.parametrize("flags, named", [
    (["--resolution", "0"], "--resolution 0"),
    (["--resolution", "-5"], "--resolution -5"),
    (["--resolution", "100000"], "--resolution 100000"),
    (["--simplify", "2"], "--simplify 2"),
    (["--smooth", "-1"], "--smooth -1"),
    (["--min-component", "nan"], "--min-component nan"),
    (["--close-holes", "-1"], "--close-holes -1"),
    (["--texture", "--out", "x.obj", "--texture-size", "0"], "--texture-size 0"),
])
def test_mesh_checks_its_numbers_before_any_work(tmp_path, flags, named, refused):
    flags = [str(tmp_path / f) if f == "x.obj" else f for f in flags]
    refused(["mesh", str(tmp_path / "no-run"), *flags], named, alone=True)


def test_mesh_shows_progress_while_it_evaluates(trained96, tmp_path, capsys, monkeypatch):
    """(mesh at 512 printed nothing for a minute.) The SDF evaluation shows a bar."""
    import neus_l0.mesh.extract as extract

    monkeypatch.setattr(extract, "PROGRESS_DELAY_S", 0.0)
    assert main(["mesh", str(trained96), "--resolution", "24", "--out",
                 str(tmp_path / "m.ply")]) == 0
    assert "SDF grid" in capsys.readouterr().err


def test_18_2_mesh_resolution_100000_is_refused_with_the_estimate(trained96, refused):
    """(Was a 7 TiB allocation.) Exit 2 with the estimate and the largest that fits."""
    line = refused(["mesh", str(trained96), "--resolution", "100000"],
                   "--resolution 100000", "largest resolution that fits", alone=True)
    assert "TiB" in line or "PiB" in line
    assert not (trained96 / "mesh.ply").exists()
