"""Structure-from-motion in-process with pycolmap: photos without poses -> a COLMAP model.

:func:`solve_cameras` runs the stages of COLMAP's pipeline on a folder of images (each with a
progress bar): SIFT features on the CPU (one camera shared by all images, SIMPLE_RADIAL,
focal length guessed from EXIF or 1.2 x the image's long side, refined by bundle adjustment),
matching (``exhaustive``: every pair, for photo sets; ``sequential``: each frame with its
``overlap`` successors, for video), incremental mapping, and undistortion to PINHOLE cameras.
It writes, in ``out``:

* ``images/``: the undistorted images; ``sparse/``: the PINHOLE model (``cameras``, ``images``,
  ``points3D`` ``.bin``), what :func:`l3d_app.data.colmap.colmap` reads;
* ``sfm.json``: the :class:`SfmReport` (images given and registered, mean reprojection error
  in pixels, sparse points, seconds per stage).

A capture SfM cannot solve raises :class:`~l3d_app.errors.UserError` with one line naming
what failed and what was found (:func:`judge`). The caller writes into a temporary folder and
renames it when this returns (:mod:`l3d_app.data.sfm_cache`), so a failed or interrupted run
never leaves a model that looks finished.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Dict, List, Sequence

from l3d_app.errors import UserError
from l3d_app.runtime.progress import progress

MATCHERS = ("exhaustive", "sequential")
SECOND_MODEL_SHARE = 0.2    # a second model this large (share of the images): two unrelated subjects


@dataclass
class SfmReport:
    """What a user needs to judge a solved capture.

    Attributes:
        given: images handed to SfM. registered: images with a recovered camera.
        reprojection_error: mean distance (pixels) between each sparse point's projection and
            the feature it was triangulated from, over all observations.
        points: sparse 3D points. models: separate reconstructions COLMAP made (1 when every
            registered photo is tied to the others). seconds: per stage and ``total``.
        unregistered: names of the images without a camera (at most the first 20).
    """

    given: int
    registered: int
    reprojection_error: float
    points: int
    models: int
    matcher: str
    seconds: Dict[str, float] = field(default_factory=dict)
    unregistered: List[str] = field(default_factory=list)

    def line(self) -> str:
        """One human line: registered of given, error, points, seconds."""
        return (f"registered {self.registered} of {self.given} images, mean reprojection error "
                f"{self.reprojection_error:.3f} px, {self.points} sparse points, {self.seconds.get('total', 0.0):.1f} s")


def import_pycolmap():
    """pycolmap, or a one-line :class:`UserError` naming the extra that installs it."""
    try:
        import pycolmap
    except ImportError:
        raise UserError("cameras from photos need pycolmap: pip install -e '.[sfm]' (the sfm extra)") from None
    pycolmap.logging.minloglevel = 2          # COLMAP's own log: errors only (the stages show progress bars)
    return pycolmap


def judge(given: int, sizes: Sequence[int], min_registered: float) -> None:
    """Raise the one-line :class:`UserError` for a capture SfM did not solve.

    Args:
        given: images handed to SfM.
        sizes: images registered in each reconstruction COLMAP made, largest first (may be empty).
        min_registered: share of ``given`` the largest reconstruction must hold.

    Refused: nothing registered; a second reconstruction of at least ``SECOND_MODEL_SHARE`` of
    the images (the photos show two things that share no features); a largest reconstruction
    under ``min_registered`` of the images (the photos do not overlap enough).
    """
    best = int(sizes[0]) if len(sizes) else 0
    if best == 0:
        raise UserError(f"registered 0 of {given} images: no two photos share enough matched features "
                        "(the photos do not overlap, or show too little texture)")
    big = [int(s) for s in sizes if int(s) >= 3]
    if len(big) > 1 and big[1] >= SECOND_MODEL_SHARE * given:
        groups = ", ".join(str(s) for s in big[:4])
        raise UserError(f"registered {best} of {given} images: the photos form {len(big)} separate groups "
                        f"({groups} images) that share no features (more than one object or place? "
                        "capture one object, walking around it)")
    if best < min_registered * given:
        raise UserError(f"registered {best} of {given} images: the photos do not overlap enough "
                        f"(at least {min_registered:.0%} must join one model; take photos closer together)")


def solve_cameras(image_dir: Path, names: Sequence[str], out: Path, matcher: str = "exhaustive",
                  overlap: int = 10, max_features: int = 8192, min_registered: float = 0.5,
                  seed: int = 0, threads: int = -1) -> SfmReport:
    """Find the cameras of ``names`` in ``image_dir`` and write the PINHOLE model into ``out``.

    Args:
        image_dir: folder of the images (already oriented, as SfM should see them; one size, one camera).
        names: image file names in ``image_dir`` (sorted: for ``sequential``, time order).
        out: an empty folder that receives ``images/``, ``sparse/`` and ``sfm.json``.
        matcher: ``exhaustive`` | ``sequential``. overlap: successors matched per frame (sequential).
        max_features: SIFT features kept per image.
        min_registered: share of the images the model must register, else :func:`judge` refuses.
        seed: COLMAP's random seed (RANSAC, mapping order); threads: -1 = all cores.
    Returns:
        the :class:`SfmReport` (also written as ``out/sfm.json``).
    """
    pc = import_pycolmap()
    if matcher not in MATCHERS:
        raise UserError(f"matcher must be one of {', '.join(MATCHERS)}, got {matcher!r}")
    names = list(names)
    out.mkdir(parents=True, exist_ok=True)
    db, work = out / "database.db", out / "mapping"
    seconds: Dict[str, float] = {}
    t_all = time.perf_counter()

    t0 = time.perf_counter()
    ext = pc.FeatureExtractionOptions()
    ext.num_threads = int(threads)
    ext.sift.max_num_features = int(max_features)
    reader = pc.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"
    chunk = max(4, -(-len(names) // 20))      # about 20 steps of the bar; a call costs set-up
    for s in progress(range(0, len(names), chunk), desc="sfm: features", total=-(-len(names) // chunk)):
        pc.extract_features(db, image_dir, image_names=names[s:s + chunk], camera_mode=pc.CameraMode.SINGLE,
                            reader_options=reader, extraction_options=ext, device=pc.Device.cpu)
        reader.existing_camera_id = 1         # the later chunks share the first chunk's camera
    seconds["features"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    match = pc.FeatureMatchingOptions()
    match.num_threads = int(threads)
    with progress(total=1, desc=f"sfm: {matcher} matching") as bar:
        if matcher == "sequential":
            pairing = pc.SequentialPairingOptions()
            pairing.overlap = int(overlap)
            pc.match_sequential(db, matching_options=match, pairing_options=pairing, device=pc.Device.cpu)
        else:
            pc.match_exhaustive(db, matching_options=match, device=pc.Device.cpu)
        bar.update(1)
    seconds["matching"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    opts = pc.IncrementalPipelineOptions()
    opts.num_threads = int(threads)
    opts.random_seed = int(seed)
    opts.min_model_size = 3
    opts.mapper.random_seed = int(seed)
    work.mkdir(exist_ok=True)
    with progress(total=len(names), desc="sfm: mapping") as bar:
        models = pc.incremental_mapping(db, image_dir, work, opts, next_image_callback=lambda: bar.update(1))
    seconds["mapping"] = time.perf_counter() - t0
    ranked = sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True)
    judge(len(names), [r.num_reg_images() for r in ranked], float(min_registered))
    best = ranked[0]

    t0 = time.perf_counter()
    model_dir = work / "best"
    model_dir.mkdir(exist_ok=True)
    best.write(model_dir)
    with progress(total=1, desc="sfm: undistortion") as bar:
        pc.undistort_images(out, model_dir, image_dir, output_type="COLMAP")
        bar.update(1)
    seconds["undistortion"] = time.perf_counter() - t0
    seconds["total"] = time.perf_counter() - t_all

    registered = {best.image(i).name for i in best.reg_image_ids()}
    report = SfmReport(given=len(names), registered=len(registered),
                       reprojection_error=float(best.compute_mean_reprojection_error()),
                       points=int(best.num_points3D()), models=len(ranked), matcher=matcher,
                       seconds={k: round(v, 2) for k, v in seconds.items()},
                       unregistered=[n for n in names if n not in registered][:20])
    (out / "sfm.json").write_text(json.dumps(asdict(report), indent=1))
    return report


def read_report(folder: Path) -> SfmReport:
    """The :class:`SfmReport` a finished model folder holds."""
    return SfmReport(**json.loads((folder / "sfm.json").read_text()))
