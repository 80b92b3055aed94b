"""The multiresolution hash-grid encoding against a plain per-point reference."""

import itertools
import math

import pytest
import torch

from neus_l0.config.load import load_config
from neus_l0.config.schema import EncodingConfig, ModelConfig, SDFConfig
from neus_l0.errors import ConfigError
from neus_l0.fields.encodings import (
    HASH_PRIMES,
    HashGridEncoding,
    build_encoding,
    level_resolutions,
    spatial_hash,
)
from neus_l0.fields.model import build_model
from neus_l0.fields.sdf import sdf_and_gradient


def tiny_grid(**kw) -> HashGridEncoding:
    """3 levels (2, 4, 8 cells per axis) over a 64-entry table: level 0 (27 points) is
    indexed directly, levels 1 (125) and 2 (729) through the hash, with collisions."""
    args = dict(n_levels=3, n_features=2, log2_hashmap_size=6, base_resolution=2,
                per_level_scale=2.0, init_scale=1.0, n_freqs=0)
    args.update(kw)
    torch.manual_seed(0)
    return HashGridEncoding(EncodingConfig(kind="hashgrid", **args)).double()


def reference_features(enc: HashGridEncoding, x: torch.Tensor) -> torch.Tensor:
    """Plain loops: for each point and level, the 8 corners, their weights and table rows."""
    T = enc.table_size
    table = enc.table.detach() * enc.lr_scale
    out = torch.zeros(x.shape[0], enc.n_levels, enc.n_features, dtype=x.dtype)
    offset = 0
    for lv, n in enumerate(enc.resolutions):
        direct = (n + 1) ** 3 <= T
        for p in range(x.shape[0]):
            u = [min(max((float(x[p, a]) / enc.bound + 1.0) / 2.0, 0.0), 1.0) for a in range(3)]
            pos = [ua * n for ua in u]
            cell = [min(int(math.floor(q)), n - 1) for q in pos]
            frac = [q - c for q, c in zip(pos, cell, strict=True)]
            for dx in (0, 1):
                for dy in (0, 1):
                    for dz in (0, 1):
                        cx, cy, cz = cell[0] + dx, cell[1] + dy, cell[2] + dz
                        w = ((frac[0] if dx else 1 - frac[0]) * (frac[1] if dy else 1 - frac[1])
                             * (frac[2] if dz else 1 - frac[2]))
                        if direct:
                            row = cx + cy * (n + 1) + cz * (n + 1) ** 2
                        else:
                            row = ((cx * HASH_PRIMES[0]) ^ (cy * HASH_PRIMES[1])
                                   ^ (cz * HASH_PRIMES[2])) % T
                        out[p, lv] += w * table[offset + row]
        offset += min((n + 1) ** 3, T)
    return out


def _points(n, seed=0, scale=0.95):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * scale


def test_layout_and_resolutions():
    enc = tiny_grid()
    assert enc.resolutions == [2, 4, 8]
    assert enc.level_sizes == [27, 64, 64] and enc.n_direct == 1
    assert enc.table.shape == (27 + 64 + 64, 2)
    assert enc.out_dim == 3 + 3 * 2 and enc.raw_dims == 3
    assert level_resolutions(4, 16, 2.0) == [16, 32, 64, 128]
    e = build_encoding(EncodingConfig(kind="hashgrid", n_levels=16, base_resolution=16,
                                      finest_resolution=2048, n_freqs=2), 3)
    assert e.resolutions[0] == 16 and e.resolutions[-1] in (2047, 2048)
    assert e.out_dim == 3 + 3 * 2 * 2 + 16 * 2


@pytest.mark.parametrize("kw", [{}, {"bound": 1.3, "lr_scale": 10.0}])
def test_interpolation_matches_plain_reference(kw):
    enc = tiny_grid(**kw)
    x = torch.cat([_points(40), torch.tensor([[1.0, -1.0, 0.0], [-1.0, 1.0, 1.0],
                                              [1.2, -1.5, 0.3]], dtype=torch.float64)])
    got = enc.grid_features(x)
    ref = reference_features(enc, x)
    assert torch.allclose(got, ref, atol=1e-12)
    y = enc(x)
    assert torch.equal(y[:, :3], x)
    assert torch.allclose(y[:, 3:], ref.flatten(1), atol=1e-12)


def test_grid_points_reproduce_table_entries():
    """At a grid point of a directly indexed level the feature is that point's row."""
    enc = tiny_grid()
    n = enc.resolutions[0]
    ijk = torch.tensor([[0, 0, 0], [1, 2, 0], [2, 2, 2], [2, 0, 1]], dtype=torch.float64)
    x = ijk / n * 2 - 1
    rows = (ijk[:, 0] + ijk[:, 1] * (n + 1) + ijk[:, 2] * (n + 1) ** 2).long()
    assert torch.allclose(enc.grid_features(x)[:, 0], enc.table.detach()[rows], atol=1e-12)


