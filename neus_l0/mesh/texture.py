"""Textured meshes: a UV atlas (xatlas), a texture baked from a colour function, OBJ + MTL + PNG.

Texel convention. The texture is an (H, W) image whose row 0 is the *top*; OBJ's ``vt``
coordinates have v pointing *up*. Texel (row r, column c) is centred at
``u = (c + 0.5) / W``, ``v = 1 - (r + 0.5) / H``, and belongs to the triangle of the atlas
that contains that point (barycentric coordinates all >= -`EDGE_EPS`); its colour is the
colour function at the 3-D point with the same barycentric coordinates on the mesh
triangle. Texels that no triangle covers (the gutter between charts) take the colour of
the nearest covered texel up to `dilate` texels away, so bilinear filtering and mip-maps do
not bleed the background into the charts' borders.

`neus-l0 mesh RUN --texture --out m.obj` bakes the colour network with the view direction
looking along the inward normal (``view = -normal``), as `neus_l0.mesh.extract.vertex_colors`
does for vertex colours (`network_colors`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np

from neus_l0.atomic import atomic_path, atomic_write_text
from neus_l0.errors import NeusL0Error

ColorFn = Callable[[np.ndarray], np.ndarray]
"""Maps (P, 3) points to (P, 3) RGB, float in [0, 1] or uint8."""

EDGE_EPS = 1e-6
"""Barycentric tolerance: a texel centre on a shared atlas edge belongs to a triangle."""


@dataclasses.dataclass
class TexturedMesh:
    """A mesh with one UV per face corner and its texture.

    Attributes:
        vertices: (V, 3) float64 positions (any frame).
        faces: (F, 3) int64 indices into `vertices`.
        uvs: (T, 2) float32 texture coordinates in [0, 1], v up.
        face_uvs: (F, 3) int64 indices into `uvs`, corner by corner with `faces`.
        image: (H, W, 3) uint8 RGB texture, row 0 at the top.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    face_uvs: np.ndarray
    image: np.ndarray


