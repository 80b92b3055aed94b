"""Outputs are written with ordinary file modes, and a killed writer's temporary files are
cleared when a run starts again (issue #27 item 4)."""

import os
import stat

from neus_l0.atomic import atomic_write_text, orphan_temporaries, remove_orphans
from neus_l0.config.load import load_config
from neus_l0.train.loop import train


def test_outputs_get_the_mode_the_umask_gives(tmp_path):
    old = os.umask(0o022)
    try:
        path = atomic_write_text(tmp_path / "a.txt", "x")
        assert stat.S_IMODE(path.stat().st_mode) == 0o644
        os.umask(0o002)
        path = atomic_write_text(tmp_path / "b.txt", "x")
        assert stat.S_IMODE(path.stat().st_mode) == 0o664
    finally:
        os.umask(old)


def test_orphans_are_the_writer_temporaries_only(tmp_path):
    (tmp_path / ".ckpt_0000010.pt.abc123.tmp.pt").write_bytes(b"half")
    (tmp_path / ".lock").write_text("{}")
    (tmp_path / "ckpt_0000010.pt").write_bytes(b"whole")
    assert [p.name for p in orphan_temporaries(tmp_path)] == [".ckpt_0000010.pt.abc123.tmp.pt"]
    assert len(remove_orphans(tmp_path)) == 1 and orphan_temporaries(tmp_path) == []
    assert (tmp_path / ".lock").exists() and (tmp_path / "ckpt_0000010.pt").exists()


def test_a_resumed_run_clears_what_a_killed_writer_left(small, sphere_scene, tmp_path,
                                                         capsys):
    scene = sphere_scene(tmp_path / "s")
    run = tmp_path / "run"
    cfg = load_config("demo", small + ["train.iters=10"])
    train(scene, cfg, run, progress=False)
    orphan = run / "checkpoints" / ".ckpt_0000020.pt.k1ll3d.tmp.pt"
    orphan.write_bytes(b"cut short")
    ckpt = run / "checkpoints" / "ckpt_0000010.pt"
    assert stat.S_IMODE(ckpt.stat().st_mode) == 0o666 & ~_umask()
    train(scene, load_config("demo", small + ["train.iters=12"]), run, resume=True,
          progress=False)
    assert not orphan.exists() and "killed run left" in capsys.readouterr().err


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask
