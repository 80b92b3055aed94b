"""`neus-l0 figures`: a tiny fake bench folder, the figures it makes, and the pieces."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch
import trimesh

from neus_l0.cli import main
from neus_l0.errors import NeusL0Error

COLUMNS = ["scene", "sampler", "budget_s", "seed", "status", "error", "train_seconds",
           "iterations", "its_per_s", "accuracy", "completeness", "overall", "psnr_heldout",
           "peak_mem_mb", "sample_dist_final", "run_dir", "mesh"]


def _write_results(root, rows):
    with open(root / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in COLUMNS})


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """A bench folder: the demo scene (6 views, 80x60) and two runs of 2 iterations each."""
    from neus_l0.config.load import load_config
    from neus_l0.formats.neus import load_scene
    from neus_l0.mesh.extract import export_mesh, extract_mesh
    from neus_l0.run.checkpoints import load_trained_model
    from neus_l0.synthetic.scene import make_scene
    from neus_l0.train.loop import train

    root = tmp_path_factory.mktemp("bench")
    scene_dir = root / "scenes" / "demo"
    make_scene("demo", scene_dir, views=6, width=80, height=60, seed=0, progress=False)
    scene = load_scene(scene_dir)
    rows = []
    for sampler in ("hvs", "l0"):
        name = f"demo__{sampler}__10s__seed0"
        run_dir = root / "runs" / name
        # the hull at 64 cells a side, not 128 (its carving was a third of this fixture)
        cfg = load_config("demo", [f"sampler={sampler}", "train.iters=2", "train.val_every=0",
                                   "train.save_every=0", "train.log_every=1",
                                   "render.hull.resolution=64"])
        train(scene, cfg, run_dir, progress=False)
        model, _, info = load_trained_model(run_dir)
        mesh = extract_mesh(model, np.asarray(info["scale_mat"]), resolution=32, clean=True)
        export_mesh(mesh, run_dir / "mesh.ply")
        rows.append({"scene": "demo", "sampler": sampler, "budget_s": 10, "seed": 0,
                     "status": "done", "iterations": 2, "run_dir": f"runs/{name}",
                     "mesh": f"runs/{name}/mesh.ply"})
    rows.append({"scene": "demo", "sampler": "l0", "budget_s": 20, "seed": 0, "status": "failed"})
    _write_results(root, rows)
    return root


def _png(path):
    import matplotlib.image

    assert path.is_file() and path.stat().st_size > 0, path
    return matplotlib.image.imread(path)[..., :3]


def test_figures_command_writes_readable_pngs_and_index(bench, tmp_path, capsys):
    out = tmp_path / "fig"
    rc = main(["figures", "--bench", str(bench), "--out", str(out), "--width", "160",
               "--crop", "64"])
    assert rc == 0, capsys.readouterr().err
    expected = ["overview_shaded.png", "overview_error.png", "pits_shaded.png",
                "pits_error.png", "thin_shaded.png", "thin_error.png", "ray_weights.png"]
    from neus_l0.figures.compose import DPI

    for name in expected:
        img = _png(out / name)
        h, w = img.shape[:2]
        assert w >= 300 and h >= 200, (name, img.shape)
        assert img.std() > 0.05, name  # not a blank page
    # the ray figure: 13 x (3.4 * 2 runs + 1.3) inches
    assert _png(out / "ray_weights.png").shape[:2] == (int(8.1 * DPI), 13 * DPI)
    # error pictures are coloured, shaded ones grey
    err, shaded = _png(out / "overview_error.png"), _png(out / "pits_shaded.png")
    assert (np.ptp(err, axis=-1) > 0.3).mean() > 0.01
    assert (np.ptp(shaded, axis=-1) > 0.3).mean() < (np.ptp(err, axis=-1) > 0.3).mean()
    index = (out / "index.md").read_text()
    for name in expected:
        assert f"]({name})" in index
    assert "demo__hvs__10s__seed0" in index and "demo__l0__10s__seed0" in index


def test_missing_bench_folder_is_a_one_line_error(tmp_path, capsys):
    rc = main(["figures", "--bench", str(tmp_path / "nope"), "--out", str(tmp_path / "f")])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert "no such bench folder" in err and len(err.splitlines()) == 1


def test_sampler_without_finished_runs_is_an_error(bench, tmp_path, capsys):
    from neus_l0.figures.runs import select_runs

    with pytest.raises(NeusL0Error, match="l0-linear"):
        select_runs(bench, ["hvs", "l0-linear"])
    with pytest.raises(NeusL0Error, match="budget 20"):  # l0 failed at 20 s
        select_runs(bench, ["hvs", "l0"], budget=20)
    rc = main(["figures", "--bench", str(bench), "--out", str(tmp_path / "f"),
               "--samplers", "hvs,l0-inverse"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "no finished run of sampler 'l0-inverse'" in err
    assert len(err.splitlines()) == 1


def test_select_runs_defaults_and_paths(bench):
    from neus_l0.figures.runs import select_runs

    scene_dir, runs = select_runs(bench, ["hvs", "l0"])
    assert scene_dir == bench / "scenes" / "demo"
    assert {r.budget_s for r in runs.values()} == {10.0}
    assert runs["l0"].mesh == bench / "runs" / "demo__l0__10s__seed0" / "mesh.ply"


def test_raster_render_depth_agrees_with_gt_depth(bench):
    from neus_l0.figures.raster import raster_render
    from neus_l0.figures.views import scene_cameras

    scene_dir = bench / "scenes" / "demo"
    cam = scene_cameras(scene_dir)[0]
    gt = trimesh.load(scene_dir / "gt_mesh.ply", force="mesh")
    r = raster_render(gt, cam.P, cam.width, cam.height)
    ref = np.load(scene_dir / "gt_depth.npz")["depth_0"]
    both = np.isfinite(ref) & np.isfinite(r["depth"])
    assert both.sum() > 0.9 * np.isfinite(ref).sum()
    assert np.median(np.abs(r["depth"][both] - ref[both])) < 0.05
    assert np.array_equal(np.isnan(r["shade"]), ~np.isfinite(r["depth"]))


def test_crop_box_spans_the_projected_feature():
    from neus_l0.figures.views import Camera, crop_box

    K = np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])
    cam = Camera(np.c_[K, K @ np.array([0.0, 0, 50])], 80, 60)
    box = crop_box(cam, np.array([1.0, -2.0, 0.0]), 3.0, margin=1.0)
    assert np.allclose(box[2] - box[0], 2 * 3.0 * 100 / 50)  # 2 radii at depth 50
    # centred on the feature's projection: (40 + 100 * 1 / 50, 30 - 100 * 2 / 50)
    assert np.allclose(0.5 * (box[:2] + box[2:]), [42.0, 26.0])


def test_exp_interpolation_is_a_density_through_the_nodes():
    from neus_l0.figures.ray_weights import exp_interpolation

    t = torch.tensor([0.0, 0.5, 0.7, 1.5, 2.0], dtype=torch.float64)
    w = torch.tensor([0.01, 0.3, 2.0, 2.0, 0.05], dtype=torch.float64)
    x, pdf = exp_interpolation(t, w, per_interval=2001)
    n = 2001
    mass = sum(np.trapezoid(pdf.numpy()[i * n:(i + 1) * n], x.numpy()[i * n:(i + 1) * n])
               for i in range(4))
    assert mass == pytest.approx(1.0, rel=1e-6)
    scale = pdf[0] / w[0]
    assert torch.allclose(pdf[::2001], w[:-1] * scale)  # the curve passes through the nodes


def test_surface_distance_is_exact_near_and_close_far():
    from neus_l0.figures.render import SurfaceDistance

    sphere = trimesh.creation.icosphere(subdivisions=5, radius=10.0)
    dist = SurfaceDistance(sphere, exact_within=1.0)
    dirs = np.random.default_rng(0).normal(size=(200, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    near = dist(dirs * 10.5)
    far = dist(dirs * 15.0)
    assert np.allclose(near, 0.5, atol=0.02)
    assert np.allclose(far, 5.0, atol=0.1)
    assert np.isnan(dist(np.full((2, 3), np.nan))).all()


def test_pit_ray_hits_the_true_surface_inside_the_pit(bench):
    from neus_l0.evaluation.features import load_features
    from neus_l0.figures.ray_weights import find_pit_ray
    from neus_l0.figures.render import SurfaceDistance
    from neus_l0.figures.views import scene_cameras

    scene_dir = bench / "scenes" / "demo"
    feats = load_features(scene_dir)
    ray = find_pit_ray(scene_dir, feats, scene_cameras(scene_dir))
    assert ray.feature["kind"] == "pit"
    hit = ray.origin + ray.t_surface * ray.direction
    gt = trimesh.load(scene_dir / "gt_mesh.ply", force="mesh")
    assert SurfaceDistance(gt)(hit[None])[0] < 0.5
    assert ray.below_centre > 0
    assert np.linalg.norm(hit - ray.feature["center"]) <= 1.5 * ray.feature["radius"]
    info = json.loads((scene_dir / "features.json").read_text())
    assert ray.feature["name"] in {f["name"] for f in info["features"]}


def test_section_pieces_curve_gives_each_section_its_weight():
    """The plotted L0 density of the default draw: mass 1, each section its weight's share."""
    from neus_l0.figures.ray_weights import section_pieces_curve
    from neus_l0.sampling.kernels import l0_section_pieces

    z = torch.tensor([[0.0, 0.4, 0.5, 0.9, 1.0]], dtype=torch.float64)
    w = torch.tensor([[0.1, 0.5, 0.3, 0.1]], dtype=torch.float64)
    x, pdf = section_pieces_curve(*l0_section_pieces(z, w), per_piece=4001)
    x, pdf = x.reshape(8, -1), pdf.reshape(8, -1)  # two pieces per section
    piece = (0.5 * (pdf[:, 1:] + pdf[:, :-1]) * (x[:, 1:] - x[:, :-1])).sum(-1)
    torch.testing.assert_close(piece.reshape(4, 2).sum(-1), w[0] / w.sum(), atol=1e-6, rtol=0)


def test_two_bench_folders_side_by_side(bench, tmp_path, capsys):
    """`--bench OFF,ON --samplers l0`: the arms of a paired comparison in one figure, titled
    by folder; the ray figure still draws each run's own sampler."""
    import shutil

    on = tmp_path / "ON"
    shutil.copytree(bench, on)
    out = tmp_path / "fig"
    rc = main(["figures", "--bench", f"{bench},{on}", "--samplers", "l0", "--out", str(out),
               "--width", "160", "--crop", "64"])
    assert rc == 0, capsys.readouterr().err
    index = (out / "index.md").read_text()
    assert f"| {bench.name} l0 |" in index and "| ON l0 |" in index
    assert f"`{bench}`" in index and f"`{on}`" in index
    for name in ("overview_error.png", "pits_error.png", "ray_weights.png"):
        assert _png(out / name).std() > 0.05, name
    same = tmp_path / "x" / bench.name
    shutil.copytree(bench, same)
    rc = main(["figures", "--bench", f"{bench},{same}", "--samplers", "l0",
               "--out", str(tmp_path / "fig2")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "share a name" in err and len(err.splitlines()) == 1
