"""`neus-l0 view RUN` in headless Chromium: the page shows the mesh (its pixels differ from
the background) and the run's last PSNR, and no request leaves the loopback.

Set ``NEUS_L0_VIEWER_SHOT=docs/img/viewer.png`` to keep the screenshot (the README's).
"""

from __future__ import annotations

import os
import queue
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from neus_l0.config.load import load_config
from neus_l0.formats.open import open_scene
from neus_l0.train.loop import train
from neus_l0.viewer.browser import HIDE_NOTICES, find_chromium, open_page
from neus_l0.viewer.page import reach_line
from neus_l0.viewer.run_files import last_psnr, read_rgb

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tiny_run(tiny_scene, small_overrides, tmp_path_factory):
    cfg = load_config("demo", [*small_overrides, "train.iters=30", "train.val_every=15",
                               "train.save_every=15", "train.val_downscale=2"])
    run = tmp_path_factory.mktemp("view") / "run"
    train(open_scene(tiny_scene, preview=False, log=lambda _line: None), cfg, run,
          progress=False)
    return run


def _serve(run: Path):
    """Start `neus-l0 view RUN` on a free port; return the process and the port."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "neus_l0", "view", str(run), "--port", "0",
                             "--resolution", "48", "--threads", "1"], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in proc.stderr], daemon=True).start()
    while True:
        line = lines.get(timeout=120)
        m = re.match(r"viewer: http://127\.0\.0\.1:(\d+)/", line)
        if m:
            return proc, int(m.group(1))


def test_the_page_shows_the_mesh_and_the_last_psnr_from_the_loopback(tiny_run, tmp_path):
    if find_chromium() is None:
        pytest.skip("chromium not installed (apt-get install -y chromium)")
    it, value, _key = last_psnr(tiny_run)
    proc, port = _serve(tiny_run)
    try:
        shot = open_page(f"http://127.0.0.1:{port}/", tmp_path / "viewer.png",
                         wait_text=f"{value:.2f} dB", evaluate=HIDE_NOTICES, settle=3.0,
                         timeout=45)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
    assert f"last PSNR: {value:.2f} dB" in shot.text and f"iteration {it}" in shot.text
    assert shot.requests and not shot.outside, shot.outside
    img = read_rgb(shot.path).astype(np.int16)
    h, w = img.shape[:2]
    background = np.median(img[h - 20:h - 5, 5:20].reshape(-1, 3), axis=0)
    centre = img[h // 2 - 12:h // 2 + 12, w // 2 - 12:w // 2 + 12]
    differs = np.abs(centre - background).max(axis=-1) > 12
    assert differs.mean() > 0.5, "no mesh at the centre of the view"
    if os.environ.get("NEUS_L0_VIEWER_SHOT"):
        shutil.copyfile(shot.path, os.environ["NEUS_L0_VIEWER_SHOT"])


def test_another_address_says_who_can_reach_it():
    assert "this machine only" in reach_line("127.0.0.1", 8080)
    line = reach_line("0.0.0.0", 8080)
    assert "every machine that can reach this one" in line and "\n" not in line


def test_the_page_serves_no_file_by_path():
    import http.client

    from neus_l0.viewer.page import RunPage

    page = RunPage("x", "127.0.0.1", 0)
    try:
        for path, status in (("/", 200), ("/../../../../etc/passwd", 404),
                             ("/%2e%2e/%2e%2e/%2e%2e/etc/passwd", 404), ("/run.json", 404)):
            conn = http.client.HTTPConnection("127.0.0.1", page.port, timeout=10)
            conn.request("GET", path)
            got = conn.getresponse()
            assert (got.status, b"root:" in got.read()) == (status, False), path
    finally:
        page.close()
