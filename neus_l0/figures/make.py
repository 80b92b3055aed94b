"""All figures of one bench scene: meshes (shaded and by error, overview and crops), the
weights along a ray into a pit, and `index.md`."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from neus_l0.errors import NeusL0Error
from neus_l0.figures.runs import BenchRun

if TYPE_CHECKING:
    import trimesh

    from neus_l0.figures.render import SurfaceDistance
    from neus_l0.figures.views import Camera


@dataclasses.dataclass
class FigureEntry:
    """One figure for the index: file name, what it shows, the runs it came from."""

    file: str
    shows: str
    runs: list[str]


def load_mesh(path: Path) -> trimesh.Trimesh:
    """A mesh file as one trimesh, unprocessed (NeusL0Error: unreadable or without faces)."""
    import trimesh

    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # noqa: BLE001 - any reader failure is a bad file
        raise NeusL0Error(f"{path}: unreadable mesh ({exc})") from exc
    if len(mesh.faces) == 0:
        raise NeusL0Error(f"{path}: mesh has no faces")
    return mesh


def _percentile_vmax(errors: list[np.ndarray], q: float = 95.0) -> float:
    """Top of the shared error colour scale: the q-th percentile of all error pixels,
    rounded up to 2 significant digits."""
    vals = np.concatenate([e[np.isfinite(e)].ravel() for e in errors] + [np.zeros(1)])
    v = float(np.percentile(vals, q)) if vals.size > 1 else 1.0
    if v <= 0:
        return 1.0
    mag = 10 ** np.floor(np.log10(v) - 1)
    return float(np.ceil(v / mag) * mag)


def _content_origin(renders: dict, pad: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """Column and row ranges holding every seen pixel of the renders, plus `pad` pixels."""
    seen = np.zeros_like(next(iter(renders.values()))["shade"], dtype=bool)
    for r in renders.values():
        seen |= np.isfinite(r["shade"])
    h, w = seen.shape
    if not seen.any():
        return (0, w), (0, h)
    cols, rows = np.flatnonzero(seen.any(0)), np.flatnonzero(seen.any(1))
    return ((max(0, cols[0] - pad), min(w, cols[-1] + pad + 1)),
            (max(0, rows[0] - pad), min(h, rows[-1] + pad + 1)))


def _stats(err: np.ndarray) -> str:
    e = err[np.isfinite(err)]
    if e.size == 0:
        return "nothing seen"
    return f"mean {e.mean():.2f}, p90 {np.percentile(e, 90):.2f}"


@dataclasses.dataclass
class FigureInputs:
    """What every figure of one scene needs, loaded once.

    Attributes:
        scene_dir: the synthetic scene; runs: {sampler: finished run}.
        features: features.json entries (world units); cams: the scene's cameras.
        gt: the true mesh; preds: {sampler: predicted mesh}.
        distance: distances to the true surface (colours the errors).
        what: "scene ..., budget ..., seed ..." for the titles.
    """

    scene_dir: Path
    runs: dict[str, BenchRun]
    features: list[dict]
    cams: list[Camera]
    gt: trimesh.Trimesh
    preds: dict[str, trimesh.Trimesh]
    distance: SurfaceDistance
    what: str

    @property
    def names(self) -> list[str]:
        """The samplers, in the order of `runs`."""
        return list(self.runs)

    @property
    def run_names(self) -> list[str]:
        """The run folders' names (for the index)."""
        return [r.run_dir.name for r in self.runs.values()]


@dataclasses.dataclass
class Overview:
    """The overview renders: camera `view`, {"ground truth" | sampler: render} cropped to
    what is seen, and the features' (name, kind, box (4,)) in the cropped pixels."""

    view: int
    renders: dict
    boxes: list


def describe_runs(runs: dict[str, BenchRun]) -> str:
    """"scene ..., budget ... s, seed ..." of runs that share them (for the titles)."""
    any_run = next(iter(runs.values()))
    return f"scene '{any_run.scene}', budget {any_run.budget_s:g} s, seed {any_run.seed}"


