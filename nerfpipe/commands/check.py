"""``nerfpipe check``: placeholder until the kornia consistency check lands (same session)."""


def check(path: str) -> int:
    """Check camera conventions of a dataset independently with kornia."""
    raise NotImplementedError
