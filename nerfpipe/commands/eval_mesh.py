"""``nerfpipe eval-mesh``: geometry metrics of a mesh against a reference mesh or a dataset's points."""

from pathlib import Path

from typing import Annotated

import tyro
from tyro.conf import Positional

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".glb", ".gltf")


def eval_mesh(
    mesh: Annotated[Path, Positional, tyro.conf.arg(metavar="MESH")],
    ref: Annotated[Path, Positional, tyro.conf.arg(metavar="REF")],
    threshold: "float | None" = None,
    samples: int = 100_000,
    crop: bool = True,
    json: bool = False,
) -> int:
    """Compare MESH with REF: a reference mesh file, or a dataset folder (its sparse points).

    Against a mesh: accuracy, completeness, Chamfer-L1, precision/recall/F-score at the
    threshold and normal consistency. Against a dataset (e.g. COLMAP): the fraction of its
    sparse points within the threshold of MESH, in the dataset's input frame (the frame
    nerfpipe exports in), and the free-space violation: the share of its track observations
    whose camera-to-point sight line hits MESH more than 1% of the points' extent before the
    point (fog scores high, a correct surface near 0); a synthetic scene folder is also
    compared with its gt_mesh.ply.

    Args:
        mesh: the mesh to evaluate (PLY, OBJ, STL, OFF, GLB).
        ref: reference mesh file, or dataset folder with sparse points.
        threshold: distance threshold in the meshes' units (default: 1% of the reference
            mesh's box diagonal, or of MESH's for points).
        samples: points sampled on each surface.
        crop: against points, keep only those inside MESH's bounding box grown by the threshold
            (the points on the object, not the background).
        json: print the figures as JSON.
    """
    import json as _json

    from nerfpipe.mesh.export import read_mesh
    from nerfpipe.util.errors import refuse_unless

    refuse_unless([("samples", samples >= 1, "at least 1", samples),
                   ("threshold", threshold is None or threshold > 0, "a positive distance", threshold)])  # fmt: skip
    pred = read_mesh(mesh)
    if Path(ref).is_file() and Path(ref).suffix.lower() in MESH_SUFFIXES:
        result = {"reference": str(ref), **_against_mesh(pred, read_mesh(ref), threshold, samples)}
    else:
        result = {"reference": str(ref), **_against_dataset(pred, Path(ref), threshold, samples, crop)}
    if json:
        print(_json.dumps(result, indent=2))
    else:
        for key, value in result.items():
            print(f"{key:>22}: {value:.6g}" if isinstance(value, float) else f"{key:>22}: {value}")
    return 0


def _against_mesh(pred, ref_mesh, threshold, samples) -> dict:
    from nerfpipe.mesh.metrics import compare_meshes

    return compare_meshes(pred, ref_mesh, threshold, num_samples=samples).to_dict()


def _against_dataset(pred, ref: Path, threshold, samples, crop: bool) -> dict:
    from nerfpipe.data_adapters import load
    from nerfpipe.mesh.reference import dataset_references, reference_figures, sight_lines
    from nerfpipe.util.errors import NerfpipeError

    scene = load(ref)
    gt, points = dataset_references(scene, ref)
    above = None
    if crop and points is not None and scene.points is not None and len(scene.points.xyz) == len(points):
        from nerfpipe.training.trainer import above_support

        above = above_support(scene)  # not on the table the object stands on, as the mesh stage counts them
    try:
        return reference_figures(pred, gt, points, threshold, samples, crop, gt_prefix="gt_mesh_", sight_lines=sight_lines(scene),
                                 above_support=above)
    except NerfpipeError as exc:
        raise NerfpipeError(exc.problem, ref) from exc
