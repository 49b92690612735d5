"""A battery of bad inputs across every command and format (issue 14).

Each case builds a tiny broken input (a synthetic scene of a few 16x16 views, a pycolmap model of
3 frames, a small npz, a run folder trained for 2 iterations) and runs the command in-process.
Every case must give: exit code 2, exactly one line on stderr that names the culprit (file or
parameter), no traceback, nothing left in the ``--out`` folder (or the run folder's output
folder), and it must finish within seconds.
"""

import json
import shutil
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from nerfpipe.cli import main

pycolmap = pytest.importorskip("pycolmap")

from colmap_synth import make_scene  # noqa: E402

PACKAGE_DIRS = ("/nerfpipe/", "/benchmarks/")
"""Warnings raised from these count as extra stderr lines (library deprecations under pytest do not)."""
SECONDS = 30.0
"""A case must be refused within this (generous for a shared 2-core machine; most take well under 1 s)."""


# ---------------------------------------------------------------- tiny inputs, made once per module


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """Base inputs to copy from: a Blender set, a COLMAP model, a trained run folder."""
    from nerfpipe.data.synthetic import SynthConfig, generate

    root = tmp_path_factory.mktemp("bad-inputs-base")
    generate(root / "blender", SynthConfig(layout="blender", scene="sphere", views=8, width=16, height=16))
    make_scene(root / "colmap", "PINHOLE", frames=3, points=20)
    argv = ["train", str(root / "blender"), "--iters", "2", "--video-frames", "0", "--eval-every", "0", "--out", str(root / "run")]
    assert main(argv) == 0
    return root


@dataclass
class Case:
    """``make(tmp) -> (argv, culprit, out)``: the command line, what the error line must name, and the
    folder that must not exist afterwards (None: nothing to check)."""

    make: Callable
    missing_module: "str | None" = None
    """Simulate this optional module as not installed (``sys.modules[name] = None``)."""


def _copy(base: Path, name: str, tmp: Path) -> Path:
    dst = tmp / name
    shutil.copytree(base / name, dst, symlinks=True)
    return dst


def _json_edit(file: Path, edit: Callable) -> None:
    doc = json.loads(file.read_text())
    edit(doc)
    file.write_text(json.dumps(doc))


def _blender(base, tmp, edit=None, split="train"):
    root = _copy(base, "blender", tmp)
    if edit is not None:
        _json_edit(root / f"transforms_{split}.json", edit)
    return root


def _frame(key, value, i=0):
    return lambda d: d["frames"][i].__setitem__(key, value)


def _capture(base, tmp, edit=None):
    """A single-file capture (instant-ngp flavour) made of the Blender set's train views."""
    root = _copy(base, "blender", tmp)
    doc = json.loads((root / "transforms_train.json").read_text())
    for split in ("train", "val", "test"):
        (root / f"transforms_{split}.json").unlink()
    if edit is not None:
        edit(doc)
    (root / "transforms.json").write_text(json.dumps(doc))
    return root


def _image(root: Path, rel="train/view_001.png") -> Path:
    return root / rel


def _truncate(path: Path, keep: float = 0.7) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    return path


def _symlink_out(path: Path, tmp: Path) -> Path:
    outside = tmp / "outside" / path.name
    outside.parent.mkdir(exist_ok=True)
    shutil.copyfile(path, outside)
    path.unlink()
    path.symlink_to(outside)
    return path


def _cmd(command, data, *rest, out=None):
    argv = [command, str(data), *map(str, rest)]
    return argv + (["--out", str(out)] if out is not None else [])


# ---------------------------------------------------------------- dataset cases (info, check, train, run)


def blender_case(edit, culprit, command="info", split="train"):
    def make(base, tmp):
        root = _blender(base, tmp, edit, split)
        return [command, str(root)], culprit(root) if callable(culprit) else culprit, None

    return Case(make)


def image_case(damage, command="info", rel="train/view_001.png", extra=()):
    """Damage one image of the Blender set; the error must name it. Commands with --out must leave none."""

    def make(base, tmp):
        root = _blender(base, tmp)
        victim = damage(_image(root, rel), tmp)
        out = tmp / "out" if command in ("train", "run") else None
        return _cmd(command, root, *extra, out=out), str(victim), out

    return Case(make)


def capture_case(edit, culprit, command="info"):
    def make(base, tmp):
        root = _capture(base, tmp, edit)
        return [command, str(root)], culprit(root) if callable(culprit) else culprit, None

    return Case(make)


def capture_text_case(text):
    """A capture whose transforms.json holds ``text`` (invalid JSON, empty)."""

    def make(base, tmp):
        root = _capture(base, tmp)
        (root / "transforms.json").write_text(text)
        return ["info", str(root)], str(root / "transforms.json"), None

    return Case(make)


def colmap_case(damage, command="info"):
    def make(base, tmp):
        root = _copy(base, "colmap", tmp)
        return [command, str(root)], str(damage(root, tmp)), None

    return Case(make)


