"""Analytic signed distance functions, constructive solid geometry, and the built-in shapes.

Every shape is a callable ``sdf(x) -> d`` on (N, 3) tensors (any float dtype, world units)
returning (N,) signed distances, negative inside. Primitives are exact SDFs (Inigo Quilez's
formulas); union / difference / intersection by min / max give a lower bound of the true
distance (1-Lipschitz), which is all sphere tracing and Newton projection need.

Built-in shapes (`builtin_shape(name)`) are centred near the origin, z up, sized like DTU
objects in millimetres (about 250 across); `features` lists where their pits and thin parts
are, in the same frame.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence

import numpy as np
import torch

Tensor = torch.Tensor
SDF = Callable[[Tensor], Tensor]


_VEC_CACHE: dict = {}


def _vec(v: Sequence[float], like: Tensor) -> Tensor:
    """`v` as a tensor matching `like`'s dtype and device (cached: SDFs run in tight loops)."""
    key = (tuple(v), like.dtype, like.device)
    out = _VEC_CACHE.get(key)
    if out is None:
        out = _VEC_CACHE[key] = torch.as_tensor(v, dtype=like.dtype, device=like.device)
    return out


@dataclasses.dataclass(frozen=True)
class Sphere:
    """Sphere of `radius` around `center`."""

    center: tuple[float, float, float]
    radius: float

    def __call__(self, x: Tensor) -> Tensor:
        return (x - _vec(self.center, x)).norm(dim=-1) - self.radius


@dataclasses.dataclass(frozen=True)
class Box:
    """Axis-aligned box with half extents `half`, edges rounded by `rounding`."""

    center: tuple[float, float, float]
    half: tuple[float, float, float]
    rounding: float = 0.0

    def __call__(self, x: Tensor) -> Tensor:
        q = (x - _vec(self.center, x)).abs() - _vec(self.half, x) + self.rounding  # (N, 3)
        outside = q.clamp_min(0).norm(dim=-1)
        inside = q.max(dim=-1).values.clamp_max(0)
        return outside + inside - self.rounding


@dataclasses.dataclass(frozen=True)
class CappedCone:
    """Solid cone frustum from point `a` (radius `ra`) to point `b` (radius `rb`).

    With ``ra == rb`` it is a capped cylinder; with one radius 0 a pointed cone.
    """

    a: tuple[float, float, float]
    b: tuple[float, float, float]
    ra: float
    rb: float

    def __call__(self, x: Tensor) -> Tensor:
        a, b = _vec(self.a, x), _vec(self.b, x)
        ra, rb = self.ra, self.rb
        ba = b - a
        baba = (ba * ba).sum()
        pa = x - a  # (N, 3)
        papa = (pa * pa).sum(-1)
        paba = (pa @ ba) / baba  # (N,) position along the axis in [0, 1] between caps
        r2 = (papa - paba * paba * baba).clamp_min(0)
        rad = r2.sqrt()  # (N,) distance from the axis
        rba = rb - ra
        cax = (rad - torch.where(paba < 0.5, ra, rb)).clamp_min(0)
        cay = (paba - 0.5).abs() - 0.5
        k = rba * rba + baba
        f = ((rba * (rad - ra) + paba * baba) / k).clamp(0, 1)
        cbx = rad - ra - f * rba
        cby = paba - f
        sign = torch.where((cbx < 0) & (cay < 0), -1.0, 1.0).to(x.dtype)
        d2 = torch.minimum(cax * cax + cay * cay * baba, cbx * cbx + cby * cby * baba)
        return sign * d2.sqrt()


@dataclasses.dataclass(frozen=True)
class Capsule:
    """Segment a-b swept by a ball of `radius`."""

    a: tuple[float, float, float]
    b: tuple[float, float, float]
    radius: float

    def __call__(self, x: Tensor) -> Tensor:
        a, b = _vec(self.a, x), _vec(self.b, x)
        ba = b - a
        h = (((x - a) @ ba) / (ba * ba).sum()).clamp(0, 1)
        return (x - a - h[:, None] * ba).norm(dim=-1) - self.radius


