"""The sphere found for a clean transforms.json scene is as tight as its masks allow.

The demo scene (`scene96`: 8 views, 96x72) is exported with alpha as the mask; the sphere
found for the export must hold every ground-truth point, lie within `TIGHT` of the true
visual hull's reach (the hull carved from the full-resolution masks with no margin, finer
cells), and the carving must report no view whose masks disagree.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from neus_l0.bounds.hull import carve_hull, hull_from_scene
from neus_l0.bounds.static import check_fit
from neus_l0.formats.neus import load_scene
from neus_l0.formats.open import open_scene
from neus_l0.formats.sphere import _pad

TOOL = Path(__file__).resolve().parents[2] / "tools" / "export_transforms.py"
#: The found radius over the true hull's reach, at most.
TIGHT = 1.2


@pytest.fixture(scope="module")
def exported(scene96, tmp_path_factory) -> Path:
    """The demo at 96x72 as a nerfstudio transforms.json scene, RGBA images."""
    out = tmp_path_factory.mktemp("tight") / "ns"
    r = subprocess.run([sys.executable, str(TOOL), str(scene96), str(out), "--kind",
                        "nerfstudio", "--rgba"], capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr
    return out


def _true_reach(scene96: Path) -> float:
    """The reach of the full-resolution masks' visual hull (no margin, 128^3 cells in twice
    the twin's sphere) from its cells' box centre, world units."""
    twin = load_scene(scene96)
    big = 2.0
    c2w = twin.c2w.double().clone()
    c2w[:, :3, 3] /= big
    masks, K = _pad((twin.masks > 0.5).float().numpy(), twin.intrinsics.double().numpy(),
                    c2w.numpy())
    hull = carve_hull(torch.from_numpy(masks), torch.from_numpy(K).float(), c2w.float(),
                      resolution=128, margin_px=0.0, exclude_suspicious=False)
    R = hull.resolution
    idx = torch.nonzero(hull.carved).double()
    pts = (-1.0 + (idx + 0.5) * 2.0 / R).numpy()
    assert np.linalg.norm(pts, axis=1).max() < 0.9  # the hull lies well inside
    mid = 0.5 * (pts.min(0) + pts.max(0))
    return float(np.linalg.norm(pts - mid, axis=1).max()) * big * float(twin.scale_mat[0, 0])


def test_found_sphere_is_tight_and_holds_the_object(exported, scene96):
    lines: list[str] = []
    scene = open_scene(exported, preview=False, log=lines.append)
    sm = scene.scale_mat
    radius = float(sm[0, 0])
    gt = np.asarray(trimesh.load(scene96 / "gt_points.ply").vertices, np.float64)
    assert np.linalg.norm(gt - sm[:3, 3], axis=1).max() < radius
    reach = _true_reach(scene96)
    assert reach < radius < TIGHT * reach
    assert not [line for line in lines if line.startswith("visual hull:")]
    hull = hull_from_scene(scene)
    check_fit(hull, scene)  # train would not refuse it
    assert not any("disagree" in w for w in hull.report.warnings)


def test_inspect_prints_no_masks_disagree(exported, tmp_path, capsys):
    from neus_l0.cli import main

    assert main(["inspect", str(exported), "--hull", str(tmp_path / "hull.ply")]) == 0
    out = capsys.readouterr()
    assert "disagree" not in out.out + out.err
    assert "warning" not in out.out
