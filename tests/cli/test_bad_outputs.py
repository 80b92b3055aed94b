"""An output path under a file (issue #27): train, mesh and eval name the file before any
work.
"""

from __future__ import annotations

import pytest


@pytest.mark.parametrize("argv", [
    ["train", "SCENE", "--out", "{f}/run"],
    ["mesh", "RUN", "--resolution", "24", "--out", "{f}/m.ply"],
    ["eval", "SCENE/gt_mesh.ply", "--scene", "SCENE", "--json", "{f}/r.json"],
    ["eval", "SCENE/gt_mesh.ply", "--scene", "SCENE", "--error-maps", "{f}/maps"],
], ids=["train --out", "mesh --out", "eval --json", "eval --error-maps"])
def test_an_output_under_a_file_is_named_before_any_work(scene96, trained96, tmp_path, argv,
                                                         refused):
    """An output path whose parent is a file: exit 2 naming that file."""
    f = tmp_path / "afile"
    f.write_text("keep me\n")
    args = [a.format(f=f).replace("SCENE", str(scene96)).replace("RUN", str(trained96))
            for a in argv]
    refused(args, str(f))
    assert f.read_text() == "keep me\n"