@dataclasses.dataclass(frozen=True)
class Torus:
    """Ring around `center` whose axis is the world axis `axis` (0: x, 1: y, 2: z): the
    circle of radius `major` in the plane across the axis, swept by a ball of `minor`."""

    center: tuple[float, float, float]
    axis: int
    major: float
    minor: float

    def __call__(self, x: Tensor) -> Tensor:
        p = x - _vec(self.center, x)
        across = [i for i in range(3) if i != self.axis]
        ring = p[:, across].norm(dim=-1) - self.major
        return torch.stack([ring, p[:, self.axis]], -1).norm(dim=-1) - self.minor


@dataclasses.dataclass(frozen=True)
class Union:
    """Union of shapes (pointwise min)."""

    parts: tuple

    def __call__(self, x: Tensor) -> Tensor:
        d = self.parts[0](x)
        for p in self.parts[1:]:
            d = torch.minimum(d, p(x))
        return d


@dataclasses.dataclass(frozen=True)
class Difference:
    """`base` minus the union of `cutters` (max(base, -cutters))."""

    base: object
    cutters: tuple

    def __call__(self, x: Tensor) -> Tensor:
        return torch.maximum(self.base(x), -Union(self.cutters)(x))


@dataclasses.dataclass(frozen=True)
class Translated:
    """`shape` moved by `offset`."""

    shape: object
    offset: tuple[float, float, float]

    def __call__(self, x: Tensor) -> Tensor:
        return self.shape(x - _vec(self.offset, x))


@dataclasses.dataclass
class BuiltinShape:
    """An analytic shape with its annotated features.

    Attributes:
        name: the built-in name.
        sdf: the signed distance function (world units).
        features: dicts with ``kind`` ("pit" | "thin"), ``name``, ``center`` [x, y, z],
            ``radius`` and ``axis`` ([x, y, z] or None), world units.
        bounds: (lo, hi) corners of an axis-aligned box that contains the shape.
        description: one line on what it is.
    """

    name: str
    sdf: SDF
    features: list[dict]
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]]
    description: str


def _pit(x: float, y: float, top: float, radius: float, depth: float, tip: float | None = None,
         name: str = "") -> tuple[CappedCone, dict]:
    """A vertical hole of `radius` and `depth` into a top face at height `top`.

    ``tip`` (radius at the bottom) makes it conical. The cutter pokes 10 units above the face.
    """
    bottom = tip if tip is not None else radius
    cutter = CappedCone((x, y, top - depth), (x, y, top + 10.0), bottom,
                        radius + (radius - bottom) * 10.0 / depth)
    feat = {"kind": "pit", "name": name, "center": [x, y, top - depth / 2],
            "radius": float(max(radius, depth / 2)), "axis": [0.0, 0.0, 1.0]}
    return cutter, feat


def _rod(x: float, y: float, z0: float, height: float, radius: float,
         name: str) -> tuple[CappedCone, dict]:
    rod = CappedCone((x, y, z0 - 1.0), (x, y, z0 + height), radius, radius)
    feat = {"kind": "thin", "name": name, "center": [x, y, z0 + height / 2],
            "radius": float(height / 2), "axis": [0.0, 0.0, 1.0]}
    return rod, feat


def demo_shape() -> BuiltinShape:
    """A rounded slab with one deep pit and one thick slanted horn: cheap and recognisable."""
    top = 30.0
    body = Box((0.0, 0.0, 0.0), (90.0, 65.0, top), rounding=12.0)
    pit, pit_feat = _pit(-40.0, 10.0, top, 24.0, 40.0, name="pit r24 d40")
    horn = Capsule((35.0, -10.0, 10.0), (75.0, -25.0, 105.0), 17.0)
    knob = Sphere((-50.0, -40.0, top), 18.0)
    sdf = Union((Difference(body, (pit,)), horn, knob))
    features = [pit_feat,
                {"kind": "thin", "name": "horn r17", "center": [55.0, -17.5, 57.5],
                 "radius": 55.0, "axis": [0.38, -0.14, 0.91]}]
    return BuiltinShape("demo", sdf, features, ((-92.0, -67.0, -32.0), (93.0, 67.0, 123.0)),
                        "rounded slab (180x130x60) with a pit (r 24, depth 40), a slanted "
                        "horn (r 17) and a knob")