def test_gradcheck_inputs_and_table():
    # 1, 2, 4 cells per axis over 16 entries: level 0 (8 points) direct, 1 and 2 hashed
    enc = tiny_grid(lr_scale=3.0, base_resolution=1, log2_hashmap_size=4)
    assert enc.n_direct == 1 and enc.level_sizes == [8, 16, 16]
    x = _points(4, seed=1).requires_grad_(True)
    table = enc.table

    def f(x_, t_):
        enc.table = t_  # the same module with the table as an explicit input
        return enc(x_)

    try:
        t = torch.nn.Parameter(table.detach().clone())
        assert torch.autograd.gradcheck(f, (x, t), eps=1e-6, atol=1e-7)
        assert torch.autograd.gradgradcheck(f, (x, t), eps=1e-6, atol=1e-6)
    finally:
        enc.table = table


def test_sdf_gradient_and_eikonal_double_backward_match_finite_differences():
    """The SDF network with a hash grid: autograd's spatial gradient equals central
    differences, and the Eikonal loss's gradient wrt the table equals its own finite
    differences (the double backward through the interpolation)."""
    # no geometric init: it zeroes the first layer's grid columns (no gradient to the table)
    cfg = SDFConfig(hidden=16, layers=2, skip=[], feature_dim=4, weight_norm=False,
                    geometric_init=False,
                    encoding=EncodingConfig(kind="hashgrid", n_levels=2, base_resolution=2,
                                            per_level_scale=2.0, log2_hashmap_size=6,
                                            n_freqs=0, init_scale=0.3))
    torch.manual_seed(0)
    net = build_model(ModelConfig(sdf=cfg)).sdf.double()
    x = _points(5, seed=2)
    _, g = sdf_and_gradient(net, x, create_graph=True)
    h = 1e-6
    fd = torch.stack([(net.sdf(x + h * e) - net.sdf(x - h * e))[:, 0] / (2 * h)
                      for e in torch.eye(3, dtype=torch.float64)], dim=-1)
    assert torch.allclose(g, fd, atol=1e-7)

    def eikonal() -> torch.Tensor:
        _, gr = sdf_and_gradient(net, x, create_graph=True)
        return ((gr.norm(dim=-1) - 1.0) ** 2).sum()

    table = net.encoding.table
    (dtable,) = torch.autograd.grad(eikonal(), table)
    assert dtable.abs().sum() > 0
    rows = dtable.abs().sum(-1).nonzero()[:4, 0]
    with torch.no_grad():
        for r in rows:
            for c in range(table.shape[1]):
                old = table[r, c].item()
                table[r, c] = old + h
                up = eikonal()
                table[r, c] = old - h
                down = eikonal()
                table[r, c] = old
                assert abs((up - down).item() / (2 * h) - dtable[r, c].item()) < 1e-6


def test_continuous_across_cell_boundaries():
    enc = tiny_grid()
    finest = enc.resolutions[-1]
    g = torch.Generator().manual_seed(3)
    base = torch.rand(50, 3, generator=g, dtype=torch.float64) * 1.6 - 0.8
    # put the x coordinate exactly on a boundary of the finest level (also one of the others)
    k = torch.randint(1, finest, (50,), generator=g)
    base[:, 0] = k / finest * 2 - 1
    for eps in (1e-6, 1e-9):
        left = enc(base - torch.tensor([eps, 0, 0], dtype=torch.float64))
        right = enc(base + torch.tensor([eps, 0, 0], dtype=torch.float64))
        # Lipschitz: |table| <= 1, 8 corners, 2 * finest / 2 cells per unit
        assert (left - right).abs().max() <= 2 * eps * finest * 8 + 1e-12


def test_hash_is_in_range_and_direct_levels_are_bijective():
    g = torch.Generator().manual_seed(4)
    c = torch.randint(0, 2**20, (10000, 3), generator=g)
    for log2 in (4, 10, 19):
        h = spatial_hash(c, 2**log2)
        assert h.dtype == torch.int64 and h.min() >= 0 and h.max() < 2**log2
    enc = build_encoding(EncodingConfig(kind="hashgrid", n_levels=4, base_resolution=4,
                                        per_level_scale=2.0, log2_hashmap_size=10), 3)
    # every grid point of every level lands in its own level's rows
    for lv, n in enumerate(enc.resolutions):
        r = torch.arange(n + 1)
        pts = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
        cells = torch.minimum(pts, torch.tensor(n - 1))
        full = enc.grid_indices(cells[:, None, :].expand(-1, enc.n_levels, 3).contiguous())
        corner_of = cells[:, None, :] + enc.corners  # (P, 8, 3)
        hit = (corner_of == pts[:, None, :]).all(-1)  # the corner that is the point itself
        rows = full[:, lv][hit]
        lo, hi = int(enc.offsets[lv]), int(enc.offsets[lv]) + enc.level_sizes[lv]
        assert rows.min() >= lo and rows.max() < hi
        if lv < enc.n_direct:
            assert rows.unique().numel() == (n + 1) ** 3  # no collisions
    assert enc.n_direct == 2  # 5^3 and 9^3 fit 1024 entries, 17^3 does not