def _colmap_first_image(root: Path) -> Path:
    return sorted((root / "images").iterdir())[0]


def _colmap_rename(root: Path, tmp: Path, name: str) -> Path:
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    image_id = sorted(rec.reg_image_ids())[0]
    rec.image(image_id).name = name
    rec.write_binary(str(root / "sparse" / "0"))
    return root / "sparse" / "0" / "images.bin"


def _colmap_camera(root: Path, params) -> Path:
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    for cam in rec.cameras.values():
        cam.params = params
    rec.write_binary(str(root / "sparse" / "0"))
    return root / "sparse" / "0" / "cameras.bin"


def _colmap_model(root: Path, model: str) -> Path:
    shutil.rmtree(root)
    make_scene(root, model, frames=3, points=20)
    return root / "sparse" / "0" / "cameras.bin"


def _empty_colmap(root: Path) -> Path:
    shutil.rmtree(root / "sparse" / "0")
    (root / "sparse" / "0").mkdir(parents=True)
    pycolmap.Reconstruction().write_binary(str(root / "sparse" / "0"))
    return root / "sparse" / "0" / "images.bin"


def npz_case(change, culprit_key=None, command="info"):
    """A CS180 npz with one array changed; the error names the file (and the key, when given)."""

    def make(base, tmp):
        n, h, w = 3, 8, 8
        poses = np.tile(np.eye(4), (n, 1, 1))
        poses[:, 2, 3] = 4.0 + np.arange(n)
        arrays = {"images_train": np.zeros((n, h, w, 3), np.uint8), "c2ws_train": poses, "images_val": np.zeros((n, h, w, 3), np.uint8),
                  "c2ws_val": poses.copy(), "c2ws_test": poses.copy(), "focal": np.float64(10.0)}  # fmt: skip
        file = tmp / "scene.npz"
        raw = change(arrays, file)
        if raw is not None:
            np.savez(file, **raw)
        return [command, str(file)], culprit_key or str(file), None

    return Case(make)


def _set(key, value):
    def change(arrays, file):
        arrays[key] = value(arrays[key]) if callable(value) else value
        return arrays

    return change


def _nan_at(index):
    def value(m):
        m = np.array(m, dtype=np.float64)
        m[index] = np.nan
        return m

    return value


def _write_bytes(data: bytes):
    def change(arrays, file):
        file.write_bytes(data)

    return change


def _truncated_npz(arrays, file):
    np.savez_compressed(file, **arrays)
    _truncate(file, 0.5)


# ---------------------------------------------------------------- parameter cases


def param_case(command, flags, culprit, out_name="out", data="blender", missing_module=None):
    """``command DATA FLAGS --out OUT``: refused naming ``culprit`` with no OUT left behind."""

    def make(base, tmp):
        source = base / data if data else None
        out = tmp / out_name if out_name else None
        argv = [command] + ([str(source)] if source else []) + [str(f).replace("{tmp}", str(tmp)) for f in flags]
        return argv + (["--out", str(out)] if out is not None else []), culprit, out

    return Case(make, missing_module)


def _file_out(tmp: Path) -> Path:
    (tmp / "a_file").write_text("not a folder")
    return tmp / "a_file" / "out"


def out_under_file_case(command, flags=(), data="blender"):
    def make(base, tmp):
        out = _file_out(tmp)
        return [command] + ([str(base / data)] if data else []) + list(flags) + ["--out", str(out)], str(out), out

    return Case(make)


# ---------------------------------------------------------------- run-folder cases (render, mesh, stage)


def run_case(damage, command="render", flags=(), output="render"):
    """A copy of the trained run folder, damaged; the command must name the culprit and write no output."""

    def make(base, tmp):
        run = _copy(base, "run", tmp)
        culprit = damage(run, tmp)
        return [command, str(run), *flags], str(culprit), run / output

    return Case(make)


def _not_a_run(run: Path, tmp: Path) -> Path:
    shutil.rmtree(run)
    run.mkdir()
    return run


def _config(edit):
    def damage(run, tmp):
        _json_edit(run / "config.json", edit)
        return run / "config.json"

    return damage


def _config_text(text):
    def damage(run, tmp):
        (run / "config.json").write_text(text)
        return run / "config.json"

    return damage


def _checkpoint_of_another_model(run: Path, tmp: Path) -> Path:
    from nerfpipe.models.registry import get_model
    from nerfpipe.training.runs import to_dict

    _json_edit(run / "config.json", lambda d: d.update(model="vanilla", model_config=to_dict(get_model("vanilla").config())))
    return run / "checkpoint.safetensors"


def _checkpoint_missing_tensors(run: Path, tmp: Path) -> Path:
    from nerfpipe.training.checkpoint import load_checkpoint, save_checkpoint

    state = load_checkpoint(run / "checkpoint.safetensors")
    drop = next(k for k in state["model"] if "tables" in k)  # a grid: no model gives it a default
    state["model"] = {k: v for k, v in state["model"].items() if k != drop}
    save_checkpoint(run / "checkpoint.safetensors", state)
    return run / "checkpoint.safetensors"


