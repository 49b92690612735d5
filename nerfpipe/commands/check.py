"""``nerfpipe check``: verify a dataset's camera conventions independently (kornia, COLMAP points).

The checks live in :mod:`nerfpipe.data.consistency`; this command only formats them. Exit code 1
means a convention is broken (see the listed failures), 0 means every check passed.
"""

from nerfpipe.commands.info import DatasetPath


def check(path: DatasetPath, json: bool = False, samples: int = 16, seed: int = 0) -> int:
    """Check a dataset's cameras against kornia, a nerfpipe round trip and COLMAP's own points.

    Args:
        path: Dataset file or folder (any format nerfpipe reads).
        json: Print the figures as JSON only.
        samples: Random pixels per camera, besides the four corners and the centre.
        seed: Seed of the random pixels.
    """
    import json as _json

    import torch

    from nerfpipe import data_adapters
    from nerfpipe.commands.info import print_table
    from nerfpipe.data.consistency import check_scene

    from nerfpipe.util.errors import refuse_unless
    from nerfpipe.util.scoped import torch_threads

    refuse_unless([("samples", samples >= 0, "0 or more", samples)])
    with torch_threads(min(2, torch.get_num_threads())):  # handed back after (a caller's own count stays)
        report = check_scene(data_adapters.load(path), samples=samples, seed=seed)
    figures = report.as_dict()
    if json:
        print(_json.dumps(figures, indent=2))
    else:
        failures = figures.pop("failures")
        print_table(f"nerfpipe check: {path}", {k: v for k, v in figures.items() if v is not None})
        for line in failures:
            print(f"FAILED: {line}")
        print("all checks passed" if not failures else f"{len(failures)} check(s) failed")
    return 1 if report.failures else 0
