"""Per-photo exposure gains from the sparse points' tracks (nerfpipe.data.exposure), and the colour corrections' rule."""

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from nerfpipe.data.exposure import exposure_gains, exposure_spread, srgb_to_linear, track_log_luminance
from nerfpipe.data.scene import ImageSet, Points3D
from nerfpipe.models.base import SceneInfo
from nerfpipe.models.fast import APPEARANCE_EXPOSURE_SPREAD, FastConfig, appearance_by_default


def linear_to_srgb(x):
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.clip(x, 0, None) ** (1 / 2.4) - 0.055)


def _scene(gains, num_points=300, size=128, outliers=0.0, seed=0):
    """Photos of ``num_points`` flat patches of random linear albedo, each photo's light scaled by ``exp(gains[c])``,
    every point seen by 4 random photos, each in a 6 x 6 cell of its own (keypoint off the cell's centre by under a
    pixel); a share ``outliers`` of the observations is a highlight."""
    rng = np.random.default_rng(seed)
    n, cells = len(gains), size // 6
    albedo = rng.uniform(0.05, 0.6, (num_points, 3))
    images = np.full((n, size, size, 3), 0.5)
    point, camera, xy, used = [], [], [], np.zeros(n, dtype=np.int64)
    for p in range(num_points):
        for c in rng.choice(n, 4, replace=False):
            cell = used[c]
            used[c] += 1
            assert cell < cells * cells
            centre = 6 * np.array([cell % cells, cell // cells]) + 3.0
            point.append(p), camera.append(c), xy.append(centre + rng.uniform(-0.9, 0.9, 2))
    shiny = rng.random(len(point)) < outliers
    for k, (p, c, (x, y)) in enumerate(zip(point, camera, xy)):
        value = albedo[p] * np.exp(gains[c]) * (2.5 if shiny[k] else 1.0)
        x0, y0 = 6 * (int(x) // 6), 6 * (int(y) // 6)
        images[c, y0:y0 + 6, x0:x0 + 6] = linear_to_srgb(np.clip(value, 0, 0.95))
    pts = Points3D(torch.zeros(num_points, 3), torch.zeros(num_points, 3, dtype=torch.uint8), None,
                   torch.tensor(point), torch.tensor(camera), torch.tensor(np.array(xy)))
    return pts, ImageSet(array=(images * 255 + 0.5).astype(np.uint8))


def test_gains_recovered_with_highlights():
    """Known gains (log, zero median) come back within the 8-bit rounding's error, a tenth of the observations being
    highlights 2.5 times too bright (the robust weights ignore them; a plain mean would not)."""
    truth = np.array([0.0, 0.4, -0.3, 0.7, -0.6, 0.1, 0.0, -0.1])
    pts, images = _scene(truth, outliers=0.1)
    g = exposure_gains(pts, images, len(truth)).numpy()
    assert np.abs((g - np.median(g)) - (truth - np.median(truth))).max() < 0.03
    assert exposure_spread(torch.from_numpy(g)) == pytest.approx(truth.std(), abs=0.02)
    same = exposure_gains(*_scene(np.zeros(8), outliers=0.1), 8)
    assert exposure_spread(same) < 0.02


def test_clipped_and_unseen_photos():
    """Clipped or dark patches say nothing (NaN), a photo without usable observations has no gain (NaN), and the gains
    are measured only over the cameras asked for."""
    truth = np.array([0.0, 0.3, -0.3, 0.2, 0.0])
    pts, images = _scene(truth)
    arr = images.array.copy()
    arr[1] = 255  # photo 1 blown out
    arr[2] = 2  # photo 2 black
    lum = track_log_luminance(pts, ImageSet(array=arr))
    cam = pts.track_camera.numpy()
    assert torch.isnan(lum[(cam == 1) | (cam == 2)]).all() and torch.isfinite(lum[cam == 0]).all()
    g = exposure_gains(pts, ImageSet(array=arr), 6).numpy()  # camera 5 has no observation at all
    assert np.isnan(g[[1, 2, 5]]).all() and np.isfinite(g[[0, 3, 4]]).all()
    sub = exposure_gains(pts, images, 5, cameras=np.array([0, 3, 4])).numpy()
    assert np.isnan(sub[[1, 2]]).all() and abs((sub[3] - sub[0]) - 0.2) < 0.03
    assert exposure_spread(torch.tensor([0.5, float("nan")])) == 0.0


def test_srgb_curve_matches_kornia():
    kornia = pytest.importorskip("kornia")
    x = torch.linspace(0, 1, 101)
    ref = kornia.color.rgb_to_linear_rgb(x.reshape(1, 1, 101).expand(3, 1, 101)).reshape(3, 101)[0]
    assert np.allclose(srgb_to_linear(x.numpy().astype(np.float64)), ref.numpy(), atol=1e-6)


def test_colmap_mouse_gains(scene_path, tmp_path, monkeypatch):
    """On colmap_mouse (one phone, steady light) the photos' gains spread about 0.2, below the threshold; scaling each photo's linear light
    by a known factor is recovered photo by photo (correlation above 0.95) and raises the spread above the rule's threshold."""
    from nerfpipe.data_adapters import load

    scene = load(scene_path("colmap_mouse"))
    n = len(scene.cameras)
    g0 = exposure_gains(scene.points, scene.images, n).numpy()
    assert 0.15 < exposure_spread(torch.from_numpy(g0)) < APPEARANCE_EXPOSURE_SPREAD  # steady: no corrections
    from nerfpipe.training import trainer

    monkeypatch.setattr(trainer, "EXPOSURE_MAX_PHOTOS", 20)  # the trainer's measurement, over 20 of the training photos
    assert abs(trainer.exposure_spread_of(scene) - exposure_spread(torch.from_numpy(g0))) < 0.05
    applied = np.random.default_rng(0).normal(0, 0.4, n)
    some = np.arange(0, n, 3)  # every third photo (19), to keep it short
    scaled = [None] * n  # the photos differ in size: files, as a capture's
    for i in some:
        lin = srgb_to_linear(scene.images.load(int(i))[..., :3].astype(np.float32) / 255) * np.float32(np.exp(applied[i]))
        scaled[i] = tmp_path / f"{i}.png"
        iio.imwrite(scaled[i], (linear_to_srgb(np.clip(lin, 0, 1)) * 255 + 0.5).astype(np.uint8), compress_level=1)
    g1 = exposure_gains(scene.points, ImageSet(paths=scaled), n, cameras=some).numpy()
    ok = np.isfinite(g0) & np.isfinite(g1)
    assert ok.sum() >= len(some) - 1 and not np.isfinite(g1[1])
    assert np.corrcoef(g1[ok] - g0[ok], applied[ok])[0, 1] > 0.95
    assert exposure_spread(torch.from_numpy(g1)) > APPEARANCE_EXPOSURE_SPREAD


def _info(**kw):
    base = dict(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]), near=0.5, far=10.0, num_images=4, pixels_per_image=100)
    return SceneInfo(**base, **kw)


def test_colour_corrections_rule_and_checkpoints():
    """One camera's session gets the colour corrections when its photos' exposure spreads above the threshold; a
    checkpoint is rebuilt with what it was trained with, whatever its scene info says now."""
    steady = _info(unbounded=True, focal_spread=0.02, exposure_spread=0.2)
    varied = _info(unbounded=True, focal_spread=0.02, exposure_spread=APPEARANCE_EXPOSURE_SPREAD + 0.05)
    assert not appearance_by_default(steady) and appearance_by_default(varied)
    assert appearance_by_default(_info(unbounded=True, focal_spread=1.0))
    assert not appearance_by_default(_info(has_alpha=True, exposure_spread=1.0))  # synthetic: never
    cfg = FastConfig(preset="small")
    on, off = cfg.setup(varied), cfg.setup(steady)
    collection = cfg.setup(_info(unbounded=True, focal_spread=1.0))
    assert on.appearance is not None and off.appearance is None
    assert on.image_codes is None and on.sky is None  # a session: the affine maps alone
    assert on.appearance_fit_steps == 0 and collection.appearance_fit_steps > 0  # its fit: the colour-fitted figure's
    assert collection.image_codes is not None and collection.sky is not None  # a collection: its codes and skies too
    rebuilt = cfg.for_checkpoint(on.state_dict(), steady).setup(steady)  # the photos not measured: info says steady
    assert rebuilt.appearance is not None and rebuilt.image_codes is None
    rebuilt.load_state_dict(on.state_dict())
    old = cfg.for_checkpoint(collection.state_dict(), steady).setup(steady)  # what it has, not what the info says
    assert old.image_codes is not None and old.sky is not None
    old.load_state_dict(collection.state_dict())
    assert cfg.for_checkpoint(off.state_dict(), varied).setup(varied).appearance is None
    assert FastConfig(preset="small", appearance=False).for_checkpoint(on.state_dict(), varied).appearance is False
    with pytest.raises(ValueError, match="appearance_dim"):
        FastConfig(appearance_dim=-1)


def test_the_trainer_turns_the_corrections_on_for_a_capture_whose_exposure_varies(tmp_path):
    """A synthetic capture (points with tracks, no alpha) has a small spread and no colour corrections; its photos
    rewritten with each one's linear light scaled by a known factor get the affine maps alone, reported in the stats."""
    from nerfpipe.data.synthetic import SynthConfig, generate
    from nerfpipe.data_adapters import load
    from nerfpipe.training.trainer import Trainer, TrainerConfig

    root = tmp_path / "scene"
    generate(root, SynthConfig(views=16, width=48, height=48, num_points=800))
    cfg = TrainerConfig(iters=1, rays_per_step=64, eval_every=0, checkpoint_every=0, video_frames=0, write_outputs=False)

    def built(name):
        return Trainer(cfg, load(root), "fast", FastConfig(preset="small"), tmp_path / name).model

    steady = built("steady")
    assert steady.appearance is None and steady.exposure_spread < APPEARANCE_EXPOSURE_SPREAD
    # brighter only: a pixel clipped in the photo stays clipped (and skipped), where a darker copy of it would not be
    # the darker exposure of the scene that a camera would record (a real exposure change does not have this problem)
    gains = np.random.default_rng(1).permutation(np.linspace(0.0, 1.2, 16))
    for i, path in enumerate(sorted((root / "images").iterdir())):
        img = iio.imread(path)
        lin = srgb_to_linear(img[..., :3] / 255.0) * np.exp(gains[i])
        iio.imwrite(path, (linear_to_srgb(np.clip(lin, 0, 1)) * 255 + 0.5).astype(np.uint8))
    varied = built("varied")
    assert varied.exposure_spread > APPEARANCE_EXPOSURE_SPREAD and varied.stats()["exposure_spread"] == varied.exposure_spread
    assert varied.appearance is not None and varied.image_codes is None and varied.sky is None
    assert varied.stats()["appearance"] == 1.0 and steady.stats()["appearance"] == 0.0


def test_the_summary_line_names_the_figure_that_sees_through_exposure():
    from nerfpipe.training.evaluation import fitted_figure_note

    assert fitted_figure_note({"val_psnr": 18.0, "val_psnr_colour_fitted": 24.0}) == ""  # no corrections: none
    session = fitted_figure_note({"val_psnr": 18.0, "val_psnr_colour_fitted": 24.4, "appearance": 1.0})
    assert "24.40 dB" in session and "affine colour map" in session
    collection = {"val_psnr": 12.0, "val_psnr_colour_fitted": 15.0, "val_psnr_appearance_fitted": 16.1, "appearance": 1.0}
    assert "16.10 dB" in fitted_figure_note(collection) and "appearance fitted" in fitted_figure_note(collection)
