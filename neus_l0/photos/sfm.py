"""Structure from motion on the CPU with pycolmap: photos -> one registered sparse model.

Stages (each logged with its time): checking the photos, SIFT feature extraction, matching
(exhaustive or sequential), incremental mapping (a progress bar over registered images).
COLMAP's own log is silenced below warnings.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from neus_l0.data.image_io import imread_bytes
from neus_l0.errors import NeusL0Error
from neus_l0.photos.sparse_io import SparseModel, from_reconstruction

PHOTO_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
#: --camera-model choices -> COLMAP model names.
CAMERA_MODELS = {
    "simple-pinhole": "SIMPLE_PINHOLE", "pinhole": "PINHOLE",
    "simple-radial": "SIMPLE_RADIAL", "radial": "RADIAL", "opencv": "OPENCV",
    "full-opencv": "FULL_OPENCV", "simple-radial-fisheye": "SIMPLE_RADIAL_FISHEYE",
    "radial-fisheye": "RADIAL_FISHEYE", "opencv-fisheye": "OPENCV_FISHEYE",
}
#: Default camera model (see docs/PHOTOS.md for the measurements behind it).
DEFAULT_CAMERA_MODEL = "simple-radial"
#: Up to this many photos the default matcher is exhaustive; beyond, sequential.
EXHAUSTIVE_MAX_IMAGES = 100
#: Default SIFT features per image.
DEFAULT_MAX_FEATURES = 8192
#: Minimum registered fraction of the photos (and absolute minimum) for success.
MIN_REGISTERED_FRACTION = 0.5
MIN_REGISTERED = 3

Log = Callable[[str], None]


@dataclasses.dataclass
class SfmOptions:
    """Settings of `run_sfm`.

    Attributes:
        camera_model: a key of `CAMERA_MODELS` (one camera shared by all photos).
        matcher: ``"exhaustive"``, ``"sequential"`` or ``"auto"`` (exhaustive up to
            `EXHAUSTIVE_MAX_IMAGES` photos).
        max_size: longest image side for feature extraction (-1: full size).
        max_features: SIFT features per image.
        threads: CPU threads (-1: all).
        seed: random seed of RANSAC and the mapper (-1: random).
        refine_principal_point: let bundle adjustment move the principal point (COLMAP
            keeps it at the image centre by default).
    """

    camera_model: str = DEFAULT_CAMERA_MODEL
    matcher: str = "auto"
    max_size: int = -1
    max_features: int = DEFAULT_MAX_FEATURES
    threads: int = -1
    seed: int = 0
    refine_principal_point: bool = False


def list_photos(folder: str | Path, same_size: bool = True
                ) -> tuple[list[Path], dict[str, tuple[int, int]]]:
    """The photos in `folder` (sorted by name), each checked readable (and of one size).

    Args:
        folder: the photo folder.
        same_size: require one size (SfM here shares one camera among all photos).

    Returns:
        paths: the photo files.
        sizes: file name -> (width, height).

    Raises:
        NeusL0Error: missing or empty folder, fewer than 3 photos, an unreadable photo, or
            a photo whose size differs from the first (one camera is shared by all).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise NeusL0Error(f"{folder}: photo folder not found")
    paths = sorted(p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in PHOTO_EXTENSIONS)
    if not paths:
        raise NeusL0Error(f"{folder}: no photos ({'/'.join(PHOTO_EXTENSIONS)}) found")
    if len(paths) < 3:
        raise NeusL0Error(f"{folder}: {len(paths)} photo(s) found; structure from motion "
                          "needs at least 3 (better 20 or more, overlapping)")
    size = None
    sizes = {}
    for p in paths:
        img = imread_bytes(Path(p), cv2.IMREAD_UNCHANGED)
        if img is None or img.size == 0:
            raise NeusL0Error(f"{p}: unreadable image")
        hw = (int(img.shape[1]), int(img.shape[0]))
        sizes[p.name] = hw
        if size is None:
            size = hw
        elif hw != size and same_size:
            raise NeusL0Error(f"{p}: size {hw[0]}x{hw[1]} differs from {size[0]}x{size[1]} of "
                              f"{paths[0].name}; all photos share one camera, so they must "
                              "have one size (resize or crop them alike)")
    return paths, sizes


def choose_matcher(matcher: str, n_images: int) -> str:
    """Resolve ``"auto"``: exhaustive up to `EXHAUSTIVE_MAX_IMAGES` photos, else sequential."""
    if matcher == "auto":
        return "exhaustive" if n_images <= EXHAUSTIVE_MAX_IMAGES else "sequential"
    if matcher not in ("exhaustive", "sequential"):
        raise NeusL0Error(f"unknown matcher '{matcher}' (exhaustive, sequential or auto)")
    return matcher


def _quiet_colmap() -> None:
    import pycolmap

    pycolmap.logging.minloglevel = 1  # warnings and errors only
    pycolmap.logging.stderrthreshold = 1


