"""How much host memory a mesh extraction needs, estimated before anything is allocated.

`neus-l0 mesh --resolution R` checks the estimate against the memory available, so that
``--resolution 100000`` is a one-line refusal naming the largest resolution that fits
instead of numpy failing to allocate terabytes.

The estimate (bytes) has two parts:

- the grids, exact: *dense* holds the float32 volume, 4 R^3; *sparse* (blocks of ``block``
  cells, nb = ceil((R - 1) / block) per axis) holds the float32 coarse grid,
  4 (nb + 1)^3, and `keep_blocks`'s per-block temporaries (about 16 bytes a block);
- one batch of `chunk` points through the SDF network: `EVAL_BYTES_PER_POINT` a point
  (above the peak of the largest shipped network, so every config is covered);
- the mesh, assumed: marching cubes gives about `FACES_PER_AREA` triangles per grid step
  squared of surface, and extraction, clean-up and export peak at about `BYTES_PER_FACE`
  bytes a face (both from measured extractions, the bytes above the largest peak; see
  docs/BENCHMARKS.md, "Mesh clean-up, textures and the memory estimate"). The surface area
  is not known before the extraction; `TYPICAL_AREA` (a sphere of radius 1/sqrt(2) in the
  normalised frame, where the object's bounding sphere is the unit sphere) stands in for it.
"""

from __future__ import annotations

import math

from neus_l0.device import available_memory
from neus_l0.errors import NeusL0Error

FACES_PER_AREA = 3.0
"""Marching-cubes triangles per (grid step)^2 of surface area (as marching cubes gives on
spheres; docs/benchmarks/mesh.md)."""

BYTES_PER_FACE = 1100
"""Peak bytes per output face of extraction + clean-up + export (above every measured
peak, dense and sparse, so the estimate errs on the safe side)."""

TYPICAL_AREA = 2.0 * math.pi
"""Assumed surface area in the normalised frame: a sphere of radius 1/sqrt(2)."""

KEEP_BLOCK_BYTES = 16
"""`keep_blocks` temporaries per block (absolute maximum, counts, masks, dilation)."""

EVAL_BYTES_PER_POINT = 8192
"""Bytes per point of one SDF evaluation batch (network activations; above the measured
peak of every shipped config)."""


def mesh_faces(resolution: int, bound: float = 1.0, area: float = TYPICAL_AREA) -> float:
    """Expected marching-cubes faces for a surface of `area` on ``linspace(-bound, bound, R)^3``."""
    step = 2.0 * bound / max(int(resolution) - 1, 1)
    return FACES_PER_AREA * area / step**2


def extraction_bytes(method: str, resolution: int, block: int = 8, bound: float = 1.0,
                     area: float = TYPICAL_AREA, chunk: int = 2**18) -> int:
    """Estimated peak host memory of `neus_l0.mesh.extract.extract_mesh` (see the module docstring).

    Args:
        method: "dense" or "sparse".
        resolution: R, grid samples per axis.
        block: the sparse path's cells per block edge.
        bound: half-size of the cube (the grid's extent).
        area: assumed surface area in the normalised frame.
        chunk: points per SDF call.

    Returns:
        bytes.
    """
    R = int(resolution)
    if method == "dense":
        grid = 4 * R**3
    elif method == "sparse":
        nb = -(-(R - 1) // int(block))
        grid = 4 * (nb + 1) ** 3 + KEEP_BLOCK_BYTES * nb**3
    else:
        raise NeusL0Error(f"mesh method '{method}': use dense or sparse")
    batch = EVAL_BYTES_PER_POINT * min(int(chunk), R**3)
    return int(grid + batch + BYTES_PER_FACE * mesh_faces(R, bound, area))


def largest_resolution(method: str, budget: int, block: int = 8, bound: float = 1.0,
                       area: float = TYPICAL_AREA) -> int:
    """The largest R whose `extraction_bytes` fits in `budget` bytes (0 when not even R = 8).

    `extraction_bytes` grows with R, so a bisection finds it.
    """
    def fits(r: int) -> bool:
        return extraction_bytes(method, r, block, bound, area) <= budget

    if not fits(8):
        return 0
    lo, hi = 8, 16
    while fits(hi):
        lo, hi = hi, hi * 2
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return lo


def _gib(n: float) -> str:
    """Bytes as GiB, or TiB / PiB where large."""
    for unit, scale in (("PiB", 2**50), ("TiB", 2**40)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n / 2**30:.3g} GiB"


def plan_extraction(method: str, resolution: int, block: int = 8,
                    available: int | None = None) -> tuple[str, str | None]:
    """Check that an extraction fits in memory; route dense to sparse where only that fits.

    Args:
        method: "dense" or "sparse" (``auto`` already resolved).
        resolution: R.
        block: the sparse path's block size.
        available: bytes available (default: `available_memory()`; None = unknown, no check).

    Returns:
        (method to use, a note for the user or None).

    Raises:
        NeusL0Error: one line with the estimate, the memory available and the largest
            resolution that fits.
    """
    if available is None:
        available = available_memory()
    if available is None:
        return method, None
    need = extraction_bytes(method, resolution, block)
    if need <= available:
        return method, None
    if method == "dense" and extraction_bytes("sparse", resolution, block) <= available:
        sparse = extraction_bytes("sparse", resolution, block)
        return "sparse", (f"--resolution {resolution}: the dense grid needs about {_gib(need)} "
                          f"({_gib(available)} available); using the sparse path (about "
                          f"{_gib(sparse)})")
    best = largest_resolution("sparse", available, block)
    fit = (f"the largest resolution that fits is about {best} (sparse)" if best else
           "not even --resolution 8 fits; free some memory")
    raise NeusL0Error(f"--resolution {resolution}: {method} extraction needs about "
                      f"{_gib(need)} of memory, {_gib(available)} is available; {fit}")