def _checkpoint_bytes(data: bytes):
    def damage(run, tmp):
        (run / "checkpoint.safetensors").write_bytes(data)
        return run / "checkpoint.safetensors"

    return damage


def _data_moved(run: Path, tmp: Path) -> Path:
    _json_edit(run / "config.json", lambda d: d.update(data=str(tmp / "gone")))
    return tmp / "gone"


def _keep(run: Path, tmp: Path) -> Path:
    return run


# ---------------------------------------------------------------- pipeline cases (run, stage)


def pipeline_case(damage, flags=(), culprit=None):
    """``nerfpipe run`` on a damaged Blender set: refused before any stage's work, no run folder left."""

    def make(base, tmp):
        root = _blender(base, tmp)
        named = damage(root, tmp)
        out = tmp / "run-out"
        argv = ["run", str(root), *[str(f).replace("{tmp}", str(tmp)) for f in flags], "--out", str(out)]
        return argv, culprit or str(named), out

    return Case(make)


def photo_case(damage):
    """``nerfpipe run`` on a folder of photos (SfM first) with one broken or escaping photo."""

    def make(base, tmp):
        photos = tmp / "photos"
        photos.mkdir()
        for p in sorted((base / "colmap" / "images").iterdir()):
            shutil.copyfile(p, photos / p.name)
        culprit = damage(sorted(photos.iterdir())[0], tmp)
        out = tmp / "run-out"
        return ["run", str(photos), "--out", str(out)], str(culprit), out

    return Case(make)


def stage_case(damage, name="render"):
    def make(base, tmp):
        run = tmp / "piperun"
        run.mkdir()
        culprit = damage(run, tmp)
        return ["stage", name, str(run)], str(culprit), None

    return Case(make)


def _toml(text):
    def damage(root, tmp):
        (tmp / "pipe.toml").write_text(text)
        return tmp / "pipe.toml"

    return damage


# ---------------------------------------------------------------- other commands


def file_case(command, write, flags=(), out=True, name="input.png"):
    """``command FILE`` where FILE is written by ``write(path, base)``."""

    def make(base, tmp):
        file = tmp / name
        write(file, base)
        out_dir = tmp / "out" if out else None
        return [command, str(file), *flags] + (["--out", str(out_dir)] if out_dir else []), str(file), out_dir

    return Case(make)


def _text(path, base):
    path.write_text("hello, I am not an image\n")


def _empty(path, base):
    path.write_bytes(b"")


def _truncated_png(path, base):
    shutil.copyfile(base / "blender" / "train" / "view_001.png", path)
    _truncate(path, 0.6)


def _float_tiff(path, base):
    from PIL import Image

    Image.fromarray(np.linspace(0, 300, 64 * 64, dtype=np.float32).reshape(64, 64)).save(path)


def _nan_tiff(path, base):
    from PIL import Image

    a = np.full((64, 64), 0.5, np.float32)
    a[3, 3] = np.nan
    Image.fromarray(a).save(path)


def _one_pixel(path, base):
    from PIL import Image

    Image.new("RGB", (1, 1)).save(path)


def mesh_file_case(write, flags=()):
    def make(base, tmp):
        mesh = tmp / "mesh.ply"
        write(mesh)
        return ["eval-mesh", str(mesh), str(mesh), *flags], str(mesh) if not flags else flags[0], None

    return Case(make)


def synth_case(flags, culprit, prepare=None):
    def make(base, tmp):
        out = tmp / "synth"
        if prepare is not None:
            out = prepare(tmp)
        return ["synth", str(out), *flags], culprit if culprit != "{out}" else str(out), out if prepare is None else None

    return Case(make)


def _full_folder(tmp: Path) -> Path:
    (tmp / "mine").mkdir()
    (tmp / "mine" / "notes.txt").write_text("mine")
    return tmp / "mine"


# ---------------------------------------------------------------- the battery

