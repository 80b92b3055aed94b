"""`neus-l0 train --viewer`: the run's page, live, fed by a training callback.

The training thread only hands over work: at each log step a note that new metrics are in
``metrics.jsonl``, and every ``train.val_every`` steps a CPU copy of the networks' weights.
One worker thread, at the lowest CPU priority, does the rest (reading the metrics, building a
coarse mesh from the copy, updating the page), taking only the newest of each kind of work
when it falls behind.
"""

from __future__ import annotations

import queue
import sys
import threading
from pathlib import Path

import numpy as np

from neus_l0.train.callbacks import TrainingCallback, step_check
from neus_l0.train.state import RunState
from neus_l0.viewer import run_files
from neus_l0.viewer.page import RunPage, reach_line
from neus_l0.viewer.serve import PageState, refresh, status_markdown

#: Marching-cubes cells per axis of the live mesh.
LIVE_RESOLUTION = 96


def coarse_mesh(cfg, weights: dict, scale_mat: np.ndarray, hull, resolution: int,
                view_scale: float = 1.0):
    """A mesh with vertex colours (world units) from a copy of the weights, on the CPU.

    `view_scale` is the colour network's view-encoding weight at the step the weights were
    taken (`model.color.view_warmup`'s ramp; not part of the state dict).

    Returns:
        a trimesh, or None when the field has no surface yet.
    """
    import torch

    from neus_l0.errors import NeusL0Error
    from neus_l0.fields.model import make_model
    from neus_l0.mesh.extract import extract_mesh

    model = make_model(cfg, "cpu")
    model.load_state_dict(weights)
    model.color.view_scale.fill_(view_scale)
    model.eval()
    try:
        with torch.no_grad():
            return extract_mesh(model, scale_mat, resolution=resolution, colors=True,
                                device="cpu", method="dense", hull=hull)
    except NeusL0Error:
        return None


def lowest_priority() -> None:
    """Give the calling thread the lowest CPU priority (nice 19) where the OS allows one
    thread its own (Linux); elsewhere nothing."""
    import os

    if sys.platform.startswith("linux") and hasattr(os, "setpriority"):
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        except OSError:
            pass


class LiveViewer(TrainingCallback):
    """Serves the run's page while it trains (see the module docstring).

    Args:
        port: where the page listens (0: a free one); host: the address.
        resolution: marching-cubes cells per axis of the live mesh.
        finish: at the end of training, finish the pending work (the last mesh) before the
            page closes, instead of dropping it.
    """

    def __init__(self, port: int = 8080, host: str = "127.0.0.1",
                 resolution: int = LIVE_RESOLUTION, finish: bool = False) -> None:
        self.port, self.host, self.resolution, self.finish = port, host, resolution, finish
        self.jobs: queue.Queue = queue.Queue()
        self.page: RunPage | None = None
        self.worker: threading.Thread | None = None
        self.state = PageState(follow=False)
        self.stopping = threading.Event()

    def on_start(self, run: RunState) -> None:
        self.page = RunPage(run.run_dir.name, self.host, self.port)
        print(reach_line(self.host, self.page.port), file=sys.stderr, flush=True)
        scale = np.asarray(run.scene.scale_mat, np.float64)
        self.worker = threading.Thread(target=self._work, name="neus-l0-viewer", daemon=True,
                                       args=(run.run_dir, run.cfg, scale))
        self.worker.start()

    def on_log(self, run: RunState, metrics: dict) -> None:
        self.jobs.put(("log", run.iteration, None))

    def after_step(self, run: RunState) -> None:
        if step_check(run.iteration, run.cfg.train.val_every):
            weights = {k: v.detach().to("cpu", copy=True)
                       for k, v in run.model.state_dict().items()}
            view_scale = float(run.model.color.view_scale)  # a host sync, every val_every steps
            self.jobs.put(("mesh", run.iteration, (weights, view_scale)))

    def on_end(self, run: RunState) -> None:
        """Stop the worker (a mesh it is building is dropped unless `finish`) and the page."""
        if not self.finish:
            self.stopping.set()
        self.jobs.put(("stop", run.iteration, None))
        if self.worker is not None:
            self.worker.join(timeout=300.0 if self.finish else 1.0)
        if self.page is not None:
            self.page.close()

    def _work(self, run_dir: Path, cfg, scale_mat: np.ndarray) -> None:
        """The worker thread, at the lowest CPU priority (Linux: a thread's own nice value),
        so that training keeps its core when the cores are busy; once training ends, what
        it was doing no longer matters."""
        lowest_priority()
        try:
            self._serve(run_dir, cfg, scale_mat)
        except Exception as exc:  # the page is closing under it, or a bad frame
            if not self.stopping.is_set():
                print(f"neus-l0 viewer: stopped updating ({type(exc).__name__}: {exc})",
                      file=sys.stderr, flush=True)

    def _serve(self, run_dir: Path, cfg, scale_mat: np.ndarray) -> None:
        """Cameras once, then the newest log and mesh work until told to stop."""
        from neus_l0.bounds.hull import load_run_hull

        page = self.page
        page.set_cameras(run_files.training_cameras(run_dir), scale=0.15 * scale_mat[0, 0])
        hull = load_run_hull(run_dir, "cpu")
        while True:
            batch = [self.jobs.get()]
            while not self.jobs.empty():
                batch.append(self.jobs.get_nowait())
            kinds = {kind: (it, data) for kind, it, data in batch}
            if self.stopping.is_set():
                return
            if "mesh" in kinds:
                it, (weights, view_scale) = kinds["mesh"]
                mesh = coarse_mesh(cfg, weights, scale_mat, hull, self.resolution, view_scale)
                self.state.shown = it
                page.set_mesh(mesh)
            if "log" in kinds or "mesh" in kinds:
                refresh(page, run_dir, self.state, self.resolution)
                page.set_status(status_markdown(run_dir, self.state.shown))
            if "stop" in kinds:
                return
