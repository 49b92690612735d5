"""Stage ``sfm``: structure from motion with pycolmap on CPU, for a folder of photos (or a video) without a model,
and triangulation with the known poses for posed photographs without sparse points.

Steps, each shown as progress: downscale the photos (longest side ``max_image_size``, EXIF
kept so COLMAP can use the focal length) → SIFT features → exhaustive matching → incremental
mapping (the largest model is kept) → undistortion. The result is a COLMAP folder
``RUN_DIR/sfm`` (``images/`` undistorted, ``sparse/`` PINHOLE model, ``sfm.json`` summary)
that the ``load`` stage reads with the COLMAP adapter. Scratch files (database, downscaled
photos, distorted models) stay in ``RUN_DIR/sfm.work``.

The stage applies when the input is a folder (or its ``images/`` subfolder) of photos that no
data adapter recognises, or a video file (:data:`nerfpipe.data.video.VIDEO_SUFFIXES`): then the sharpest frame of each
of ``video_frames`` equal stretches of it (:func:`nerfpipe.data.video.write_frames`) is written to ``RUN_DIR/frames``
first, and those frames are the photos. It also applies to a real capture that an adapter reads with poses but no sparse
points (an instant-ngp or nerfstudio ``transforms.json`` without a point file;
:func:`nerfpipe.plugins.triangulate.wants_points`): then it only triangulates points with the poses fixed
(:func:`nerfpipe.plugins.triangulate.triangulate`) and writes them as ``RUN_DIR/sfm/points`` (a COLMAP model
in the input's frame), which the ``load`` stage adds to the scene.
"""

import contextlib
import json
import shutil
import time
from dataclasses import dataclass
from dataclasses import replace as dataclasses_replace
from pathlib import Path
from typing import Literal

from nerfpipe.data.image_file import HEIF_SUFFIXES, PHOTO_SUFFIXES, image_header, open_image, photo_folder
from nerfpipe.data.video import is_video, write_frames
from nerfpipe.pipeline.report_items import Shown
from nerfpipe.pipeline.stages import StageContext, StageSpec, atomic_path
from nerfpipe.plugins import unfold
from nerfpipe.util.errors import NerfpipeError, refuse_unless, require
from nerfpipe.util.paths import resolve_inside

SFM_DIR = "sfm"
FRAMES_DIR = "frames"
"""The frames taken from a video input (the photos of its structure from motion)."""
WORK_DIR = "sfm.work"
POINTS_DIR = "points"
"""Inside ``SFM_DIR``: the triangulated points of a posed input (a COLMAP model in the input's frame)."""