CASES: "dict[str, Case]" = {
    # transforms.json (Blender and single-file captures)
    "info/nonexistent": Case(lambda b, t: (["info", str(t / "nope")], str(t / "nope"), None)),
    "info/empty-folder": Case(lambda b, t: (["info", str(t)], str(t), None)),
    "info/transforms-invalid-json": capture_text_case('{"frames": ['),
    "info/transforms-empty-file": capture_text_case(""),
    "info/transforms-no-frames": capture_case(lambda d: d.pop("frames"), lambda r: str(r / "transforms.json")),
    "info/file-path-dotdot": blender_case(_frame("file_path", "../../outside"), lambda r: str(r / "transforms_train.json")),
    "info/file-path-absolute": blender_case(_frame("file_path", "/etc/passwd"), lambda r: str(r / "transforms_train.json")),
    "info/file-path-symlink-out": image_case(_symlink_out),
    "info/file-path-nul": blender_case(_frame("file_path", "./train/view\u0000_001"), lambda r: str(r / "transforms_train.json")),
    "info/file-path-too-long": blender_case(_frame("file_path", "./train/" + "v" * 300), lambda r: str(r / "transforms_train.json")),
    "check/file-path-symlink-out": image_case(_symlink_out, command="check"),
    "info/ply-path-escape": capture_case(lambda d: d.update(ply_file_path="../points.ply"), lambda r: str(r / "transforms.json")),
    "info/nan-pose": blender_case(lambda d: d["frames"][1]["transform_matrix"][0].__setitem__(3, float("nan")), "transform_matrix[1] contains NaN"),
    "info/pose-3x3": blender_case(_frame("transform_matrix", [[1, 0, 0], [0, 1, 0], [0, 0, 1]]), "transform_matrix"),
    "info/pose-scaled": blender_case(lambda d: [r.__setitem__(0, 2.0 * r[0]) for r in d["frames"][0]["transform_matrix"][:3]], "is not a rotation"),
    "info/nan-focal": blender_case(lambda d: d.update(camera_angle_x=float("nan")), lambda r: str(r / "transforms_train.json")),
    "info/negative-focal": capture_case(lambda d: d.update(fl_x=-3.0), "fl_x must be a positive"),
    "info/text-focal": capture_case(lambda d: d.update(fl_x="wide"), lambda r: str(r / "transforms.json")),
    "info/field-of-view-zero": blender_case(lambda d: d.update(camera_angle_x=0.0), "camera_angle_x must be a field of view"),
    "info/nan-principal-point": capture_case(lambda d: d.update(fl_x=20.0, cx=float("nan")), "NaN"),
    "info/nan-distortion": capture_case(lambda d: d.update(fl_x=20.0, k1=float("nan")), "NaN"),
    "train/cameras-at-one-position": capture_case(
        lambda d: [f.update(transform_matrix=d["frames"][0]["transform_matrix"]) for f in d["frames"]], "degenerate scene", command="train"),
    "info/unsupported-camera-model": capture_case(lambda d: d.update(camera_model="EQUIRECTANGULAR"), "EQUIRECTANGULAR"),
    "info/image-missing": image_case(lambda p, t: (p.unlink(), p)[1]),
    "info/capture-every-image-missing": capture_case(lambda d: [f.update(file_path=f"gone/{i}.png") for i, f in enumerate(d["frames"])],
                                                     lambda r: str(r / "transforms.json")),
    "info/image-is-text": image_case(lambda p, t: (p.write_text("not a png"), p)[1]),
    "info/image-empty": image_case(lambda p, t: (p.write_bytes(b""), p)[1]),
    "check/image-size-mismatch": capture_case(lambda d: d.update(w=99, fl_x=20.0), lambda r: str(r / "train" / "view_001.png"), command="check"),
    "train/image-truncated": image_case(lambda p, t: _truncate(p), command="train", extra=("--iters", "1")),
    "train/val-image-truncated": image_case(lambda p, t: _truncate(p), command="train", rel="val/view_004.png", extra=("--iters", "1")),
    "train/image-is-text": image_case(lambda p, t: (p.write_text("not a png"), p)[1], command="train"),
    "train/image-float-range": image_case(lambda p, t: _as_float_tiff(p), command="train", rel="val/view_004.png"),
    "run/image-truncated": image_case(lambda p, t: _truncate(p), command="run"),
    "run/image-is-text": image_case(lambda p, t: (p.write_text("not a png"), p)[1], command="run"),
    # COLMAP
    "info/colmap-unsupported-model": colmap_case(lambda r, t: _colmap_model(r, "FULL_OPENCV")),
    "info/colmap-empty-model": colmap_case(lambda r, t: _empty_colmap(r)),
    "info/colmap-images-missing": colmap_case(lambda r, t: [_unlink(f) for f in sorted((r / "images").iterdir())][0].parent),  # one: a warning
    "info/colmap-image-symlink-out": colmap_case(lambda r, t: _symlink_out(_colmap_first_image(r), t)),
    "info/colmap-image-name-dotdot": colmap_case(lambda r, t: _colmap_rename(r, t, "../../secret.png")),
    "info/colmap-image-name-absolute": colmap_case(lambda r, t: _colmap_rename(r, t, "/etc/hostname")),
    "info/colmap-images-bin-truncated": colmap_case(lambda r, t: _truncate(r / "sparse" / "0" / "images.bin", 0.5).parent),
    "info/colmap-image-is-text": colmap_case(lambda r, t: (_colmap_first_image(r).write_text("text"), _colmap_first_image(r))[1]),
    "info/colmap-image-size-mismatch": colmap_case(lambda r, t: _small_png(_colmap_first_image(r))),
    "info/colmap-nan-focal": colmap_case(lambda r, t: _colmap_camera(r, [float("nan"), 58.0, 32.0, 24.0])),
    "info/colmap-zero-focal": colmap_case(lambda r, t: _colmap_camera(r, [0.0, 58.0, 32.0, 24.0])),
    "info/colmap-points-bin-truncated": colmap_case(lambda r, t: _truncate(r / "sparse" / "0" / "points3D.bin", 0.5)),
    "info/colmap-points-bin-huge-count": colmap_case(lambda r, t: _huge_count(r / "sparse" / "0" / "points3D.bin")),
    "check/colmap-unsupported-model": colmap_case(lambda r, t: _colmap_model(r, "FULL_OPENCV"), command="check"),
    # npz (CS180)
    "info/npz-garbage": npz_case(_write_bytes(b"this is not a zip archive" * 8)),
    "info/npz-empty": npz_case(_write_bytes(b"")),
    "info/npz-truncated": npz_case(_truncated_npz),
    "info/npz-nan-pose": npz_case(_set("c2ws_train", _nan_at((1, 0, 3))), "c2ws_train[1] contains NaN"),
    "info/npz-nan-focal": npz_case(_set("focal", np.float64(np.nan)), "focal must be a positive"),
    "info/npz-negative-focal": npz_case(_set("focal", np.float64(-5.0)), "focal must be a positive"),
    "info/npz-float-images-300": npz_case(_set("images_val", lambda a: np.full(a.shape, 300.0, np.float32)), "images_val has float values outside"),
    "info/npz-nan-images": npz_case(_set("images_train", lambda a: np.full(a.shape, np.nan, np.float32)), "images_train contains NaN"),
    "info/npz-int64-images": npz_case(_set("images_train", lambda a: a.astype(np.int64)), "images_train has dtype int64"),
    "info/npz-images-wrong-shape": npz_case(_set("images_train", lambda a: a[..., 0]), "images_train must have shape"),
    "info/npz-pose-count": npz_case(_set("c2ws_val", lambda a: a[:1]), "c2ws_val has 1 poses"),
    "info/npz-missing-key": npz_case(lambda a, f: {k: v for k, v in a.items() if k != "focal"}, "missing key(s) focal"),
    "info/npz-pickled-object": npz_case(_set("focal", np.array([{"f": 1.0}], dtype=object))),
    # impossible parameters (train, run, render, mesh, bench, fit2d, check, eval-mesh, synth)
    "train/out-under-a-file": out_under_file_case("train"),
    "train/device-unknown": param_case("train", ["--device", "bogus"], "--device"),
    "train/device-absent-gpu": param_case("train", ["--device", "cuda:99"], "--device"),
    "train/rays-per-step-0": param_case("train", ["--rays-per-step", "0"], "--rays-per-step"),
    "train/time-budget-negative": param_case("train", ["--time-budget", "-5"], "--time-budget"),
    "train/lr-nan": param_case("train", ["--lr", "nan"], "--lr"),
    "train/eval-scale-0": param_case("train", ["--eval-scale", "0"], "--eval-scale"),
    "train/background-unknown": param_case("train", ["--background", "purple"], "--background"),
    "train/num-samples-zero": param_case("train", ["--model", "vanilla", "--model.num-samples", "0"], "--model.num-samples must be"),
    "train/model-unknown": param_case("train", ["--model", "nosuch"], "nosuch"),
    "train/missing-mp4-writer": param_case("train", ["--iters", "1"], "imageio_ffmpeg", missing_module="imageio_ffmpeg"),
    "train/missing-matplotlib": param_case("train", ["--iters", "1"], "matplotlib", missing_module="matplotlib"),
    "run/out-under-a-file": out_under_file_case("run"),
    "run/device-unknown": param_case("run", ["--device", "tpu9"], "--device", out_name="run-out"),
    "run/time-budget-nan": param_case("run", ["--time-budget", "nan"], "--time-budget", out_name="run-out"),
    "run/unknown-stage": param_case("run", ["--stages", "load,nosuch"], "nosuch", out_name="run-out"),
    "run/nonexistent-input": Case(lambda b, t: (["run", str(t / "nope"), "--out", str(t / "run-out")], str(t / "nope"), t / "run-out")),
    "run/missing-mp4-writer": param_case("run", [], "imageio_ffmpeg", out_name="run-out", missing_module="imageio_ffmpeg"),
    "run/pipeline-toml-invalid": pipeline_case(_toml("stages = [load"), ["--pipeline", "{tmp}/pipe.toml"]),
    "run/pipeline-toml-wrong-type": pipeline_case(_toml('stages = ["load", "render"]\n[render]\nframes = "many"\n'), ["--pipeline", "{tmp}/pipe.toml"]),
    "run/pipeline-toml-zero-frames": pipeline_case(_toml('stages = ["load", "render"]\n[render]\nframes = 0\n'), ["--pipeline", "{tmp}/pipe.toml"], "pipe.toml: render.frames must be"),
    "run/pipeline-toml-nested-negative": pipeline_case(_toml('stages = ["load", "train"]\n[train.trainer]\niters = -1\n'), ["--pipeline", "{tmp}/pipe.toml"],
                                                        "pipe.toml: train.trainer.iters must be 0 or more"),
    "run/empty-stage-list": param_case("run", ["--stages", ","], "at least one stage", out_name="run-out"),
    "run/one-photo-registers-nothing": Case(lambda b, t: _one_photo(b, t)),
    "run/pipeline-unknown-model": pipeline_case(_toml('stages = ["load", "train"]\n[train]\nmodel = "nosuch"\n'), ["--pipeline", "{tmp}/pipe.toml"]),
    "run/pipeline-unknown-model-option": pipeline_case(_toml('stages = ["load", "train"]\n[train]\nmodel_options = {bogus = 1}\n'), ["--pipeline", "{tmp}/pipe.toml"]),
    "run/pipeline-unknown-model-preset": pipeline_case(_toml('stages = ["load", "train"]\n[train]\nmodel_options = {preset = "huge"}\n'), ["--pipeline", "{tmp}/pipe.toml"]),
    "train/rays-per-step-huge": param_case("train", ["--rays-per-step", "1000000000"], "--rays-per-step"),
    "render/frames-huge": run_case(lambda r, t: "--frames", flags=("--frames", "1000000")),
    "run/photo-is-text": photo_case(lambda p, t: (p.write_text("not a photo"), p)[1]),
    "run/photo-truncated": photo_case(lambda p, t: _truncate(p, 0.5)),
    "run/photo-symlink-out": photo_case(_symlink_out),
    "bench/budget-negative": param_case("bench", ["--budgets", "-1"], "--budgets"),
    "bench/preset-unknown": param_case("bench", ["--presets", "nosuch"], "nosuch"),
    "bench/preset-option-not-a-number": param_case("bench", ["--presets", "fast-small:tv_weight=abc"], "tv_weight"),
    "bench/out-under-a-file": out_under_file_case("bench"),
    "check/samples-negative": param_case("check", ["--samples", "-1"], "--samples", out_name=None),
    # run folders (render, mesh, stage)
    "render/not-a-run-folder": run_case(_not_a_run),
    "render/nonexistent-run": Case(lambda b, t: (["render", str(t / "nope")], str(t / "nope"), t / "nope")),
    "render/config-invalid-json": run_case(_config_text("{not json")),
    "render/config-no-model": run_case(_config(lambda d: d.pop("model"))),
    "render/config-unknown-model": run_case(_config(lambda d: d.update(model="nosuch"))),
    "render/data-moved": run_case(_data_moved),
    "render/checkpoint-of-another-model": run_case(_checkpoint_of_another_model),
    "render/checkpoint-missing-tensors": run_case(_checkpoint_missing_tensors),
    "render/checkpoint-garbage": run_case(_checkpoint_bytes(b"\x00garbage" * 16)),
    "render/checkpoint-empty": run_case(_checkpoint_bytes(b"")),
    "render/checkpoint-old-pickle": run_case(lambda r, t: _legacy_checkpoint(r)),
    "render/size-zero": run_case(lambda r, t: "--size", flags=("--size", "0x10")),
    "render/frames-zero": run_case(lambda r, t: "--frames", flags=("--frames", "0")),
    "render/device-unknown": run_case(lambda r, t: "--device", flags=("--device", "bogus")),
    "render/missing-mp4-writer": Case(run_case(lambda r, t: "imageio_ffmpeg").make, missing_module="imageio_ffmpeg"),
    "train/resume-checkpoint-of-another-model": Case(lambda b, t: _resume_other_model(b, t)),
    "mesh/not-a-run-folder": run_case(_not_a_run, command="mesh", output="mesh"),
    "mesh/checkpoint-of-another-model": run_case(_checkpoint_of_another_model, command="mesh", output="mesh"),
    "mesh/resolution-zero": run_case(lambda r, t: "--resolution", command="mesh", flags=("--resolution", "0"), output="mesh"),
    "mesh/tsdf-views-zero": run_case(lambda r, t: "--views.tsdf-views must be", command="mesh", flags=("--views.tsdf-views", "0"), output="mesh"),
    "mesh/level-without-mc": run_case(lambda r, t: "--level", command="mesh", flags=("--level", "5"), output="mesh"),
    "mesh/out-under-a-file": Case(lambda b, t: (lambda run, out: (["mesh", str(run), "--out", str(out)], str(out), out))(_copy(b, "run", t), _file_out(t))),
    "stage/not-a-run-folder": stage_case(_keep),
    "stage/run-json-invalid": stage_case(lambda r, t: _write(r / "run.json", "[1, 2")),
    "stage/unknown-stage": stage_case(lambda r, t: (_write(r / "run.json", json.dumps({"source": None})), "nosuch")[1], name="nosuch"),
    "stage/marker-wrong-type": stage_case(lambda r, t: _bad_marker(r)),
    "stage/scene-json-escapes": stage_case(lambda r, t: _escaping_scene_json(r, t), name="check"),
    # fit2d's image
    "fit2d/text-file": file_case("fit2d", _text),
    "fit2d/empty-file": file_case("fit2d", _empty),
    "fit2d/truncated-png": file_case("fit2d", _truncated_png),
    "fit2d/float-tiff-300": file_case("fit2d", _float_tiff, name="input.tiff"),
    "fit2d/nan-tiff": file_case("fit2d", _nan_tiff, name="input.tiff"),
    "fit2d/one-pixel": file_case("fit2d", _one_pixel),
    "fit2d/iterations-zero": Case(lambda b, t: (["fit2d", str(b / "blender" / "train" / "view_001.png"), "--iterations", "0", "--out", str(t / "out")], "--iterations", t / "out")),
    "fit2d/out-under-a-file": Case(lambda b, t: (lambda out: (["fit2d", str(b / "blender" / "train" / "view_001.png"), "--out", str(out)], str(out), out))(_file_out(t))),
    # eval-mesh
    "eval-mesh/text-mesh": mesh_file_case(lambda p: p.write_text("ply\nnonsense\n")),
    "eval-mesh/empty-mesh": mesh_file_case(lambda p: p.write_bytes(b"")),
    "eval-mesh/nan-vertices": mesh_file_case(lambda p: p.write_text(NAN_PLY)),
    "fit2d/a-folder": Case(lambda b, t: (["fit2d", str(b / "blender"), "--out", str(t / "out")], str(b / "blender"), t / "out")),
    "eval-mesh/samples-zero": Case(lambda b, t: (["eval-mesh", str(b / "blender" / "gt_mesh.ply"), str(b / "blender" / "gt_mesh.ply"), "--samples", "0"], "--samples", None)),
    # synth
    "demo/device-unknown": param_case("demo", ["--device", "bogus"], "--device", data=None),
    "demo/out-under-a-file": out_under_file_case("demo", data=None),
    "demo/train-seconds-negative": param_case("demo", ["--train-seconds", "-1"], "--train-seconds", data=None),
    "synth/size-garbage": synth_case(["--size", "bigxsmall"], "--size"),
    "synth/size-tiny": synth_case(["--size", "2x2"], "2x2"),
    "synth/one-view": synth_case(["--views", "1"], "at least 2 views"),
    "synth/views-huge": synth_case(["--views", "100000"], "at most"),
    "synth/out-under-a-file": Case(lambda b, t: (lambda out: (["synth", str(out)], str(out), out))(_file_out(t))),
    "synth/out-not-empty": synth_case([], "{out}", prepare=_full_folder),
}


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _unlink(path: Path) -> Path:
    path.unlink()
    return path


def _small_png(path: Path) -> Path:
    from PIL import Image

    Image.new("RGB", (8, 8)).save(path)
    return path


def _as_float_tiff(path: Path) -> Path:
    """Replace a PNG with a float TIFF of values up to 300 under the same name (the decoder reads the content)."""
    from PIL import Image

    rgb = np.asarray(Image.open(path).convert("L"), np.float32) * 300.0 / 255.0
    Image.fromarray(rgb).save(path, format="TIFF")
    return path


def _resume_other_model(base: Path, tmp: Path):
    """``train --resume --model vanilla`` into a run folder whose checkpoint is the fast model's (the folder exists)."""
    run = _copy(base, "run", tmp)
    argv = ["train", str(base / "blender"), "--model", "vanilla", "--resume", "--iters", "1", "--out", str(run)]
    return argv, str(run / "checkpoint.safetensors"), None


NAN_PLY = """ply
format ascii 1.0
element vertex 3
property float x
property float y
property float z
element face 1
property list uchar int vertex_indices
end_header
nan 0 0
1 0 0
0 1 0
3 0 1 2
"""


def _huge_count(file: Path) -> Path:
    data = bytearray(file.read_bytes())
    data[8 + 43 : 8 + 51] = (2**40).to_bytes(8, "little")  # the first point's track length
    file.write_bytes(bytes(data))
    return file