def test_geometric_init_with_hash_grid_is_a_sphere_of_radius_half():
    cfg = SDFConfig(hidden=64, layers=2, skip=[], feature_dim=16,
                    encoding=EncodingConfig(kind="hashgrid", n_levels=8, n_features=2,
                                            log2_hashmap_size=14, base_resolution=16,
                                            finest_resolution=256, n_freqs=0))
    torch.manual_seed(0)
    model = build_model(ModelConfig(sdf=cfg))
    g = torch.Generator().manual_seed(0)
    d = torch.randn(400, 3, generator=g)
    d = d / d.norm(dim=-1, keepdim=True)
    radii = torch.linspace(0.0, 1.2, 121)
    with torch.no_grad():
        f = model.sdf.sdf((d[:, None, :] * radii[None, :, None]).reshape(-1, 3)).reshape(400, 121)
    inside = f < 0
    assert inside[:, 0].all() and not inside[:, -1].any()
    assert ((inside[:, :-1] != inside[:, 1:]).sum(-1) == 1).all()
    crossing = radii[inside.sum(-1)]
    assert 0.4 <= crossing.median() <= 0.6
    _, grad = sdf_and_gradient(model.sdf, d * 0.5, create_graph=False)
    assert torch.nn.functional.cosine_similarity(grad, d, dim=-1).mean() > 0.8
    assert 0.6 < grad.norm(dim=-1).mean() < 1.4


def test_progressive_levels_count_training_passes_only():
    enc = tiny_grid(start_level=1, update_steps=2)
    x = _points(8)
    with torch.no_grad():
        y = enc(x)
    assert int(enc.steps) == 0  # no gradient: not a training pass
    assert (y[:, 3 + 2:] == 0).all() and (y[:, 3:5] != 0).all()  # only level 0 active
    for _ in range(2):
        enc(x)  # training mode with gradients
    assert int(enc.steps) == 2 and int(enc.active_levels()) == 2
    enc.eval()
    y = enc(x)
    assert int(enc.steps) == 2
    assert (y[:, 5:7] != 0).all() and (y[:, 7:] == 0).all()
    enc.train()
    for _ in range(10):
        enc(x)
    assert int(enc.active_levels()) == 3
    assert "steps" in enc.state_dict()  # checkpoints keep the schedule
    assert torch.allclose(enc(x)[:, 3:], reference_features(enc, x).flatten(1), atol=1e-12)


def test_lr_scale_multiplies_the_tables_adam_step():
    x = _points(16)
    steps = {}
    for scale in (1.0, 10.0):
        enc = tiny_grid(lr_scale=scale)
        before = (enc.table * scale).detach().clone()
        opt = torch.optim.Adam(enc.parameters(), lr=1e-3)
        enc(x).square().sum().backward()
        opt.step()
        steps[scale] = ((enc.table * scale).detach() - before).abs().max().item()
    assert steps[1.0] == pytest.approx(1e-3, rel=1e-3)
    assert steps[10.0] == pytest.approx(1e-2, rel=1e-3)


def test_hashgrid_config_errors():
    with pytest.raises(ConfigError, match="per_level_scale"):
        load_config("demo", ["model.sdf.encoding.kind=hashgrid",
                             "model.sdf.encoding.per_level_scale=0.5"])
    with pytest.raises(ConfigError, match="log2_hashmap_size"):
        load_config("demo", ["model.sdf.encoding.kind=hashgrid",
                             "model.sdf.encoding.log2_hashmap_size=40"])
    with pytest.raises(ConfigError, match="unknown choice"):
        load_config("demo", ["model.sdf.encoding.kind=hash"])


@pytest.mark.parametrize("name", ["demo", "fast"])
def test_fast_configs_build(name):
    cfg = load_config(name)
    model = build_model(cfg.model)
    assert isinstance(model.sdf.encoding, HashGridEncoding)
    out, g = sdf_and_gradient(model.sdf, torch.rand(32, 3) - 0.5, create_graph=True)
    assert torch.isfinite(out).all() and torch.isfinite(g).all()