def load_inputs(scene_dir: Path, runs: dict[str, BenchRun], log=print) -> FigureInputs:
    """Read the scene's features, cameras and true mesh and every run's mesh.

    Raises:
        NeusL0Error: a missing or unreadable file, or a scene without cameras.
    """
    from neus_l0.evaluation.features import load_features
    from neus_l0.figures.render import SurfaceDistance
    from neus_l0.figures.views import scene_cameras

    features = load_features(scene_dir)
    cams = scene_cameras(scene_dir)
    if not cams:
        raise NeusL0Error(f"{scene_dir / 'cameras_sphere.npz'}: no cameras")
    gt = load_mesh(scene_dir / "gt_mesh.ply")
    preds = {s: load_mesh(r.mesh) for s, r in runs.items()}
    what = describe_runs(runs)
    inputs = FigureInputs(scene_dir, runs, features, cams, gt, preds, SurfaceDistance(gt), what)
    log(f"figures: {what}; runs {', '.join(inputs.run_names)}")
    return inputs


def render_overview(inp: FigureInputs, width: int, log=print) -> Overview:
    """Every mesh from the scene camera that sees the features best, `width` pixels wide,
    cropped to the part where something is seen."""
    from neus_l0.figures.render import render_mesh
    from neus_l0.figures.views import overview_camera

    view = overview_camera(inp.cams, inp.features)
    cam = inp.cams[view].scaled(width / inp.cams[view].width)
    log(f"  rendering the overview from camera {view} ({cam.width}x{cam.height})")
    over = {"ground truth": render_mesh(inp.gt, cam)}
    for s in inp.names:
        over[s] = render_mesh(inp.preds[s], cam, inp.distance)
    return Overview(view, over, crop_to_content(over, cam, inp.features))


def crop_to_content(renders: dict, cam: Camera, features: list[dict], pad: int = 12) -> list:
    """Crop every render of `renders` ({panel: {image name: (H, W) array}}, in place) to the
    part where something is seen, plus `pad` pixels.

    Returns:
        the features' (name, kind, box (4,)) in the cropped pixels, for `overview_figure`.
    """
    from neus_l0.figures.views import crop_box

    x0, y0 = _content_origin(renders, pad)
    for r in renders.values():
        for k in list(r):
            r[k] = r[k][y0[0]:y0[1], x0[0]:x0[1]]
    return [(f["name"], f["kind"], crop_box(cam, f["center"], f["radius"]) - [x0[0], y0[0]] * 2)
            for f in features]


def render_crops(inp: FigureInputs, view: int, size: int, log=print) -> list[tuple[dict, dict]]:
    """Every mesh clipped to a ball of 2.5 radii around each feature, from a virtual camera
    per feature (`size` x `size` pixels).

    Returns:
        [(feature, {"ground truth" | sampler: render})] in features.json order.
    """
    from neus_l0.figures.render import clip_to_ball, render_mesh
    from neus_l0.figures.views import feature_camera

    crops = []
    for f in inp.features:
        fcam = feature_camera(f, inp.cams[view], size)
        ball = 2.5 * f["radius"]
        r = {"ground truth": render_mesh(clip_to_ball(inp.gt, f["center"], ball), fcam)}
        for s in inp.names:
            r[s] = render_mesh(clip_to_ball(inp.preds[s], f["center"], ball), fcam, inp.distance)
        crops.append((f, r))
    log(f"  rendered {len(crops)} feature crops")
    return crops


def overview_figures(out: Path, inp: FigureInputs, ov: Overview,
                     vmax: float) -> list[FigureEntry]:
    """overview_shaded.png and overview_error.png (errors on the scale 0 to `vmax`)."""
    from neus_l0.figures.compose import overview_figure
    from neus_l0.figures.render import error_rgb, shaded_rgb

    names, over, view, what = inp.names, ov.renders, ov.view, inp.what
    cols = ["ground truth"] + names
    overview_figure(out / "overview_shaded.png",
                    [(c, shaded_rgb(over[c]["shade"])) for c in cols], ov.boxes,
                    f"Meshes from scene camera {view} ({what}); boxes: the features' crops")
    overview_figure(out / "overview_error.png",
                    [("ground truth", shaded_rgb(over["ground truth"]["shade"]))]
                    + [(f"{s}: {_stats(over[s]['error'])}",
                        error_rgb(over[s]["error"], over[s]["shade"], vmax)) for s in names],
                    ov.boxes, f"Distance to the true surface, camera {view} ({what})", vmax)
    return [FigureEntry("overview_shaded.png",
                        f"ground truth and the {', '.join(names)} meshes from scene "
                        f"camera {view}, shaded, with numbered boxes on the features "
                        "(red: pits, blue: thin parts)", inp.run_names),
            FigureEntry("overview_error.png",
                        "the same view coloured by the distance of each visible point "
                        f"of the predicted mesh to the true surface (shared scale 0 to "
                        f"{vmax:g} world units; titles: mean and 90th percentile)",
                        inp.run_names)]