#: The deep pit of ``pits_and_thin_shape(deep_pit=True)``: centre (x, y), radius, depth
#: (as deep as it is wide), and its rods: (x, y) offsets from the pit's axis, radius, height.
DEEP_PIT = ((-5.0, -15.0), 18.0, 36.0)
DEEP_PIT_RODS = (((0.0, 11.0), 1.5, 28.0), ((-9.5, -5.5), 3.0, 28.0), ((9.5, -5.5), 5.0, 28.0))
#: Radius of the deep pit's floor feature: the floor's centre, clear of the rods.
DEEP_FLOOR_RADIUS = 5.5


def deep_pit_parts(top: float) -> tuple[CappedCone, list[CappedCone], list[dict]]:
    """The deep pit into a top face at height `top`, the rods standing on its floor, and
    their features: the whole pit, its floor (a ball of `DEEP_FLOOR_RADIUS` on the floor's
    centre, clear of the rods) and each rod (world units, z up).

    Returns:
        (cutter, rods, features).
    """
    (x, y), r, depth = DEEP_PIT
    cutter, pit = _pit(x, y, top, r, depth, name=f"deep pit r{r:g} d{depth:g}")
    pit["radius"] = float(np.hypot(r, depth / 2))  # the ball holds the wall, floor and rim
    floor = {"kind": "pit", "name": "deep pit floor", "center": [x, y, top - depth],
             "radius": DEEP_FLOOR_RADIUS, "axis": [0.0, 0.0, 1.0]}
    rods, feats = [], [pit, floor]
    for (dx, dy), rr, h in DEEP_PIT_RODS:
        rod, f = _rod(x + dx, y + dy, top - depth, h, rr, name=f"deep pit rod r{rr:g}")
        rods.append(rod)
        feats.append(f)
    return cutter, rods, feats


def pits_and_thin_shape(deep_pit: bool = False) -> BuiltinShape:
    """A slab with pits of several widths/depths, a cone pit, rods and fins of several radii.

    With `deep_pit` (the built-in ``pits-deep``) the slab also has a pit as deep as it is
    wide (`DEEP_PIT`) with thin rods standing on its floor (`DEEP_PIT_RODS`), below the rim.
    """
    top = 25.0
    body = Box((0.0, 0.0, 0.0), (100.0, 70.0, top), rounding=3.0)
    cutters, feats = [], []
    # a row of cylindrical pits: widths and depths vary together and separately
    for x, r, d in [(-82.0, 3.0, 12.0), (-62.0, 6.0, 24.0), (-35.0, 10.0, 40.0),
                    (-5.0, 10.0, 15.0), (40.0, 18.0, 30.0)]:
        c, f = _pit(x, 40.0, top, r, d, name=f"pit r{r:g} d{d:g}")
        cutters.append(c)
        feats.append(f)
    c, f = _pit(75.0, -5.0, top, 16.0, 35.0, tip=1.5, name="cone pit r16 d35")
    cutters.append(c)
    feats.append(f)
    # a slot (long narrow pit)
    cutters.append(Box((-55.0, -5.0, top), (30.0, 3.0, 20.0)))
    feats.append({"kind": "pit", "name": "slot w6 d20", "center": [-55.0, -5.0, top - 10.0],
                  "radius": 30.0, "axis": [0.0, 0.0, 1.0]})
    deep_rods, deep_feats = [], []
    if deep_pit:
        c, deep_rods, deep_feats = deep_pit_parts(top)
        cutters.append(c)
    parts = [Difference(body, tuple(cutters)), *deep_rods]
    # thin rods standing on the top face
    for i, r in enumerate([1.0, 2.0, 3.5, 6.0]):
        rod, f = _rod(-75.0 + 35.0 * i, -45.0, top, 55.0, r, name=f"rod r{r:g}")
        parts.append(rod)
        feats.append(f)
    # thin fins (plates) standing on the top face
    for i, th in enumerate([1.5, 4.0]):
        y = -20.0 + 20.0 * i
        parts.append(Box((35.0, y, top + 20.0), (18.0, th / 2, 21.0)))
        feats.append({"kind": "thin", "name": f"fin t{th:g}", "center": [35.0, y, top + 20.0],
                      "radius": 25.0, "axis": [0.0, 1.0, 0.0]})
    feats.extend(deep_feats)  # last: the other features keep their order
    deep = ("; a deep pit r 18 depth 36 with rods r 1.5/3/5 (28 tall) on its floor"
            if deep_pit else "")
    return BuiltinShape("pits-deep" if deep_pit else "pits-and-thin", Union(tuple(parts)),
                        feats, ((-102.0, -72.0, -27.0), (102.0, 72.0, 82.0)),
                        "slab 200x140x50 with 5 cylindrical pits (r 3..18, depth 12..40), a "
                        "cone pit, a slot, rods r 1/2/3.5/6 (55 tall) and fins 1.5/4 thick"
                        + deep)


