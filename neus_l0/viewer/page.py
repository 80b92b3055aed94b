"""The viser page of a run: the mesh (vertex colours or normals), the training cameras as
frustums (click one to see its image), the curves, the validation images and a checkpoint
slider.

`RunPage` owns one `viser.ViserServer` and its handles; its ``set_*`` methods replace what
the page shows and may be called from any thread. It serves viser's own web client, which
ships inside the viser wheel (no CDN), and the data these methods hand it; it serves no
file by path. viser's "share URL" (a tunnel to share.viser.studio) is switched off.
"""

from __future__ import annotations

import contextlib
import io
import threading
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from neus_l0.viewer.run_files import Camera, mesh_normal_colors

#: Colours of the curves' series, in order.
_STROKES = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd")

#: The addresses that reach the page from this machine only.
LOOPBACK = ("127.0.0.1", "localhost", "::1")


def reach_line(host: str, port: int) -> str:
    """One line: the page's address and who can reach it."""
    if host in LOOPBACK:
        return (f"viewer: http://127.0.0.1:{port}/ (this machine only; ssh -L {port}:"
                f"127.0.0.1:{port} to see it from another)")
    everyone = "every machine that can reach this one" if host in ("0.0.0.0", "::") else \
        f"every machine that can reach {host}"
    return (f"viewer: http://{host}:{port}/ is open to {everyone}, without a password "
            "(--host 127.0.0.1 for this machine only)")


