"""Bad inputs of issue #27 that the bounds meet (`neus_l0.bounds`): an object the unit sphere
cuts, cameras inside the sphere, and the box dilation that made a coarse mesh hang.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from neus_l0.cli import main


def scale_spheres(root: Path, factor: float, block: slice = slice(0, 3)) -> None:
    """Multiply the columns `block` of the top three rows of every scale_mat_i by `factor`."""
    cams = dict(np.load(root / "cameras_sphere.npz"))
    for key in [k for k in cams if k.startswith("scale_mat_")]:
        m = cams[key].copy()
        m[:3, block] *= factor
        cams[key] = m
    np.savez(root / "cameras_sphere.npz", **cams)


def test_an_object_the_sphere_cuts_is_refused_naming_the_fix(scene96_copy, train_cli, tmp_path,
                                                             refused, checkpoint_names):
    """scale_mat halved: refused before training, with the fix; once fixed, the same --out
    trains (the refused start left no hull behind)."""
    good = (scene96_copy / "cameras_sphere.npz").read_bytes()
    scale_spheres(scene96_copy, 0.5)
    run = tmp_path / "run"
    refused(train_cli(scene96_copy, run, "train.iters=2"), str(scene96_copy),
            "does not fit its unit sphere", "enlarge the sphere")
    assert checkpoint_names(run) == [] and not (run / "hull.pt").exists()
    (scene96_copy / "cameras_sphere.npz").write_bytes(good)
    assert main(train_cli(scene96_copy, run, "train.iters=2")) == 0
    assert checkpoint_names(run) == ["ckpt_0000002.pt"]


def test_a_huge_scale_mat_is_named_not_a_traceback(scene96_copy, train_cli, tmp_path, capsys,
                                                   refused, checkpoint_names):
    """scale_mat x1e30 (was a cv2 traceback): inspect warns; train refuses, naming the
    cameras inside the sphere (not advising a larger sphere)."""
    scale_spheres(scene96_copy, 1e30, slice(0, 4))
    assert main(["inspect", str(scene96_copy)]) == 0
    assert "cameras inside the unit sphere" in capsys.readouterr().out
    line = refused(train_cli(scene96_copy, tmp_path / "run", "train.iters=2"),
                   str(scene96_copy), "inside the unit sphere", "scale_mat")
    assert "enlarge" not in line
    assert checkpoint_names(tmp_path / "run") == []


def test_box_dilation_equals_the_max_pool_at_every_radius():
    from neus_l0.bounds.grid import dilate
    from neus_l0.bounds.hull import dilate_box

    g = torch.Generator().manual_seed(0)
    for R in (5, 8, 13):
        occ = torch.rand(R, R, R, generator=g) < 0.03
        occ[R // 2, 0, R - 1] = True
        for n in range(R + 3):
            assert torch.equal(dilate_box(occ, n), dilate(occ, n)), (R, n)
    assert not dilate_box(torch.zeros(6, 6, 6, dtype=torch.bool), 9).any()