def _one_photo(base: Path, tmp: Path):
    """One photo: SfM registers nothing; the error names the photos, and the new run folder is removed."""
    photos = tmp / "photos"
    photos.mkdir()
    shutil.copyfile(sorted((base / "colmap" / "images").iterdir())[0], photos / "a.png")
    return ["run", str(photos), "--out", str(tmp / "run-out")], str(photos), tmp / "run-out"


def _legacy_checkpoint(run: Path) -> Path:
    (run / "checkpoint.safetensors").unlink()
    (run / "checkpoint.pt").write_bytes(b"\x80\x04K\x01.")
    return run / "checkpoint.pt"


def _bad_marker(run: Path) -> Path:
    (run / "run.json").write_text(json.dumps({"source": None, "chain": ["render"]}))
    (run / "stages").mkdir()
    marker = run / "stages" / "render.done.json"
    marker.write_text(json.dumps({"config": {"frames": "many"}}))
    return marker


def _escaping_scene_json(run: Path, tmp: Path) -> Path:
    """A run folder whose scene.json points the load stage's restore at a folder elsewhere."""
    (run / "run.json").write_text(json.dumps({"source": None, "chain": ["load", "check"]}))
    (run / "stages").mkdir()
    (run / "stages" / "load.done.json").write_text(json.dumps({"stage": "load", "status": "ran", "config": {}, "artifacts": ["scene.json"]}))
    (run / "scene.json").write_text(json.dumps({"input": str(tmp / "elsewhere"), "format": None}))
    return run / "scene.json"


