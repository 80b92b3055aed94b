"""`neus-l0 figures` on a scene without ground truth: the places where the meshes differ most,
and the command on a bench folder whose scene has only cameras, images and masks."""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest
import trimesh

from neus_l0.cli import main

BUMP = np.array([0.0, 0.6, 0.8])  # unit direction of the bump on the unit sphere
HEIGHT = 0.3  # how far the bump's top stands out


def _bumped(mesh: trimesh.Trimesh, where: np.ndarray, height: float,
            width: float) -> trimesh.Trimesh:
    """`mesh` with the vertices near `where` pushed out along their normals (a Gaussian bump
    of `height`, standard deviation `width`)."""
    v = np.asarray(mesh.vertices, np.float64)
    d = np.linalg.norm(v - where, axis=1)
    push = height * np.exp(-0.5 * (d / width) ** 2)
    return trimesh.Trimesh(v + push[:, None] * mesh.vertex_normals, mesh.faces, process=False)


@pytest.fixture(scope="module")
def spheres():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    return {"a": sphere, "b": _bumped(sphere, BUMP, HEIGHT, 0.15)}


def test_first_region_is_the_bump(spheres):
    from neus_l0.figures.real import disagreement_regions

    regions = disagreement_regions(spheres, k=4, samples=4000)
    first = regions[0]
    assert first["kind"] == "region" and first["axis"] is None
    assert first["center"].shape == (3,)
    # the top of the bump (on "b") is HEIGHT from the sphere "a"
    assert np.linalg.norm(first["center"] - (1 + HEIGHT) * BUMP) < first["radius"]
    assert first["disagreement"] == pytest.approx(HEIGHT, abs=0.03)
    assert first["name"] == f"region 1 (differ {first['disagreement']:.3g})"
    # default radius: 6 % of the diagonal of the joint bounding box
    box = np.ptp(np.concatenate([spheres["a"].bounds, spheres["b"].bounds]), axis=0)
    assert first["radius"] == pytest.approx(0.06 * np.linalg.norm(box))
    # away from the bump the meshes agree (within the faceting)
    assert all(r["disagreement"] < 0.3 * HEIGHT for r in regions[1:])


def test_regions_are_apart_sorted_and_deterministic(spheres):
    from neus_l0.figures.real import disagreement_regions

    regions = disagreement_regions(spheres, k=5, radius=0.1, samples=3000)
    assert len(regions) == 5 and all(r["radius"] == 0.1 for r in regions)
    centres = np.stack([r["center"] for r in regions])
    gaps = np.linalg.norm(centres[:, None] - centres[None], axis=-1)[np.triu_indices(5, 1)]
    assert gaps.min() >= 0.2
    d = [r["disagreement"] for r in regions]
    assert d == sorted(d, reverse=True)
    again = disagreement_regions(spheres, k=5, radius=0.1, samples=3000)
    assert [r["name"] for r in again] == [r["name"] for r in regions]
    assert np.array_equal(np.stack([r["center"] for r in again]), centres)
    # a radius as large as the sphere leaves room for one region only
    assert len(disagreement_regions(spheres, k=3, radius=1.5, samples=3000)) == 1


# ------------------------------------------------------------------------------------------
# The command on a bench folder whose scene has no ground truth.

COLUMNS = ["scene", "sampler", "budget_s", "seed", "status", "iterations", "accuracy",
           "run_dir", "mesh"]


@pytest.fixture(scope="module")
def real_bench(tiny_scene, tmp_path_factory):
    """A bench folder laid out as `neus-l0 bench --scenes FOLDER` leaves it: the scene (the
    tiny demo's cameras, images and masks, no ground truth) linked as scenes/<basename>,
    spec.json naming the folder, and two runs whose meshes are the demo's true surface and
    the same surface with a bump (the hvs and l0 meshes stand-ins)."""
    root = tmp_path_factory.mktemp("real_bench")
    scan = root / "data" / "scan65"
    scan.mkdir(parents=True)
    for part in ("image", "mask"):
        shutil.copytree(tiny_scene / part, scan / part)
    shutil.copy(tiny_scene / "cameras_sphere.npz", scan)
    bench = root / "bench"
    (bench / "scenes").mkdir(parents=True)
    (bench / "scenes" / "scan65").symlink_to(scan, target_is_directory=True)
    true = trimesh.load(tiny_scene / "gt_mesh.ply", force="mesh", process=False)
    top = true.vertices[np.argmax(true.vertices[:, 2])]  # the top of the demo object
    meshes = {"hvs": true, "l0": _bumped(true, top, 25.0, 10.0)}
    with open(bench / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for sampler, mesh in meshes.items():
            name = f"scan65__{sampler}__30s__seed0"
            (bench / "runs" / name).mkdir(parents=True)
            mesh.export(bench / "runs" / name / "mesh.ply")
            (bench / "runs" / name / "spec.json").write_text(json.dumps({"scene_dir": str(scan)}))
            w.writerow({"scene": "scan65", "sampler": sampler, "budget_s": 30, "seed": 0,
                        "status": "done", "iterations": 100, "accuracy": "",
                        "run_dir": f"runs/{name}", "mesh": f"runs/{name}/mesh.ply"})
    return bench, top


def test_figures_command_on_a_scene_without_ground_truth(real_bench, tmp_path, capsys):
    import matplotlib.image

    bench, top = real_bench
    out = tmp_path / "fig"
    rc = main(["figures", "--bench", str(bench), "--out", str(out), "--width", "128",
               "--crop", "48", "--regions", "2", "--pit", "pit 1"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "no gt_mesh.ply" in cap.out and "--pit ignored" in cap.err
    for name in ("overview_shaded.png", "regions_shaded.png"):
        img = matplotlib.image.imread(out / name)[..., :3]
        assert img.shape[0] >= 150 and img.shape[1] >= 200, (name, img.shape)
        assert img.std() > 0.05, name  # not a blank page
    assert not (out / "overview_error.png").exists() and not (out / "ray_weights.png").exists()
    index = (out / "index.md").read_text()
    assert "](overview_shaded.png)" in index and "](regions_shaded.png)" in index
    assert "no ground truth" in index and "differ most" in index
    assert "scan65__hvs__30s__seed0" in index and "--regions 2" in index


def test_regions_of_the_bench_meshes_start_at_the_bump(real_bench):
    from neus_l0.figures.make import load_mesh
    from neus_l0.figures.real import disagreement_regions
    from neus_l0.figures.runs import select_runs
    from neus_l0.figures.views import overview_camera, scene_cameras

    bench, top = real_bench
    scene_dir, runs = select_runs(bench, ["hvs", "l0"])
    assert scene_dir == bench / "scenes" / "scan65"
    regions = disagreement_regions({s: load_mesh(r.mesh) for s, r in runs.items()}, k=2,
                                   samples=3000)
    assert np.linalg.norm(regions[0]["center"] - top) < regions[0]["radius"] + 25.0
    assert regions[0]["disagreement"] > 10.0
    cams = scene_cameras(scene_dir)  # no scene.json: the size from the first image
    assert (cams[0].width, cams[0].height) == (64, 48)
    assert 0 <= overview_camera(cams, regions) < len(cams)


def test_scene_folder_from_spec_json_when_the_link_is_missing(real_bench, tmp_path):
    from neus_l0.figures.runs import select_runs

    bench, _ = real_bench
    copy = tmp_path / "bench"
    shutil.copytree(bench, copy, ignore=shutil.ignore_patterns("scenes"))
    scene_dir, _ = select_runs(copy, ["hvs", "l0"])
    assert scene_dir == bench.parent / "data" / "scan65"