class RunPage:
    """A viser server showing one run.

    Args:
        title: the page's heading (the run folder's name).
        host, port: where the server listens (port 0: a free one).
    """

    def __init__(self, title: str, host: str = "127.0.0.1", port: int = 8080) -> None:
        import viser

        with contextlib.redirect_stdout(io.StringIO()):  # viser's own address box
            self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        self.server.request_share_url = lambda verbose=True: None  # no tunnel off the machine
        self.server.gui.configure_theme(show_share_button=False, show_logo=False,
                                        control_width="large")
        self.lock = threading.RLock()
        self.meshes: dict[str, object] = {}
        self.mesh_handle = None
        self.plots: dict[str, tuple[tuple[str, ...], object]] = {}
        self.target = np.zeros(3)
        self.offset: np.ndarray | None = None  # the first camera, from the target
        gui = self.server.gui
        self.status = gui.add_markdown(f"**{title}**")
        self.shading = gui.add_dropdown("Mesh", ("vertex colours", "normals"),
                                        initial_value="vertex colours")
        self.shading.on_update(lambda _e: self._show_mesh())
        self.ckpt_folder = gui.add_folder("Checkpoints")
        self.ckpt_slider = None
        self.curve_folder = gui.add_folder("Curves")
        self.val_folder = gui.add_folder("Validation")
        with self.val_folder:
            self.val_label = gui.add_markdown("no validation image yet")
            self.val_slider = None
            self.val_image = None
        self.cam_folder = gui.add_folder("Training view")
        with self.cam_folder:
            self.cam_label = gui.add_markdown("click a camera")
            self.cam_image = None
        self.validation: list[tuple[int, int, np.ndarray]] = []
        self.server.on_client_connect(self._aim)

    @property
    def port(self) -> int:
        """The port the server listens on."""
        return int(self.server.get_port())

    def _aim(self, client) -> None:
        """Point a new client's camera from the first training camera at the mesh."""
        if self.offset is not None:
            client.camera.position = tuple(self.target + 0.75 * self.offset)
            client.camera.look_at = tuple(self.target)

    def set_status(self, markdown: str) -> None:
        """Replace the text at the top of the panel."""
        self.status.content = markdown

    def set_mesh(self, mesh, label: str = "") -> None:
        """Show a trimesh (world units, with vertex colours); None: no surface yet."""
        with self.lock:
            if mesh is None:
                self.meshes = {}
            else:
                normals = mesh.copy()
                normals.visual.vertex_colors = mesh_normal_colors(mesh)
                self.meshes = {"vertex colours": mesh, "normals": normals}
                self.target = np.asarray(mesh.bounding_box.centroid, np.float64)
            self._show_mesh()

    def _show_mesh(self) -> None:
        with self.lock:
            mesh = self.meshes.get(self.shading.value)
            if mesh is None:
                if self.mesh_handle is not None:
                    self.mesh_handle.visible = False
                return
            self.mesh_handle = self.server.scene.add_mesh_trimesh("/mesh", mesh)

    def set_cameras(self, cams: Sequence[Camera], scale: float) -> None:
        """Frustums of the training cameras (`scale`: frustum size in world units)."""
        if not cams:
            return
        ups = [-_rotation(c.wxyz)[:, 1] for c in cams]  # OpenCV: y points down
        up = np.mean(ups, axis=0)
        self.server.scene.set_up_direction(tuple(up / max(np.linalg.norm(up), 1e-9)))
        centre = np.mean([c.position for c in cams], axis=0)
        self.offset = cams[0].position - centre
        self.target = centre if not self.meshes else self.target
        for c in cams:
            handle = self.server.scene.add_camera_frustum(
                f"/cameras/{c.index:04d}", fov=c.fov, aspect=c.aspect, scale=scale,
                image=c.image, wxyz=c.wxyz, position=c.position, color=(60, 60, 60))
            handle.on_click(lambda _e, cam=c: self.show_camera(cam))

    def show_camera(self, cam: Camera) -> None:
        """Show a training camera's image in the panel."""
        with self.cam_folder:
            self.cam_label.content = f"view {cam.index}: {cam.name}"
            if self.cam_image is None:
                self.cam_image = self.server.gui.add_image(cam.image, label=cam.name)
            else:
                self.cam_image.image = cam.image

    def set_curves(self, data: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]) -> None:
        """One uplot per title: {title: {key: (iterations, values)}} (`run_files.curves`)."""
        from viser import uplot

        with self.lock:
            for title, series in data.items():
                keys = tuple(series)
                xs = series[keys[0]][0]  # the keys of a title are logged on the same lines
                cols = [np.interp(xs, *series[k]) for k in keys]
                arrays = (xs, *cols)
                old = self.plots.get(title)
                if old is not None and old[0] == keys:
                    old[1].data = arrays
                    continue
                if old is not None:
                    old[1].remove()
                with self.curve_folder:
                    handle = self.server.gui.add_uplot(
                        data=arrays, series=(uplot.Series(label="iteration"), *(
                            uplot.Series(label=k, stroke=_STROKES[i % len(_STROKES)], width=2)
                            for i, k in enumerate(keys))),
                        title=title, aspect=2.0,
                        scales={"x": uplot.Scale(time=False, auto=True)})
                self.plots[title] = (keys, handle)

    def set_validation(self, images: Sequence[tuple[int, int, Path]],
                       read: Callable[[Path], np.ndarray]) -> None:
        """The validation images (iteration, view, path), newest shown, with a slider."""
        with self.lock:
            known = {(it, v) for it, v, _ in self.validation}
            new = [(it, v, read(p)) for it, v, p in images if (it, v) not in known]
            if not new:
                return
            self.validation = sorted(self.validation + new, key=lambda t: (t[0], t[1]))
            n = len(self.validation)
            with self.val_folder:
                if self.val_slider is None:
                    self.val_slider = self.server.gui.add_slider(
                        "image", min=0, max=max(n - 1, 1), step=1, initial_value=n - 1)
                    self.val_slider.on_update(lambda _e: self._show_validation())
                    self.val_image = self.server.gui.add_image(self.validation[-1][2])
                else:
                    self.val_slider.max = max(n - 1, 1)
                    self.val_slider.value = n - 1
            self._show_validation()

    def _show_validation(self) -> None:
        with self.lock:
            i = min(int(self.val_slider.value), len(self.validation) - 1)
            it, view, img = self.validation[i]
            self.val_label.content = (f"iteration {it}, view {view} (ground truth | colour | "
                                      "normals)")
            self.val_image.image = img

    def set_checkpoints(self, iterations: Sequence[int],
                        on_pick: Callable[[int], None]) -> None:
        """A slider over the checkpoints' iterations; `on_pick(iteration)` when moved."""
        with self.lock:
            its = list(iterations)
            if not its:
                return
            if self.ckpt_slider is not None:
                self.ckpt_slider.remove()
            with self.ckpt_folder:
                self.ckpt_slider = self.server.gui.add_slider(
                    "iteration", min=its[0], max=max(its[-1], its[0] + 1), step=1,
                    initial_value=its[-1], marks=tuple(its) if len(its) <= 12 else None)

            def picked(_event) -> None:
                value = self.ckpt_slider.value
                on_pick(min(its, key=lambda it: abs(it - value)))

            self.ckpt_slider.on_update(picked)

    def close(self) -> None:
        """Stop the server."""
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()


def _rotation(wxyz: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion -> (3, 3) rotation."""
    w, x, y, z = wxyz
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
