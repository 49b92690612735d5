"""Bad input on the command line: one error line naming the file, exit code 2, no traceback."""

import os
import subprocess
import sys

import numpy as np
import pytest

from nerfpipe.cli import main
from nerfpipe.util.errors import NerfpipeError

pycolmap = pytest.importorskip("pycolmap")

from colmap_synth import make_scene  # noqa: E402


def _empty_model(root):
    (root / "sparse" / "0").mkdir(parents=True)
    pycolmap.Reconstruction().write_binary(str(root / "sparse" / "0"))
    return root, root / "sparse" / "0" / "images.bin"


def _unsupported_model(root):
    return make_scene(root, "FULL_OPENCV", frames=3, points=20), root / "sparse" / "0" / "cameras.bin"


def _missing_images(root):
    """Every registered image's file missing (one missing is left out with a warning: below)."""
    make_scene(root, "PINHOLE", frames=3, points=20)
    for victim in (root / "images").iterdir():
        victim.unlink()
    return root, root / "images"


def _size_mismatch(root):
    import imageio.v3 as iio

    make_scene(root, "PINHOLE", frames=3, points=20)
    victim = sorted((root / "images").iterdir())[0]
    iio.imwrite(victim, np.zeros((8, 8, 3), np.uint8))
    return root, victim


def _nonexistent(root):
    return root / "nope", root / "nope"


def _unknown_format(root):
    (root / "notes.txt").write_text("not a dataset")
    return root, root


def _raw_photos(root):
    (root / "images").mkdir()
    for i in range(3):
        (root / "images" / f"IMG_{i}.CR2").write_bytes(b"II*\x00raw")
    return root, root


def _photos_without_poses(root):
    import imageio.v3 as iio

    (root / "images").mkdir()
    for i in range(3):
        iio.imwrite(root / "images" / f"IMG_{i}.jpg", np.zeros((8, 8, 3), np.uint8))
    return root, root


def _video(root):
    (root / "walk.mp4").write_bytes(b"\x00" * 64)  # not decoded: the suffix says what it is
    return root / "walk.mp4", root / "walk.mp4"


CASES = {
    "empty-model": _empty_model,
    "unsupported-camera": _unsupported_model,
    "missing-images": _missing_images,
    "size-mismatch": _size_mismatch,
    "nonexistent": _nonexistent,
    "unknown-format": _unknown_format,
    "raw-photos": _raw_photos,
    "photos-without-poses": _photos_without_poses,
    "video": _video,
}


@pytest.mark.parametrize("command", ["info", "check"])
@pytest.mark.parametrize("case", list(CASES))
def test_one_line_error(tmp_path, capsys, case, command):
    path, culprit = CASES[case](tmp_path)
    assert main([command, str(path)]) == 2
    err = capsys.readouterr().err
    # Only nerfpipe's lines count: under pytest, beartype's import hook adds deprecation
    # warnings (the subprocess test below checks that a real run prints nothing else).
    lines = [line for line in err.splitlines() if line.startswith("nerfpipe")]
    assert len(lines) == 1, err
    assert lines[0].startswith("nerfpipe: error: ") and str(culprit) in lines[0]
    assert "Traceback" not in err
    if case == "raw-photos":  # said what they are and what to do
        assert "3 photos in a format nerfpipe does not read (.CR2): convert them to JPEG" in lines[0]
    if case in ("photos-without-poses", "video"):  # the command that takes them
        assert "without camera poses: `nerfpipe run" in lines[0]


def test_a_warning_is_one_line(tmp_path, capsys):
    """A registered image without its file: the command goes on, with one ``nerfpipe: warning:`` line naming it."""
    make_scene(tmp_path, "PINHOLE", frames=3, points=20)
    victim = sorted((tmp_path / "images").iterdir())[1]
    victim.unlink()
    assert main(["info", str(tmp_path)]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("nerfpipe")]
    assert len(lines) == 1 and lines[0].startswith("nerfpipe: warning: ") and victim.name in lines[0], lines


def test_debug_raises(tmp_path):
    """``--debug`` lets the exception (and so Python's traceback) through."""
    with pytest.raises(NerfpipeError) as info:
        main(["info", "--debug", str(tmp_path / "nope")])
    assert info.value.path == tmp_path / "nope"


def test_subprocess(tmp_path):
    """The real entry point prints exactly one line on stderr and exits 2."""
    path, culprit = _unsupported_model(tmp_path)
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    cmd = [sys.executable, "-m", "nerfpipe", "info", str(path)]
    run = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert run.stderr.strip().count("\n") == 0 and str(culprit) in run.stderr and "FULL_OPENCV" in run.stderr


def test_a_closed_pipe_ends_quietly(tmp_path):
    """``nerfpipe info DATA --json | head -0``: the reader is gone before the output; no traceback."""
    path = make_scene(tmp_path, "PINHOLE", frames=3, points=20)
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    proc = subprocess.Popen([sys.executable, "-m", "nerfpipe", "info", str(path), "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    proc.stdout.close()  # before the command has printed anything
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=300) == 141 and "Traceback" not in err and "BrokenPipe" not in err


def test_clean_errors_keep_their_cause_for_debug(tmp_path):
    """One line for the user, but ``--debug`` can still show what the library raised (``from exc``)."""
    from nerfpipe.data.scene import read_image_uint8
    from nerfpipe.util.errors import NerfpipeError

    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n not really")
    with pytest.raises(NerfpipeError) as info:
        read_image_uint8(bad)
    assert info.value.__cause__ is not None and "broken.png" in str(info.value)


@pytest.mark.parametrize(
    "args, name",
    [
        (["train", "{data}", "--time-budget", "-5"], "--time-budget"),
        (["train", "{data}", "--rays-per-step", "0"], "--rays-per-step"),
        (["train", "{data}", "--iters", "-1"], "--iters"),
        (["run", "{data}", "--time-budget", "-5"], "--time-budget"),
        (["run", "{data}", "--time-budget", "nan"], "--time-budget"),
        (["run", "{data}", "--train.trainer.iters", "-1"], "--train.trainer.iters must be"),  # as typed, not the config's own name
        (["run", "{data}", "--render.frames", "0"], "--render.frames must be"),
    ],
)
def test_impossible_parameters_are_one_line_and_write_nothing(tmp_path, scene_path, capsys, args, name):
    from nerfpipe.cli import main

    data = str(scene_path("lego_200x200") / "lego_200x200.npz")
    out = tmp_path / "out"
    argv = [a.replace("{data}", data) for a in args] + ["--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and name in err[0]
    assert not out.exists()
