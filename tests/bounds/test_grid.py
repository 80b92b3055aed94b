"""The shared voxel grid (`neus_l0.bounds.grid`) against plain references."""

import itertools

import torch

from neus_l0.bounds.grid import cell_axis, cell_centres, dilate, lookup, occupied_span


def test_cell_centres_are_the_middles_of_the_cells():
    R = 6
    c = cell_centres(R)
    assert c.shape == (R, R, R, 3)
    ax = torch.tensor([-1.0 + (2 * i + 1) / R for i in range(R)])
    torch.testing.assert_close(cell_axis(R), ax)
    torch.testing.assert_close(c[1, 2, 3], torch.stack([ax[1], ax[2], ax[3]]))


def test_dilate_matches_a_brute_force_chebyshev_ball():
    g = torch.Generator().manual_seed(0)
    occ = torch.rand(9, 9, 9, generator=g) > 0.93
    for cells in (0, 1, 2):
        ref = torch.zeros_like(occ)
        for i, j, k in itertools.product(range(9), repeat=3):
            lo = [max(0, x - cells) for x in (i, j, k)]
            hi = [x + cells + 1 for x in (i, j, k)]
            ref[i, j, k] = occ[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].any()
        assert torch.equal(dilate(occ, cells), ref)


def test_lookup_finds_the_cell_of_each_point_and_nothing_outside_the_cube():
    g = torch.Generator().manual_seed(1)
    R = 8
    occ = torch.rand(R, R, R, generator=g) > 0.5
    pts = torch.rand(4000, 3, generator=g) * 2.4 - 1.2
    ijk = torch.floor((pts.double() + 1.0) * R / 2.0).long()
    inside = ((ijk >= 0) & (ijk < R)).all(-1)
    ijk = ijk.clamp(0, R - 1)
    ref = occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] & inside
    assert torch.equal(lookup(occ, pts), ref)


def test_occupied_span_is_the_first_to_last_occupied_lookup_widened_and_clipped():
    t = torch.tensor([[0.0, 1.0, 2.0, 3.0, 4.0], [0.0, 1.0, 2.0, 3.0, 4.0]])
    occupied = torch.tensor([[False, True, False, True, False], [False] * 5])
    near, far = torch.tensor([[0.0], [0.0]]), torch.tensor([[3.5], [4.0]])
    lo, hi, hits = occupied_span(t, occupied, near, far, 0.5)
    assert hits.tolist() == [True, False]
    assert lo[:, 0].tolist() == [0.5, 0.0] and hi[:, 0].tolist() == [3.5, 4.0]
