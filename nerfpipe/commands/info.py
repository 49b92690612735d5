"""``nerfpipe info``: placeholder until it lands (same session)."""


def info(path: str) -> int:
    """Summarise a dataset."""
    raise NotImplementedError
