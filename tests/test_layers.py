"""The layer rule of the package tree: a module never imports a package of a higher layer.

Every ``import nerfpipe...`` / ``from nerfpipe... import`` in the source counts, the lazy ones inside
functions included (a lazy import is still a dependency, only a later one). Packages of one layer may
use each other; the README's "Layout" section shows the same order.
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "nerfpipe"

LAYERS = [
    {"util"},
    {"functional"},
    {"data"},
    {"encoders", "fields", "estimators", "data_adapters"},
    {"models", "image_field"},
    {"outputs", "mesh"},
    {"training"},
    {"pipeline", "viewer"},
    {"plugins", "commands", "cli", "__main__", "__init__"},
]
"""Top-level names under ``nerfpipe/`` (subpackage or module), lowest layer first."""

RANK = {name: i for i, names in enumerate(LAYERS) for name in names}


def top_name(dotted: str) -> "str | None":
    """``nerfpipe.data.cameras`` -> ``data``; ``nerfpipe`` itself -> None."""
    parts = dotted.split(".")
    return parts[1] if parts[0] == "nerfpipe" and len(parts) > 1 else None


def imported_tops(source: str) -> "set[str]":
    """The top-level nerfpipe names a module's source imports (``from nerfpipe import x`` counts as ``x``)."""
    tops = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            tops |= {top_name(alias.name) for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module == "nerfpipe":
                tops |= {alias.name for alias in node.names if alias.name in RANK}
            else:
                tops.add(top_name(node.module))
    return tops - {None}


def layer_violations(files: "dict[str, str]") -> "list[str]":
    """``'importer -> imported'`` for each import from a lower layer into a higher one; ``files`` maps
    a path relative to ``nerfpipe/`` to its source."""
    found = []
    for rel, source in sorted(files.items()):
        own = Path(rel).parts[0].removesuffix(".py")
        for top in sorted(imported_tops(source)):
            if RANK[top] > RANK[own]:
                found.append(f"nerfpipe/{rel} (layer {RANK[own]}) imports nerfpipe.{top} (layer {RANK[top]})")
    return found


def package_sources() -> "dict[str, str]":
    return {str(p.relative_to(PACKAGE)): p.read_text() for p in PACKAGE.rglob("*.py")}


def test_every_top_level_name_has_a_layer():
    names = {p.name.removesuffix(".py") for p in PACKAGE.iterdir() if p.suffix == ".py" or (p / "__init__.py").is_file()}
    assert names == set(RANK), f"not in LAYERS: {sorted(names - set(RANK))}; gone: {sorted(set(RANK) - names)}"


def test_lower_layers_never_import_higher_ones():
    assert layer_violations(package_sources()) == []


@pytest.mark.parametrize(
    ("rel", "line"),
    [
        ("data/cameras.py", "from nerfpipe.training.trainer import Trainer"),
        ("util/errors.py", "    import nerfpipe.data.scene"),
        ("outputs/render.py", "    from nerfpipe import training"),
        ("functional/volrend.py", "from nerfpipe.models.base import Model"),
    ],
)
def test_an_upward_import_is_found(rel, line):
    """The check is not vacuous: one bad import (module level or lazy) added to a real module is reported."""
    files = package_sources()
    body = f"def f():\n{line}\n" if line.startswith(" ") else f"{line}\n"
    files[rel] += "\n" + body
    (found,) = layer_violations(files)
    assert found.startswith(f"nerfpipe/{rel}")


def test_same_layer_and_downward_imports_pass():
    files = {"mesh/x.py": "from nerfpipe.outputs.render import render_cameras\nfrom nerfpipe.util import errors\n"}
    assert layer_violations(files) == []