#: The cup's cavity: radius and depth (as deep as it is wide), and the rods on its floor:
#: (x, y) offsets from the axis, radius, height.
CUP_CAVITY = (26.0, 52.0)
CUP_RODS = (((0.0, 13.0), 3.0, 36.0), ((-12.0, -7.0), 4.0, 36.0), ((12.0, -7.0), 6.0, 36.0))


def cup_shape() -> BuiltinShape:
    """A held-out object for the pits issue (#35; no setting was tuned on it): a thick-walled
    cup with a cavity as deep as it is wide, three thin rods standing on the cavity's floor
    below the rim, a thin handle (a torus) and four dimples on its side."""
    outer_r, height, base = 60.0, 90.0, -45.0
    top = base + height
    body = CappedCone((0.0, 0.0, base), (0.0, 0.0, top), outer_r, outer_r)
    r, depth = CUP_CAVITY
    cavity, feat = _pit(0.0, 0.0, top, r, depth, name=f"cavity r{r:g} d{depth:g}")
    feat["radius"] = float(np.hypot(r, depth / 2))
    feats = [feat, {"kind": "pit", "name": "cavity floor", "center": [0.0, 0.0, top - depth],
                    "radius": 7.0, "axis": [0.0, 0.0, 1.0]}]
    dimples = []
    for k, z in enumerate((-20.0, 10.0)):
        for ang in (0.5 * np.pi + 0.6 * k, 1.3 * np.pi - 0.4 * k):
            c = (outer_r * float(np.cos(ang)), outer_r * float(np.sin(ang)), z)
            dimples.append(Sphere(c, 9.0))
            feats.append({"kind": "pit", "name": f"dimple {len(dimples)}", "center": list(c),
                          "radius": 9.0, "axis": None})
    parts = [Difference(body, (cavity, *dimples))]
    for (dx, dy), rr, h in CUP_RODS:
        rod, f = _rod(dx, dy, top - depth, h, rr, name=f"cavity rod r{rr:g}")
        parts.append(rod)
        feats.append(f)
    handle = Torus((outer_r + 18.0, 0.0, 0.0), 1, 26.0, 5.0)
    parts.append(handle)
    feats.append({"kind": "thin", "name": "handle r5", "center": [outer_r + 24.0, 0.0, 0.0],
                  "radius": 27.0, "axis": None})
    return BuiltinShape("cup", Union(tuple(parts)), feats,
                        ((-62.0, -62.0, -47.0), (115.0, 62.0, 47.0)),
                        "cup r 60, 90 tall, with a cavity r 26 depth 52, rods r 3/4/6 (36 tall) "
                        "on its floor, a handle (torus tube r 5) and 4 dimples r 9")


#: The well's square shaft: half width and depth (deeper than wide), and the rods on its
#: floor: (x, y) offsets from the axis, radius, height.
WELL_SHAFT = (20.0, 50.0)
WELL_RODS = (((-9.0, 9.0), 2.0, 30.0), ((9.0, -9.0), 4.0, 30.0))


