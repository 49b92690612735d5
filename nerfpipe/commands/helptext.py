"""Help text as a reader sees it: the attribute docstrings tyro shows, without reStructuredText markup.

Docstrings are written for the API docs (``code``, :class:`~nerfpipe.training.trainer.TrainerConfig`, hard-wrapped
lines); ``--help`` shows them as plain paragraphs. :func:`plain_help` wraps tyro's two docstring readers
while a command line is parsed (a private tyro API: when it is absent, help keeps the raw docstrings).
"""

import contextlib
import re

_ROLE = re.compile(r":[a-z]+(?::[a-z]+)?:`~?([^`<]*?)(?:\s*<[^>]*>)?`")


def plain(text: "str | None") -> "str | None":
    """Docstring text without RST roles and literals, single line breaks joined.

    Example:
        >>> plain("Uses :func:`~nerfpipe.outputs.render.plan_frames` and ``chunk``\\nrays.\\n\\nNext.")
        'Uses plan_frames and chunk rays.\\n\\nNext.'
    """
    if not text:
        return text
    text = _ROLE.sub(lambda m: m.group(1).rsplit(".", 1)[-1] if m.group(0).count("~") else m.group(1), text)
    text = text.replace("``", "")
    paragraphs = re.split(r"\n\s*\n", text)
    return "\n\n".join(" ".join(line.strip() for line in p.splitlines() if line.strip()) for p in paragraphs)


@contextlib.contextmanager
def plain_help():
    """While active, tyro's field and command descriptions go through :func:`plain`."""
    try:
        from tyro import _docstrings
    except ImportError:  # pragma: no cover - another tyro layout: raw docstrings
        yield
        return
    field_doc, callable_doc = _docstrings.get_field_docstring, _docstrings.get_callable_description
    _docstrings.get_field_docstring = lambda *a, **k: plain(field_doc(*a, **k))
    _docstrings.get_callable_description = lambda *a, **k: plain(callable_doc(*a, **k))
    try:
        yield
    finally:
        _docstrings.get_field_docstring, _docstrings.get_callable_description = field_doc, callable_doc
