"""The mesh of a run folder: its trained networks, inside its visual hull, in world units.

The one path from a checkpoint to a mesh that `neus-l0 mesh`, the demo, the bench and the
tools share, so none of them can forget the hull or the run's ``scale_mat``.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import torch
import trimesh

from neus_l0.bounds.hull import load_run_hull
from neus_l0.config.schema import Config
from neus_l0.data.cameras import read_grays, read_masks, read_world_mats
from neus_l0.errors import NeusL0Error
from neus_l0.fields.model import NeuSModel
from neus_l0.mesh.extract import extract_mesh, progress_bars
from neus_l0.mesh.inset import inset
from neus_l0.mesh.mask_outliers import mask_outliers
from neus_l0.mesh.missed_parts import missed_solid, solid_model
from neus_l0.mesh.photo_carve import carve_solid, carved_model
from neus_l0.mesh.underside import cut_below, underside_line, underside_plane
from neus_l0.run.checkpoints import load_trained_model


@dataclasses.dataclass(frozen=True)
class MeshSteps:
    """The optional steps between the trained SDF and the mesh (all off by default).

    Attributes:
        close_underside: close the underside no training view sees flat, at the plane
            `neus_l0.mesh.underside.underside_plane` finds on a first mesh (then extracted
            again, cut there); reads the masks.
        drop_outside_masks: drop the connected pieces that a training view sees outside its
            mask (`neus_l0.mesh.mask_outliers`); reads the masks.
        inset: K >= 0: extract the level ``-K / s`` instead of 0 (`neus_l0.mesh.inset`).
        fill_missed: add the visual hull's points on the pixels a mask sees and the first
            mesh misses (`neus_l0.mesh.missed_parts`) as pieces of their own, after the
            other steps; reads the masks.
        photo_carve: carve the free space that a plane sweep of the training images finds
            behind the first mesh in its concavities (`neus_l0.mesh.photo_carve`: a pit's
            raised floor); reads the masks and the images.
    """

    close_underside: bool = False
    drop_outside_masks: bool = False
    inset: float = 0.0
    fill_missed: bool = False
    photo_carve: bool = False

    def __post_init__(self):
        if not 0 <= self.inset < float("inf"):
            raise NeusL0Error(f"--inset {self.inset}: must be a finite number >= 0")

    @property
    def needs_masks(self) -> bool:
        """Whether a step reads the run's scene and masks."""
        return (self.close_underside or self.drop_outside_masks or self.fill_missed
                or self.photo_carve)


@dataclasses.dataclass
class RunMesh:
    """A run's mesh and what it was made from.

    Attributes:
        mesh: world units; ``mesh.metadata["extraction"]`` has the extraction's numbers.
        model: the networks (eval mode), for colours and textures.
        cfg: the run's config.
        info: the checkpoint's light fields (``iteration``, ``scale_mat``, ``path``, ...).
    """

    mesh: trimesh.Trimesh
    model: NeuSModel
    cfg: Config
    info: dict

    @property
    def scale_mat(self) -> np.ndarray:
        """(4, 4) float64 normalised -> world of the run's scene."""
        return np.asarray(self.info["scale_mat"], dtype=np.float64)


