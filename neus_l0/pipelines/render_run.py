"""Novel views of a run folder: its trained networks, inside its visual hull, along a camera
path (a turntable orbit, the training views or held-out views), written as PNG frames and
one MP4 per channel, with PSNR / SSIM where the views have ground-truth images.

The render counterpart of `neus_l0.mesh.from_run`: `render_run` reads the run (the newest
checkpoint, ``hull.pt``, ``run.json``'s scene), so `neus-l0 render` cannot forget the hull or
render a different scene's cameras. It lives in ``render/`` and reads ``run/`` (which imports
only config, fields and the root modules, so no cycle); nothing here imports training.

Layout of the output folder ``DIR``: ``color/0000.png``, ``normal/0000.png``,
``depth/0000.png`` (one per frame), ``color.mp4``, ``normal.mp4``, ``depth.mp4`` (H.264,
`neus_l0.render.video`) and, for
views with ground truth, ``metrics.json``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import re
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from neus_l0.atomic import atomic_path, atomic_write_json, atomic_write_png, inside
from neus_l0.bounds.hull import VisualHull, load_run_hull
from neus_l0.data.scene import Scene
from neus_l0.data.split import split_views
from neus_l0.errors import NeusL0Error
from neus_l0.formats.open import open_scene
from neus_l0.render.cameras import (
    depth_range,
    mean_intrinsics,
    orbit_from_training,
    resize_intrinsics,
)
from neus_l0.render.video import Mp4Writer, check_video
from neus_l0.render.views import (
    ViewRender,
    depth_picture,
    mean_metrics,
    normal_picture,
    render_view,
    to_uint8,
    view_metrics,
)
from neus_l0.run.checkpoints import latest_checkpoint, load_trained_model

#: The pictures of a frame, each a folder of PNGs and an MP4.
CHANNELS = ("color", "normal", "depth")
VIEWS = ("orbit", "train", "test")
#: What a render writes at the top of its folder (its own, for --out checks).
RENDER_NAMES = (*CHANNELS, *(f"{c}.mp4" for c in CHANNELS), "metrics.json")
_FRAME = re.compile(r"^(\d{4,})\.png$")


@dataclasses.dataclass
class RenderOptions:
    """What `render_run` renders (the flags of `neus-l0 render`).

    Attributes:
        views: ``orbit`` (turntable), ``train`` (the training cameras) or ``test`` (held out).
        frames: orbit cameras (ignored for train / test).
        elevation: orbit elevation in degrees (default the training cameras' mean).
        width, height: output size (one alone keeps the training images' aspect).
        downscale: output = training image size / downscale (instead of width/height).
        fps: video frame rate.
        video: write the MP4s.
        test_views: held-out view indices; holdout: hold out every K-th view (``i % K ==
            0``, as `neus_l0.data.split.split_views`); give one of them (or neither).
        scene: the scene folder (default the one ``RUN/run.json`` names).
        checkpoint: a specific checkpoint file (default the newest that loads).
    """

    views: str = "orbit"
    frames: int = 60
    elevation: float | None = None
    width: int | None = None
    height: int | None = None
    downscale: float | None = None
    fps: float = 24.0
    video: bool = True
    test_views: tuple[int, ...] | None = None
    holdout: int = 0
    scene: str | Path | None = None
    checkpoint: str | Path | None = None

    def check(self) -> None:
        """Refuse impossible options before any work.

        Raises:
            NeusL0Error: one line naming the flag.
        """
        if self.views not in VIEWS:
            raise NeusL0Error(f"--views {self.views}: choose one of {', '.join(VIEWS)}")
        for flag, value in (("--frames", self.frames), ("--width", self.width),
                            ("--height", self.height)):
            if value is not None and value < 1:
                raise NeusL0Error(f"{flag} {value}: must be at least 1")
        if self.downscale is not None and (self.width or self.height):
            raise NeusL0Error("--downscale: give it or --width/--height, not both")
        if self.downscale is not None and not self.downscale > 0:
            raise NeusL0Error(f"--downscale {self.downscale}: must be > 0")
        if not self.fps > 0:
            raise NeusL0Error(f"--fps {self.fps}: must be > 0")
        if self.elevation is not None and not -90.0 < self.elevation < 90.0:
            raise NeusL0Error(f"--elevation {self.elevation}: must lie strictly between -90 "
                              "and 90 degrees")
        if self.holdout < 0:
            raise NeusL0Error(f"--holdout {self.holdout}: must be 0 (none) or a positive K")
        if self.test_views is not None and self.holdout:
            raise NeusL0Error("--test-views and --holdout: give one of them, not both")
        if (self.test_views is not None or self.holdout) and self.views == "orbit":
            flag = "--test-views" if self.test_views is not None else "--holdout"
            raise NeusL0Error(f"{flag} chooses held-out views, but --views orbit renders "
                              "none of the scene's views: add --views test (or train: the "
                              "others)")
        if self.test_views is not None and any(v < 0 for v in self.test_views):
            raise NeusL0Error(f"--test-views {self.test_views}: view indices must be >= 0")


@dataclasses.dataclass
class CameraPath:
    """The cameras of a render, in the normalised frame.

    Attributes:
        K: (F, 3, 3) float64 intrinsics for `size`.
        c2w: (F, 4, 4) float64 camera-to-world poses (OpenCV axes).
        size: (H, W) output pixels.
        views: the scene view of each frame (train / test), or None (orbit).
    """

    K: np.ndarray
    c2w: np.ndarray
    size: tuple[int, int]
    views: list[int] | None = None


@dataclasses.dataclass
class RenderResult:
    """What `render_run` wrote.

    Attributes:
        out: the output folder.
        frames: frames rendered; size: (H, W).
        seconds: wall-clock time of the frames (rendering and writing).
        videos: channel -> MP4 path (empty with ``video=False``).
        metrics: what ``metrics.json`` holds (None without ground truth: the orbit).
        checkpoint: the checkpoint rendered; iteration: its iteration.
    """

    out: Path
    frames: int
    size: tuple[int, int]
    seconds: float
    videos: dict[str, Path]
    metrics: dict | None
    checkpoint: Path
    iteration: int

    def summary(self) -> dict:
        """One JSON-able dict: where, how many, how fast, and the metrics if any."""
        H, W = self.size
        out = {"out": str(self.out), "frames": self.frames, "width": W, "height": H,
               "seconds": round(self.seconds, 3),
               "seconds_per_frame": round(self.seconds / max(self.frames, 1), 4),
               "videos": {k: str(v) for k, v in self.videos.items()},
               "checkpoint": str(self.checkpoint), "iteration": self.iteration}
        return {**out, **(self.metrics or {})}


def output_size(src_hw: tuple[int, int], options: RenderOptions) -> tuple[int, int]:
    """(H, W) of the output: the training size, scaled by `options`.

    Raises:
        NeusL0Error: a size that rounds to 0 pixels.
    """
    H0, W0 = src_hw
    if options.width and options.height:
        return options.height, options.width
    if options.width:
        return max(1, round(options.width * H0 / W0)), options.width
    if options.height:
        return options.height, max(1, round(options.height * W0 / H0))
    if options.downscale:
        H, W = round(H0 / options.downscale), round(W0 / options.downscale)
        if H < 1 or W < 1:
            raise NeusL0Error(f"--downscale {options.downscale}: leaves {W}x{H} pixels of the "
                              f"{W0}x{H0} training images")
        return H, W
    return H0, W0


def select_views(n_views: int, options: RenderOptions) -> list[int]:
    """The scene views of ``--views train`` / ``test``.

    Training views: all but the held-out ones. Held-out views: `options.test_views`, or
    every K-th view for ``holdout = K`` (`neus_l0.data.split.split_views`).

    Raises:
        NeusL0Error: an index out of range, no held-out view for ``test``, none left for
            ``train``.
    """
    if options.test_views is not None:
        bad = [v for v in options.test_views if v >= n_views]
        if bad:
            raise NeusL0Error(f"--test-views: {bad} out of range 0..{n_views - 1}")
        held = sorted(set(options.test_views))
    else:
        held = split_views(n_views, options.holdout)[1]
    if options.views == "test":
        if not held:
            raise NeusL0Error("--views test: no held-out views (give --test-views 0,8,16 or "
                              "--holdout K)")
        return held
    train = [i for i in range(n_views) if i not in set(held)]
    if not train:
        raise NeusL0Error(f"--views {options.views}: every one of the {n_views} views is held "
                          "out")
    return train


def run_views(run_dir: Path) -> dict | None:
    """The views record of ``RUN/run.json`` (``{"holdout", "n_views", "train", "heldout"}``,
    `neus_l0.data.split.holdout_split`); None without run.json. A run.json from before the
    record is a run trained on every view: ``{"holdout": 0, "heldout": []}``."""
    path = run_dir / "run.json"
    if not path.is_file():
        return None
    meta = json.loads(path.read_text(encoding="utf-8"))
    return meta.get("views") or {"holdout": 0, "heldout": []}


def resolve_held_out(options: RenderOptions, record: dict | None, run_dir: Path,
                     n_views: int) -> tuple[RenderOptions, list[int]]:
    """The options with the run's own held-out views, and the rendered views it trained on.

    Without ``--test-views`` / ``--holdout`` the held-out views are the run's
    (``train.holdout``); with them, the views asked for, and those of them that the run
    trained on are returned, so that their metrics are not called held-out.

    Raises:
        NeusL0Error: ``--views test`` on a run trained on every view, without those flags.
    """
    held = list((record or {}).get("heldout") or [])
    if options.test_views is None and not options.holdout:
        if options.views == "test" and not held:
            raise NeusL0Error(f"{run_dir}: trained on every view, so it has no held-out views "
                              "for --views test (train with --holdout K, or render --views "
                              "train)")
        return (dataclasses.replace(options, test_views=tuple(held)) if held else options), []
    if options.views != "test":
        return options, []
    trained = set(range(n_views)) - set(held) if record is not None else set()
    return options, sorted(trained & set(select_views(n_views, options)))


def camera_path(scene: Scene, options: RenderOptions) -> CameraPath:
    """The cameras `options` asks for, with intrinsics scaled to the output size.

    Args:
        scene: the run's scene (its cameras, after the run's downscale).

    Returns:
        a `CameraPath` (the orbit is fitted to the training views, see `select_views`).
    """
    src = (scene.height, scene.width)
    size = output_size(src, options)
    K = scene.intrinsics.double().cpu().numpy()  # (V, 3, 3)
    c2w = scene.c2w.double().cpu().numpy()  # (V, 4, 4)
    if options.views == "orbit":
        train = select_views(scene.n_views, dataclasses.replace(options, views="train"))
        poses = orbit_from_training(c2w[train], options.frames, options.elevation)
        k = resize_intrinsics(mean_intrinsics(K[train]), src, size)
        return CameraPath(np.broadcast_to(k, (len(poses), 3, 3)).copy(), poses, size)
    views = select_views(scene.n_views, options)
    return CameraPath(resize_intrinsics(K[views], src, size), c2w[views], size, views)


def run_scene(run_dir: Path, options: RenderOptions, downscale: int) -> Scene:
    """The scene a run trained on (``RUN/run.json``, or `options.scene`), on the CPU.

    Raises:
        NeusL0Error: no run.json and no `options.scene`, a missing scene folder, or a
            scene whose scale_mat differs from the run's.
    """
    meta_path = run_dir / "run.json"
    meta = json.loads(meta_path.read_text(encoding="utf-8")) if meta_path.is_file() else None
    if options.scene is None and meta is None:
        raise NeusL0Error(f"{meta_path}: missing (not a run folder of `neus-l0 train`?); pass "
                          "--scene DIR")
    root = Path(options.scene if options.scene is not None else meta["scene"])
    if not root.is_dir():
        where = "--scene" if options.scene is not None else f"{meta_path}: scene"
        raise NeusL0Error(f"{where} {root}: no such folder (moved? pass --scene DIR)")
    scene = open_scene(root, downscale=downscale, preview=False, log=lambda _line: None)
    if meta is not None and "scale_mat" in meta:
        ref = np.asarray(meta["scale_mat"], np.float64)
        if not np.allclose(scene.scale_mat, ref, rtol=1e-5, atol=1e-6 * np.abs(ref).max()):
            raise NeusL0Error(f"{root}: its scale_mat differs from {meta_path}'s (another "
                              "scene than the run trained on?)")
    return scene


def check_out(out: Path) -> Path:
    """Create the output folder and make sure files can be written there.

    Raises:
        NeusL0Error: it cannot be created or written to.
    """
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        raise NeusL0Error(f"--out {out}: cannot write there ({exc.strerror or exc})") from None
    return out


def _pictures(view: ViewRender, near_far: tuple[float, float]) -> dict[str, np.ndarray]:
    """The (H, W, 3) uint8 RGB picture of each channel."""
    return {"color": to_uint8(view.color), "normal": normal_picture(view.normal),
            "depth": depth_picture(view.depth, view.weight, *near_far)}


def _ground_truth(scene: Scene, view: int, size: tuple[int, int]
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """(H, W, 3) float image and (H, W) bool mask (None without masks) of a view, resized to
    `size` by area averaging when it differs."""
    gt = scene.images[view].cpu().numpy()
    mask = scene.masks[view].cpu().numpy() if scene.has_masks else None
    if gt.shape[:2] != tuple(size):
        dsize = (size[1], size[0])
        gt = cv2.resize(gt, dsize, interpolation=cv2.INTER_AREA)
        mask = None if mask is None else cv2.resize(mask, dsize, interpolation=cv2.INTER_AREA)
    return gt, None if mask is None else mask > 0.5


def _remove_stale_frames(folder: Path, n_frames: int) -> None:
    """Delete frame PNGs numbered ``n_frames`` and up (left by a longer earlier render)."""
    for p in folder.glob("*.png"):
        m = _FRAME.match(p.name)
        if m and int(m.group(1)) >= n_frames:
            p.unlink(missing_ok=True)


def hull_box(hull: VisualHull | None) -> np.ndarray | None:
    """(2, 3) the lower and upper corner of the hull's occupied cells (None: no hull or an
    empty one), in the normalised frame."""
    if hull is None or not bool(hull.occupancy.any()):
        return None
    idx = hull.occupancy.nonzero().cpu().numpy()  # (n, 3) cell indices (x, y, z)
    return np.stack([-1.0 + hull.cell * idx.min(0), -1.0 + hull.cell * (idx.max(0) + 1)])


def _render_frames(model, cfg, path: CameraPath, scene: Scene, out: Path,
                   hull: VisualHull | None, options: RenderOptions, device,
                   progress: bool) -> tuple[dict, list[dict]]:
    """Render and write every frame (PNGs, videos); return the videos and per-view metrics."""
    from tqdm import tqdm

    near_far = depth_range(path.c2w, hull_box(hull))
    bounds = (hull,) if hull is not None else ()
    n = len(path.c2w)
    per_view = []
    with contextlib.ExitStack() as stack:
        videos = {}
        for ch in CHANNELS if options.video else ():
            tmp = stack.enter_context(atomic_path(out / f"{ch}.mp4"))
            videos[ch] = Mp4Writer(tmp, path.size, options.fps)
            stack.callback(videos[ch].close)  # before the rename / removal
        for i in tqdm(range(n), desc="render", unit="frame", disable=not progress):
            K = torch.as_tensor(path.K[i], dtype=torch.float32, device=device)
            c2w = torch.as_tensor(path.c2w[i], dtype=torch.float32, device=device)
            view = render_view(model, K, c2w, path.size, cfg, bounds)
            for ch, rgb in _pictures(view, near_far).items():
                atomic_write_png(out / ch / f"{i:04d}.png", np.ascontiguousarray(rgb[..., ::-1]))
                if ch in videos:
                    videos[ch].write(rgb)
            if path.views is not None:
                v = path.views[i]
                gt, mask = _ground_truth(scene, v, path.size)
                per_view.append({"frame": i, "view": v, "image": scene.image_names[v],
                                 **view_metrics(view.color, gt, mask)})
        for ch, video in videos.items():
            video.close()
            check_video(video.path, video.count, video.size, out / f"{ch}.mp4")
    for ch in CHANNELS:
        _remove_stale_frames(out / ch, n)
    return {ch: out / f"{ch}.mp4" for ch in videos}, per_view


def render_run(run_dir: str | Path, out: str | Path | None = None,
               options: RenderOptions | None = None, device: str | torch.device = "cpu",
               progress: bool = True) -> RenderResult:
    """Render a trained run along a camera path into PNG frames, MP4s and metrics.

    Colour, normals (camera frame) and camera-z depth of every camera
    (`neus_l0.render.views.render_view`, NeuS's unbiased opacity: cos annealing 1), the
    rays narrowed by the run's visual hull (``RUN/hull.pt``) when it has one. Views with
    ground truth (train / test) get PSNR, SSIM (and the PSNR inside the mask with masks)
    against the scene's images, area-resized to the output size; they are written to
    ``OUT/metrics.json``. ``views="test"`` renders the run's held-out views
    (``train.holdout``, recorded in ``run.json``) and refuses a run trained on every view;
    views given by `options` that the run trained on are labelled ``"views": "train"``
    (``"held_out": false``, ``"trained_on"``), never held-out.

    Args:
        run_dir: the run folder (``checkpoints/``, ``run.json``, optional ``hull.pt``).
        out: the output folder (default ``RUN/render/<views>``).
        options: what to render (default a 60-frame orbit at the training size).
        device: where the networks run.
        progress: a tqdm bar over the frames (stderr).

    Returns:
        a `RenderResult`.

    Raises:
        NeusL0Error: bad options, no checkpoint, no scene, no held-out view, an unwritable
            `out`, or a video that does not read back.
    """
    options = options or RenderOptions()
    options.check()
    run_dir = Path(run_dir)
    if options.checkpoint is None and latest_checkpoint(run_dir) is None:
        raise NeusL0Error(f"{run_dir}: no checkpoints/ckpt_*.pt (train first)")
    if out is None:  # inside the run: nothing of it may lead out (`neus_l0.atomic.inside`)
        out = run_dir / "render" / options.views
        for name in RENDER_NAMES:
            inside(run_dir, out / name)
    out = Path(out)
    model, cfg, info = load_trained_model(run_dir, device, options.checkpoint)
    scene = run_scene(run_dir, options, cfg.data.downscale)
    options, trained = resolve_held_out(options, run_views(run_dir), run_dir, scene.n_views)
    path = camera_path(scene, options)
    check_out(out)
    hull = load_run_hull(run_dir, device)
    t0 = time.monotonic()
    videos, per_view = _render_frames(model, cfg, path, scene, out, hull, options, device,
                                      progress)
    seconds = time.monotonic() - t0
    metrics = None
    if path.views is not None:
        label = "train" if trained else options.views
        metrics = {"views": label, "held_out": label == "test", "trained_on": trained,
                   "frames": len(per_view), "width": path.size[1],
                   "height": path.size[0], "checkpoint": str(info["path"]),
                   "iteration": int(info["iteration"]), **mean_metrics(per_view),
                   "per_view": per_view}
        atomic_write_json(out / "metrics.json", metrics)
    return RenderResult(out, len(path.c2w), path.size, seconds, videos, metrics,
                        Path(info["path"]), int(info["iteration"]))