def parametrize(vertices: np.ndarray, faces: np.ndarray,
                size: int = 1024, padding: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                             tuple[int, int]]:
    """A UV atlas of the mesh with xatlas, packed into one texture of about `size` texels a side.

    Args:
        vertices: (V, 3) positions.
        faces: (F, 3) indices.
        size: the texture's target side in texels (xatlas picks the texel density to
            match it; the packed atlas comes out close to it).
        padding: texels of gutter between charts.

    Returns:
        vmapping (T,) int64 (the input vertex of each atlas vertex), face_uvs (F, 3) int64
        (indices into the atlas vertices), uvs (T, 2) float32 in [0, 1] (v up), and the
        atlas's (height, width) in texels.

    Raises:
        NeusL0Error: an empty mesh, or xatlas packed more than one atlas.
    """
    import xatlas

    if len(faces) == 0:
        raise NeusL0Error("texture: the mesh has no faces")
    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(vertices, np.float32),
                   np.ascontiguousarray(faces, np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = int(size)
    pack.padding = int(padding)
    pack.bilinear = True
    atlas.generate(pack_options=pack)
    if atlas.atlas_count != 1:
        raise NeusL0Error(f"texture: xatlas packed {atlas.atlas_count} atlases for size {size}; "
                          "use a larger --texture-size")
    vmapping, indices, uvs = atlas[0]
    return (vmapping.astype(np.int64), indices.astype(np.int64), uvs.astype(np.float32),
            (int(atlas.height), int(atlas.width)))


def rasterize_atlas(uvs: np.ndarray, face_uvs: np.ndarray, height: int, width: int,
                    chunk: int = 2**20) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which triangle covers each texel centre, and where: vectorised over triangles and texels.

    Each triangle's candidate texels are those of its bounding box in texel space; all
    (triangle, texel) pairs of a batch of triangles are formed at once (at most about
    `chunk` pairs per batch) and the barycentric coordinates of the texel centre decide.
    A texel covered by several triangles (on a shared edge) keeps the last one.

    Args:
        uvs: (T, 2) atlas coordinates in [0, 1], v up.
        face_uvs: (F, 3) indices into `uvs`.
        height, width: the texture's size in texels.
        chunk: the most (triangle, texel) pairs held at once.

    Returns:
        texels (K,) int64 flat indices ``row * width + col`` (row 0 at the top), faces (K,)
        int64 the covering triangle, and bary (K, 3) float64 barycentric coordinates of the
        texel centre in that triangle (corner order of `face_uvs`).
    """
    H, W = int(height), int(width)
    p = uvs.astype(np.float64) * [W, H] - 0.5  # (T, 2) texel-centre units: (col, row from bottom)
    tri = p[face_uvs]  # (F, 3, 2)
    lo = np.clip(np.ceil(tri.min(1) - EDGE_EPS), 0, [W - 1, H - 1]).astype(np.int64)  # (F, 2)
    hi = np.clip(np.floor(tri.max(1) + EDGE_EPS), -1, [W - 1, H - 1]).astype(np.int64)
    ext = np.maximum(hi - lo + 1, 0)  # (F, 2) columns, rows of each bounding box
    counts = ext[:, 0] * ext[:, 1]  # (F,)
    # corner 0 and the inverse of the 2x2 edge matrix, per triangle
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]  # (F, 2)
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]  # (F,)
    ok = np.abs(det) > 1e-12
    counts = np.where(ok, counts, 0)
    out_t, out_f, out_b = [], [], []
    ends = np.cumsum(counts)
    start = 0
    while start < len(counts):
        # the largest batch of triangles whose pairs fit in `chunk` (at least one)
        stop = int(np.searchsorted(ends, (ends[start - 1] if start else 0) + chunk, "right"))
        stop = max(stop, start + 1)
        f = np.repeat(np.arange(start, stop), counts[start:stop])  # (P,)
        if len(f):
            first = np.repeat(ends[start:stop] - counts[start:stop], counts[start:stop])
            k = np.arange(len(f)) + (ends[start - 1] if start else 0) - first  # rank in box
            col = lo[f, 0] + k % ext[f, 0]
            row_b = lo[f, 1] + k // ext[f, 0]  # row counted from the bottom
            d = np.stack([col, row_b], -1) - tri[f, 0]  # (P, 2)
            b1 = (d[:, 0] * e2[f, 1] - d[:, 1] * e2[f, 0]) / det[f]
            b2 = (e1[f, 0] * d[:, 1] - e1[f, 1] * d[:, 0]) / det[f]
            b0 = 1.0 - b1 - b2
            inside = (b0 >= -EDGE_EPS) & (b1 >= -EDGE_EPS) & (b2 >= -EDGE_EPS)
            out_t.append(((H - 1 - row_b) * W + col)[inside])
            out_f.append(f[inside])
            out_b.append(np.stack([b0, b1, b2], -1)[inside])
        start = stop
    if not out_t:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))
    texels, tfaces, bary = np.concatenate(out_t), np.concatenate(out_f), np.concatenate(out_b)
    # one triangle per texel: the last one listed
    _, last = np.unique(texels[::-1], return_index=True)
    keep = len(texels) - 1 - last
    return texels[keep], tfaces[keep], np.clip(bary[keep], 0.0, 1.0)


def dilate_texture(image: np.ndarray, covered: np.ndarray, texels: int) -> np.ndarray:
    """Copy the nearest covered texel's colour into uncovered texels up to `texels` away.

    Args:
        image: (H, W, C) texture.
        covered: (H, W) bool, texels that a triangle covers.
        texels: the most distance (Euclidean, in texels) to fill.

    Returns:
        the (H, W, C) texture with the gutter near charts filled (farther texels unchanged).
    """
    if texels <= 0 or covered.all() or not covered.any():
        return image
    from scipy import ndimage

    dist, (iy, ix) = ndimage.distance_transform_edt(~covered, return_indices=True)
    fill = (~covered) & (dist <= texels)
    out = image.copy()
    out[fill] = image[iy[fill], ix[fill]]
    return out


def bake_texture(vertices: np.ndarray, faces: np.ndarray, color_fn: ColorFn, size: int = 1024,
                 padding: int = 2, dilate: int = 4, background: int = 0,
                 chunk: int = 2**16) -> TexturedMesh:
    """Parametrize a mesh and bake `color_fn` into its texture.

    Args:
        vertices: (V, 3) points where `color_fn` is evaluated (e.g. the normalised frame).
        faces: (F, 3) indices.
        color_fn: (P, 3) points -> (P, 3) RGB in [0, 1] (float) or uint8.
        size: about how many texels a side (see `parametrize`).
        padding: gutter texels between charts.
        dilate: texels the charts' colours are grown into the gutter.
        background: grey level (0..255) of texels no chart reaches.
        chunk: points per call of `color_fn`.

    Returns:
        the `TexturedMesh` (its `vertices` are the input vertices, not split at seams).
    """
    vmapping, face_uvs, uvs, (H, W) = parametrize(vertices, faces, size, padding)
    texels, tfaces, bary = rasterize_atlas(uvs, face_uvs, H, W)
    corners = vertices[vmapping[face_uvs[tfaces]]]  # (K, 3, 3)
    points = np.einsum("kc,kcd->kd", bary, corners)  # (K, 3)
    rgb = np.concatenate([_as_uint8(color_fn(points[i:i + chunk]))
                          for i in range(0, len(points), chunk)] or [np.zeros((0, 3), np.uint8)])
    image = np.full((H * W, 3), background, np.uint8)
    image[texels] = rgb
    covered = np.zeros(H * W, bool)
    covered[texels] = True
    image = dilate_texture(image.reshape(H, W, 3), covered.reshape(H, W), dilate)
    faces_v = vmapping[face_uvs]  # (F, 3) input vertex indices, same corners as face_uvs
    return TexturedMesh(np.asarray(vertices, np.float64), faces_v, uvs, face_uvs, image)


def _as_uint8(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb)[:, :3]
    if rgb.dtype == np.uint8:
        return rgb
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def network_colors(model, device="cpu") -> ColorFn:
    """The colour network as a `ColorFn` on normalised-frame points, view = -normal."""
    from neus_l0.mesh.extract import vertex_colors

    def fn(points: np.ndarray) -> np.ndarray:
        return vertex_colors(model, points, device)[:, :3]

    return fn


def _fmt_rows(prefix: str, rows: np.ndarray, fmt: str) -> str:
    if len(rows) == 0:
        return ""
    return "\n".join(prefix + fmt % tuple(r) for r in rows) + "\n"


def write_textured_obj(mesh: TexturedMesh, path: str | Path) -> list[Path]:
    """Write ``NAME.obj``, ``NAME.mtl`` and ``NAME.png`` next to each other, each atomically.

    The texture and the material are written first and the OBJ last, so an OBJ on disk
    always finds its material and texture.

    Returns:
        the three paths (obj, mtl, png).

    Raises:
        NeusL0Error: `path` does not end in ``.obj``.
    """
    import cv2

    path = Path(path)
    if path.suffix.lower() != ".obj":
        raise NeusL0Error(f"{path}: a textured mesh is written as .obj (with .mtl and .png)")
    mtl, png = path.with_suffix(".mtl"), path.with_suffix(".png")
    with atomic_path(png) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(mesh.image, cv2.COLOR_RGB2BGR)):
            raise NeusL0Error(f"{png}: cannot write the texture")
    atomic_write_text(mtl, f"newmtl material_0\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\n"
                           f"map_Kd {png.name}\n")
    corners = np.stack([mesh.faces + 1, mesh.face_uvs + 1], -1).reshape(-1, 6)  # 1-based
    text = (f"# neus-l0 textured mesh\nmtllib {mtl.name}\n"
            + _fmt_rows("v ", mesh.vertices, "%.7g %.7g %.7g")
            + _fmt_rows("vt ", mesh.uvs, "%.7g %.7g")
            + "usemtl material_0\n"
            + _fmt_rows("f ", corners, "%d/%d %d/%d %d/%d"))
    atomic_write_text(path, text)
    return [path, mtl, png]
