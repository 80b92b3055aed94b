"""The oracle sampling study: exact hits, the dense reference, and the command."""

from __future__ import annotations

import csv

import pytest
import torch

from neus_l0.cli import main
from neus_l0.experiments.oracle import (
    FINAL_S,
    VARIANTS,
    Case,
    _sphere_rays,
    dense_reference,
    first_hit,
)
from neus_l0.synthetic.shapes import Sphere


def _sphere_case(B: int = 24) -> tuple[Case, torch.Tensor]:
    o, d = _sphere_rays(torch.Generator().manual_seed(5), B)
    b = (o * d).sum(-1)
    exact = -b - (b * b - ((o * o).sum(-1) - 0.25)).sqrt()  # ray-sphere, radius 0.5
    sdf = Sphere((0.0, 0.0, 0.0), 0.5)
    return Case("sphere", sdf, o, d, first_hit(sdf, o, d)), exact


def test_first_hit_is_the_ray_sphere_intersection():
    case, exact = _sphere_case()
    torch.testing.assert_close(case.hit, exact, rtol=0, atol=1e-12)
    o = torch.tensor([[0.8, 0.0, -2.0]], dtype=torch.float64)  # passes 0.8 from the centre
    miss = first_hit(Sphere((0.0, 0.0, 0.0), 0.5), o, torch.tensor([[0.0, 0.0, 1.0]],
                                                                   dtype=torch.float64))
    assert torch.isnan(miss).all()


def test_dense_reference_renders_the_sphere_where_it_is():
    """4096 samples at s = 512: opaque, and the depth at the intersection."""
    case, exact = _sphere_case()
    depth, opacity = dense_reference(case, 1.0)
    torch.testing.assert_close(opacity, torch.ones_like(opacity), rtol=0, atol=1e-9)
    # NeuS is unbiased to first order; the rest is the sphere's curvature over a logistic
    # width 1/s, and the grid's spacing 2/4096
    assert (depth - exact).abs().max().item() < 0.1 / FINAL_S


def test_study_command_quick(tmp_path, capsys):
    assert main(["study", "sampling", "--out", str(tmp_path), "--quick", "--rays", "4"]) == 0
    rows = list(csv.DictReader(open(tmp_path / "sampling.csv")))
    assert {r["sampler"] for r in rows} == set(VARIANTS)
    assert {r["case"] for r in rows} == {"sphere", "plane 80deg", "pit r0.05 d0.2",
                                         "rod r0.02"}
    for r in rows:
        for key in ("within_0.001", "within_0.01", "within_0.03"):
            assert 0.0 <= float(r[key]) <= 1.0
        assert float(r["within_0.001"]) <= float(r["within_0.03"])
        assert float(r["median_dist"]) >= 0 and float(r["depth_err"]) >= 0
    assert (tmp_path / "summary.md").read_text().count("| hvs |") == 2
    assert (tmp_path / "within_0.01.png").stat().st_size > 1000
    assert "summary.md" in capsys.readouterr().out


def test_study_command_errors(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["study", "sampling", "--out", str(f / "sub"), "--quick"]) == 2
    assert "cannot create" in capsys.readouterr().err
    assert main(["study", "sampling", "--out", str(tmp_path), "--rays", "0"]) == 2
    with pytest.raises(SystemExit):
        main(["study", "nothing", "--out", str(tmp_path)])