def _extract(db: Path, photo_dir: str | Path, names: list[str], opts: SfmOptions) -> None:
    """SIFT features of `names` into the database (one shared camera)."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = CAMERA_MODELS[opts.camera_model]
    extract = pycolmap.FeatureExtractionOptions()
    extract.sift.max_num_features = opts.max_features
    extract.max_image_size = opts.max_size if opts.max_size > 0 else -1
    extract.num_threads = opts.threads
    pycolmap.extract_features(db, photo_dir, image_names=list(names),
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extract, device=pycolmap.Device.cpu)


def _match(db: Path, matcher: str, opts: SfmOptions) -> None:
    """Match the features (exhaustive or sequential) and verify the two-view geometry."""
    import pycolmap

    match = pycolmap.FeatureMatchingOptions()
    match.num_threads = opts.threads
    verify = pycolmap.TwoViewGeometryOptions()
    if opts.seed >= 0:
        verify.ransac.random_seed = opts.seed
    run = pycolmap.match_exhaustive if matcher == "exhaustive" else pycolmap.match_sequential
    run(db, matching_options=match, verification_options=verify, device=pycolmap.Device.cpu)


def _map(db: Path, photo_dir: str | Path, sparse: Path, n_photos: int, opts: SfmOptions,
         progress: bool) -> dict:
    """Incremental mapping into `sparse/<k>`, with a bar of the registered photos.

    Returns:
        pycolmap's {k: Reconstruction}.
    """
    import pycolmap

    pipe = pycolmap.IncrementalPipelineOptions()
    pipe.num_threads = opts.threads
    pipe.min_model_size = MIN_REGISTERED
    pipe.ba_refine_principal_point = opts.refine_principal_point
    if opts.seed >= 0:
        pipe.random_seed = opts.seed
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_photos, desc="registered", unit="img", leave=False)

    def _tick() -> None:
        if bar is not None:
            bar.update(1)

    def _init_pair() -> None:
        if bar is not None:
            bar.update(2)

    sparse.mkdir(exist_ok=True)
    try:
        return pycolmap.incremental_mapping(db, photo_dir, sparse, options=pipe,
                                            initial_image_pair_callback=_init_pair,
                                            next_image_callback=_tick)
    finally:
        if bar is not None:
            bar.close()


def run_sfm(photo_dir: str | Path, names: list[str], work_dir: str | Path,
            options: SfmOptions | None = None, log: Log = print,
            progress: bool = True) -> tuple[list[SparseModel], dict]:
    """Extract, match and map `names` (relative to `photo_dir`); models largest first.

    Args:
        photo_dir: folder holding the photos.
        names: photo file names to use.
        work_dir: folder for ``database.db`` and the raw ``sparse/<k>`` models (created;
            an old database there is replaced).
        options: `SfmOptions`.
        log: where the stage lines go.
        progress: show a tqdm bar while mapping.

    Returns:
        models: every reconstruction as a `SparseModel`, most registered views first
            (empty when mapping failed).
        timings: seconds per stage (``extract``, ``match``, ``map``) and the resolved
            ``matcher`` and ``camera_model``.
    """
    import pycolmap

    opts = options or SfmOptions()
    if opts.camera_model not in CAMERA_MODELS:
        raise NeusL0Error(f"unknown camera model '{opts.camera_model}' "
                          f"(one of {', '.join(CAMERA_MODELS)})")
    matcher = choose_matcher(opts.matcher, len(names))
    _quiet_colmap()
    if opts.seed >= 0:
        pycolmap.set_random_seed(opts.seed)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    db = work / "database.db"
    for f in (db, work / "database.db-wal", work / "database.db-shm"):
        f.unlink(missing_ok=True)
    timings: dict = {"matcher": matcher, "camera_model": opts.camera_model}

    t0 = time.perf_counter()
    log(f"[1/3] extracting SIFT features from {len(names)} photos "
        f"(camera model {opts.camera_model}, up to {opts.max_features} features"
        + (f", images at most {opts.max_size} px" if opts.max_size > 0 else "") + ")")
    _extract(db, photo_dir, names, opts)
    timings["extract"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    log(f"[2/3] matching features ({matcher})")
    _match(db, matcher, opts)
    timings["match"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    log("[3/3] incremental mapping")
    recs = _map(db, photo_dir, work / "sparse", len(names), opts, progress)
    timings["map"] = time.perf_counter() - t0
    models = [from_reconstruction(r) for r in recs.values()]
    models.sort(key=lambda m: -m.n_views)
    models = [m for m in models if m.n_views > 0]
    sizes = [m.n_views for m in models]
    log(f"      extract {timings['extract']:.1f} s, match {timings['match']:.1f} s, "
        f"map {timings['map']:.1f} s; models registering {sizes or 'no'} photos")
    return models, timings


def check_models(models: list[SparseModel], n_photos: int, photo_dir: str | Path) -> SparseModel:
    """The one usable model, or a `NeusL0Error` saying what to try.

    Fails when mapping found no model, found several disconnected models of 3 or more
    views each, or registered fewer than `MIN_REGISTERED_FRACTION` of the photos (or fewer
    than `MIN_REGISTERED`).
    """
    hint = ("try photos with more overlap (each part of the object in 3+ photos, "
            "small steps between shots), --matcher sequential for ordered shots, or "
            "another --camera-model (pinhole, simple-radial, opencv)")
    if not models:
        raise NeusL0Error(f"{photo_dir}: structure from motion registered no photos; {hint}")
    # COLMAP's extra models may share views with the first (max_model_overlap); only models
    # adding 3+ views of their own are disconnected parts
    seen = set(models[0].names)
    big = [models[0]] + [m for m in models[1:]
                         if len(set(m.names) - seen) >= MIN_REGISTERED]
    if len(big) > 1:
        raise NeusL0Error(f"{photo_dir}: the photos fall into {len(big)} disconnected models "
                          f"({', '.join(str(m.n_views) for m in big)} photos); {hint}")
    best = models[0]
    need = max(MIN_REGISTERED, int(np.ceil(MIN_REGISTERED_FRACTION * n_photos)))
    if best.n_views < need:
        raise NeusL0Error(f"{photo_dir}: only {best.n_views} of {n_photos} photos registered "
                          f"(need {need}); {hint}")
    return best
