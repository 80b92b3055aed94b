"""`neus-l0 view RUN`: the page of a run folder, kept up to date while the folder changes.

`open_run_page` fills a `RunPage` from the run folder (`neus_l0.viewer.run_files`);
`refresh` re-reads what changed (new metrics lines, validation images, checkpoints) and
`serve_run` does so every few seconds until interrupted, so a page opened on a run that is
still training follows it.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from neus_l0.errors import NeusL0Error
from neus_l0.viewer import run_files
from neus_l0.viewer.page import RunPage


@dataclasses.dataclass
class PageState:
    """What the page of a run shows now (to tell what changed).

    Attributes:
        metrics_mtime: ``metrics.jsonl``'s modification time when last read.
        checkpoints: the checkpoints' iterations last listed.
        shown: the iteration whose mesh is shown; follow: show the newest checkpoint's.
    """

    metrics_mtime: float = -1.0
    checkpoints: tuple[int, ...] = ()
    shown: int | None = None
    follow: bool = True


def status_markdown(run_dir: Path, shown: int | None) -> str:
    """The panel's heading: the run, its last PSNR and the mesh's iteration."""
    last = run_files.last_psnr(run_dir)
    lines = [f"**{run_dir.name}**"]
    if last is not None:
        it, value, key = last
        what = {"val_psnr": "validation PSNR", "val_psnr_mask": "validation PSNR inside the mask"
                }.get(key, "training PSNR")
        lines.append(f"last PSNR: **{value:.2f} dB** ({what}, iteration {it})")
    lines.append(f"mesh: iteration {shown}" if shown is not None else "mesh: none yet")
    return "  \n".join(lines)


def show_checkpoint(page: RunPage, run_dir: Path, state: PageState, iteration: int,
                    resolution: int) -> None:
    """Extract and show the mesh of the checkpoint at `iteration`."""
    path = dict(run_files.checkpoints(run_dir)).get(iteration)
    if path is None:
        return
    page.set_status(f"{status_markdown(run_dir, state.shown)}  \nmeshing iteration "
                    f"{iteration} at {resolution}^3 ...")
    try:
        mesh = run_files.checkpoint_mesh(run_dir, path, resolution)
    except (NeusL0Error, OSError) as exc:
        page.set_status(f"{status_markdown(run_dir, state.shown)}  \n{exc}")
        return
    state.shown = iteration
    page.set_mesh(mesh)
    page.set_status(status_markdown(run_dir, state.shown))


def refresh(page: RunPage, run_dir: Path, state: PageState, resolution: int) -> None:
    """Re-read the run folder and update what changed on the page."""
    path = run_dir / "metrics.jsonl"
    mtime = path.stat().st_mtime if path.is_file() else -1.0
    if mtime != state.metrics_mtime:
        state.metrics_mtime = mtime
        page.set_curves(run_files.curves(run_dir))
    page.set_validation(run_files.validation_images(run_dir), run_files.read_rgb)
    its = tuple(it for it, _ in run_files.checkpoints(run_dir))
    if its != state.checkpoints:
        state.checkpoints = its

        def pick(it: int) -> None:
            state.follow = it == state.checkpoints[-1]
            threading.Thread(target=show_checkpoint, daemon=True,
                             args=(page, run_dir, state, it, resolution)).start()

        page.set_checkpoints(its, pick)
        if state.follow and its:
            show_checkpoint(page, run_dir, state, its[-1], resolution)
    page.set_status(status_markdown(run_dir, state.shown))


def open_run_page(run_dir: str | Path, host: str = "127.0.0.1", port: int = 8080,
                  resolution: int = 128) -> tuple[RunPage, PageState]:
    """Start the page of a run folder, filled with its cameras, curves, images and mesh.

    Args:
        run_dir: a run folder of `neus-l0 train`.
        host, port: where the server listens (port 0: a free one).
        resolution: marching-cubes cells per axis of the meshes shown.

    Raises:
        NeusL0Error: not a run folder.
    """
    run_dir = Path(run_dir)
    if not (run_dir / "config.yaml").is_file() and not (run_dir / "metrics.jsonl").is_file():
        raise NeusL0Error(f"{run_dir}: not a run folder (no config.yaml or metrics.jsonl)")
    page = RunPage(run_dir.name, host, port)
    meta = run_files.run_meta(run_dir)
    scale = float(np.asarray(meta.get("scale_mat", np.eye(4)))[0, 0])
    page.set_cameras(run_files.training_cameras(run_dir), scale=0.15 * scale)
    state = PageState()
    refresh(page, run_dir, state, resolution)
    return page, state


def serve_run(run_dir: str | Path, host: str = "127.0.0.1", port: int = 8080,
              resolution: int = 128, every: float = 3.0, seconds: float = 0.0,
              ready: Callable[[RunPage], None] | None = None) -> None:
    """Serve the page of a run folder until interrupted (or for `seconds` when > 0),
    re-reading the folder every `every` seconds; `ready(page)` once it is up."""
    page, state = open_run_page(run_dir, host, port, resolution)
    if ready is not None:
        ready(page)
    t0 = time.monotonic()
    try:
        while not seconds or time.monotonic() - t0 < seconds:
            time.sleep(every)
            refresh(page, Path(run_dir), state, resolution)
    finally:
        page.close()