def test_battery_has_at_least_50_cases():
    assert len(CASES) >= 50


@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input_is_one_line_exit_2_nothing_written(name, base, tmp_path, capsys, monkeypatch):
    case = CASES[name]
    if case.missing_module is not None:
        monkeypatch.setitem(sys.modules, case.missing_module, None)
    argv, culprit, out = case.make(base, tmp_path)
    capsys.readouterr()
    start = time.monotonic()
    with warnings.catch_warnings(record=True) as caught:  # under pytest, warnings are recorded, not printed
        code = main(argv)
    seconds = time.monotonic() - start
    err = capsys.readouterr().err
    ours = [f"{w.filename}: {w.message}" for w in caught if issubclass(w.category, ResourceWarning) or any(s in w.filename for s in PACKAGE_DIRS)]
    assert not ours, ours  # each would be more lines on the real stderr
    lines = err.strip().splitlines()
    assert code == 2, err
    assert "Traceback" not in err
    assert len(lines) == 1, err
    assert lines[0].startswith("nerfpipe: error: ") and str(culprit) in lines[0], (culprit, lines[0])
    if out is not None:
        assert not Path(out).exists(), f"{out} was left behind"
    assert seconds < SECONDS


@pytest.mark.parametrize("name", ["train/image-truncated", "info/file-path-symlink-out", "render/checkpoint-of-another-model"])
def test_real_entry_point_prints_one_line(name, base, tmp_path):
    """The installed command, not only ``main()``: one line on stderr, exit 2, no warnings or traceback."""
    import os
    import subprocess

    argv, culprit, out = CASES[name].make(base, tmp_path)
    run = subprocess.run([sys.executable, "-m", "nerfpipe", *argv], capture_output=True, text=True, timeout=300, env={**os.environ})
    assert run.returncode == 2 and run.stderr.count("\n") == 1 and str(culprit) in run.stderr, run.stderr
    assert out is None or not Path(out).exists()


