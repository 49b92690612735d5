"""What a stage shows in ``report.html``: small typed declarations next to its :class:`~nerfpipe.pipeline.stages.StageSpec`.

A stage lists :class:`Shown` items in ``StageSpec.shows``: which of its files are images, videos or
tables, under which title, and the ``role`` a report section knows them by (``colour``: the novel-view
GIF, ``metrics``: the training figures, ...). :mod:`nerfpipe.pipeline.report` names no artifact file: it asks
for roles, so renaming a stage's file is one edit, in its declaration, and the report follows; a
declared item no section asks for is shown in the report's "Other outputs" section (third-party
stages show their pictures without touching the report).
"""

from dataclasses import dataclass
from pathlib import PurePosixPath
from typing import Literal


@dataclass(frozen=True)
class Shown:
    """One file of a stage shown in the report."""

    role: str
    """Name a report section asks for (unique across the stages)."""
    kind: Literal["image", "video", "table"]
    """image (PNG/GIF, embedded), video (linked) or table (a JSON object's figures)."""
    files: "tuple[str, ...]"
    """Paths relative to the run folder, first existing wins (e.g. ``render/orbit.gif`` then ``render/test.gif``);
    each in a folder the stage ``produces`` into. A run folder of ``nerfpipe train`` (the stage's folder itself)
    is also searched without the folder prefix."""
    title: str
    """What the report calls it (captions, "not produced" notes)."""

    def candidates(self) -> "tuple[str, ...]":
        """``files``, then the same names without their stage folder (a ``nerfpipe train`` folder)."""
        bare = tuple(str(PurePosixPath(*PurePosixPath(f).parts[1:])) for f in self.files if len(PurePosixPath(f).parts) > 1)
        return self.files + tuple(b for b in bare if b not in self.files)


def declared(specs) -> "dict[str, Shown]":
    """``{role: Shown}`` of the given stage specs; a role declared twice is an error naming both stages."""
    out: "dict[str, Shown]" = {}
    owner: "dict[str, str]" = {}
    for spec in specs:
        for item in getattr(spec, "shows", ()):
            if item.role in out:
                raise ValueError(f"report role '{item.role}' declared by both '{owner[item.role]}' and '{spec.name}'")
            out[item.role], owner[item.role] = item, spec.name
    return out


def outside_produces(spec) -> "list[str]":
    """The declared files of ``spec`` that are not in a folder it produces into (should be none)."""
    folders = {PurePosixPath(p).parent for p in spec.produces} | {PurePosixPath(p) for p in spec.produces}
    return [f for item in spec.shows for f in item.files if PurePosixPath(f).parent not in folders and PurePosixPath(f) not in folders]