def crop_figures(out: Path, inp: FigureInputs, crops: list[tuple[dict, dict]],
                 vmax: float) -> list[FigureEntry]:
    """pits_* and thin_* PNGs (shaded, and by error on the scale 0 to `vmax`), for the
    kinds of feature the scene has."""
    from neus_l0.figures.compose import crops_figure
    from neus_l0.figures.render import error_rgb, shaded_rgb

    names, what, entries = inp.names, inp.what, []
    cols = ["ground truth"] + names
    for kind, word in (("pit", "pits"), ("thin", "thin structures")):
        sel = [(f, r) for f, r in crops if f["kind"] == kind]
        if not sel:
            continue
        stem = "pits" if kind == "pit" else "thin"
        rows = [(f["name"], [shaded_rgb(r[c]["shade"]) for c in cols], [""] * len(cols))
                for f, r in sel]
        crops_figure(out / f"{stem}_shaded.png", cols, rows,
                     f"Zoom on the {word}: virtual camera per feature ({what})")
        entries.append(FigureEntry(f"{stem}_shaded.png",
                                   f"zoomed, shaded renders of each of the {word} (one row "
                                   "each; a virtual camera per feature, "
                                   + ("looking into the pit 25° off its axis"
                                      if kind == "pit" else "looking across the part")
                                   + "; the mesh clipped to a ball of 2.5 feature radii)",
                                   inp.run_names))
        rows = [(f["name"], [shaded_rgb(r["ground truth"]["shade"])]
                 + [error_rgb(r[s]["error"], r[s]["shade"], vmax) for s in names],
                 [""] + [_stats(r[s]["error"]) for s in names]) for f, r in sel]
        crops_figure(out / f"{stem}_error.png", ["ground truth"] + [f"{s} error" for s in names],
                     rows, f"Zoom on the {word}: distance to the true surface ({what})", vmax)
        entries.append(FigureEntry(f"{stem}_error.png",
                                   f"the same crops coloured by the distance to the true surface "
                                   f"(shared scale 0 to {vmax:g} world units; captions: mean "
                                   "and 90th percentile over the crop)", inp.run_names))
    return entries


def make_figures(scene_dir: Path, runs: dict[str, BenchRun], out: Path,
                 overview_width: int = 480, crop_size: int = 192,
                 error_max: float | None = None, pit: str | None = None,
                 log=print) -> list[FigureEntry]:
    """Write every figure into `out` and return the index entries.

    Args:
        scene_dir: the synthetic scene (gt_mesh.ply, features.json, gt_depth.npz, cameras).
        runs: {sampler: finished run} (all on the same scene, budget and seed).
        out: output folder (created).
        overview_width: width of the overview renders in pixels.
        crop_size: side of the square zoomed crops in pixels.
        error_max: top of the error colour scale (world units); default: the 95th
            percentile of all error pixels, shared by all samplers.
        pit: name of the pit for the ray figure (default: the one seen deepest).
        log: progress printer.
    """
    out.mkdir(parents=True, exist_ok=True)
    inp = load_inputs(scene_dir, runs, log)
    # ---- renders: the overview and a crop per feature, one shared error scale
    ov = render_overview(inp, overview_width, log)
    crops = render_crops(inp, ov.view, crop_size, log)
    vmax = error_max or _percentile_vmax([ov.renders[s]["error"] for s in inp.names]
                                         + [r[s]["error"] for _, r in crops for s in inp.names])
    # ---- mesh figures
    entries = overview_figures(out, inp, ov, vmax) + crop_figures(out, inp, crops, vmax)
    log(f"  wrote the mesh figures (error scale 0-{vmax:g})")
    # ---- weights along a ray into a pit
    entries.extend(ray_figure(out, inp, pit, log))
    return entries