def test_missing_optional_dependency_is_found_before_training(base, tmp_path, monkeypatch):
    """The MP4 writer is needed only at the end; without it, training must not start (a lost result),
    and metrics.json or anything else must not be half-written."""
    from nerfpipe.training.trainer import Trainer

    started = []
    monkeypatch.setattr(Trainer, "train_step", lambda self: started.append(1))
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    out = tmp_path / "out"
    assert main(["train", str(base / "blender"), "--iters", "5", "--out", str(out)]) == 2
    assert not started and not out.exists()
    assert main(["run", str(base / "blender"), "--stages", "load,train,render", "--out", str(out)]) == 2
    assert not started and not out.exists()


@pytest.mark.parametrize("name, array, message", [
    ("../../escaped.png", np.zeros((48, 64, 3), np.uint8), "points outside the folder"),
    ("frame.png", np.full((48, 64, 3), 300.0, np.float32), "float values outside"),
    ("frame.png", np.zeros((48, 64, 3), np.int64), "dtype int64"),
])  # fmt: skip
def test_in_memory_images_handed_to_the_load_stage_are_checked(tmp_path, name, array, message):
    """The Python API's other input: image names stay inside the run folder, arrays must be images."""
    from colmap_synth import synthesize

    from nerfpipe.pipeline.stages import Pipeline
    from nerfpipe.util.errors import NerfpipeError

    with pytest.raises(NerfpipeError, match=message):
        Pipeline(["load"]).run(None, tmp_path / "run", reconstruction=synthesize(frames=3, points=20), images={name: array})
    assert not (tmp_path / "escaped.png").exists() and not (tmp_path / "run").exists()


def test_a_run_whose_config_names_a_retired_option_still_loads_with_a_warning(base, tmp_path):
    """A run folder written by an earlier nerfpipe may name a model option this version no longer has: the run
    still loads (the checkpoint's tensors must fit), with one warning naming the file and the options."""
    from nerfpipe.training.runs import RetiredOptionWarning, load_run
    from nerfpipe.util.errors import NerfpipeError

    run = _copy(base, "run", tmp_path)
    _json_edit(run / "config.json", lambda d: (d["model_config"].update(opacity_entropy_weight=0.0), d["model_config"]["occupancy"].update(gone=1)))
    with pytest.warns(RetiredOptionWarning, match=r"config\.json: .*opacity_entropy_weight, occupancy\.gone"):
        _, model, _ = load_run(run, "cpu")
    assert model is not None
    _checkpoint_missing_tensors(run, tmp_path)  # a checkpoint that does not fit is still refused
    with pytest.raises(NerfpipeError, match="missing tensors"):
        load_run(run, "cpu")