def mesh_from_run(run_dir: str | Path, resolution: int, device: str | torch.device = "cpu",
                  checkpoint: str | Path | None = None, clean: bool = True,
                  method: str = "auto", progress: bool = False,
                  steps: MeshSteps = MeshSteps()) -> RunMesh:
    """Marching cubes of a run's SDF at `resolution`^3, restricted to the run's visual hull
    (``RUN/hull.pt``, when it has one).

    Args:
        run_dir: the run folder.
        resolution: grid cells per axis over the unit sphere's box.
        device: where the networks run.
        checkpoint: a specific checkpoint file; default the newest that loads.
        clean: drop floating specks (see `extract_mesh`).
        method: ``auto``, ``dense`` or ``sparse`` (see `extract_mesh`).
        progress: a tqdm bar on stderr while the SDF is evaluated (`progress_bars`).
        steps: the optional steps (`MeshSteps`); those that read masks need the run's
            scene with masks.

    Raises:
        NeusL0Error: no usable checkpoint, or no surface in the field; with a step that
            reads the masks (`MeshSteps.needs_masks`), the run's scene or a training view's
            mask missing (`training_views`); with `photo_carve`, a training view's image
            missing or unreadable (`training_grays`).
    """
    model, cfg, info = load_trained_model(run_dir, device, checkpoint)
    scale_mat = np.asarray(info["scale_mat"], dtype=np.float64)
    hull = load_run_hull(run_dir, device)
    views = training_views(run_dir) if steps.needs_masks else None
    field, delta = inset(model, steps.inset)
    with progress_bars(progress):
        mesh = extract_mesh(field, scale_mat, resolution=resolution, clean=clean,
                            device=device, method=method, hull=hull)
        plane = underside_plane(mesh, *views) if steps.close_underside else None
        solid, filled = None, None
        if steps.fill_missed:
            solid, filled = missed_solid(mesh, *views, scale_mat,
                                         None if hull is None else hull.contains, resolution)
        carved, carve_report = None, None
        if steps.photo_carve:
            carved, carve_report = carve_solid(mesh, *views, training_grays(run_dir),
                                               scale_mat, resolution)
        if carved is not None:
            field = carved_model(field, carved)
        if plane is not None:
            field = cut_below(field, *plane_to_normalised(plane, scale_mat))
        if plane is not None or carved is not None:
            mesh = extract_mesh(field, scale_mat, resolution=resolution, clean=clean,
                                device=device, method=method, hull=hull)
        parts = None
        if solid is not None:
            parts = solid_model(solid)
            if plane is not None:
                parts = cut_below(parts, *plane_to_normalised(plane, scale_mat))
            try:
                parts = extract_mesh(parts, scale_mat, resolution=resolution, clean=False,
                                     device=device, method=method)
            except NeusL0Error:  # nothing of it above the underside's plane
                parts = None
    meta = dict(mesh.metadata)
    if steps.inset:
        meta["inset"] = {"k": steps.inset, "level": -delta,
                         "world": delta * float(np.cbrt(abs(np.linalg.det(scale_mat[:3, :3]))))}
    if steps.close_underside:
        meta["underside_plane"] = (None if plane is None else
                                   {"up": plane[0].tolist(), "height": plane[1]})
    if steps.fill_missed:
        meta["filled_missed"] = filled
    if steps.photo_carve:
        meta["photo_carved"] = carve_report
    if steps.drop_outside_masks:
        mesh, meta["dropped_outside_masks"] = mask_outliers(mesh, *views)
    if parts is not None and len(parts.faces):  # after the drop: a part merges with nothing
        mesh = trimesh.util.concatenate([mesh, parts])
    mesh.metadata.update(meta)
    return RunMesh(mesh, model, cfg, info)


def run_scene(run_dir: str | Path) -> tuple[Path, list[int] | None]:
    """The run's scene folder and its training views (``run.json``; None: every view).

    Raises:
        NeusL0Error: no readable ``run.json``.
    """
    record = Path(run_dir) / "run.json"
    try:
        run = json.loads(record.read_text())
        return Path(run["scene"]), (run.get("views") or {}).get("train")
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise NeusL0Error(f"{record}: cannot read the run's scene, which the masks come "
                          f"from ({e})") from None