@dataclass
class SfmConfig:
    """Options of the ``sfm`` stage."""

    max_image_size: int = 1024
    """Longest image side used for SfM and written to the result; larger photos are downscaled (0: keep)."""
    video_frames: int = 50
    """Frames taken from a video input: the sharpest (least blurred) of each of this many equal stretches of it.
    Above ``exhaustive_max_photos`` each frame is matched with its most similar ones only."""
    camera_mode: Literal["auto", "single", "per_image"] = "auto"
    """``auto``: one camera (intrinsics estimated once) per group of photos of the same size and EXIF camera
    model, as the photos of one phone or camera are; ``per_image``: one per photo. Per photo, a few photos fit
    wild intrinsics: on 23 photos of colmap_mouse (two orientations, no EXIF) it registered 18 with focal
    lengths of 117 to 1.5e6 px and one camera 1,000x farther than the others; one camera per size registered 18
    with two plausible focal lengths and 926 points instead of 659. One camera's photos of both orientations share it
    (``turn``)."""
    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model estimated before undistortion."""
    turn: bool = True
    """With ``camera_mode`` ``auto``: where one camera's photos come in both orientations of one size, map the
    rarer orientation's photos turned a quarter so that they share the camera's intrinsics, and turn the result
    back (:func:`photos_to_turn`, :func:`unturn`). 23 photos of colmap_mouse (9 portrait, no EXIF), 23 mappings at
    1,024 px: the one focal length 735-748 px every time (COLMAP's model of all 59 photos: 741), where the portrait
    camera alone fitted 746-785 px and once 166 (one run of the stage: 1,466 px and distortion -3.2, 10 of 23 photos
    registered); median rotation error 0.37-0.74 degrees against 0.39-1.0 where right. Folds are as frequent either
    way (16 of 23 right against 17 of 23: README, "A phone's portrait and landscape photos share one camera")."""
    max_num_features: int = 8192
    """SIFT features per image."""
    num_threads: int = 2
    """CPU threads for extraction, matching and mapping (-1: all)."""
    exhaustive_max_photos: int = 40
    """Photos up to which every pair is matched; above, each photo is matched with its ``match_neighbours`` most
    similar ones only (:func:`similar_pairs`). instant-ngp's fox (67 photos at 1,024 px): every pair (2,211) took
    61.8 s of matching, the 644 pairs of 15 neighbours 20.8 s (plus 4 s to choose them), and registered all 67 photos
    within 0.03 degrees (median) of the exhaustive reconstruction, 14,358 points against 15,017."""
    match_neighbours: int = 15
    """Most similar photos each photo is matched with above ``exhaustive_max_photos``."""
    max_centre_spread: float = 20.0
    """A registered photo whose centre lies farther from the median centre than this many times the
    median distance is dropped as a failed registration (as one with bogus intrinsics is); 0: keep all."""
    min_registered: int = 3
    """Fail when fewer photos than this are registered."""
    triangulate: bool = True
    """Posed photographs of a real capture without sparse points (instant-ngp's fox, a nerfstudio capture without
    its point file) get points triangulated with their poses fixed, as COLMAP captures bring them: the object
    region, the field behind the box, the depth loss and the mesh region stand on them. instant-ngp's fox
    (``nerfpipe run --time-budget 180``) trained a fog box without them."""
    triangulate_neighbours: int = 8
    """Each posed photograph is matched with this many nearest cameras (by viewing direction and position)."""
    triangulate_max_image_size: int = 640
    """Longest image side for the triangulation's features. instant-ngp's fox (67 photos, 1080x1920): at 1024 px,
    8,192 features and 12 neighbours 16,754 points in 40 s (0.61 px); at 640 px, 4,096 and 8, 9,599 points in 15.5 s
    (0.50 px)."""
    triangulate_max_features: int = 4096
    """SIFT features per photograph for the triangulation."""
    triangulate_max_photos: int = 100
    """Triangulate from at most this many of the posed photographs, spread evenly (a video's frames: every k-th);
    the others are trained on all the same (0: all). The fox's 67 took 14 s; a 300-frame capture would take a minute."""
    candidate_sizes: "tuple[int, ...]" = (640,)
    """Longest image sides of further reconstructions of the same photos, for captures of at most
    ``candidate_max_photos``: on a few photos incremental mapping can fold part of a capture onto a wrong but
    self-consistent place (23 of colmap_mouse's photos at 1,024 px: 11 of 22 registered photos 70-84 degrees off in 5
    of 6 runs; at 640 px 19 registered, all within 2 degrees of COLMAP's model of all 56, in 5 of 5; at 720 px right in 3
    of 4). Where the reconstructions disagree (:func:`rotation_agreement`), a short radiance-field fit on each picks the
    one whose held-out photographs it renders best (:func:`photometric_check`). Each costs 4-12 s where they agree
    (measured with 720 and 640: Sacre Coeur's SfM 18 s instead of 8, the Sceaux castle's 24 s instead of about 12).
    Empty: one reconstruction."""
    candidate_max_photos: int = 40
    """Photos above which no further reconstruction is made (larger captures constrain their poses better, and
    each reconstruction costs more)."""
    check_steps: int = 100
    """Training steps of each reconstruction's fit in :func:`photometric_check` where reconstructions at two image sizes
    disagree."""
    strict_check_steps: int = 400
    """Training steps of each fit in :func:`subset_check` (of :data:`STRICT_CHECK_RAYS` rays each). A fit on the subset's
    fewer photos converges sooner, so a short check favours it whether or not the other photos fit: on two 23-photo
    cuts of colmap_mouse, a fold left out by the strict mapping (11 of 20 photos right) and a right reconstruction of
    19 against 10 of its photos, the subset's held-out PSNR minus the full one's was +0.11 / +0.73 dB after 100 steps
    of 4,096 rays (the fold missed, the right photos lost), and with 2,048 rays -0.42 / +1.21 after 200, +0.01 / +0.61
    after 300, **+0.83 / -0.45 after 400**, +1.14 / -0.30 after 500 and +1.57 / -0.44 after 700 (session 31): the
    fold's fit gets worse with the steps, the right one's better."""
    strict_min_inliers: int = 60
    """Verified matches a photo pair needs in the strict reconstruction (COLMAP's default: 15), mapped again from the
    chosen reconstruction's matches for captures of at most ``candidate_max_photos``: where a few wrong but consistent
    matches attach a block of photos to the rest in the wrong place (a fold at every image size), the strict mapping
    leaves that block out. Where no reconstruction at another image size agrees with the chosen one and the strict
    mapping registers fewer photos, a fit on each decides whether the others belong (:func:`strict_check`). Where
    the sizes agree the check is skipped: run there anyway (session 31) it cost a right 30-photo cut 50 s and nearly 4
    right photos (+0.50 dB), and on a 27-photo cut whose sizes agreed on the same fold (12 of 21 right) it kept the
    fold (the strict mapping's 14, all right, rendered the held-out photos 1.09 dB worse). Under a time budget too short
    for the fits, only the photos that another image size's reconstruction places alike are kept
    (:func:`keep_consensus`). 0: no strict reconstruction."""
    unfold: bool = True
    """Where every pair of photos was matched (at most ``exhaustive_max_photos``), look for a fold in each
    reconstruction (photos it places side by side that share no matches) and undo it by mapping again without the
    weak photo pairs that support it (:func:`nerfpipe.plugins.unfold.unfold`): on 23 of colmap_mouse's photos at
    1,024 px, three folded reconstructions (10-11 of 23 photos within 5 degrees of COLMAP's model of all 59) became
    20 of 22, 20 of 22 and 19 of 19, for 3 s of mapping each."""
    extend_unfolded: bool = True
    """Where an unfolding left photos out, map on from it with every photo pair, keeping the photos placed where their
    matches agree (:func:`nerfpipe.plugins.unfold.extended`; 2-3 s for 23 photos)."""
    undistort: bool = True
    """Undistort the images into a PINHOLE model (otherwise keep the distorted model and photos)."""
    verbose: bool = False
    """Show COLMAP's own INFO log (otherwise only warnings and the progress bars)."""

    def __post_init__(self) -> None:
        """Impossible values stop here, before any photo is read."""
        refuse_unless([("video_frames", self.video_frames >= 3, "at least 3", self.video_frames)])


def applies(ctx: StageContext) -> bool:
    """Photos that no adapter can read, a video, or a posed real capture without points (:func:`posed_without_points`);
    never an in-memory reconstruction."""
    if "reconstruction" in ctx.cache or ctx.source is None:
        return False
    if is_video(ctx.source):
        return True
    if not _adapter_reads(ctx.source):
        return photo_folder(ctx.source) is not None
    return posed_without_points(ctx) is not None


def posed_without_points(ctx: StageContext):
    """The input's scene when it is a real capture with poses and without sparse points that the config lets
    this stage triangulate (:func:`nerfpipe.plugins.triangulate.wants_points`), else None."""
    from nerfpipe import data_adapters
    from nerfpipe.plugins.triangulate import wants_points

    config = ctx.configs.get("sfm") or SfmConfig()
    if not config.triangulate or "scene" in ctx.cache:
        return None
    scene = data_adapters.load(ctx.source, getattr(ctx.configs.get("load"), "format", None))
    return scene if wants_points(scene) else None


def _photos(folder: Path) -> "list[Path]":
    """The photos of ``folder``; one that is a symlink out of it is refused, as in every dataset."""
    return sorted(resolve_inside(folder, p.name) for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES and p.is_file())


def camera_tag(exif) -> str:
    """The camera a photo's EXIF names: its model and, when given, its focal length (a zoom setting is
    another camera); empty without EXIF."""
    model = str(exif.get(0x0110, "")).strip()  # Model
    focal = exif.get_ifd(0x8769).get(0x920A)  # Exif IFD: FocalLength
    return f"{model} {float(focal):g}mm".strip() if focal else model


def sfm_name(photo: Path) -> str:
    """A photo's file name in the reconstruction: its own, or a HEIF photo's with ``.jpg`` added (written as a JPEG by
    :func:`prepare_images`: COLMAP reads and writes JPEG and PNG)."""
    return photo.name + ".jpg" if photo.suffix.lower() in HEIF_SUFFIXES else photo.name


def prepare_images(photos: "list[Path]", out: Path, max_size: int) -> "list[tuple[int, int, str]]":
    """Downscale (or link) the photos into ``out``, turned upright as their EXIF orientation says (a phone's
    portrait photo is stored sideways with a tag that only viewers apply; COLMAP would see it sideways, and
    the world's up is taken from upright photos); return ``(width, height, EXIF camera tag)`` per photo."""
    from PIL import Image, ImageOps

    out.mkdir(parents=True, exist_ok=True)
    info = []
    for p in photos:
        h, w, _ = image_header(p)
        scale = max_size / max(w, h) if max_size > 0 else 1.0
        size = (round(w * scale), round(h * scale)) if scale < 1.0 else None
        with open_image(p, draft=size) as im:  # decoded here, so a broken photo is one line naming it
            exif = im.getexif()
            model, orientation = camera_tag(exif), exif.get(0x0112, 1)
            if size is None and orientation in (0, 1) and p.name == sfm_name(p):
                (out / p.name).symlink_to(p.resolve())
                info.append((w, h, model))
                continue
            small = ImageOps.exif_transpose(im).convert("RGB")
            if size is not None:
                small = small.resize(size[::-1] if orientation in (5, 6, 7, 8) else size, Image.LANCZOS)
            exif[0x0112] = 1
            small.save(out / sfm_name(p), quality=95, exif=exif.tobytes())
            info.append((*small.size, model))
    return info


UPRIGHT_DIR = "upright"
"""Beside a reconstruction's images folder: the upright copies of the photos turned a quarter for the mapping
(:func:`turn_photos`); the names in it are the turned photos."""

QUARTER = ((0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
"""The rotation from a camera turned a quarter counter-clockwise with its photo (:func:`turn_photos`) to the upright
camera: an upright ``cam_from_world`` rotation is ``QUARTER @ R`` of the turned one's ``R``."""

TURNABLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL")
"""Camera models whose parameters describe the same lens after a quarter turn of the image (focal lengths and
principal point swap; the radial terms are symmetric): photos are turned to share a camera only for these."""


def photos_to_turn(info: "list[tuple[int, int, str]]") -> "set[int]":
    """The photos (indices into ``info``: width, height, EXIF camera tag) to turn a quarter so that one camera's
    photos of both orientations share its intrinsics: a phone's portrait and landscape photos are one sensor, but
    COLMAP gives each image size its own camera, and a few photos of the rarer orientation fit wild intrinsics (23
    photos of colmap_mouse, 9 portrait: focal 1,466 px and distortion -3.2 at 1,024 px, against 736 for the 14
    landscape ones, whose true focal is within 1 % of it). Within one camera tag the orientation of fewer photos is
    turned (portrait on a tie)."""
    from collections import Counter

    sizes = Counter(info)
    return {i for i, (w, h, tag) in enumerate(info)
            if w != h and (h, w, tag) in sizes and (sizes[(w, h, tag)], w > h) < (sizes[(h, w, tag)], h > w)}  # fmt: skip


def turn_photos(out: Path, names: "list[str]", info: "list[tuple[int, int, str]]", turn: "set[int]") -> "list[tuple[int, int, str]]":
    """Turn the photos ``turn`` (indices) of ``out`` a quarter counter-clockwise in place, their upright copies moved
    to :data:`UPRIGHT_DIR` beside ``out``; returns ``info`` with the turned sizes (see :func:`unturn`)."""
    from PIL import Image

    upright = out.parent / UPRIGHT_DIR
    shutil.rmtree(upright, ignore_errors=True)
    if not turn:
        return info
    upright.mkdir(parents=True)
    info = list(info)
    for i in sorted(turn):
        (out / names[i]).rename(upright / names[i])
        with Image.open(upright / names[i]) as im:
            exif = im.getexif()
            im.convert("RGB").transpose(Image.Transpose.ROTATE_90).save(out / names[i], quality=95, exif=exif.tobytes())
        w, h, tag = info[i]
        info[i] = (h, w, tag)
    return info


def turned_names(images: Path) -> "set[str]":
    """The photos of a reconstruction's ``images`` folder that :func:`turn_photos` turned (named in :data:`UPRIGHT_DIR`)."""
    upright = images.parent / UPRIGHT_DIR
    return {p.name for p in upright.iterdir()} if upright.is_dir() else set()


def unturn(rec, images: Path) -> "tuple[object, Path]":
    """``rec`` (mapped on ``images``, some photos turned by :func:`turn_photos`) for the upright photos: a turned
    photo's image of width W gets a camera of the turned one's intrinsics turned back (focal lengths swapped,
    principal point (W - cy, cx)), its keypoints (x, y) -> (W - y, x) and its pose turned a quarter about its
    optical axis; and the folder of the upright photos (``images`` where nothing was turned)."""
    import numpy as np

    pycolmap = require("pycolmap", "colmap")
    upright, turned = images.parent / UPRIGHT_DIR, turned_names(images)
    if not turned:
        return rec, images
    folder = images.parent / "images_upright"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for name in (p.name for p in images.iterdir()):
        (folder / name).symlink_to(((upright if name in turned else images) / name).resolve())
    out = pycolmap.Reconstruction()
    for cam in rec.cameras.values():
        out.add_camera_with_trivial_rig(pycolmap.Camera(model=cam.model_name, width=cam.width, height=cam.height,
                                                        params=list(cam.params), camera_id=cam.camera_id))
    quarter = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array(QUARTER)), np.zeros(3))
    turned_cams: "dict[int, int]" = {}
    registered = set()
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        cam, cam_id, pose = image.camera, image.camera_id, image.cam_from_world()
        xy = np.array([p.xy for p in image.points2D], dtype=np.float64).reshape(-1, 2)
        if Path(image.name).name in turned:
            if cam_id not in turned_cams:
                params, (fi, pi) = list(cam.params), (list(cam.focal_length_idxs()), list(cam.principal_point_idxs()))
                if len(fi) == 2:
                    params[fi[0]], params[fi[1]] = params[fi[1]], params[fi[0]]
                params[pi[0]], params[pi[1]] = cam.height - cam.params[pi[1]], cam.params[pi[0]]
                turned_cams[cam_id] = max(max(rec.cameras), max(turned_cams.values(), default=0)) + 1
                out.add_camera_with_trivial_rig(pycolmap.Camera(model=cam.model_name, width=cam.height, height=cam.width,
                                                                params=params, camera_id=turned_cams[cam_id]))
            cam_id, pose = turned_cams[cam_id], quarter * pose
            xy = np.c_[cam.height - xy[:, 1], xy[:, 0]]
        out.add_image_with_trivial_frame(pycolmap.Image(name=image.name, keypoints=xy, camera_id=cam_id, image_id=image_id), pose)
        registered.add(image_id)
    for point in rec.points3D.values():
        track = pycolmap.Track()
        for el in point.track.elements:
            if el.image_id in registered:
                track.add_element(el.image_id, el.point2D_idx)
        if track.length() >= 2:
            out.add_point3D(point.xyz, track, point.color)
    out.update_point_3d_errors()
    return out, folder


def _camera_mode(pycolmap, mode: str):
    """COLMAP's mode over the grouped folder of :func:`group_photos`: one camera per group folder for ``auto``."""
    return {"auto": pycolmap.CameraMode.PER_FOLDER, "single": pycolmap.CameraMode.SINGLE}.get(mode, pycolmap.CameraMode.PER_IMAGE)


def group_photos(flat: Path, names: "list[str]", info: "list[tuple[int, int, str]]", out: Path) -> None:
    """Link each photo of ``flat`` into ``out/<width>x<height>[-<model>]/``: one folder per camera group."""
    for name, (w, h, model) in zip(names, info):
        tag = "".join(c if c.isalnum() else "_" for c in model.strip())[:40]
        folder = out / (f"{w}x{h}" + (f"-{tag}" if tag else ""))
        folder.mkdir(parents=True, exist_ok=True)
        (folder / name).symlink_to((flat / name).resolve())


def flatten_names(rec) -> None:
    """Name the images by their file name again (the group folders were only for COLMAP's cameras)."""
    for image in rec.images.values():
        image.name = Path(image.name).name


def drop_untracked_points(rec) -> None:
    """Delete the points of ``rec`` that fewer than two registered photos still see (after deregistrations)."""
    for point_id in list(rec.point3D_ids()):
        if rec.point3D(point_id).track.length() < 2:
            rec.delete_point3D(point_id)


def size_work(work: Path, size: int) -> Path:
    """The work folder of the reconstruction at ``size`` px among ``candidate_sizes`` (its photos, matches and model)."""
    return work / f"size{size}"


def keep_registered(rec, names: "set[str]") -> None:
    """Deregister from ``rec`` the photos (by file name) not in ``names``, and the points that no longer have a track."""
    for image_id in list(rec.reg_image_ids()):
        image = rec.image(image_id)
        if Path(image.name).name not in names:
            rec.deregister_frame(image.frame_id)
    drop_untracked_points(rec)


def drop_failed_registrations(rec, max_spread: float) -> "list[str]":
    """Deregister photos with bogus intrinsics (COLMAP's own test: focal length within 0.1-10x the image
    size, distortion below 1) or a centre far outside the others' (``max_spread`` x the median distance
    from the median centre); return their names."""
    import numpy as np

    ids = list(rec.reg_image_ids())
    centres = np.array([rec.image(i).projection_center() for i in ids]).reshape(-1, 3)
    dist = np.linalg.norm(centres - np.median(centres, axis=0), axis=1)
    far = dist > max_spread * max(float(np.median(dist)), 1e-12) if max_spread > 0 and len(ids) > 2 else np.zeros(len(ids), bool)
    dropped = []
    for image_id, is_far in zip(ids, far):
        image = rec.image(image_id)
        if is_far or image.camera.has_bogus_params(0.1, 10.0, 1.0):
            dropped.append(image.name)
            rec.deregister_frame(image.frame_id)
    drop_untracked_points(rec)
    return sorted(dropped)


def _options(pycolmap, config: SfmConfig, time_left: "float | None"):
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = config.num_threads
    ext.sift.max_num_features = config.max_num_features
    match = pycolmap.FeatureMatchingOptions()
    match.num_threads = config.num_threads
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = config.num_threads
    if time_left is not None:
        mapping.max_runtime_seconds = max(1, int(time_left))
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = config.camera_model
    return ext, match, mapping, reader


def _progress():
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("sfm: {task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())


@contextlib.contextmanager
def _colmap_log(pycolmap, verbose: bool):
    """Silence COLMAP's INFO and WARNING lines unless ``verbose`` (restored afterwards): its warnings are for COLMAP's
    own mapper (a 23-photo folder printed 13-24 lines of "Discarding reconstruction due to insufficient size" among the
    progress bars); what they amount to, the stage says itself (registered photos, dropped registrations, checks)."""
    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = old if verbose else max(old, 2)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def reconstruct(images: Path, work: Path, config: SfmConfig, info, time_left: "float | None" = None,
                matches_from: "Path | None" = None, min_inliers: int = 0, single_model: bool = False):
    """Features, matching and mapping over ``images`` (grouped as :func:`group_photos`: one folder per
    camera); return (largest reconstruction, seconds per step). ``matches_from``: a database of the same images
    whose features and verified matches are mapped instead, without the photo pairs of fewer than ``min_inliers``
    verified matches (:func:`strict_check`). ``single_model``: only the model grown from the first initial pair, not
    further models from the photos left over (an unfolding's mapping, :func:`_candidate`: on a database of 23 of
    colmap_mouse's photos without a fold's pairs, the one model of 11 photos in 1.1 s, against 11 and 15 (a fold) in
    6.6 s within a 10 s limit, 11 and 6 in 33 s within 30 s, and 293.6 s without a limit)."""
    pycolmap = require("pycolmap", "colmap")
    ext, match, mapping, reader = _options(pycolmap, config, time_left)
    mapping.multiple_models = not single_model
    db, n = work / "database.db", len(info)
    db.unlink(missing_ok=True)
    seconds, cpu = {}, pycolmap.Device.cpu
    with _progress() as bar, _colmap_log(pycolmap, config.verbose):
        t = time.monotonic()
        if matches_from is None:
            task = bar.add_task("features", total=1)
            pycolmap.extract_features(db, images, camera_mode=_camera_mode(pycolmap, config.camera_mode),
                                      reader_options=reader, extraction_options=ext, device=cpu)  # fmt: skip
            bar.update(task, completed=1, description=f"features ({n} images)")
            seconds["features"], t = time.monotonic() - t, time.monotonic()
            task = bar.add_task("matching", total=1)
            if n > config.exhaustive_max_photos and config.match_neighbours < n - 1:
                pair_list = work / "pairs.txt"
                pair_list.write_text("".join(f"{a} {b}\n" for a, b in similar_pairs(db, config.match_neighbours)))
                pairing = pycolmap.ImportedPairingOptions()
                pairing.match_list_path = str(pair_list)
                pycolmap.match_image_pairs(db, matching_options=match, pairing_options=pairing, device=cpu)
            else:
                pycolmap.match_exhaustive(db, matching_options=match, device=cpu)
            bar.update(task, completed=1)
        else:
            shutil.copyfile(matches_from, db)
            drop_weak_pairs(db, min_inliers)
        seconds["matching"], t = time.monotonic() - t, time.monotonic()
        task = bar.add_task("registered images", total=n)
        registered = [0]  # registrations counted, capped at the photos: a mapping that starts a second model registers again

        def advance(k: int) -> None:
            registered[0] += k
            bar.update(task, completed=min(registered[0], n))

        models = pycolmap.incremental_mapping(db, images, work / "sparse", options=mapping,
                                              initial_image_pair_callback=lambda: advance(2),
                                              next_image_callback=lambda: advance(1))  # fmt: skip
        seconds["mapping"] = time.monotonic() - t
    if not models:
        raise NerfpipeError("structure from motion registered no images (too few matches between the photos)", images)
    return max(models.values(), key=lambda r: r.num_reg_images()), seconds


SIMILARITY_FEATURES = 512
"""Features per photo (COLMAP's first, the largest) that :func:`similar_pairs` matches between every pair."""


def similar_pairs(database: Path, neighbours: int) -> "list[tuple[str, str]]":
    """Pairs of image names (as the database holds them) to match: each photo with the ``neighbours`` photos that
    most of its :data:`SIMILARITY_FEATURES` first features match (:func:`similarity_scores`)."""
    import numpy as np

    pycolmap = require("pycolmap", "colmap")
    with contextlib.closing(pycolmap.Database.open(str(database))) as db:
        images = db.read_all_images()
        descriptors = [np.asarray(db.read_descriptors(im.image_id).data)[:SIMILARITY_FEATURES] for im in images]
    scores = similarity_scores(descriptors)
    pairs = set()
    for i, row in enumerate(scores):
        for j in np.argsort(-row, kind="stable")[:neighbours]:
            if j != i:
                pairs.add((min(i, int(j)), max(i, int(j))))
    return [(images[a].name, images[b].name) for a, b in sorted(pairs)]


def similarity_scores(descriptors: "list[object]", ratio: float = 0.8) -> "object":
    """``[n, n]`` symmetric counts of feature matches between photos (``descriptors``: one ``[k, d]`` array per photo,
    SIFT's): a feature of one photo matches its nearest in the other where that is nearer than ``ratio`` times the
    second nearest (Lowe's test), on L2-normalised descriptors; the diagonal is -1."""
    import numpy as np
    import torch

    n, k = len(descriptors), max((len(d) for d in descriptors), default=0)
    dim = next((d.shape[1] for d in descriptors if len(d)), 128)
    table = torch.zeros(n, k, dim)
    valid = torch.zeros(n, k, dtype=torch.bool)
    for i, d in enumerate(descriptors):
        if len(d):
            v = torch.as_tensor(np.asarray(d, dtype=np.float32))
            table[i, : len(v)] = v / v.norm(dim=1, keepdim=True).clamp(min=1e-12)
            valid[i, : len(v)] = True
    counts = torch.zeros(n, n)
    if k >= 2:
        for i in range(n):
            for j in range(0, n, 64):  # [k, 64, k] similarities at a time (64 MB at k = 512)
                m = min(64, n - j)
                sims = (table[i] @ table[j : j + m].reshape(m * k, dim).T).reshape(k, m, k).masked_fill(~valid[None, j : j + m], -2.0)
                dist = (2.0 - 2.0 * sims.topk(2, dim=-1).values).clamp(min=0.0).sqrt()
                counts[i, j : j + m] = ((dist[..., 0] < ratio * dist[..., 1]) & valid[i][:, None]).sum(0).float()
    counts = counts + counts.T
    counts.fill_diagonal_(-1.0)
    return counts.numpy()


def drop_weak_pairs(database: Path, min_inliers: int) -> int:
    """Delete from a COLMAP database the verified photo pairs with fewer than ``min_inliers`` inlier matches (as
    verification requiring that many would have left them out); returns how many."""
    pycolmap = require("pycolmap", "colmap")
    with contextlib.closing(pycolmap.Database.open(str(database))) as db:
        pair_ids, geometries = db.read_two_view_geometries()
        weak = [pycolmap.pair_id_to_image_pair(p) for p, g in zip(pair_ids, geometries) if len(g.inlier_matches) < min_inliers]
        for a, b in weak:
            db.delete_two_view_geometry(a, b)
    return len(weak)


def summary(rec, photos: "list[Path]", seconds: dict) -> dict:
    """What ``sfm/sfm.json`` records."""
    registered = sorted(rec.image(i).name for i in rec.reg_image_ids())
    kept = set(registered)
    return {
        "num_photos": len(photos),
        "num_registered": len(registered),
        "unregistered": sorted(p.name for p in photos if sfm_name(p) not in kept),
        "num_points3D": rec.num_points3D(),
        "mean_reprojection_error_px": rec.compute_mean_reprojection_error(),
        "cameras": [{"id": int(cid), "model": c.model.name, "width": c.width, "height": c.height,
                     "params": [float(v) for v in c.params]} for cid, c in rec.cameras.items()],  # fmt: skip
        "seconds": {k: round(v, 2) for k, v in seconds.items()},
    }


def _write_result(rec, images: Path, work: Path, target: Path, undistort: bool, record: dict, verbose: bool = False) -> None:
    """``target``: the reconstruction and its photos (undistorted by COLMAP, its INFO lines silenced unless ``verbose``)."""
    pycolmap = require("pycolmap", "colmap")
    model_dir = work / "best"
    shutil.rmtree(model_dir, ignore_errors=True)
    model_dir.mkdir(parents=True)
    rec.write(str(model_dir))
    with atomic_path(target) as tmp:
        if undistort:
            with _colmap_log(pycolmap, verbose):
                pycolmap.undistort_images(tmp, model_dir, images)
        else:
            shutil.copytree(images, tmp / "images")
            shutil.copytree(model_dir, tmp / "sparse" / "0")
        (tmp / "sfm.json").write_text(json.dumps(record, indent=2) + "\n")


def run(config: SfmConfig, ctx: StageContext) -> "dict[str, object]":
    pycolmap = require("pycolmap", "colmap")
    if _adapter_reads(ctx.source):  # applies() said: a posed capture without points
        posed = posed_without_points(ctx)
        if posed is None:
            raise NerfpipeError("the input has poses and needs no structure from motion (sfm.triangulate is off, or it has points)", ctx.source)
        return run_triangulation(config, ctx, posed)
    folder = _video_frames(config, ctx) if is_video(ctx.source) else photo_folder(ctx.source)
    photos = _photos(folder)
    work = ctx.path(WORK_DIR)
    shutil.rmtree(work, ignore_errors=True)
    try:
        rec, seconds, images, unfolded = _candidate(photos, work, config, ctx.time_left(), ctx.log)
        dropped = drop_failed_registrations(rec, config.max_centre_spread)
        if dropped:
            ctx.log.warning("sfm: dropped %d registrations as failed (bogus intrinsics or far off): %s", len(dropped), ", ".join(dropped))
        rec, images, chosen = choose_reconstruction(photos, work, config, (rec, images), ctx.time_left(), ctx.log, unfolded)
    except NerfpipeError as exc:  # name the user's photos, not the scratch folder (a photo at fault keeps its name)
        if exc.path is not None and (exc.path == work or work in exc.path.parents):
            raise NerfpipeError(exc.problem, folder) from exc
        raise
    if rec.num_reg_images() < config.min_registered:
        raise NerfpipeError(f"sfm registered only {rec.num_reg_images()} of {len(photos)} photos", ctx.source)
    chosen["unfold"] = {config.max_image_size: unfolded} | chosen.get("unfold", {})
    turned = turned_names(images)
    if turned:
        chosen["turned"] = sorted(turned)
    rec, images = unturn(rec, images)
    record = summary(rec, photos, seconds) | {"dropped": dropped} | chosen
    _write_result(rec, images, work, ctx.path(SFM_DIR), config.undistort, record, config.verbose)
    ctx.log.info("sfm: %d of %d photos registered, %d points", record["num_registered"], len(photos), rec.num_points3D())
    result = pycolmap.Reconstruction(str(_model_dir(ctx.path(SFM_DIR))))
    return {"sfm_reconstruction": result, "sfm_summary": record}


VIDEO_SFM_SHARE = 0.2
"""Under a time budget, the share of the time left that a video's structure from motion is planned to take
(:func:`frames_for_budget`)."""
SFM_SECONDS_PER_FRAME = 0.6
"""Seconds of structure from motion per frame on this 2-core CPU: a video of 67 of ngp_fox's photos (544 x 960),
50 frames in 30.0 s (features 7.4, matching 12.3, mapping 6.1; session 80, a fast hour)."""
MIN_VIDEO_FRAMES = 12
"""The fewest frames a time budget cuts a video down to."""


def frames_for_budget(frames: int, time_left: "float | None") -> int:
    """How many of a video's frames to reconstruct: ``frames`` (:attr:`SfmConfig.video_frames`), fewer where their
    structure from motion would take more than :data:`VIDEO_SFM_SHARE` of the time left (at
    :data:`SFM_SECONDS_PER_FRAME`), but not under :data:`MIN_VIDEO_FRAMES`. ``--time-budget 180``: 50; 120: 40; 60: 20.

    Example:
        >>> frames_for_budget(50, None), frames_for_budget(50, 180.0), frames_for_budget(50, 60.0), frames_for_budget(50, 10.0)
        (50, 50, 20, 12)
    """
    if time_left is None:
        return frames
    fits = int(VIDEO_SFM_SHARE * max(time_left, 0.0) / SFM_SECONDS_PER_FRAME)
    return min(frames, max(fits, MIN_VIDEO_FRAMES))


def _video_frames(config: SfmConfig, ctx: StageContext) -> Path:
    """``RUN_DIR/frames``: the video input's sharpest frames (:attr:`SfmConfig.video_frames`, fewer under a tight
    time budget: :func:`frames_for_budget`) at most ``max_image_size`` on the longer side (what the reconstruction
    uses), written once (an interrupted stage resumes with them)."""
    frames = ctx.path(FRAMES_DIR)
    if not frames.is_dir():
        count = frames_for_budget(config.video_frames, ctx.time_left())
        with atomic_path(frames) as tmp:
            written = write_frames(ctx.source, tmp, count, config.max_image_size)
        ctx.log.info("sfm: %d frames taken from %s", len(written), Path(ctx.source).name)
    return frames


def rotation_agreement(rotations: "dict[str, object]", reference: "dict[str, object]", tolerance: float = 5.0) -> "dict[str, float | int]":
    """Agreement of camera rotations (``cam_from_world``, 3x3 arrays, by name) with a reference's, up to one rotation of
    the world: for each shared name the alignment that makes that camera exact, keeping the one under which most cameras
    agree within ``tolerance`` degrees (a reconstruction that folds part of a capture keeps the rest exact, and a
    least-squares alignment would blur which part is wrong). Returns the shared count, the agreeing count and the
    median error in degrees under that alignment (None where they share no photo)."""
    import numpy as np

    errors = rotation_errors(rotations, reference, tolerance)
    if not errors:
        return {"shared": 0, "agree": 0, "median_error": None}  # None, not NaN: sfm.json stays JSON
    best = np.array(list(errors.values()))
    return {"shared": len(errors), "agree": int((best < tolerance).sum()), "median_error": round(float(np.median(best)), 2)}


def added_agreement(rotations: "dict[str, object]", other: "dict[str, object]", added: "frozenset[str]" = frozenset(),
                    other_added: "frozenset[str]" = frozenset()) -> "dict[str, float | int]":
    """:func:`rotation_agreement` of two reconstructions where the photos an unfolding's continuation added to one
    (``added``, ``other_added``: :func:`nerfpipe.plugins.unfold.extended`) and the other lacks count as shared photos
    that disagree, where they are more than the share of photos that may disagree (``1 - SAME_POSES`` of them all): they
    did not pass the unfolding, and a reconstruction without them cannot vouch for a block of them (23 of
    colmap_mouse's photos from the second, session 91: 640 px continuations added blocks of 2-4 photos 147-167 degrees
    off to 11-13, without a conflict). A photo or two beside many are left to the comparison of the others (the 23
    photos from the first: 2 right photos added at 1,024 px to 19, where the 640 px reconstruction placed 18 of those
    19 alike: counted, the consensus kept 18 of 21 in 2 of 4 runs)."""
    agreement = rotation_agreement(rotations, other)
    unconfirmed = len((set(added) - set(other)) | (set(other_added) - set(rotations)))
    if unconfirmed <= int((1.0 - SAME_POSES) * (agreement["shared"] + unconfirmed) + 1e-9):
        return agreement
    return agreement | {"shared": agreement["shared"] + unconfirmed}


def rotation_errors(rotations: "dict[str, object]", reference: "dict[str, object]", tolerance: float = 5.0) -> "dict[str, float]":
    """Each shared photo's rotation error in degrees under :func:`rotation_agreement`'s alignment (the one under which
    most agree within ``tolerance``), by name."""
    import numpy as np

    names = sorted(set(rotations) & set(reference))
    if not names:
        return {}
    ours = np.stack([np.asarray(rotations[n], dtype=float) for n in names])
    ref = np.stack([np.asarray(reference[n], dtype=float) for n in names])
    best = None
    for k in range(len(names)):
        world = ref[k].T @ ours[k]  # the reference's world from ours
        rel = np.einsum("nij,kj,nlk->nil", ours, world, ref)  # ours @ world.T @ ref.T per camera
        err = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
        if best is None or (err < tolerance).sum() > (best < tolerance).sum():
            best = err
    return {n: float(e) for n, e in zip(names, best)}


def model_rotations(rec, images: "Path | None" = None) -> "dict[str, object]":
    """``cam_from_world`` rotations (3x3 arrays) of a pycolmap reconstruction's posed images, by file name; of the
    upright cameras where ``images`` (the folder it was mapped on) names photos that :func:`turn_photos` turned, so
    that reconstructions at image sizes that turned different photos compare. Photos of different sizes round to
    swapped sizes at one size and not at another: the Sacre Coeur's ten photos (no EXIF), a portrait one turned at
    640 px and not at 1,024, read 90 degrees apart as the sizes' only disagreement in 4 of 5 runs (session 90), and one
    run's 100-step check then kept the 640 px reconstruction of 8 photos, and its consensus 7."""
    import numpy as np

    turned = turned_names(images) if images is not None else set()
    rotations = {Path(img.name).name: np.asarray(img.cam_from_world().rotation.matrix()) for img in rec.images.values() if img.has_pose}
    return {name: np.array(QUARTER) @ r if name in turned else r for name, r in rotations.items()}


SAME_POSES = 0.9
"""Share of the shared photos whose rotations agree (:func:`rotation_agreement`) for two reconstructions to count as one."""

MIN_REGISTERED_SHARE = 0.75
"""Reconstructions registering fewer photos than this share of the most any registered are not candidates."""

CHECK_SECONDS = 15.0
"""What one reconstruction's :func:`photometric_check` takes on a 2-core CPU (about 100 steps and the load), for the budget."""

CHECK_MAX_SHARE = 0.25
"""Share of the time left that the checks may take under a time budget (otherwise the first reconstruction is kept)."""

CHECK_VIEWS = 3
"""Held-out photographs of :func:`photometric_check` (registered in every reconstruction, spread over their names)."""

CHECK_MAX_SIZE = 200
"""Longest side of the check's renders."""


def photometric_check(folders: "list[Path]", steps: int, work: Path, rays_per_step: "int | None" = None) -> "list[float]":
    """Held-out PSNR of a short ``fast`` fit (``steps`` steps) on each reconstruction (COLMAP folders of the same
    photos), scored on the same :data:`CHECK_VIEWS` photographs registered in all of them, left out of every fit:
    poses that fold part of a capture cannot be rendered consistently from the others' views. NaN for every one
    when they share no more than :data:`CHECK_VIEWS` photos. ``rays_per_step``: the trainer's default where None."""
    import dataclasses

    import numpy as np

    from nerfpipe.data.background import background_colors
    from nerfpipe.data_adapters import load
    from nerfpipe.models.fast import FastConfig
    from nerfpipe.training.evaluation import eval_sizes, score_views
    from nerfpipe.training.trainer import Trainer, TrainerConfig
    from nerfpipe.util.progress import track

    scenes = [load(folder) for folder in folders]
    names = [[Path(p).name for p in scene.images.paths] for scene in scenes]
    shared = sorted(set.intersection(*(set(n) for n in names)))
    if len(shared) <= CHECK_VIEWS:  # nothing to train on and score alike
        return [float("nan")] * len(scenes)
    held = set(shared[:: max(1, len(shared) // CHECK_VIEWS)][:CHECK_VIEWS])
    scores = []
    for k, (scene, scene_names) in track(enumerate(zip(scenes, names)), "sfm: checking the reconstructions", total=len(scenes)):
        val = np.array([i for i, n in enumerate(scene_names) if n in held], dtype=np.int64)
        train = np.array([i for i, n in enumerate(scene_names) if n not in held], dtype=np.int64)
        scene = dataclasses.replace(scene, splits={"train": train, "val": val, "test": np.zeros(0, dtype=np.int64)})
        # iters unbounded: the schedules of a run of the usual length, whose first steps these are
        cfg = TrainerConfig(iters=10**9, rays_per_step=rays_per_step, eval_every=0, video_frames=0, checkpoint_every=0, eval_max_size=CHECK_MAX_SIZE,
                            eval_supersample=1)
        trainer = Trainer(cfg, scene, "fast", FastConfig(), work / f"check{k}")
        trainer.model.train()
        while trainer.step < steps:
            trainer.train_step()
        idx = [int(i) for i in val]  # rendered in eval mode without gradients (render_cameras)
        out = score_views(trainer.model, scene, idx, eval_sizes(scene, idx, 1.0, CHECK_MAX_SIZE),
                          background_colors(trainer.eval_bg, 1)[0], trainer.cfg.device, trainer.cfg.chunk)
        scores.append(float(np.mean(out["psnr"])))
    return scores


UNFOLD_MODELS_SECONDS = 10.0
"""Seconds an unfolding's mapping may take to grow several models, where the one model grown from the first initial
pair registers too few photos to be kept (fewer than a third of the folded reconstruction's). On a 1,024 px fold of 23
of colmap_mouse's photos stored as HEIC (session 73; every mapping of it folded: 11 of 23 photos within 5 degrees of
COLMAP's model, 4-5 conflicts), the first initial pair without the fold's 76-78 weak pairs grew no model that COLMAP
kept (0 photos, 0.1 s, three times out of three; likewise with ``max_num_models`` 1), and the several models' largest
had 20-21 photos, 18 within 5 degrees, no conflict, in 1.8-3.8 s."""


def remap_unfolded(work: Path, config: SfmConfig, info, database: Path, needed: int, time_left: "float | None"):
    """An unfolding's mapping (:func:`nerfpipe.plugins.unfold.unfold`'s ``remap``) of the photos grouped in ``work``
    from ``database`` (the verified matches without the fold's weak pairs): the one model grown from the first initial
    pair, or where that registers fewer than ``needed`` photos (the fewest a remap is kept with) the largest of several
    models grown within :data:`UNFOLD_MODELS_SECONDS`; the larger of the two where neither has enough, None where
    neither maps. Failed registrations are dropped first, as the stage keeps a reconstruction."""
    started, best = time.monotonic(), None
    for single in (True, False):
        left = None if time_left is None else max(1.0, time_left - (time.monotonic() - started))
        if not single:
            left = UNFOLD_MODELS_SECONDS if left is None else min(left, UNFOLD_MODELS_SECONDS)
        try:
            other = reconstruct(work / "grouped", work / "unfold", config, info, left, matches_from=database, single_model=single)[0]
        except NerfpipeError:
            continue
        drop_failed_registrations(other, config.max_centre_spread)
        if best is None or other.num_reg_images() > best.num_reg_images():
            best = other
        if best.num_reg_images() >= needed:
            break
    return best


EXTEND_SECONDS = 20.0
"""Seconds at most that :func:`extend_mapping` may take (2-3 s for 23 photos at 1,024 px, session 91)."""


def extend_mapping(work: Path, config: SfmConfig, kept, database: Path, time_left: "float | None"):
    """The mapping of the photos grouped in ``work`` continued from the reconstruction ``kept`` (an unfolding's, of
    the same database's photos) with every verified pair of ``database`` (:func:`nerfpipe.plugins.unfold.extended`):
    the model it grows, its failed registrations dropped, or None where it fails."""
    pycolmap = require("pycolmap", "colmap")
    left = EXTEND_SECONDS if time_left is None else min(time_left, EXTEND_SECONDS)
    mapping = _options(pycolmap, config, left)[2]
    mapping.multiple_models = False
    folder = work / "unfold" / "extend"
    shutil.rmtree(folder, ignore_errors=True)
    (folder / "input").mkdir(parents=True)
    (folder / "sparse").mkdir()
    kept.write(folder / "input")
    try:
        with _colmap_log(pycolmap, config.verbose):
            models = pycolmap.incremental_mapping(database, work / "grouped", folder / "sparse", options=mapping, input_path=folder / "input")
    except (RuntimeError, ValueError):  # COLMAP refuses the input (it checks the images against the database)
        return None
    if not models:
        return None
    other = max(models.values(), key=lambda r: r.num_reg_images())
    drop_failed_registrations(other, config.max_centre_spread)
    return other


def _candidate(photos: "list[Path]", work: Path, config: SfmConfig, time_left: "float | None", log=None):
    """One reconstruction of ``photos`` in ``work`` at ``config.max_image_size``, unfolded where every pair of photos
    was matched (:attr:`SfmConfig.unfold`): (reconstruction, seconds, images folder, what the unfolding did)."""
    info, names = prepare_images(photos, work / "images", config.max_image_size), [sfm_name(p) for p in photos]
    if config.turn and config.camera_mode == "auto" and config.camera_model in TURNABLE_MODELS:
        info = turn_photos(work / "images", names, info, photos_to_turn(info))
    group_photos(work / "images", names, info, work / "grouped")
    started = time.monotonic()
    rec, seconds = reconstruct(work / "grouped", work, config, info, time_left)
    unfolded: dict = {}
    if config.unfold and len(photos) <= config.exhaustive_max_photos:
        t, needed = time.monotonic(), -(-rec.num_reg_images() // 3)  # what unfold.unfold keeps a remap from

        def left() -> "float | None":
            return None if time_left is None else max(1.0, time_left - (time.monotonic() - started))

        def remap(database: Path):
            return remap_unfolded(work, config, info, database, needed, left())

        def extend(kept):
            return extend_mapping(work, config, kept, work / "database.db", left())

        longest = max(max(w, h) for w, h, _ in info)
        rec, unfolded = unfold.unfold(rec, work / "database.db", work / "unfold" / "pairs", remap, weak=unfold.weak_inliers(longest),
                                      extend=extend if config.extend_unfolded else None)
        seconds["unfold"] = time.monotonic() - t
        if unfolded.get("kept") and log is not None:
            kept = [r for r in unfolded["rounds"] if r.get("kept")][-1]
            log.warning("sfm: at %d px the reconstruction placed %d pairs of photos that share no matches side by side (a "
                        "fold); mapped again without the weak photo pairs that agree with it: %d of %d photos registered, "
                        "%d such pairs left", config.max_image_size, unfolded["conflicts"], kept["registered"], len(photos),
                        kept["conflicts"])  # fmt: skip
            extended = unfolded.get("extended", {})
            if extended.get("kept"):
                left_out = extended["registered"] - extended["final"]
                log.warning("sfm: mapped on from it with every photo pair: %d of %d photos registered%s", extended["final"],
                            len(photos), f" ({left_out} more left out: their matches disagree with where they were placed)" if left_out else "")
    flatten_names(rec)
    return rec, seconds, work / "images", unfolded


def choose_reconstruction(photos: "list[Path]", work: Path, config: SfmConfig, first, time_left: "float | None", log,
                          first_unfolded: "dict | None" = None) -> "tuple[object, Path, dict]":
    """The reconstruction to keep among ``first`` (``(rec, images folder)``, at ``max_image_size``, made in ``work``,
    its failed registrations dropped) and those at ``candidate_sizes`` (see :attr:`SfmConfig.candidate_sizes`), then
    without the photos that only weak matches attach (:func:`strict_check`) where no reconstruction at another size
    agrees with it; returns it, its images folder and what was decided."""
    started = time.monotonic()
    rec, images, record, rivals = _choose_by_size(photos, work, config, first, time_left, log, first_unfolded)
    chosen, kept = rec, record.get("kept_max_image_size", config.max_image_size)
    added = frozenset(record.get("added", {}).get(kept, ()))  # photos that did not pass the unfolding (unfold.extended)
    if config.strict_min_inliers > 0 and len(photos) <= config.candidate_max_photos and not record.get("corroborated", False):
        left = None if time_left is None else time_left - (time.monotonic() - started)
        others = [work] + [size_work(work, size) for size in config.candidate_sizes if (size_work(work, size) / "database.db").is_file()]
        # witnesses whose unfolding left a block out, where the kept reconstruction was not itself unfolded (keep_consensus)
        unfolded = frozenset(record.get("unfolded", ()))
        witnesses = frozenset() if kept in unfolded else unfolded
        rec, images, record["strict"] = strict_check(photos, work, config, (rec, images), left, log, tuple(others), rivals, witnesses, added)
    if added and rec is chosen and not record.get("corroborated", False) and "consensus" not in record.get("strict", {}):
        # no other image size vouched for them (none agrees, or none is left to compare: 23 of colmap_mouse's photos from
        # the second, session 91, a 1,024 px fold not undone and a 640 px continuation adding 3 photos 147-162 degrees off)
        names = set(model_rotations(rec))
        if names & added:
            keep_registered(rec, names - added)
            record["added_left_out"] = sorted(names & added)
            log.warning("sfm: left out the %d photos that mapping on from the unfolding added: no reconstruction at another "
                        "image size places them alike", len(record["added_left_out"]))
    return rec, images, record


STRICT_MARGIN = 0.4
"""dB by which the strict reconstruction's fit must render the held-out photographs better for its photos alone to be
kept (:func:`strict_check`). Measured on 23-photo cuts of colmap_mouse after 100 steps of 4,096 rays (session 30):
where the capture folds, +0.70, +0.45, +0.73 and +0.62 dB in four runs; where it is right, +0.15 and +0.39: a thin
separation, and in session 31 a fold at +0.11 and a right reconstruction at +0.73. Since then the fits are longer
(:attr:`SfmConfig.strict_check_steps`): folds at **+0.55, +0.83, +1.65 and +1.91**, right reconstructions at **-0.45 and
-0.59**; and +0.50 for a right 30-photo cut whose two sizes agreed (checked for the measurement only: agreement skips
the check). The two overlap; a kept fold breaks the model, a dropped right photo costs a view: 0.4 (0.65 for part of
session 31 let the +0.55 fold through). Session 35, 23 photos of colmap_mouse through ``nerfpipe run --time-budget 180``:
the strict mapping's 6 photos, all right, against the chosen 18 (8 right): -1.63 dB (18.41 against 20.04; three of the six
held out, three to fit): a subset this small loses the check whatever the others' poses, and the fold was kept."""


STRICT_CHECK_RAYS = 2048
"""Rays per step of :func:`subset_check`'s fits (0.6x the seconds per step of 4,096 on these cuts; see
:attr:`SfmConfig.strict_check_steps`)."""

STRICT_FIT_SECONDS = 45.0
"""What one of :func:`subset_check`'s fits takes on a 2-core CPU, for the budget: 15-20 s for the cuts' 400 steps when
measured (session 30), but a 23-photo folder's two fits took 91 s on a slower hour (session 41, colmap_mouse's
training steps 0.2 s instead of 0.1), under ``--time-budget 180`` with 144 s left: the test ran where it seemed to fit
in :data:`CHECK_MAX_SHARE` of the time, and training had 34 s (143 steps; 21.19 dB, mesh 52 % of the points)."""


STRICT_MIN_LEFT_OUT = 3
"""Photos the strict reconstruction must leave out for :func:`subset_check` to test them (its two fits take about 35 s
on a 2-core CPU; one or two weakly attached photos are left to the reconstruction as it is)."""


def strict_check(photos: "list[Path]", work: Path, config: SfmConfig, chosen, time_left: "float | None", log,
                 others: "tuple[Path, ...]" = (), rivals: "dict | None" = None,
                 unfolded_sizes: "frozenset[int]" = frozenset(), added: "frozenset[str]" = frozenset()) -> "tuple[object, Path, dict]":
    """``chosen`` (``(rec, images folder)``), or the strict reconstruction (the chosen reconstruction's own verified
    matches, those of its image size, mapped again in ``work`` without the photo pairs of fewer than
    ``strict_min_inliers``, then fewer (:func:`strict_thresholds`), then the same with the matches of the work folders
    ``others`` (the other image sizes'), until one leaves more than :data:`CHECK_VIEWS` + 2 photos: at 640 px the
    matches of 23 of colmap_mouse's photos left two at every requirement, at 1,024 px seven, all right) where that
    registers a proper subset of its photos and a fit on it renders photographs
    registered in both, left out of both fits, at least
    :data:`STRICT_MARGIN` dB better: the other photos are attached by matches that do not fit them. Called only where no
    reconstruction at another image size corroborates the chosen one. 23 photos of
    colmap_mouse whose 1,024 px and 640 px reconstructions both fold (11 of 23 and 11 of 18 photos within 5 degrees of
    COLMAP's model of all 56): the strict one registers 11, all right, and renders the held-out photos 20.86 against
    20.13 dB. Where the time budget leaves too little for the test, and reconstructions at other image sizes disagree
    with the chosen one (``rivals``: their rotations by image size), only the photos that one of them places alike are
    kept (:func:`keep_consensus`; ``unfolded_sizes``: the sizes whose reconstruction is an unfolding). Returns the one
    kept, its images folder and what was decided."""
    rec, images = chosen
    if time_left is not None and CHECK_MAX_SHARE * time_left < 2 * STRICT_FIT_SECONDS:
        database = images.parent / "database.db"
        unfolded = config.unfold and len(photos) <= config.exhaustive_max_photos and database.is_file()
        unshared = bool(unfolded and not unfold.view_conflicts(rec, unfold.verified_pairs(database)))  # not one conflict
        consensus = keep_consensus(rec, rivals or {}, keep_unshared=unshared, unfolded=unfolded_sizes, images=images, added=added)
        if consensus:
            log.warning("sfm: no time to test the reconstruction for a fold (%.0f s left): kept the %d of its %d photos that the "
                        "%d px reconstruction %s (a run with a larger --time-budget tests them all)", time_left,
                        consensus["kept"], consensus["of"], consensus["max_image_size"],
                        "does not place otherwise" if consensus["unshared"] else "places alike")  # fmt: skip
            return rec, images, {"skipped": "too little time left", "consensus": consensus}
        if unshared:  # no photos side by side without matches: no sign of a fold
            log.info("sfm: no reconstruction at another image size agrees with the one kept; it shows no sign of a fold "
                     "(a run with a larger --time-budget tests it further)")
            return rec, images, {"skipped": "too little time left", "conflicts": "none"}
        log.warning("sfm: no reconstruction at another image size agrees with the one kept, and the time budget leaves too "
                    "little (%.0f s) to test it for a fold: its poses may fold part of the capture (look at "
                    "mesh/mesh_views.png; a run with a larger --time-budget tests it)", time_left)
        return rec, images, {"skipped": "too little time left"}
    strict_work = work / "strict"
    strict, threshold, source, registered = None, 0, images.parent, set(model_rotations(rec))
    # the chosen reconstruction's own image size's matches and photos first, then the other sizes'
    sources = list(dict.fromkeys([images.parent, *(Path(f) for f in others)]))
    for source, threshold in ((f, t) for f in sources for t in strict_thresholds(config.strict_min_inliers)):
        shutil.rmtree(strict_work, ignore_errors=True)
        strict_work.mkdir(parents=True)
        try:
            strict, _ = reconstruct(source / "grouped", strict_work, config, photos, time_left,
                                    matches_from=source / "database.db", min_inliers=threshold)  # fmt: skip
        except NerfpipeError:
            strict = None
            continue
        flatten_names(strict)
        drop_failed_registrations(strict, config.max_centre_spread)
        keep_registered(strict, registered)  # a photo the chosen one dropped (far off there) is no photo to check
        if strict.num_reg_images() > CHECK_VIEWS + 2:  # the strictest that leaves enough photos to check
            break
    if strict is None:
        return rec, images, {"registered": 0}
    strict_images = source / "images"
    record = {"min_inliers": threshold, **({"matches_of": source.name} if source != images.parent else {})}
    record |= subset_check((rec, images), (strict, strict_images), strict_work, config.strict_check_steps, config.undistort, config.verbose)
    if not record.get("kept"):
        return rec, images, record
    registered = record["registered"]
    log.warning("sfm: %d of the %d registered photos do not fit the others (a %d-step fit without them renders held-out photos "
                "%.2f against %.2f dB): kept the %d that strong matches tie together", rec.num_reg_images() - registered,
                rec.num_reg_images(), config.strict_check_steps, record["check_psnr"][1], record["check_psnr"][0], registered)  # fmt: skip
    return strict, strict_images, record


def keep_consensus(rec, rivals: "dict[int, dict]", keep_unshared: bool = False, unfolded: "frozenset[int]" = frozenset(),
                   images: "Path | None" = None, added: "frozenset[str]" = frozenset()) -> "dict | None":
    """Deregister from ``rec`` the photos that no reconstruction in ``rivals`` (rotations by name, by image size) places
    alike (:func:`rotation_errors` within 5 degrees), taking the rival that agrees on the most; where that leaves more
    than :data:`CHECK_VIEWS` + 2 photos and fewer than all. ``keep_unshared`` (where ``rec`` shows no sign of a fold:
    not one :func:`nerfpipe.plugins.unfold.view_conflicts`; until session 74 fewer than ``MIN_CONFLICTS``, and a 1,024
    px reconstruction of 17 photos with one conflict kept 3 photos 5 degrees or more off that the rival lacked): only
    the photos that rival places otherwise, not those it leaves out (23 of colmap_mouse's photos, session 61:
    unfolded at 1,024 px, 21 registered, 19 of them right; at 640 px 12, 10 of them placed alike: the 10 alone
    trained to 20.62 dB, `--time-budget 180`).
    Two independent mappings rarely fold the same block the same way: in three runs of a 23-photo folder of
    colmap_mouse at 1,024 and 640 px (session 41; aligned to COLMAP's model of all 56 photos) the chosen reconstructions held 11, 10 and 11 right photos of 23; the photos the other size
    placed alike were 10, 10 and 17, the first two all mutually consistent (within 0.4 and 0.6 degrees), the third 10
    of 17 (both sizes folded alike there: no worse than before). A rival at a size in ``unfolded`` (a fold found and
    undone there: :func:`nerfpipe.plugins.unfold.unfold`) vouches only for the photos it places alike, ``keep_unshared``
    or not: the photos it lacks include the block its unfolding left out. 23 of colmap_mouse's photos from the second
    (session 74): unfolded at 1,024 px, 11 photos, all within 5 degrees of COLMAP's model; at 640 px 15 photos without a
    conflict, 4 of them 148-166 degrees off and absent at 1,024 px: all 15 were kept. Only where ``rec`` was not unfolded
    itself (:func:`choose_reconstruction`): an unfolded reconstruction's photos passed that test, and an unfolded 640 px
    witness of 11 photos (23 of colmap_mouse's photos as HEIC) made the unfolded 1,024 px one's 18-19 right photos 11
    in 2 of 5 runs. ``added``: photos an unfolding's continuation added to ``rec`` (:func:`nerfpipe.plugins.unfold.extended`),
    kept only where the rival places them alike (they did not pass the unfolding). ``images``: the folder ``rec`` was
    mapped on (upright rotations: :func:`model_rotations`). Returns what was kept
    (``unshared``: whether the photos the rival lacks were), or None where nothing was."""
    if not rivals:
        return None
    rotations = model_rotations(rec, images)
    best = None
    for size, rival in rivals.items():
        errors = rotation_errors(rotations, rival)
        unshared = keep_unshared and size not in unfolded
        alike = {n for n, e in errors.items() if e < 5.0} | ({n for n in rotations if n not in errors and n not in added} if unshared else set())
        if best is None or len(alike) > len(best[1]):
            best = size, alike, unshared
    if best is None or not CHECK_VIEWS + 2 < len(best[1]) < len(rotations):
        return None
    keep_registered(rec, best[1])
    return {"max_image_size": best[0], "kept": len(best[1]), "of": len(rotations), "unshared": best[2]}


STRICT_STEP = 10
"""Verified matches by which :func:`strict_thresholds` lowers the strict mapping's requirement."""

STRICT_FLOOR = 50
"""The lowest requirement :func:`strict_thresholds` tries. Seven folded 1,024 px reconstructions of 23 of colmap_mouse's
photos (session 35): their matches mapped without the pairs of fewer than 80 / 60 / 50 / 40 verified matches registered
6 / 7 / 7 / 14, 6 / 6 / 7 / 14, 6 / 7 / 7 / 14, 6 / 6 / 7 / 14, 2 / 2 / 8 / 14, 2 / 2 / 7 / 14 and 2 / 2 / 7 / 14 photos:
at 50 every photo within 5 degrees of COLMAP's model of all 56 but one (of 8), at 40 only 7-8 of the 14."""


def strict_thresholds(start: int) -> "list[int]":
    """The strict mapping's requirements in verified matches per photo pair, strictest first: ``start``, then
    :data:`STRICT_STEP` less each time down to :data:`STRICT_FLOOR` (``start`` alone where it is at or below the floor):
    at 60 three of seven folded reconstructions of colmap_mouse's photos left only two photos, too few to check."""
    return [start] + list(range(start - STRICT_STEP, STRICT_FLOOR - 1, -STRICT_STEP))


def subset_check(full, subset, work: Path, steps: int, undistort: bool = True, verbose: bool = False, margin: float = STRICT_MARGIN) -> dict:
    """Whether the photos that ``full`` (``(reconstruction, images folder)``) registers beyond ``subset``'s fit the
    others: where ``subset`` registers a proper subset of them (more than :data:`CHECK_VIEWS` + 2, leaving out at least
    :data:`STRICT_MIN_LEFT_OUT`), a ``steps``-step fit
    on each (:func:`photometric_check`, held-out photographs registered in both); ``kept`` is True where the subset's
    renders them at least ``margin`` dB better (:data:`STRICT_MARGIN`). Returns what :func:`strict_check` records."""
    (rec, images), (other, other_images) = full, subset
    rotations, subset_rotations = model_rotations(rec, images), model_rotations(other, other_images)
    names, subset_names = set(rotations), set(subset_rotations)
    record = {"registered": len(subset_names), **rotation_agreement(subset_rotations, rotations)}
    if not subset_names < names or len(subset_names) <= CHECK_VIEWS + 2 or len(names - subset_names) < STRICT_MIN_LEFT_OUT:
        return record  # the same photos, others, too few to fit, or too few left out to be a folded block
    folders = []
    for name, (model, model_images) in (("full", (rec, images)), ("subset", (other, other_images))):
        folder = work / f"check_{name}"
        shutil.rmtree(folder, ignore_errors=True)
        _write_result(model, model_images, work / f"model_{name}", folder, undistort, {}, verbose)
        folders.append(folder)
    psnr = photometric_check(folders, steps, work, rays_per_step=STRICT_CHECK_RAYS)
    record["check_psnr"] = [round(p, 2) for p in psnr]
    record["kept"] = bool(psnr[1] >= psnr[0] + margin)
    return record


def prepared_sources(photos: "list[Path]", images: Path) -> "list[Path]":
    """What the reconstructions at the smaller ``candidate_sizes`` downscale: ``photos``, or where some are HEIF, the
    upright copies that :func:`prepare_images` made of them in ``images`` (the first size's, JPEG, of the same names:
    a 12 MP HEIC photo takes 0.35 s to decode on 2 cores, a JPEG's reduced decode 0.02 s, so 23 of them decoded
    again cost 8 s of a budget)."""
    if not any(p.suffix.lower() in HEIF_SUFFIXES for p in photos):
        return photos
    upright = images.parent / UPRIGHT_DIR
    return [upright / sfm_name(p) if (upright / sfm_name(p)).exists() else images / sfm_name(p) for p in photos]


def with_conflicts(candidates: "list[tuple[int, object, Path]]", unfoldings: "dict[int, dict]") -> "list[int]":
    """The image sizes of ``candidates`` (``(size, reconstruction, images folder)``) whose reconstruction keeps a
    conflict (:func:`nerfpipe.plugins.unfold.view_conflicts`: fewer than ``MIN_CONFLICTS``, so not unfolded) and places
    the photos otherwise than a candidate without one does, in a capture whose mapping folded at some size
    (``unfoldings``: what :func:`nerfpipe.plugins.unfold.unfold` recorded, by size). 23 of colmap_mouse's photos stored
    as HEIC (session 73): at 1,024 px a fold (4 conflicts) undone, 19 photos, 18-19 within 5 degrees of COLMAP's model;
    at 640 px, in 4 of 8 mappings, 20 photos with one conflict: in 2 of those 4 placed as the unfolded ones (18 of 19
    alike), in the other 2 otherwise (8 of 19 alike: a second fold). A 100-step fit rendered the held-out photos 0.2-1.1
    dB better on the second fold than on the unfolded reconstruction (four runs), so the size check kept it and then
    only the 7-10 photos the two place alike."""
    if not any(u.get("conflicts", 0) >= unfold.MIN_CONFLICTS for u in unfoldings.values()):
        return []
    clean = [(rec, images) for size, rec, images in candidates if unfoldings.get(size, {}).get("conflicts_left", 1) == 0]
    return [size for size, rec, images in candidates
            if unfoldings.get(size, {}).get("conflicts_left", 0) > 0
            and any(not unfold.same_poses(rec, other, images, other_images) for other, other_images in clean)]  # fmt: skip


def _choose_by_size(photos: "list[Path]", work: Path, config: SfmConfig, first, time_left: "float | None", log,
                    first_unfolded: "dict | None" = None) -> "tuple[object, Path, dict, dict]":
    """:func:`choose_reconstruction` among the reconstructions at the image sizes; also the rotations
    (:func:`model_rotations`) of the reconstructions that do not corroborate the one kept (they disagree with it, or
    register too few photos to be candidates), by their image size. Where some reconstructions keep a fold that
    :func:`nerfpipe.plugins.unfold.unfold` could not undo and others show none, the folded ones are neither candidates
    nor witnesses (23 of colmap_mouse's photos, session 61: the 640 px reconstruction with 16 conflicts left made the
    unfolded 1,024 px one's consensus keep 9 of its 16 photos)."""
    rec, images = first
    record: dict = {}
    if not config.candidate_sizes or len(photos) > config.candidate_max_photos:
        return rec, images, record, {}
    started = time.monotonic()
    candidates = [(config.max_image_size, rec, images)]
    folded = {config.max_image_size: unfold.still_folded(first_unfolded or {})}
    sources = prepared_sources(photos, images)
    for size in config.candidate_sizes:
        if time_left is not None and time.monotonic() - started > CHECK_MAX_SHARE * time_left:
            break
        cfg = dataclasses_replace(config, max_image_size=size)
        try:
            other, _, other_images, unfolded = _candidate(sources, size_work(work, size), cfg, time_left, log)
        except NerfpipeError:
            continue
        drop_failed_registrations(other, config.max_centre_spread)
        candidates.append((size, other, other_images))
        record.setdefault("unfold", {})[size] = unfolded
        folded[size] = unfold.still_folded(unfolded)
    if not all(folded.values()) and any(folded.values()):
        record["still_folded"] = [c[0] for c in candidates if folded[c[0]]]
        candidates = [c for c in candidates if not folded[c[0]]]
    unfoldings = {config.max_image_size: first_unfolded or {}} | record.get("unfold", {})
    unfolded = [size for size, u in unfoldings.items() if u.get("kept")]  # unfold.unfold keeps a remap only of a fold
    if unfolded:  # a fold found and undone at these sizes (keep_consensus)
        record["unfolded"] = unfolded
    added = {size: frozenset(u["extended"]["added"]) for size, u in unfoldings.items() if u.get("extended", {}).get("kept")}
    if added:  # and continued with the photos the unfolding had left out (unfold.extended)
        record["added"] = {size: sorted(names) for size, names in added.items()}
    conflicted = with_conflicts(candidates, unfoldings)
    if conflicted:
        record["with_conflicts"] = conflicted
        log.warning("sfm: the reconstruction at %s px keeps photos side by side that share no matches and places them otherwise "
                    "than one without: left out (a second fold)", ", ".join(str(size) for size in conflicted))  # fmt: skip
        candidates = [c for c in candidates if c[0] not in conflicted]
    most = max(c[1].num_reg_images() for c in candidates)  # one that registers far fewer photos is no alternative
    few = [c for c in candidates if c[1].num_reg_images() < MIN_REGISTERED_SHARE * most]  # no alternatives, but witnesses (rivals)
    candidates = [c for c in candidates if c[1].num_reg_images() >= MIN_REGISTERED_SHARE * most]
    rotations = [model_rotations(other, other_images) for _, other, other_images in candidates]
    rows, groups = [], []  # groups: indices of candidates whose poses agree, the first of each its representative
    sizes = [c[0] for c in candidates]

    def agreement_of(i: int, j: int) -> dict:  # the photos an extension added that the other lacks count as unconfirmed
        return added_agreement(rotations[i], rotations[j], added.get(sizes[i], frozenset()), added.get(sizes[j], frozenset()))

    for i, (size, other, _) in enumerate(candidates):
        agreement = agreement_of(i, 0)
        rows.append({"max_image_size": size, "registered": other.num_reg_images(), **agreement})
        for group in groups:
            a = agreement if group[0] == 0 else agreement_of(i, group[0])
            if a["agree"] >= SAME_POSES * a["shared"]:
                group.append(i)
                break
        else:
            groups.append([i])
    record["candidates"] = rows
    record["corroborated"] = len(groups[0]) >= 2  # another image size's reconstruction agrees with the first

    def rivals(kept: int) -> dict:  # the reconstructions that do not corroborate candidate ``kept``'s poses
        group = next(g for g in groups if kept in g)
        return {size: model_rotations(other, other_images) for size, other, other_images in few} | {candidates[i][0]: rotations[i] for i in range(len(candidates)) if i not in group}

    record["kept_max_image_size"] = candidates[0][0]  # unless the check below keeps another
    if len(groups) == 1:
        return candidates[0][1], candidates[0][2], record, rivals(0)
    reps = [max(group, key=lambda i: candidates[i][1].num_reg_images()) for group in groups]
    reps.sort(key=lambda i: -candidates[i][1].num_reg_images())
    if time_left is not None:  # as many as the time allows, those registering the most photos first
        reps = reps[: int(CHECK_MAX_SHARE * (time_left - (time.monotonic() - started)) // CHECK_SECONDS)]
    if len(reps) < 2:
        log.warning("sfm: the reconstructions at %s px disagree, and the time left allows no check: kept the first",
                    ", ".join(str(r["max_image_size"]) for r in rows))
        record["unchecked"] = True
        return candidates[0][1], candidates[0][2], record, rivals(0)
    folders = []
    for i in reps:
        size, other, other_images = candidates[i]
        folder = work / f"check_model{size}"
        shutil.rmtree(folder, ignore_errors=True)
        _write_result(other, other_images, work / f"model{size}", folder, config.undistort, {}, config.verbose)
        folders.append(folder)
    psnr = photometric_check(folders, config.check_steps, work)
    if any(p != p for p in psnr):  # NaN: too few photos registered in all of them to compare
        log.warning("sfm: the reconstructions at %s px disagree and share too few photos to compare: kept the first",
                    ", ".join(str(r["max_image_size"]) for r in rows))
        record["unchecked"] = True
        return candidates[0][1], candidates[0][2], record, rivals(0)
    for i, p in zip(reps, psnr):
        rows[i]["check_psnr"] = round(p, 2)
    best = reps[max(range(len(reps)), key=lambda k: (psnr[k], candidates[reps[k]][1].num_reg_images()))]
    record["corroborated"] = any(best in group and len(group) >= 2 for group in groups)
    size, rec, images = candidates[best]
    log.info("sfm: the reconstructions at %s px disagree; kept %d px (held-out PSNR of a %d-step fit: %s dB)",
             ", ".join(str(r["max_image_size"]) for r in rows), size, config.check_steps,
             " / ".join(f"{candidates[i][0]} px {p:.2f}" for i, p in zip(reps, psnr)))
    record["kept_max_image_size"] = size
    return rec, images, record, rivals(best)


def _adapter_reads(path: Path) -> bool:
    from nerfpipe import data_adapters

    try:
        data_adapters.detect(path)
    except NerfpipeError:
        return False
    return True


def run_triangulation(config: SfmConfig, ctx: StageContext, scene) -> "dict[str, object]":
    """Points for a posed capture: ``sfm/points`` (COLMAP model, input frame) and ``sfm/sfm.json``."""
    from nerfpipe.plugins.triangulate import image_name, triangulate

    pycolmap = require("pycolmap", "colmap")
    work = ctx.path(WORK_DIR)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    with _progress() as bar, _colmap_log(pycolmap, config.verbose):
        task = bar.add_task(f"points for {len(scene.cameras)} posed photos", total=3)
        rec, seconds = triangulate(scene, work, config.triangulate_max_image_size, config.triangulate_max_features, config.triangulate_neighbours,
                                   config.num_threads, config.triangulate_max_photos, on_step=lambda name: bar.advance(task))  # fmt: skip
        bar.advance(task)
    record = {
        "mode": "triangulated with the input's poses",
        "num_photos": len(scene.cameras),
        "num_triangulated_photos": rec.num_reg_images(),
        "num_points3D": rec.num_points3D(),
        "mean_reprojection_error_px": rec.compute_mean_reprojection_error(),
        "images": {image_name(i): scene.images.name(i) for i in sorted(int(Path(im.name).stem) for im in rec.images.values())},
        "seconds": {k: round(v, 2) for k, v in seconds.items()},
    }
    with atomic_path(ctx.path(SFM_DIR)) as tmp:
        (tmp / POINTS_DIR).mkdir(parents=True)
        rec.write(str(tmp / POINTS_DIR))
        (tmp / "sfm.json").write_text(json.dumps(record, indent=2) + "\n")
    ctx.log.info("sfm: %d points triangulated with the poses of %d of %d photos (%.2f px)", rec.num_points3D(), rec.num_reg_images(),
                 len(scene.cameras), record["mean_reprojection_error_px"])  # fmt: skip
    return {"sfm_reconstruction": rec, "sfm_summary": record}


def _model_dir(root: Path) -> Path:
    for folder in (root / "sparse" / "0", root / "sparse", root / POINTS_DIR):
        if folder.is_dir():
            return folder
    return root / "sparse"


def restore(config: SfmConfig, ctx: StageContext) -> "dict[str, object]":
    pycolmap = require("pycolmap", "colmap")
    root = ctx.path(SFM_DIR)
    return {"sfm_reconstruction": pycolmap.Reconstruction(str(_model_dir(root))),
            "sfm_summary": json.loads((root / "sfm.json").read_text())}  # fmt: skip


STAGE = StageSpec(
    name="sfm",
    description="pycolmap structure from motion on CPU (only for a folder of photos or a video without a model)",
    config=SfmConfig,
    run=run,
    produces=(SFM_DIR,),
    provides=("sfm_summary", "sfm_reconstruction"),
    applies=applies,
    restore=restore,
    shows=(Shown("sfm", "table", (f"{SFM_DIR}/sfm.json",), "structure from motion summary"),),
)
