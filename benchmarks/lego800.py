"""An 800x800 NeRF-synthetic scene with its true poses, for issue #18's ceiling (the held-out 800² scene's stand-in),
built from two shared scenes outside the project: ``blender_lego`` holds lego's 100 training views at 400² with
Blender's poses, ``nerfstudio_lego`` the same 100 renders at 800² (with COLMAP's poses, off by about 0.2°, which
would blur an 800² scene). Each 800² image is matched to its 400² view (the 400² images are its 2x2 mean: the match
is checked to within 1/255 per value), and written with that view's pose in the Blender layout: every 8th view
(``i % 8 == 4``) is held out (``transforms_val.json``, also ``transforms_test.json``), the others train.

Run: ``python -m benchmarks.lego800 OUT`` (``OUT`` outside the project; ``--data`` the shared data folder), then e.g.
``python -m benchmarks.steps OUT --preset auto --marks 300 1000 3000 --eval-views 4 --eval-max-size None
--eval-supersample 1``.
"""

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import tyro

HOLD_OUT_PERIOD = 8
"""Views ``i % 8 == 4`` are held out."""


@dataclass
class Lego800Config:
    out: tyro.conf.Positional[Path]
    """Folder to write (new, or empty)."""
    data: Path = Path("../shared/data")
    """The shared data folder (holds ``blender_lego`` and ``nerfstudio_lego``)."""


def match_views(small_dir: Path, large_dir: Path) -> "dict[int, Path]":
    """The 800² image of each 400² training view ``r_i``: the one whose 2x2 mean equals it (within 1/255)."""
    small = {int(p.stem.split("_")[1]): iio.imread(p).astype(np.float32) for p in small_dir.glob("r_*.png")}
    keys = sorted(small)
    stack = np.stack([small[i][..., :3] for i in keys])
    out: "dict[int, Path]" = {}
    for path in sorted(large_dir.glob("*.png")):
        img = iio.imread(path).astype(np.float32)
        pooled = img.reshape(img.shape[0] // 2, 2, img.shape[1] // 2, 2, -1).mean((1, 3))
        err = np.abs(stack - pooled[None, ..., :3]).mean((1, 2, 3))
        best = keys[int(err.argmin())]
        if np.abs(small[best] - pooled).max() > 1.0 + 1e-3:
            raise ValueError(f"{path}: no 400² view is its 2x2 mean")
        if best in out:
            raise ValueError(f"{path} and {out[best]} both match r_{best}")
        out[best] = path
    return out


def build(cfg: Lego800Config) -> None:
    blender, nerfstudio = cfg.data / "blender_lego", cfg.data / "nerfstudio_lego"
    if cfg.out.exists() and any(cfg.out.iterdir()):
        raise SystemExit(f"{cfg.out}: not empty")
    large = match_views(blender / "train", nerfstudio / "images")
    src = json.loads((blender / "transforms_train.json").read_text())
    splits: "dict[str, list]" = {"train": [], "val": []}
    for frame in src["frames"]:
        i = int(frame["file_path"].split("_")[-1])
        split = "val" if i % HOLD_OUT_PERIOD == HOLD_OUT_PERIOD // 2 else "train"
        (cfg.out / split).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(large[i], cfg.out / split / f"r_{i}.png")
        splits[split].append(dict(frame, file_path=f"./{split}/r_{i}"))
    for name, frames in (("train", splits["train"]), ("val", splits["val"]), ("test", splits["val"])):
        doc = {"camera_angle_x": src["camera_angle_x"], "frames": frames}
        (cfg.out / f"transforms_{name}.json").write_text(json.dumps(doc, indent=1))
    print(f"{cfg.out}: {len(splits['train'])} training and {len(splits['val'])} held-out views at 800x800")


if __name__ == "__main__":
    build(tyro.cli(Lego800Config))
