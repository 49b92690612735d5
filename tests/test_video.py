"""A video as the input: the sharpest frame of each stretch, a rotated phone video turned upright, one error line for
a file ffmpeg cannot decode, and the ``sfm`` stage on a video of real photographs (the Sceaux castle's)."""

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from nerfpipe.data.video import is_video, sharpest_frames, sharpness, stretch_of, write_frames
from nerfpipe.util.errors import NerfpipeError


def blur(image: np.ndarray, passes: int = 3) -> np.ndarray:
    """A box blur (each pass a 3 x 3 mean), as a step's motion smears a frame."""
    out = image.astype(np.float32)
    for _ in range(passes):
        padded = np.pad(out, ((1, 1), (1, 1), (0, 0)), mode="edge")
        out = sum(padded[i:i + out.shape[0], j:j + out.shape[1]] for i in range(3) for j in range(3)) / 9.0
    return out.round().astype(np.uint8)


def write_video(path: Path, frames: "list[np.ndarray]", fps: int = 10) -> Path:
    import imageio.v3 as iio

    iio.imwrite(path, np.stack(frames), fps=fps, quality=9, macro_block_size=1)
    return path


@pytest.fixture(scope="module")
def blurry_video(tmp_path_factory) -> "tuple[Path, list[int]]":
    """24 frames of a texture in 6 stretches of 4, one frame of each sharp, the others blurred; and the sharp ones."""
    rng = np.random.default_rng(0)
    texture = np.kron(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8), np.ones((4, 4, 1), dtype=np.uint8))
    sharp = [4 * k + int(rng.integers(4)) for k in range(6)]
    frames = [np.roll(texture, 2 * i, axis=1) if i in sharp else blur(np.roll(texture, 2 * i, axis=1)) for i in range(24)]
    return write_video(tmp_path_factory.mktemp("video") / "walk.mp4", frames), sharp


def test_sharpness_ranks_a_blurred_frame_below_the_sharp_one():
    rng = np.random.default_rng(1)
    image = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    assert sharpness(image) > 4 * sharpness(blur(image))
    assert sharpness(np.full((60, 80, 3), 128, np.uint8)) == 0.0


def test_stretches_split_the_frames_evenly():
    assert [stretch_of(i, 10, 5) for i in range(10)] == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4]
    assert stretch_of(12, 10, 5) == 4  # frames past an undercounted total fall in the last stretch


def test_the_sharpest_frame_of_each_stretch_is_taken(blurry_video, tmp_path):
    import imageio.v3 as iio

    video, sharp = blurry_video
    assert is_video(video) and not is_video(video.parent)
    taken = sharpest_frames(video, 6)
    assert [index for index, _, _ in taken] == sharp
    assert all(pixels.shape == (96, 128, 3) and pixels.dtype == np.uint8 for _, _, pixels in taken)
    assert len(sharpest_frames(video, 100)) == 24  # more stretches than frames: every frame
    scaled = sharpest_frames(video, 6, max_size=64)  # ffmpeg scales as it decodes: the same frames, smaller
    assert [index for index, _, _ in scaled] == sharp and scaled[0][2].shape == (48, 64, 3)
    paths = write_frames(video, tmp_path / "frames", 6)
    assert [p.name for p in paths] == [f"frame_{i:05d}.jpg" for i in sharp] and all(p.is_file() for p in paths)
    small = write_frames(video, tmp_path / "small", 6, max_size=64)
    assert [p.name for p in small] == [p.name for p in paths] and iio.imread(small[0]).shape == (48, 64, 3)


def test_a_rotated_phone_video_is_turned_upright(blurry_video, tmp_path):
    import imageio_ffmpeg

    turned = tmp_path / "portrait.mp4"
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-display_rotation", "90", "-i",
                    str(blurry_video[0]), "-c", "copy", str(turned)], check=True)
    _, _, pixels = sharpest_frames(turned, 1)[0]
    assert pixels.shape == (128, 96, 3)  # the stored 128 x 96 frames shown a quarter turned


@pytest.mark.parametrize("content", [b"", b"not a video at all"])
def test_a_file_ffmpeg_cannot_decode_is_one_error_naming_it(tmp_path, content):
    bad = tmp_path / "clip.mp4"
    bad.write_bytes(content)
    with pytest.raises(NerfpipeError, match="not a video ffmpeg can decode") as info:
        sharpest_frames(bad, 5)
    assert info.value.path == bad


def test_the_cli_names_a_broken_video_in_one_line(tmp_path, capsys):
    from nerfpipe.cli import main

    bad = tmp_path / "clip.mov"
    bad.write_bytes(b"\x00" * 100)
    assert main(["run", str(bad), "--out", str(tmp_path / "run"), "--stages", "sfm"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0] and "not a video ffmpeg can decode" in err[0]


def test_sfm_stage_on_a_video_of_real_photographs(scene_path, tmp_path):
    """The Sceaux castle's 11 photos as the frames of a video, each shown sharp once and blurred twice: the stage
    takes the sharp ones and registers them."""
    from PIL import Image, ImageFilter

    from nerfpipe.pipeline.stages import Pipeline

    frames = []
    for k, photo in enumerate(sorted((scene_path("photos_sceaux_castle") / "images").iterdir())):
        image = Image.open(photo).convert("RGB").resize((480, 360))
        frames += [np.asarray(image if j == k % 3 else image.filter(ImageFilter.GaussianBlur(2))) for j in range(3)]
    video = write_video(tmp_path / "castle.mp4", frames, fps=3)
    config = {"max_image_size": 480, "max_num_features": 2048, "candidate_sizes": (), "video_frames": 11}
    result = Pipeline(["sfm", "load"], {"sfm": config}).run(video, tmp_path / "run")
    assert [r.status for r in result.records] == ["ran", "ran"]
    taken = sorted(p.name for p in (tmp_path / "run" / "frames").iterdir())
    assert taken == [f"frame_{3 * k + k % 3:05d}.jpg" for k in range(11)]
    summary = json.loads((tmp_path / "run" / "sfm" / "sfm.json").read_text())
    assert summary["num_registered"] >= 9 and len(result["scene"].cameras) == summary["num_registered"]
