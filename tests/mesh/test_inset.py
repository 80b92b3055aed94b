"""`neus-l0 mesh --inset K`: the level -K/s of the trained SDF (`neus_l0.mesh.inset`)."""

import numpy as np
import pytest
import torch
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from neus_l0.cli import main
from neus_l0.config.schema import VarianceConfig
from neus_l0.fields.variance import SingleVariance
from neus_l0.mesh.extract import extract_mesh
from neus_l0.mesh.inset import inset, logistic_scale


def sphere_model(radius: float, variance: float):
    """A model with an exact sphere SDF and NeuS's variance at `variance` (s = e^(10 v))."""

    class Sdf:
        def sdf(self, p):
            return (p.norm(dim=-1) - radius)[:, None]

    class Model:
        sdf = Sdf()
        color = None

    m = Model()
    m.variance = SingleVariance(VarianceConfig(init=variance))
    return m


@settings(max_examples=30, deadline=None)
@given(st.floats(-0.3, 0.6), st.floats(0.0, 3.0))
def test_the_inset_field_is_the_sdf_raised_by_k_over_s(v, k):
    model = sphere_model(0.5, v)
    s = float(np.exp(10 * v))
    assert logistic_scale(model) == pytest.approx(1 / s, rel=1e-5)
    field, delta = inset(model, k)
    assert delta == pytest.approx(k / s, rel=1e-5)
    p = torch.randn(64, 3, generator=torch.Generator().manual_seed(0))
    want = model.sdf.sdf(p) + k / s
    assert torch.allclose(field.sdf.sdf(p), want, atol=1e-6)


def test_zero_is_the_model_itself_and_bad_k_is_refused():
    model = sphere_model(0.5, 0.3)
    assert inset(model, 0.0) == (model, 0.0)
    for k in (-0.1, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="inset"):
            inset(model, k)


def test_the_mesh_of_a_sphere_shrinks_by_k_over_s():
    """s = e^3 ~ 20: K = 1 moves the sphere of radius 0.5 in by 1/s = 0.0498; the mesh's
    radius follows to well under a cell (2/63)."""
    model = sphere_model(0.5, 0.3)
    plain = extract_mesh(model, np.eye(4), resolution=64, clean=False, method="dense")
    field, delta = inset(model, 1.0)
    moved = extract_mesh(field, np.eye(4), resolution=64, clean=False, method="dense")
    r0 = np.linalg.norm(plain.vertices, axis=1).mean()
    r1 = np.linalg.norm(moved.vertices, axis=1).mean()
    assert delta == pytest.approx(np.exp(-3.0), rel=1e-5)
    assert r0 - r1 == pytest.approx(delta, abs=2e-3)


def test_the_command_insets_a_trained_run(run_copy, capsys):
    plain, inner = run_copy.parent / "plain.ply", run_copy.parent / "inner.ply"
    args = ["--resolution", "48", "--quiet", "--threads", "1", "--no-clean"]
    assert main(["mesh", str(run_copy), "--out", str(plain), *args]) == 0
    assert "inset: level" not in capsys.readouterr().out
    assert main(["mesh", str(run_copy), "--inset", "2", "--out", str(inner), *args]) == 0
    said = capsys.readouterr().out
    line = [ln for ln in said.splitlines() if ln.startswith("inset: level ")]
    assert len(line) == 1 and "(-2/s)" in line[0], said
    world = float(line[0].split("), ")[1].split()[0])
    a, b = trimesh.load(plain), trimesh.load(inner)
    assert world > 0 and b.volume < a.volume
    # the volume lost is a shell of about the offset times the area (a 4-step SDF's gradient
    # is not yet of norm 1, so only its order)
    assert 0.3 < (a.volume - b.volume) / (a.area * world) < 3


def test_a_negative_inset_is_refused(run_copy, refused):
    refused(["mesh", str(run_copy), "--inset", "-1", "--out", str(run_copy.parent / "m.ply")],
            "--inset")