def well_shape() -> BuiltinShape:
    """A second held-out object for the pits issue (#35; added after the photometric term
    was tuned, no setting was chosen on it): a tall block with a square shaft deeper than
    it is wide, two thin rods standing on the shaft's floor, a thin slanted bar over the top
    (fixed at one end) and two narrow round pits."""
    half, top = 60.0, 45.0
    body = Box((0.0, 0.0, 0.0), (half, half, top), rounding=4.0)
    w, depth = WELL_SHAFT
    cx, cy = -15.0, -10.0
    floor = top - depth
    shaft = Box((cx, cy, floor + (depth + 10.0) / 2), (w, w, (depth + 10.0) / 2))
    feats = [{"kind": "pit", "name": f"shaft w{2 * w:g} d{depth:g}",
              "center": [cx, cy, top - depth / 2], "radius": float(np.hypot(w, depth / 2)),
              "axis": [0.0, 0.0, 1.0]},
             {"kind": "pit", "name": "shaft floor", "center": [cx, cy, floor], "radius": 6.0,
              "axis": [0.0, 0.0, 1.0]}]
    cutters = [shaft]
    for x, y, r, d in ((35.0, 35.0, 4.0, 20.0), (35.0, -30.0, 8.0, 16.0)):
        c, f = _pit(x, y, top, r, d, name=f"pit r{r:g} d{d:g}")
        f["radius"] = float(np.hypot(r, d / 2))  # the ball holds the wall, floor and rim
        cutters.append(c)
        feats.append(f)
    parts = [Difference(body, tuple(cutters))]
    for (dx, dy), rr, h in WELL_RODS:
        rod, f = _rod(cx + dx, cy + dy, floor, h, rr, name=f"shaft rod r{rr:g}")
        parts.append(rod)
        feats.append(f)
    bar = Capsule((-55.0, 45.0, top), (45.0, 45.0, top + 18.0), 3.0)
    parts.append(bar)
    feats.append({"kind": "thin", "name": "bar r3", "center": [-5.0, 45.0, top + 9.0],
                  "radius": 51.0, "axis": None})
    return BuiltinShape("well", Union(tuple(parts)), feats,
                        ((-62.0, -62.0, -47.0), (62.0, 62.0, 67.0)),
                        "block 120x120x90 with a square shaft 40 wide and 50 deep, rods r 2/4 "
                        "(30 tall) on its floor, a bar r 3 across the top, pits r 4 d 20 and "
                        "r 8 d 16")


BUILTIN_SHAPES: dict[str, Callable[[], BuiltinShape]] = {
    "demo": demo_shape,
    "pits-and-thin": pits_and_thin_shape,
    "pits-deep": functools.partial(pits_and_thin_shape, deep_pit=True),
    "cup": cup_shape,
    "well": well_shape,
}


def builtin_shape(name: str) -> BuiltinShape:
    """Return the built-in shape `name` (a key of `BUILTIN_SHAPES`)."""
    return BUILTIN_SHAPES[name]()


def sdf_gradient(sdf: SDF, x: Tensor, h: float = 1e-3) -> Tensor:
    """(N, 3) gradient of `sdf` at (N, 3) points `x` by tetrahedral differences (step h).

    Four evaluations; exact for linear functions, O(h^2) error otherwise.
    """
    k = torch.tensor([[1, -1, -1], [-1, -1, 1], [-1, 1, -1], [1, 1, 1]],
                     dtype=x.dtype, device=x.device)  # (4, 3)
    v = sdf((x[None] + h * k[:, None]).reshape(-1, 3)).reshape(4, -1)  # (4, N)
    return (k[:, None, :] * v[..., None]).sum(0) / (4 * h)


def project_to_surface(sdf: SDF, x: Tensor, iters: int = 8, h: float = 1e-4,
                       tol: float = 1e-10) -> Tensor:
    """Newton-project points onto the zero level set: x <- x - f(x) grad / |grad|^2.

    Points stop moving once |f| <= `tol`; the rest keep iterating (near creases of a CSG
    shape the convergence is only linear, so give those a few more steps).

    Args:
        sdf: the signed distance function.
        x: (N, 3) points near the surface (closer than the local feature size; use float64
            for exact results).
        iters: the most Newton steps per point.
        h: finite-difference step of the gradient.
        tol: convergence threshold on |sdf|.

    Returns:
        (N, 3) projected points.
    """
    x = x.clone()
    idx = torch.arange(x.shape[0], device=x.device)
    for _ in range(iters):
        f = sdf(x[idx])
        keep = f.abs() > tol
        idx, f = idx[keep], f[keep]
        if idx.numel() == 0:
            break
        g = sdf_gradient(sdf, x[idx], h)
        x[idx] = x[idx] - (f / (g * g).sum(-1).clamp_min(1e-12))[:, None] * g
    return x