def ray_figure(out: Path, inp: FigureInputs, pit: str | None = None,
               log=print) -> list[FigureEntry]:
    """ray_weights.png: each run's first up-sampling round along a camera ray into the pit
    `pit` (default: the pit whose bottom a camera sees deepest); nothing without pits."""
    from neus_l0.data.cameras import camera_file
    from neus_l0.figures.ray_weights import find_pit_ray, plot_ray_weights, ray_profile
    from neus_l0.run.checkpoints import load_trained_model

    runs, what = inp.runs, inp.what
    if not any(f["kind"] == "pit" for f in inp.features) and pit is None:
        log("  no pit in features.json: no ray figure")
        return []
    ray = find_pit_ray(inp.scene_dir, inp.features, inp.cams, pit)
    profiles = []
    for s, run in runs.items():
        model, cfg, info = load_trained_model(run.run_dir)
        scale_mat = info.get("scale_mat")
        if scale_mat is None:  # a checkpoint without it: the scene's own
            scale_mat = np.load(camera_file(inp.scene_dir))["scale_mat_0"]
        scale_mat = np.asarray(scale_mat, dtype=np.float64)
        profiles.append((f"{s} run (iteration {info.get('iteration', '?')})", run.sampler,
                         ray_profile(model, cfg, ray.origin, ray.direction, scale_mat,
                                     run.sampler)))
    x, y = (int(v) for v in ray.xy)
    plot_ray_weights(out / "ray_weights.png", ray, profiles,
                     f"First up-sampling round along the ray of camera {ray.view}, pixel "
                     f"({x}, {y}), into '{ray.feature['name']}' ({what})")
    log(f"  wrote the ray figure (camera {ray.view}, pixel ({x}, {y}), "
        f"{ray.feature['name']})")
    return [FigureEntry("ray_weights.png",
                        f"along the ray of camera {ray.view}, pixel ({x}, {y}), which hits the "
                        f"bottom of '{ray.feature['name']}' ({ray.below_centre:.1f} world units "
                        "below the pit centre, per gt_depth): each trained model's coarse "
                        "section weights (first up-sampling round, inv_s = 64), the HVS "
                        "piecewise-constant PDF and the L0 piecewise-exponential density after "
                        "maxblur on them, where the first-round fine samples of each sampler "
                        "land, the run's own fine samples over all rounds, the true surface "
                        "depth and the model's SDF zero crossing; left the whole ray, right a "
                        "zoom at the surface",
                        [r.run_dir.name for r in runs.values()])]


def write_index(out: Path, entries: list[FigureEntry], bench: Path | list[Path],
                runs: dict[str, BenchRun], scene_dir: Path, command: str) -> Path:
    """`out/index.md`: the command, the runs, and one section per figure."""
    from neus_l0.atomic import atomic_write_text

    folders = ", ".join(f"`{b}`" for b in (bench if isinstance(bench, list) else [bench]))
    lines = ["# Figures", "", f"Made by `{command}` from the bench folder(s) {folders}.", "",
             f"Scene: `{scene_dir}`.", "", "| arm | run | mesh | accuracy | completeness "
             "| overall | train s | iterations |", "|---|---|---|---|---|---|---|---|"]
    for s, r in runs.items():
        row = r.row
        lines.append(f"| {s} | `{r.run_dir}` | `{r.mesh}` | {row.get('accuracy', '')} | "
                     f"{row.get('completeness', '')} | {row.get('overall', '')} | "
                     f"{row.get('train_seconds', '')} | {row.get('iterations', '')} |")
    lines.append("")
    for e in entries:
        lines += [f"## [{e.file}]({e.file})", "", f"![{e.file}]({e.file})", "",
                  e.shows[0].upper() + e.shows[1:] + ".", "",
                  "Runs: " + ", ".join(f"`{n}`" for n in e.runs) + ".", ""]
    return atomic_write_text(out / "index.md", "\n".join(lines))
