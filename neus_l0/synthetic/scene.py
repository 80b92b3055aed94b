"""Synthetic NeuS-format scenes with exact ground truth (`make_scene`).

Pipeline: shape (analytic SDF or mesh) placed in a DTU-like world frame (millimetres, the
object about 250 across, centred away from the origin) -> ground-truth mesh (marching cubes
of the SDF with every vertex Newton-projected onto the analytic surface; for mesh input the
mesh itself) -> bounding sphere with a 10 % margin (``scale_mat``, as NeuS's preprocessing
does) -> camera cap (elevation `ELEVATION_DEG`, 20-70 degrees: views from above; distance
3.9-4.4 sphere radii, like DTU's 4.1) -> renders (textured, shaded, anti-aliased, textured
backdrop), masks, depth maps -> ground-truth points (dense surface samples, exact, kept
where some camera sees them).

Folder layout: see "A synthetic scene folder" in ``docs/ARCHITECTURE.md``.

The whole scene is written into a hidden temporary folder next to the output
(``.NAME.XXXXXXXX.tmp``) and swapped in at the end (the old folder is renamed away, the new
one renamed in, then the old one removed), so an interrupted run leaves the previous scene
whole and a re-run with fewer views leaves no stale images. A folder that holds anything
other than the files this tool wrote into it is never replaced: ``scene.json`` lists them
(``files``; a scene from before that list is held to the layout's names, ``image/NNN.png``
and so on), and any other file (a ``image/retouched_000.psd``) is named and kept. An
exception (Ctrl-C included) removes the temporary folder; a killed process leaves it behind.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import secrets
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from neus_l0.atomic import atomic_write, atomic_write_json, atomic_write_png
from neus_l0.data.cameras import (
    cap_centres,
    intrinsics_to_fit,
    look_at,
    pixel_indices,
    projection_matrix,
    sphere_scale_mat,
)
from neus_l0.errors import NeusL0Error
from neus_l0.synthetic.raycast import SdfSurface, Style, render_views
from neus_l0.synthetic.shapes import (
    BUILTIN_SHAPES,
    BuiltinShape,
    Translated,
    builtin_shape,
    project_to_surface,
)

if TYPE_CHECKING:
    import trimesh

    from neus_l0.synthetic.meshes import MeshSurface

#: Where built-in objects sit in the world frame (millimetres; deliberately off-origin).
WORLD_OFFSET = (12.0, -8.0, 30.0)
#: Bounding-sphere margin of ``scale_mat`` (radius = margin x the object's radius).
SPHERE_MARGIN = 1.1
#: Camera distance range in sphere radii (DTU: about 4.1).
DISTANCE_RANGE = (3.9, 4.4)
#: Elevation range of the camera cap, degrees above the horizontal (views from above).
ELEVATION_DEG = (20.0, 70.0)
#: Azimuth range of the camera cap, degrees (360: all around the object).
AZIMUTH_SPAN = 360.0
#: Default marching-cubes voxel (world units) of the ground-truth mesh, per built-in.
GT_VOXEL = {"demo": 1.5, "pits-and-thin": 0.8, "pits-deep": 0.8}
#: Rays per render batch (bounded memory; several views share one batch).
RAYS_PER_BATCH = 2_500_000
#: Peak bytes per ray of a render batch: the measured peak with a margin
#: (docs/benchmarks/demo-and-configs.md, "Numbers moved from code comments").
BYTES_PER_RAY = 256
#: Memory of a scene besides the render batch and the depth maps (ground truth, torch).
FIXED_BYTES = 256 * 2**20
#: What a synthetic scene folder holds; a folder holding anything else is never replaced.
SCENE_ENTRIES = frozenset({"image", "mask", "cameras_sphere.npz", "gt_depth.npz",
                           "gt_mesh.ply", "gt_points.ply", "features.json", "scene.json"})
#: Seeds are drawn from [0, MAX_SEED] (numpy and torch generators both take them).
MAX_SEED = 2**32 - 1
#: A mesh thinner than this fraction of its size is flat (no inside to reconstruct).
FLAT_RATIO = 1e-6


def _marching_cubes_sdf(sdf, lo: np.ndarray, hi: np.ndarray, voxel: float):
    """Marching cubes of `sdf` on a grid over [lo, hi] with spacing `voxel`.

    Returns:
        vertices (V, 3) float64 world, faces (F, 3) int64 (outward normals).
    """
    from skimage.measure import marching_cubes

    lo = lo - 2 * voxel
    hi = hi + 2 * voxel
    n = np.ceil((hi - lo) / voxel).astype(int) + 1
    axes = [torch.linspace(float(lo[i]), float(lo[i] + voxel * (n[i] - 1)), int(n[i]))
            for i in range(3)]
    vals = np.empty(tuple(n), np.float32)
    gy, gz = torch.meshgrid(axes[1], axes[2], indexing="ij")
    yz = torch.stack([gy.flatten(), gz.flatten()], -1)  # (ny*nz, 2)
    with torch.no_grad():
        for i, x in enumerate(axes[0]):  # one x-slab per call: bounded memory
            pts = torch.cat([x.expand(yz.shape[0], 1), yz], -1)
            vals[i] = sdf(pts).reshape(int(n[1]), int(n[2])).numpy()
    verts, faces, _, _ = marching_cubes(vals, level=0.0, spacing=(voxel,) * 3)
    return verts.astype(np.float64) + lo, faces[:, ::-1].astype(np.int64)


def _exact_surface_points(sdf, pts: np.ndarray, iters: int) -> np.ndarray:
    """Newton-project (N, 3) world points onto the analytic surface, in float64."""
    out = []
    with torch.no_grad():
        for chunk in torch.from_numpy(pts).split(1 << 18):
            out.append(project_to_surface(sdf, chunk.double(), iters=iters).numpy())
    return np.concatenate(out) if out else pts


def _load_mesh(path: Path):
    """Load a mesh file (OBJ/PLY/GLB/...) as one trimesh.Trimesh, y-up turned to z-up.

    Raises:
        NeusL0Error: an unreadable file, or a mesh no scene can be made of (no faces,
            non-finite vertices, faces naming missing vertices, `_check_solid`).
    """
    import trimesh

    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # noqa: BLE001 - any loader failure is the user's file
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise NeusL0Error(f"{path}: cannot read mesh ({msg})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise NeusL0Error(f"{path}: no triangles found")
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    bad = int((~np.isfinite(v).all(1)).sum())
    if bad:
        raise NeusL0Error(f"{path}: {bad} of {len(v)} vertices have NaN or infinite "
                          "coordinates")
    if f.min() < 0 or f.max() >= len(v):
        raise NeusL0Error(f"{path}: faces refer to vertices that do not exist (index "
                          f"{int(f.max() if f.max() >= len(v) else f.min())}, {len(v)} "
                          "vertices)")
    mesh = trimesh.Trimesh(v, f, process=True)
    _check_solid(path, mesh)
    # scanned models (the Stanford bunny, glTF) are y-up; this package's worlds are z-up
    rot = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])
    mesh.apply_transform(rot)
    return mesh


def _check_solid(path: Path, mesh) -> None:
    """Refuse a mesh with no extent, no area or no thickness (one line naming the file)."""
    v = np.asarray(mesh.vertices)
    size = float(np.ptp(v, axis=0).max())
    if size == 0.0:
        raise NeusL0Error(f"{path}: all vertices are the same point (the mesh has no size)")
    if not mesh.area > 0.0:
        raise NeusL0Error(f"{path}: every triangle is degenerate (zero surface area)")
    thickness = np.linalg.svd(v - v.mean(0), compute_uv=False)
    if thickness[2] <= FLAT_RATIO * thickness[0]:
        raise NeusL0Error(f"{path}: all {len(v)} vertices lie in one plane ({len(mesh.faces)} "
                          "triangle(s)): a flat mesh has no inside to reconstruct; give a "
                          "solid object")


def _visible(points: np.ndarray, world_mats: np.ndarray, depths: np.ndarray,
             K: np.ndarray) -> np.ndarray:
    """(N,) bool: seen by at least one view (in the image, not behind its depth map).

    The tolerance is 2 pixel footprints (depth / focal) + 0.1 % of the depth, since the
    depth map is sampled at pixel centres only.
    """
    H, W = depths.shape[1:]
    seen = np.zeros(len(points), bool)
    f = K[0, 0]
    for P, D in zip(world_mats, depths, strict=True):
        col, row, z = pixel_indices(P, points, H, W)
        idx = np.nonzero((col >= 0) & ~seen)[0]
        d = D[row[idx], col[idx]]
        seen[idx] = z[idx] <= d + 2.0 * z[idx] / f + 1e-3 * z[idx]
    return seen


def write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray | None = None) -> None:
    """Write a binary little-endian PLY with float64 vertices (and int32 triangles), atomically.

    Float64 keeps the ground truth exact (float32 would round 100 mm coordinates by ~1e-5).
    """
    v = np.ascontiguousarray(vertices, dtype="<f8")
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(v)}",
              "property double x", "property double y", "property double z"]
    body = v.tobytes()
    if faces is not None:
        f = np.asarray(faces, dtype="<i4")
        header += [f"element face {len(f)}", "property list uchar int vertex_indices"]
        rec = np.empty(len(f), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
        rec["n"], rec["idx"] = 3, f
        body += rec.tobytes()
    data = ("\n".join(header + ["end_header"]) + "\n").encode("ascii") + body
    atomic_write(path, lambda p: p.write_bytes(data))


def _write_png(path: Path, rgb: np.ndarray) -> None:
    """(H, W, 3) float RGB in [0, 1] as an 8-bit PNG, atomically."""
    img = np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)
    atomic_write_png(path, np.ascontiguousarray(img[..., ::-1]))


def _resolve(scene: str):
    """(name, BuiltinShape | None, trimesh | None) for a built-in name or a mesh path."""
    if scene in BUILTIN_SHAPES:
        shape = builtin_shape(scene)
        return scene, shape, None
    path = Path(scene)
    if not path.is_file():
        raise NeusL0Error(f"{scene}: neither a built-in scene ({', '.join(BUILTIN_SHAPES)}) "
                          f"nor a mesh file")
    return path.stem, None, _load_mesh(path)


@contextlib.contextmanager
def _torch_threads(n: int | None):
    """Run the block with `n` torch CPU threads (None: leave as is), then restore."""
    before = torch.get_num_threads()
    if n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _save_npz(path: Path, arrays: dict, compressed: bool) -> None:
    """Write arrays to an .npz file and close it before the atomic rename."""
    with open(path, "wb") as f:
        (np.savez_compressed if compressed else np.savez)(f, **arrays)


def make_scene(scene: str, out: str | Path, views: int = 49, width: int = 400,
               height: int = 300, seed: int = 0, *, spp: int = 2,
               gt_voxel: float | None = None, point_spacing: float = 0.5,
               progress: bool = True) -> Path:
    """Render a synthetic NeuS-format scene with exact ground truth into `out`.

    Args:
        scene: a built-in name (``demo``, ``pits-and-thin``, ``pits-deep``) or a mesh
            file path.
        out: output folder: new, empty, or a synthetic scene, which is replaced whole
            (written into a temporary folder next to it and swapped in at the end).
        views, width, height: number of cameras and image size.
        seed: seed of the camera jitter and the texture.
        spp: anti-aliasing sub-samples per pixel axis (spp^2 per pixel).
        gt_voxel: marching-cubes voxel of the ground-truth mesh (world units; default per
            built-in). Ignored for mesh input.
        point_spacing: about how far apart the ground-truth points are (world units).
        progress: show a tqdm bar while rendering.
    Returns:
        The output folder.

    Raises:
        NeusL0Error: out-of-range numbers (`check_scene_args`), an unknown scene, a mesh
            file no scene can be made of, or an `out` that must not be replaced.
    """
    with _torch_threads(1):  # many small tensor ops: more threads wait on each other
        return _make_scene(scene, out, views, width, height, seed, spp, gt_voxel,
                           point_spacing, progress)


@dataclasses.dataclass
class _TrueSurface:
    """The true surface of a scene in world units.

    Attributes:
        name: scene name; made: how it was made (for scene.json).
        mesh: the ground-truth mesh; surface: what the renderer intersects.
        sdf: the analytic SDF (None for a mesh file); voxel: its marching-cubes voxel.
        features: features.json entries (world units).
    """

    name: str
    made: str
    mesh: trimesh.Trimesh
    surface: SdfSurface | MeshSurface
    sdf: Translated | None
    voxel: float | None
    features: list[dict]


def _true_surface(scene: str | Path, gt_voxel: float | None) -> _TrueSurface:
    """The built-in shape or the mesh file `scene`, placed at `WORLD_OFFSET` in world units."""
    import trimesh

    name, shape, mesh = _resolve(scene)
    offset = np.array(WORLD_OFFSET)
    if shape is not None:
        sdf = Translated(shape.sdf, tuple(offset))
        lo, hi = np.array(shape.bounds[0]) + offset, np.array(shape.bounds[1]) + offset
        voxel = gt_voxel or GT_VOXEL.get(name, 1.0)
        verts, faces = _marching_cubes_sdf(sdf, lo, hi, voxel)
        verts = _exact_surface_points(sdf, verts, iters=12)
        features = [dict(f, center=[float(c) for c in np.add(f["center"], offset)])
                    for f in shape.features]
        return _TrueSurface(name, f"built-in analytic SDF '{name}': {shape.description}",
                            trimesh.Trimesh(verts, faces, process=False),
                            SdfSurface(sdf, tuple(lo - 1.0), tuple(hi + 1.0)), sdf, voxel,
                            features)
    from neus_l0.synthetic.meshes import MeshSurface

    ext = mesh.bounds[1] - mesh.bounds[0]
    k = 250.0 / float(ext.max())  # about 250 mm across, like the built-ins
    mesh.apply_transform(trimesh.transformations.scale_matrix(k))
    mesh.apply_translation(offset - mesh.bounds.mean(0))
    made = f"mesh file {scene} scaled by {k:.6g} (y-up turned z-up), centred at {offset}"
    return _TrueSurface(name, made, mesh,
                        MeshSurface(np.asarray(mesh.vertices), np.asarray(mesh.faces)),
                        None, None, [])


def check_scene_args(views: int, width: int, height: int, spp: int, seed: int = 0) -> None:
    """Refuse out-of-range numbers of `neus-l0 synth` (one line naming the flag).

    Raises:
        NeusL0Error: views < 1, width or height < 8, spp < 1, or a seed outside
            [0, MAX_SEED].
    """
    for flag, value, least in (("--views", views, 1), ("--width", width, 8),
                               ("--height", height, 8), ("--spp", spp, 1)):
        if value < least:
            raise NeusL0Error(f"{flag} {value}: must be >= {least}")
    if not 0 <= seed <= MAX_SEED:
        raise NeusL0Error(f"--seed {seed}: must be in [0, {MAX_SEED}]")


def _views_per_batch(width: int, height: int, spp: int) -> int:
    """Views rendered together: as many as fit in `RAYS_PER_BATCH` rays (at least one)."""
    return max(1, RAYS_PER_BATCH // ((spp * spp + 1) * width * height))


def render_bytes(views: int, width: int, height: int, spp: int) -> int:
    """Estimated peak host memory of `make_scene`: the depth maps of every view, one render
    batch (`BYTES_PER_RAY` a ray, spp^2 + 1 rays a pixel) and `FIXED_BYTES`."""
    batch = min(views, _views_per_batch(width, height, spp))
    rays = batch * (spp * spp + 1) * width * height
    return int(FIXED_BYTES + 4 * views * width * height + BYTES_PER_RAY * rays)


def check_render_memory(views: int, width: int, height: int, spp: int,
                        available: int | None) -> None:
    """Refuse a scene whose rendering would not fit in `available` bytes (None: no check).

    Raises:
        NeusL0Error: one line with the flags, the estimate and the memory available.
    """
    need = render_bytes(views, width, height, spp)
    if available is None or need <= available:
        return
    raise NeusL0Error(f"--views {views} --width {width} --height {height} --spp {spp}: "
                      f"rendering needs about {_gib(need)} of memory, {_gib(available)} is "
                      "available; use fewer views, smaller images or a smaller --spp")


def _gib(n: float) -> str:
    """Bytes as GiB, or TiB where large."""
    return f"{n / 2**40:.3g} TiB" if n >= 2**40 else f"{n / 2**30:.3g} GiB"


def _replaceable(out: Path) -> Path:
    """The folder to (re)write for `out` (a link's target); refuses what must not go.

    Raises:
        NeusL0Error: `out` is a file, the current folder (or holds it), or a folder that
            is not empty and not a synthetic scene (replacing it would delete its files).
    """
    target = Path(os.path.realpath(out))
    if target.exists() and not target.is_dir():
        raise NeusL0Error(f"{out}: exists and is not a folder")
    if not target.is_dir():
        return target
    cwd = Path.cwd().resolve()
    if target == cwd or target in cwd.parents:
        raise NeusL0Error(f"{out}: is the current folder or holds it; give another folder")
    names = sorted(p.name for p in target.iterdir())
    if names and "scene.json" not in names:
        raise NeusL0Error(f"{out}: not empty and not a synthetic scene (no scene.json); give "
                          "a new or empty folder")
    strangers = _not_written_here(target) if names else []
    if strangers:
        raise NeusL0Error(f"{out}: holds {strangers[0]}, which this tool did not write; "
                          "replacing the scene would delete it (move it away or give another "
                          "folder)")
    return target


#: A scene file of the layout (for scenes whose scene.json lists no ``files``).
_LAYOUT_FILE = re.compile(r"^(?:(?:image|mask)/\d{3,}\.png|[^/]+)$")


def _ignorable(name: str) -> bool:
    """Temporaries of killed writers and Finder's litter (never the user's work)."""
    return (name.startswith(".") and ".tmp" in name) or name == ".DS_Store"


def scene_files(folder: Path) -> list[str]:
    """Every file under `folder`, as sorted POSIX paths relative to it (what a manifest
    lists)."""
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                  if not p.is_dir() and not _ignorable(p.name))


def _not_written_here(target: Path) -> list[str]:
    """The files under a synthetic scene `target` that its ``scene.json`` does not list
    (or, without a list, that the layout does not name), sorted."""
    try:
        listed = json.loads((target / "scene.json").read_text(encoding="utf-8")).get("files")
    except (OSError, ValueError, AttributeError):
        listed = None
    files = scene_files(target)
    if isinstance(listed, list):
        own = {str(f) for f in listed} | {"scene.json"}
        strangers = [f for f in files if f not in own]
    else:
        strangers = [f for f in files
                     if not (_LAYOUT_FILE.match(f) and f.split("/")[0] in SCENE_ENTRIES)]
    folders = sorted(p.relative_to(target).as_posix() for p in target.rglob("*") if p.is_dir())
    return sorted(strangers + [d for d in folders if d not in ("image", "mask")])


def _sibling(target: Path, kind: str) -> Path:
    """A new hidden name next to `target`: ``.NAME.XXXXXXXX.<kind>``."""
    while True:
        path = target.with_name(f".{target.name}.{secrets.token_hex(4)}.{kind}")
        if not path.exists():
            return path


@contextlib.contextmanager
def _staged_folder(target: Path):
    """Yield a fresh temporary folder next to `target`; on success swap it in for `target`.

    The old `target` is renamed away, the new folder renamed in, then the old one removed
    (put back if the second rename fails). The temporary folder never outlives the block.
    """
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = _sibling(target, "tmp")
    tmp.mkdir()
    try:
        yield tmp
        if not target.exists():
            os.rename(tmp, target)
            return
        old = _sibling(target, "old")
        os.rename(target, old)
        try:
            os.rename(tmp, target)
        except BaseException:
            os.rename(old, target)
            raise
        shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


@dataclasses.dataclass
class _Rig:
    """The cameras of a scene: the object's sphere (centre, radius, scale_mat), the camera
    distance range, intrinsics K (3, 3) and per view c2w / world_mats (V, 4, 4)."""

    centre: np.ndarray
    radius: float
    scale_mat: np.ndarray
    dist: tuple[float, float]
    K: np.ndarray
    c2w: np.ndarray
    world_mats: np.ndarray


def _camera_rig(verts: np.ndarray, views: int, width: int, height: int, seed: int,
                azimuth_span: float) -> _Rig:
    """The DTU-like camera cap around the (V, 3) ground-truth vertices."""
    centre = 0.5 * (verts.min(0) + verts.max(0))
    radius = SPHERE_MARGIN * float(np.linalg.norm(verts - centre, axis=1).max())
    dist = (DISTANCE_RANGE[0] * radius, DISTANCE_RANGE[1] * radius)
    eyes = cap_centres(views, centre, dist, ELEVATION_DEG, azimuth_span_deg=azimuth_span,
                       seed=seed)
    K = intrinsics_to_fit(width, height, radius, dist[0], fill=1.0)
    w2c = np.stack([look_at(e, centre) for e in eyes])
    return _Rig(centre, radius, sphere_scale_mat(centre, radius), dist, K, np.linalg.inv(w2c),
                np.stack([projection_matrix(K, m) for m in w2c]))


def _render_into(folder: Path, truth: _TrueSurface, rig: _Rig, size: tuple[int, int],
                 spp: int, seed: int, progress: bool) -> np.ndarray:
    """Render every view, writing image/NNN.png and mask/NNN.png into `folder` batch by
    batch; returns the depth maps (V, H, W) float32 (camera z, ``inf`` on misses)."""
    from tqdm import tqdm

    width, height = size
    views = len(rig.c2w)
    style = Style(scale=rig.radius, center=tuple(rig.centre),
                  backdrop_radius=8.0 * rig.dist[1], seed=seed)
    per_batch = _views_per_batch(width, height, spp)
    depth = np.empty((views, height, width), np.float32)
    Ks = np.repeat(rig.K[None], views, axis=0)
    for sub in ("image", "mask"):
        (folder / sub).mkdir()
    with torch.no_grad(), tqdm(total=views, desc=f"render {truth.name}", unit="view",
                               disable=not progress) as bar:
        for v0 in range(0, views, per_batch):
            sl = slice(v0, min(views, v0 + per_batch))
            r = render_views(truth.surface, style, Ks[sl], rig.c2w[sl], height, width, spp)
            depth[sl] = r["depth"]
            for k, i in enumerate(range(sl.start, sl.stop)):
                _write_png(folder / "image" / f"{i:03d}.png", r["rgb"][k])
                m = (r["coverage"][k] >= 0.5).astype(np.float32)
                _write_png(folder / "mask" / f"{i:03d}.png", np.repeat(m[..., None], 3, -1))
            bar.update(sl.stop - sl.start)
    return depth


def _gt_points(truth: _TrueSurface, rig: _Rig, depth: np.ndarray, spacing: float,
               seed: int) -> np.ndarray:
    """Exact surface points about `spacing` apart that some camera sees: (N, 3) float64."""
    import trimesh

    n_pts = int(np.ceil(truth.mesh.area / spacing ** 2))
    pts, _ = trimesh.sample.sample_surface(truth.mesh, n_pts, seed=seed)
    pts = np.asarray(pts, np.float64)
    if truth.sdf is not None:
        pts = _exact_surface_points(truth.sdf, pts, iters=12)
    return pts[_visible(pts, rig.world_mats, depth, rig.K)]


def _make_scene(scene, out, views, width, height, seed, spp, gt_voxel, point_spacing,
                progress) -> Path:
    check_scene_args(views, width, height, spp, seed)
    t_start = time.time()
    target = _replaceable(Path(out))
    truth = _true_surface(scene, gt_voxel)
    gt_mesh = truth.mesh
    rig = _camera_rig(np.asarray(gt_mesh.vertices), views, width, height, seed, AZIMUTH_SPAN)
    with _staged_folder(target) as tmp:
        depth = _render_into(tmp, truth, rig, (width, height), spp, seed, progress)
        pts = _gt_points(truth, rig, depth, point_spacing, seed)
        if len(pts) == 0:
            raise NeusL0Error(f"{scene}: no camera sees any ground-truth point")
        cams = {}
        for i in range(views):
            cams[f"world_mat_{i}"] = rig.world_mats[i]
            cams[f"scale_mat_{i}"] = rig.scale_mat
        depths = {f"depth_{i}": depth[i] for i in range(views)}
        atomic_write(tmp / "cameras_sphere.npz", lambda p: _save_npz(p, cams, compressed=False))
        atomic_write(tmp / "gt_depth.npz", lambda p: _save_npz(p, depths, compressed=True))
        write_ply(tmp / "gt_mesh.ply", np.asarray(gt_mesh.vertices), np.asarray(gt_mesh.faces))
        write_ply(tmp / "gt_points.ply", pts)
        atomic_write_json(tmp / "features.json", {"features": truth.features})
        atomic_write_json(tmp / "scene.json", {
            "name": truth.name, "seed": seed, "views": views, "width": width,
            "height": height, "spp": spp, "source": str(scene), "made_by": truth.made,
            "world_units": "millimetres (DTU-like)",
            "sphere": {"center": rig.centre.tolist(), "radius": rig.radius,
                       "margin": SPHERE_MARGIN},
            "cameras": {"elevation_deg": list(ELEVATION_DEG), "azimuth_span_deg": AZIMUTH_SPAN,
                        "distance": list(rig.dist), "focal": float(rig.K[0, 0]),
                        "intrinsics": rig.K.tolist(), "c2w_world": rig.c2w.tolist()},
            "gt_points": {"count": int(len(pts)), "spacing": point_spacing},
            "gt_mesh": {"vertices": int(len(gt_mesh.vertices)),
                        "faces": int(len(gt_mesh.faces)), "voxel": truth.voxel},
            "seconds": round(time.time() - t_start, 2),
            "files": [*scene_files(tmp), "scene.json"],
        })
    return Path(out)


def builtin_names() -> list[str]:
    """Names of the built-in scenes."""
    return list(BUILTIN_SHAPES)


def scene_world_sdf(scene_dir: str | Path) -> tuple[Translated, str]:
    """(the exact SDF in world units, the shape's name) of a scene that `neus-l0 synth` made
    from a built-in analytic shape (its ``scene.json``'s ``source``).

    Raises:
        NeusL0Error: naming ``scene.json`` when it is missing, unreadable or names no
            built-in shape (a mesh file has no analytic SDF).
    """
    path = Path(scene_dir) / "scene.json"
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise NeusL0Error(f"{path}: not a scene made by `neus-l0 synth` ({exc})") from exc
    name = info.get("source") if isinstance(info, dict) else None
    if name not in BUILTIN_SHAPES:
        raise NeusL0Error(f"{path}: source {name!r} is not a built-in analytic shape "
                          f"({', '.join(sorted(BUILTIN_SHAPES))})")
    return Translated(builtin_shape(name).sdf, WORLD_OFFSET), name


__all__ = ["make_scene", "builtin_names", "BuiltinShape", "check_scene_args", "check_render_memory",
           "render_bytes", "scene_world_sdf"]