def training_views(run_dir: str | Path) -> tuple[np.ndarray, list[np.ndarray]]:
    """The run's training views (``run.json``: its scene and ``views.train``): their (V, 3, 4)
    projections world -> pixel and V (H, W) bool masks.

    Raises:
        NeusL0Error: no ``run.json``, its scene is gone or lacks a training view's mask.
    """
    scene, train = run_scene(run_dir)
    projections = read_world_mats(scene)
    masks = read_masks(scene)
    train = train or list(range(len(projections)))
    if not (isinstance(train, list)
            and all(isinstance(v, int) and 0 <= v < len(projections) for v in train)):
        raise NeusL0Error(f"{Path(run_dir) / 'run.json'}: views.train must list view indices "
                          f"below {len(projections)} (the scene's cameras), got "
                          f"{str(train)[:80]}")
    missing = [v for v in train if v not in masks]
    if missing:
        raise NeusL0Error(f"{scene / 'mask'}: no mask for training view(s) {missing[:5]}; "
                          "--close-underside, --drop-outside-masks, --fill-missed and "
                          "--photo-carve need the masks")
    return projections[train], [masks[v] for v in train]


def training_grays(run_dir: str | Path) -> np.ndarray:
    """(V, H, W) float32 grey images of the run's training views (as `training_views`).

    Raises:
        NeusL0Error: an image missing, unreadable, or of another size than the masks.
    """
    scene, train = run_scene(run_dir)
    grays = read_grays(scene)
    train = train or sorted(grays)
    missing = [v for v in train if v not in grays]
    if missing:
        raise NeusL0Error(f"{scene / 'image'}: no image for training view(s) {missing[:5]}; "
                          "--photo-carve needs the images")
    shapes = {grays[v].shape for v in train}
    if len(shapes) > 1:
        raise NeusL0Error(f"{scene / 'image'}: images of different sizes {sorted(shapes)}")
    return np.stack([grays[v] for v in train])


def plane_to_normalised(plane: tuple[np.ndarray, float], scale_mat: np.ndarray
                        ) -> tuple[np.ndarray, float]:
    """A plane ``up . x >= height`` from world units to the normalised frame of `scale_mat`
    (4, 4) normalised -> world (NeuS's: a uniform scale s and a shift t; world x = s n + t,
    so ``up . n >= (height - up . t) / s``)."""
    up, height = plane
    s, t = scale_mat[0, 0], scale_mat[:3, 3]
    if not np.allclose(scale_mat[:3, :3], s * np.eye(3)):
        raise NeusL0Error("--close-underside: the scene's scale_mat is not a uniform scale "
                          "and shift")
    return up, float((height - up @ t) / s)


def steps_report(metadata: dict) -> list[str]:
    """What the optional steps did (`mesh_from_run`'s ``metadata``), a line each: the level
    extracted, the underside's plane (`underside_line`) and the pieces dropped outside the
    masks."""
    lines = []
    if "inset" in metadata:
        ins = metadata["inset"]
        lines.append(f"inset: level {ins['level']:.5f} (-{ins['k']:g}/s), "
                     f"{ins['world']:.3f} world units inside the zero level")
    if "underside_plane" in metadata:
        lines.append(underside_line(metadata["underside_plane"]))
    if "filled_missed" in metadata:
        f = metadata["filled_missed"]
        lines.append(f"missed parts: {f['missed_pixels']} missed mask pixels, "
                     + ("nothing filled" if not f["points"] else
                        f"{f['points']} grid points filled in {f['pieces']} piece(s) "
                        f"(grid {f['grid']}^3)"))
    if "photo_carved" in metadata:
        c = metadata["photo_carved"]
        lines.append(f"photo carve: {c['swept']} pixels swept in concavities, {c['cells']} "
                     f"cells whose sweeps agree, {c['carving']} rays found free space behind "
                     "the mesh, "
                     + ("nothing carved" if not c["points"] else
                        f"{c['points']} grid points carved (grid {c['grid']}^3)"))
    if "dropped_outside_masks" in metadata:
        dropped = metadata["dropped_outside_masks"]
        lines.append("outside the masks: nothing dropped" if not dropped else
                     f"outside the masks: dropped {len(dropped)} piece(s), "
                     + ", ".join(f"{d['faces']} faces {d['diagonal']:.1f} across "
                                 f"(outside in {d['views']} views)" for d in dropped))
    return lines
