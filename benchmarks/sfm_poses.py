"""How often the ``sfm`` stage recovers a capture's poses: run its reconstruction (features, matching, incremental
mapping, as ``nerfpipe run PHOTOS`` does) several times and compare each result with a reference model of the same
photographs (COLMAP's own, from more images), by rotation: the share of photos whose rotation agrees within
``--tolerance`` degrees after the best alignment through any one photo (a reconstruction that folds part of the
capture onto the wrong side keeps the rest exact, so a least-squares alignment would blur which photos are wrong).

Run: ``python -m benchmarks.sfm_poses PHOTOS REFERENCE_MODEL --runs 5``; one JSON line per run.
Session 28: 23 of colmap_mouse's photos (every 56/23-th by name) against COLMAP's model of all 56, one line per run.
Since session 61 each run is unfolded as the stage does (``unfold`` in its line: ``nerfpipe.plugins.unfold``); since
session 72 the rarer orientation's photos are turned to share their camera as the stage does (``--no-turn``: not).
``--budget SECONDS`` (session 73): the stage's whole choice instead (every image size, unfolded, then the size check
or the consensus as the time allows), as ``nerfpipe run PHOTOS --time-budget`` gives it that many seconds. Photos are
compared with the reference by the name before its first dot (a HEIC photo ``X.HEIC`` is ``X.HEIC.jpg`` in the
reconstruction and may be ``X.jpg`` in the reference).
"""

if __name__ == "__main__":  # run as a program: the CLI's process settings, before torch loads OpenMP
    from nerfpipe.util import runtime

    runtime.apply()

import json
import logging
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import tyro


@dataclass
class SfmPosesConfig:
    photos: tyro.conf.Positional[Path]
    """A folder of photos (what ``nerfpipe run`` takes)."""
    reference: tyro.conf.Positional[Path]
    """A COLMAP model (``sparse/0``-style folder) of the same photos, by file name."""
    runs: int = 3
    """Reconstructions, each from scratch (COLMAP's RANSAC and mapping are randomised)."""
    seed: "int | None" = None
    """``IncrementalPipelineOptions.random_seed`` of the mapping (None: COLMAP's default, random)."""
    tolerance: float = 5.0
    """Degrees within which a rotation agrees."""
    turn: bool = True
    """Photos of the rarer orientation turned to share their camera (``SfmConfig.turn``; session 72)."""
    extend: bool = True
    """An unfolding that left photos out continued with every photo pair (``SfmConfig.extend_unfolded``; session 91)."""
    budget: "float | None" = None
    """Seconds the stage has (the whole choice among image sizes, as under ``nerfpipe run --time-budget``); None: the
    first image size's reconstruction only."""


def main(cfg: SfmPosesConfig) -> "list[dict]":
    import pycolmap

    from nerfpipe.plugins import sfm
    from nerfpipe.plugins.sfm import model_rotations, rotation_agreement, rotation_errors

    def by_stem(rotations: dict) -> dict:
        return {name.split(".")[0]: r for name, r in rotations.items()}

    reference = by_stem(model_rotations(pycolmap.Reconstruction(str(cfg.reference))))
    config = sfm.SfmConfig(turn=cfg.turn, extend_unfolded=cfg.extend, **({} if cfg.budget else {"candidate_sizes": ()}))
    options = sfm._options
    if cfg.seed is not None:
        def seeded(pycolmap, config, time_left):
            ext, match, mapping, reader = options(pycolmap, config, time_left)
            mapping.random_seed = cfg.seed
            return ext, match, mapping, reader

        sfm._options = seeded
    rows, log = [], logging.getLogger("sfm_poses")
    photos = sfm._photos(cfg.photos)
    try:
        for run in range(cfg.runs):
            with tempfile.TemporaryDirectory() as tmp:
                work = Path(tmp)
                start = time.monotonic()
                left = (lambda: cfg.budget - (time.monotonic() - start)) if cfg.budget else (lambda: None)
                rec, _, images, unfolded = sfm._candidate(photos, work, config, left(), log)
                sfm.drop_failed_registrations(rec, config.max_centre_spread)
                chosen = {}
                if cfg.budget:
                    rec, images, chosen = sfm.choose_reconstruction(photos, work, config, (rec, images), left(), log, unfolded)
                rec, _ = sfm.unturn(rec, images)  # the photos upright, as the reference has them
                seconds = time.monotonic() - start
                rotations = by_stem(model_rotations(rec))
                agreement = rotation_agreement(rotations, reference, cfg.tolerance)
                errors = rotation_errors(rotations, reference, cfg.tolerance)
                agreement["off"] = {name: round(e, 1) for name, e in sorted(errors.items()) if e >= cfg.tolerance}
                rows.append(dict(run=run, photos=len(photos), registered=rec.num_reg_images(), points=rec.num_points3D(),
                                 reprojection_px=round(rec.compute_mean_reprojection_error(), 3), seconds=round(seconds, 1),
                                 focal_px=sorted({round(c.mean_focal_length()) for c in rec.cameras.values()}),
                                 **agreement, unfold=unfolded, **{k: chosen[k] for k in ("candidates", "with_conflicts", "still_folded", "strict") if k in chosen},
                                 **({"unfold_other_sizes": chosen["unfold"]} if "unfold" in chosen else {})))
                print(json.dumps(rows[-1]), flush=True)
    finally:
        sfm._options = options
    return rows


if __name__ == "__main__":
    main(tyro.cli(SfmPosesConfig))