def reference_jacobian(enc: HashGridEncoding, x: torch.Tensor, active: int) -> torch.Tensor:
    """Plain loops: d feature / d x, (N, 3, L, F), of the first `active` levels (the others
    0): each corner's trilinear weight differentiated along one axis, times n / (2 bound)
    where the point is inside the box on that axis (0 where the clamp holds it)."""
    T = enc.table_size
    table = enc.table.detach() * enc.lr_scale
    out = torch.zeros(x.shape[0], 3, enc.n_levels, enc.n_features, dtype=x.dtype)
    offset = 0
    for lv, n in enumerate(enc.resolutions):
        direct = (n + 1) ** 3 <= T
        for p in range(x.shape[0] if lv < active else 0):
            xs = [float(x[p, a]) / enc.bound for a in range(3)]
            u = [min(max((xa + 1.0) / 2.0, 0.0), 1.0) for xa in xs]
            pos = [ua * n for ua in u]
            cell = [min(int(math.floor(q)), n - 1) for q in pos]
            frac = [q - c for q, c in zip(pos, cell, strict=True)]
            gain = [n / (2.0 * enc.bound) if -1.0 <= xa <= 1.0 else 0.0 for xa in xs]
            for corner in itertools.product((0, 1), repeat=3):
                c = [cell[a] + corner[a] for a in range(3)]
                if direct:
                    row = c[0] + c[1] * (n + 1) + c[2] * (n + 1) ** 2
                else:
                    row = ((c[0] * HASH_PRIMES[0]) ^ (c[1] * HASH_PRIMES[1])
                           ^ (c[2] * HASH_PRIMES[2])) % T
                for a in range(3):  # d weight / d frac_a, the other two axes' factors
                    dw = 1.0 if corner[a] else -1.0
                    for b in range(3):
                        if b != a:
                            dw *= frac[b] if corner[b] else 1.0 - frac[b]
                    out[p, a, lv] += dw * gain[a] * table[offset + row]
        offset += min((n + 1) ** 3, T)
    return out


@pytest.mark.parametrize("kw,active", [({}, 3), ({"bound": 1.3, "lr_scale": 10.0}, 3),
                                       ({"start_level": 2, "update_steps": 5}, 2),
                                       ({"n_freqs": 2, "include_input": False}, 3)])
def test_batched_grid_and_its_jacobian_equal_a_per_level_float64_reference(kw, active):
    """All levels gathered from one table with per-level offsets, interpolated together,
    and the Jacobian of that interpolation batched too: equal to the plain per-level,
    per-corner loops to 1e-10 in float64 on random points (some outside the box)."""
    enc = tiny_grid(**kw)
    enc.eval()
    g = torch.Generator().manual_seed(3)
    x = (torch.rand(60, 3, generator=g, dtype=torch.float64) * 2 - 1) * 1.15
    x = torch.cat([x, torch.tensor([[1.0, -1.0, 0.0], [0.25, 0.5, -0.75]],
                                   dtype=torch.float64)])
    ref = reference_features(enc, x)
    ref[:, active:] = 0.0  # inactive levels output 0
    ref_jac = reference_jacobian(enc, x, active)
    with torch.no_grad():
        out = enc(x)
        val, jac = enc.forward_jacobian(x)
    n_pre = enc.out_dim - enc.n_levels * enc.n_features
    torch.testing.assert_close(out[:, n_pre:], ref.flatten(1), rtol=0, atol=1e-10)
    torch.testing.assert_close(val, out, rtol=0, atol=1e-10)
    torch.testing.assert_close(jac[:, :, n_pre:], ref_jac.flatten(2), rtol=0, atol=1e-10)
    assert enc.steps.item() == 0  # eval, no gradient: no training pass counted
    # with gradients (the training path: index_select) the same numbers
    enc.train()
    val_g, jac_g = enc.forward_jacobian(x)
    torch.testing.assert_close(jac_g[:, :, n_pre:].detach(), ref_jac.flatten(2), rtol=0,
                               atol=1e-10)
    torch.testing.assert_close(val_g.detach(), val, rtol=0, atol=1e-10)


def test_active_level_cache_follows_the_step_counter():
    enc = tiny_grid(start_level=1, update_steps=1)
    x = _points(5)
    n_pre = enc.out_dim - enc.n_levels * enc.n_features
    with torch.no_grad():
        first = enc(x)[:, n_pre:].view(5, 3, 2)
        assert (first[:, 1:] == 0).all() and (first[:, 0] != 0).any()
    enc.train()
    enc(x)  # a training pass: steps 0 -> 1, level 1 switches on
    with torch.no_grad():
        second = enc(x)[:, n_pre:].view(5, 3, 2)
    assert (second[:, 1] != 0).any() and (second[:, 2] == 0).all()
    enc.load_state_dict({"steps": torch.tensor(5), "table": enc.table.detach()})
    with torch.no_grad():
        third = enc(x)[:, n_pre:].view(5, 3, 2)
    assert (third[:, 2] != 0).any()

