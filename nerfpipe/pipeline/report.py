"""``report.html``: one self-contained page summarising a run folder.

The page reads whatever the stages left in the run folder and never fails on a missing or
unreadable artifact: such an artifact is shown as "not produced" and listed at the end.

Sections: key figures, scene and convention check, training metrics and PSNR curves, novel views
(orbit and depth GIFs), speed against error (a ``nerfpipe bench`` table), mesh, cameras, other
outputs, stage timings. The files come from what each stage declares it shows
(``StageSpec.shows``, :mod:`nerfpipe.pipeline.report_items`): the sections ask for roles (``colour``,
``metrics``...), never for a stage's file names, and a declared item no section asks for goes to
"Other outputs". Images are embedded as base64 ``data:`` URIs so the file can be moved or mailed; an
image larger than ``max_embed_mb`` is linked by its path relative to the report instead. No
external resources (fonts, scripts, CDNs) are used.

Glossary:
    run_dir   the run folder of ``nerfpipe run``
    page      :class:`Page`: where the sections look things up, and what they found missing
"""

import base64
import datetime
import html
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from nerfpipe.pipeline.report_items import Shown, declared
from nerfpipe.util.errors import NerfpipeError
from nerfpipe.util.paths import resolve_inside

REPORT_FILE = "report.html"

# A ``nerfpipe bench`` folder (not a stage's output: ``ReportConfig.bench_dir`` or ``bench/``).
BENCH_JSON = ("table.json",)
BENCH_MD = ("table.md",)
BENCH_PNG = Shown("bench_curves", "image", ("psnr_vs_seconds.png",), "val PSNR against training seconds")

# Labels (and units) of the figures the stages write; other keys are shown under their own name.
LABELS = {
    "val_psnr": ("val PSNR", "dB"),
    "val_psnr_colour_fitted": ("val PSNR, right halves, colours fitted on left halves", "dB"),
    "val_psnr_appearance_fitted": ("val PSNR, right halves, appearance codes fitted on left halves", "dB"), "train_psnr": ("train PSNR", "dB"), "val_ssim": ("val SSIM", ""),
    "val_views": ("val views", ""), "eval_scale": ("eval resolution factor", ""),
    "train_seconds": ("training time", "s"), "iterations": ("iterations", ""),
    "seconds_per_iteration": ("time per iteration", "s"), "rays_per_step": ("rays per step", ""),
    "model": ("model", ""), "model_params": ("parameters", ""), "model_mb": ("model size", "MB"),
    "checkpoint_mb": ("checkpoint on disk (with optimizer state)", "MB"), "finest_resolution": ("finest grid level", "vertices along the box"),
    "finest_voxel": ("finest voxel", "scene units"), "hashed_levels": ("hashed grid levels", ""),
    "sparse_levels": ("sparse grid levels (blocks stored where space is occupied)", ""),
    "sparse_stored_share": ("share of the sparse levels' blocks stored", ""),
    "sparse_blocks_missing": ("blocks needed without a free slot (read as zeros)", ""),
    "samples_per_ray": ("samples per ray", ""), "occupied_fraction": ("occupied fraction", ""),
    "sparsity_weight": ("sparsity loss weight (0: off)", ""),
    "evidence_sparsity_weight": ("sparsity loss weight away from the sparse points (0: off)", ""),
    "distortion_weight": ("distortion loss weight in the box (0: off)", ""),
    "behind_front": ("rays through the box read the surroundings in front of it (1: on)", ""),
    "free_space_violation": ("free-space violation (sight lines blocked by the mesh)", ""),
    "sight_lines": ("sight lines (camera to sparse point)", ""), "free_space_tau": ("free-space slack before the point", ""),
    "fscore": ("F-score", ""), "chamfer_l1": ("Chamfer-L1", ""), "precision": ("precision", ""),
    "recall": ("recall", ""), "accuracy": ("accuracy", ""), "completeness": ("completeness", ""),
    "faces": ("faces", ""), "faces_simplified": ("faces (simplified)", ""), "vertices": ("vertices", ""),
    "hausdorff_max": ("Hausdorff max (simplification)", ""), "hausdorff_mean": ("Hausdorff mean (simplification)", ""),
    "level": ("density iso-level", ""), "voxel_size": ("voxel size", ""), "num_cameras": ("cameras", ""),
    "kornia_max_px": ("kornia projection max error", "px"),
    "kornia_unproject_max_px": ("kornia unprojection max error", "px"), "num_probes": ("probe pixels", ""),
    "rotation_orthonormality_err": ("rotation orthonormality error", ""), "roundtrip_max_px": ("round-trip max error", "px"),
    "facing_fraction": ("cameras facing the box", ""), "reproj_mean_px": ("reprojection error (mean)", "px"),
}  # fmt: skip


@dataclass
class ReportConfig:
    """Options of the HTML report (the ``report`` stage)."""

    title: "str | None" = None
    """Page title; default: "nerfpipe report: <input name>"."""
    max_embed_mb: float = 4.0
    """Images up to this size are embedded in the page; larger ones are linked by relative path."""
    bench_dir: "str | None" = None
    """Folder of a ``nerfpipe bench`` result to include; default: ``bench/`` in the run folder."""


@dataclass
class Page:
    """What the section builders share: the run folder, the options and what was not produced."""

    run_dir: Path
    config: ReportConfig = field(default_factory=ReportConfig)
    out_dir: "Path | None" = None
    """Folder the report is written to (relative links start here); default: the run folder."""
    missing: "list[str]" = field(default_factory=list)
    items: "dict[str, Shown] | None" = None
    """What the stages declare they show (default: every registered stage's ``shows``)."""
    used: "set[str]" = field(default_factory=set)
    """The roles the sections asked for; ``undeclared``: those no stage declares."""
    undeclared: "list[str]" = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.items is None:
            from nerfpipe.pipeline.stages import stages

            self.items = declared(stages().values())

    def item(self, role: str) -> Shown:
        """The declaration of ``role`` (one with no files, recorded in ``undeclared``, when no stage declares it)."""
        self.used.add(role)
        if role not in self.items:
            self.undeclared.append(role)
            return Shown(role, "table", (), role)
        return self.items[role]

    def first(self, *roles: str) -> Shown:
        """The first of ``roles`` whose file exists (else the first), e.g. the render stage's GIF, else the training's."""
        items = [self.item(r) for r in roles]
        return next((i for i in items if self.find(i.candidates()) is not None), items[0])

    def find(self, candidates: "tuple[str, ...]", root: "Path | None" = None) -> "Path | None":
        """First existing file among the candidate globs (relative to ``root``, default the run folder)."""
        root = self.run_dir if root is None else root
        for pattern in candidates:
            hits = sorted(p for p in root.glob(pattern) if p.is_file() and self._inside(root, p))
            if hits:
                return hits[0]
        return None

    def _inside(self, root: Path, path: Path) -> bool:
        """Whether ``path`` resolves inside ``root``: a link out of the run folder is never embedded in the page."""
        try:
            resolve_inside(root, path.relative_to(root))
        except NerfpipeError as exc:
            self.missing.append(f"{path.relative_to(root)} (not embedded: {exc.problem})")
            return False
        return True

    def optional_json(self, role: str) -> "dict | None":
        """The JSON object of ``role``'s file, None when absent (a stage that runs for some inputs only)."""
        path = self.find(self.item(role).candidates())
        return None if path is None else self.json(role)

    def json(self, role: str) -> "dict | None":
        """The JSON object of ``role``'s file; None (recorded as missing) when absent or unreadable."""
        item = self.item(role)
        path = self.find(item.candidates())
        data = read_json(path) if path is not None else None
        if data is None:
            self.missing.append(f"{item.title} ({(item.files or (role,))[0]}{'' if path is None else ': unreadable'})")
        return data


def read_json(path: Path) -> "dict | None":
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


# ---------------------------------------------------------------- formatting


def esc(value: object) -> str:
    return html.escape(str(value), quote=True)


def fmt(value: object) -> str:
    """A figure as short text: 4 significant digits, thousands separators, lists joined."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        if value != value:
            return "nan"
        return f"{value:,.0f}" if abs(value) >= 1e4 else f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        text = ", ".join(fmt(v) for v in value) if len(value) <= 6 else json.dumps(value)
        return text if len(text) <= 120 else text[:117] + "..."
    if isinstance(value, dict):
        text = json.dumps(value)
        return text if len(text) <= 120 else text[:117] + "..."
    return "—" if value is None else str(value)


def label(key: str) -> str:
    name, unit = LABELS.get(key, (key.replace("_", " "), ""))
    return f"{name} ({unit})" if unit else name


def kv_table(data: dict, keys: "list[str] | None" = None) -> str:
    """Two-column table of ``data`` (the given keys that exist, default all scalar-ish keys)."""
    keys = [k for k in (keys if keys is not None else list(data)) if k in data]
    rows = "".join(f"<tr><th>{esc(label(k))}</th><td>{esc(fmt(data[k]))}</td></tr>" for k in keys)
    return f'<table class="kv">{rows}</table>' if rows else ""


def kv_columns(data: dict, keys: "list[str] | None" = None) -> str:
    """:func:`kv_table` split into two side-by-side halves (long lists of figures)."""
    keys = [k for k in (keys if keys is not None else list(data)) if k in data]
    half = (len(keys) + 1) // 2
    return f'<div class="cols">{kv_table(data, keys[:half])}{kv_table(data, keys[half:])}</div>' if keys else ""


def table(header: "list[str]", rows: "list[list[str]]", cls: str = "grid") -> str:
    """A table of already escaped cells."""
    head = "".join(f"<th>{h}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>" for row in rows)
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def not_produced(what: str) -> str:
    return f'<div class="absent">{esc(what)}: not produced</div>'


# ---------------------------------------------------------------- images

MIME = {".png": "image/png", ".gif": "image/gif", ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".webp": "image/webp"}


def image_src(path: Path, page: Page) -> "tuple[str, bool]":
    """(``src`` value, embedded?): a data URI, or the path relative to the report when too large."""
    if path.stat().st_size <= page.config.max_embed_mb * 2**20:
        data = base64.b64encode(path.read_bytes()).decode("ascii")
        return f"data:{MIME.get(path.suffix.lower(), 'application/octet-stream')};base64,{data}", True
    rel = os.path.relpath(path.resolve(), (page.out_dir or page.run_dir).resolve())
    return Path(rel).as_posix(), False


def figure(page: Page, item: Shown, caption: str = "", cls: str = "", root: "Path | None" = None) -> str:
    """An ``<figure>`` with the item's image, or a "not produced" note (recorded as missing)."""
    path, what = page.find(item.candidates(), root), item.title
    if path is None:
        page.missing.append(f"{what} ({(item.files or (item.role,))[0]})")
        return not_produced(what)
    src, embedded = image_src(path, page)
    rel = path.relative_to(root or page.run_dir).as_posix()
    note = "" if embedded else f" — linked, {path.stat().st_size / 2**20:.1f} MB"
    text = f"<b>{esc(what)}</b> <code>{esc(rel)}</code>{note}" + (f"<br>{esc(caption)}" if caption else "")
    return f'<figure class="{cls}"><img src="{src}" alt="{esc(what)}"><figcaption>{text}</figcaption></figure>'


def section(anchor: str, title: str, body: str) -> str:
    return f'<section id="{anchor}"><h2>{esc(title)}</h2>{body}</section>'


# ---------------------------------------------------------------- sections


def key_figures(metrics: "dict | None", check: "dict | None", mesh: "dict | None") -> str:
    """A row of cards with the headline figures that exist."""
    cards = []
    for data, keys in ((metrics, ("val_psnr", "val_ssim", "train_seconds", "iterations", "model_mb", "samples_per_ray")),
                       (mesh, ("fscore", "chamfer_l1", "free_space_violation", "faces"))):  # fmt: skip
        for key in keys:
            if data and isinstance(data.get(key), (int, float)):
                name, unit = LABELS.get(key, (key, ""))
                cards.append((fmt(data[key]), unit, name, ""))
    if check is not None:
        bad = check.get("failures") or []
        cards.append(("broken" if bad else "OK", "", "camera conventions", "bad" if bad else "good"))
    if not cards:
        return ""
    html_cards = "".join(
        f'<div class="card {cls}"><div class="v">{esc(v)}<small> {esc(u)}</small></div><div class="k">{esc(k)}</div></div>'
        for v, u, k, cls in cards
    )
    return f'<div class="cards">{html_cards}</div>'


def _scene_rows(scene: dict) -> dict:
    """scene.json with its lists written the way people read them."""
    out = dict(scene)
    if isinstance(scene.get("splits"), dict):
        out["splits"] = ", ".join(f"{k} {v}" for k, v in scene["splits"].items())
    if isinstance(scene.get("image_sizes"), list):
        out["image_sizes"] = ", ".join("×".join(str(n) for n in s) for s in scene["image_sizes"] if isinstance(s, list))
    if isinstance(scene.get("aabb"), list):
        out["aabb"] = " to ".join("(" + ", ".join(fmt(x) for x in c) + ")" for c in scene["aabb"] if isinstance(c, list))
    return out


SCENE_KEYS = ["input", "adapter", "num_cameras", "splits", "image_sizes", "camera_models", "near", "far", "aabb", "num_points", "has_alpha"]
CHECK_KEYS = ["num_cameras", "num_probes", "kornia_max_px", "kornia_unproject_max_px", "roundtrip_max_px", "facing_fraction",
              "reproj_mean_px", "reproj_median_px", "colmap_reported_mean_px", "points_in_front_fraction"]  # fmt: skip


SFM_KEYS = ["mode", "num_photos", "num_triangulated_photos", "num_registered", "unregistered", "dropped", "num_points3D", "mean_reprojection_error_px"]


def scene_section(scene: "dict | None", check: "dict | None", sfm: "dict | None" = None) -> str:
    left = kv_table(_scene_rows(scene), SCENE_KEYS) if scene is not None else not_produced("scene summary (scene.json)")
    if sfm is not None:
        left += "<h3>Structure from motion</h3>" + kv_table({k: v for k, v in sfm.items() if k in SFM_KEYS}, SFM_KEYS)
    if check is None:
        right = not_produced("convention check (check.json)")
    else:
        bad = check.get("failures") or []
        status = (f'<p class="status bad">conventions broken: {esc("; ".join(map(str, bad)))}</p>' if bad
                  else '<p class="status good">camera conventions consistent with kornia and the round trip</p>')  # fmt: skip
        right = status + kv_table({k: v for k, v in check.items() if v is not None}, CHECK_KEYS)
    return section("scene", "Scene and convention check", f'<div class="cols"><div><h3>Scene</h3>{left}</div><div><h3>Check</h3>{right}</div></div>')


def training_section(page: Page, metrics: "dict | None") -> str:
    if metrics is None:
        body = not_produced("training metrics (train/metrics.json)")
    else:
        flat = {k: v for k, v in metrics.items() if not isinstance(v, dict) and k != "depth_colormap"}
        body = kv_columns(flat)
    curves = figure(page, page.item("psnr_curves"), "train (per batch) and validation PSNR against iterations and seconds", "wide")
    progress = figure(page, page.item("progress"), cls="wide")
    held_out = figure(page, page.item("held_out"), "where the held-out views go wrong", "wide")
    return section("training", "Training", f"<h3>Metrics</h3>{body}{curves}{progress}{held_out}")


def _link(page: Page, item: Shown) -> str:
    path, text = page.find(item.candidates()), item.title
    if path is None:
        return ""
    rel = os.path.relpath(path.resolve(), (page.out_dir or page.run_dir).resolve())
    return f'<p class="note"><a href="{esc(Path(rel).as_posix())}">{esc(text)}</a> (linked, not embedded)</p>'


def views_section(page: Page) -> str:
    info = read_json(p) if (p := page.find(page.item("views_info").candidates())) is not None else None
    info = info or {}
    size = info.get("size")
    caption = f"{info['frames']} frames of {size[0]}×{size[1]}" if "frames" in info and isinstance(size, list) else ""
    colour = figure(page, page.first("colour", "train_colour"), caption, "gif")
    depth = figure(page, page.first("depth", "train_depth"), info.get("depth_mapping", ""), "gif")
    mp4 = _link(page, page.first("video", "train_video"))
    return section("views", "Novel views", f'<div class="row">{colour}{depth}</div>{mp4}')


BENCH_COLUMNS = [("preset", "preset"), ("budget_s", "budget (s)"), ("train_s", "train (s, wall)"), ("iterations", "iterations"),
                 ("val_psnr", "val PSNR (dB)"), ("val_ssim", "SSIM"), ("model_mb", "MB"), ("samples_per_ray", "samples/ray")]  # fmt: skip


def bench_table(rows: "list[dict]") -> str:
    """The bench rows; the best PSNR of each budget in bold."""
    best: dict = {}
    for r in rows:
        if isinstance(r.get("val_psnr"), (int, float)):
            best[r.get("budget_s")] = max(best.get(r.get("budget_s"), float("-inf")), r["val_psnr"])
    cells = []
    for r in rows:
        row = [esc(fmt(r.get(k))) for k, _ in BENCH_COLUMNS]
        if r.get("val_psnr") is not None and r.get("val_psnr") == best.get(r.get("budget_s")):
            row[4] = f"<b>{row[4]}</b>"
        cells.append(row)
    return table([esc(h) for _, h in BENCH_COLUMNS], cells, "grid num")


def history_table(rows: "list[dict]") -> str:
    """Validation PSNR / SSIM of one run at each validation, against training seconds."""
    cols = [("step", "iteration"), ("train_seconds", "training s"), ("val_psnr", "val PSNR (dB)"), ("val_ssim", "SSIM"), ("views", "views")]
    cells = [[esc(fmt(r.get(k))) for k, _ in cols] for r in rows if isinstance(r, dict)]
    return table([esc(h) for _, h in cols], cells, "grid num")


def bench_section(page: Page) -> str:
    root = Path(page.config.bench_dir) if page.config.bench_dir else page.run_dir / "bench"
    doc = read_json(p) if (p := page.find(BENCH_JSON, root)) is not None else None
    history = page.item("history")
    if doc is not None and isinstance(doc.get("rows"), list):
        rows = [r for r in doc["rows"] if isinstance(r, dict)]
        body = f"<p>scene: {esc(doc.get('scene', '?'))}; best val PSNR per budget in bold</p>" + bench_table(rows)
    elif (md := page.find(BENCH_MD, root)) is not None:
        body = f"<pre>{esc(md.read_text())}</pre>"
    elif (hist := page.find(history.candidates())) is not None and (rows := (read_json(hist) or {}).get("val")):
        body = ("<p>this run's validations against training seconds (run <code>nerfpipe bench PATH</code> "
                "and put its folder in <code>bench/</code> to compare presets)</p>" + history_table(rows))
    else:
        page.missing.append(f"speed-against-error table ({root.name}/table.json)")
        body = not_produced("speed-against-error table (nerfpipe bench: table.json)")
    body += figure(page, BENCH_PNG, cls="wide", root=root) if root.is_dir() else ""
    return section("bench", "Speed against error", body)


MESH_KEYS = ["method", "faces", "vertices", "faces_simplified", "hausdorff_max", "hausdorff_mean", "level", "voxel_size",
             "unseen_faces_removed", "floater_faces_removed", "seconds_extract", "seconds_clean_color", "seconds_simplify"]  # fmt: skip
MESH_EVAL_KEYS = ["fscore", "precision", "recall", "chamfer_l1", "accuracy", "completeness", "normal_consistency", "threshold", "reference",
                  "points_within_threshold", "points_all_within_threshold", "points_excluded", "points_threshold", "mesh_area_near_points",
                  "free_space_violation", "sight_lines", "free_space_tau"]  # fmt: skip


def mesh_section(page: Page, mesh: "dict | None", evaluation: "dict | None") -> str:
    left = kv_table(mesh, MESH_KEYS) if mesh is not None else not_produced("mesh figures (mesh.json)")
    if evaluation is not None:
        left += "<h3>Against the reference</h3>" + kv_table(evaluation, MESH_EVAL_KEYS)
    views = figure(page, page.item("mesh_views"))
    return section("mesh", "Mesh", f'<div class="cols"><div>{left}</div><div>{views}</div></div>')


def cameras_section(page: Page) -> str:
    return section("cameras", "Cameras", figure(page, page.item("cameras"), cls="square"))


def others_section(page: Page) -> str:
    """The declared items no section asked for (a third-party stage's pictures, tables, videos) that exist."""
    parts = []
    for role, item in page.items.items():
        if role in page.used or page.find(item.candidates()) is None:
            continue
        if item.kind == "image":
            parts.append(figure(page, item, cls="wide"))
        elif item.kind == "video":
            parts.append(_link(page, item))
        else:
            data = read_json(page.find(item.candidates())) or {}
            parts.append(f"<h3>{esc(item.title)}</h3>" + kv_table({k: v for k, v in data.items() if not isinstance(v, dict)}))
    return section("others", "Other outputs", "".join(parts)) if parts else ""


def stage_markers(run_dir: Path, chain: "list[str]") -> "list[dict]":
    """The ``stages/*.done.json`` markers, in chain order, then the others by finishing time."""
    markers = [m for p in sorted((run_dir / "stages").glob("*.done.json")) if (m := read_json(p)) is not None]
    order = {name: i for i, name in enumerate(chain)}
    return sorted(markers, key=lambda m: (order.get(m.get("stage"), len(order)), m.get("finished_at", 0.0)))


def timings_section(markers: "list[dict]") -> str:
    if not markers:
        return section("timings", "Stage timings", not_produced("stage markers (stages/*.done.json)"))
    seconds = [float(s) if isinstance(s := m.get("seconds"), (int, float)) else 0.0 for m in markers]
    longest = max(max(seconds), 1e-9)
    rows = [
        [esc(m.get("stage", "?")), esc(m.get("status", "?")), esc(f"{s:.1f}"),
         f'<div class="bar" style="width:{100 * s / longest:.1f}%"></div>', esc(str(m.get("finished", "")).replace("T", " "))]
        for m, s in zip(markers, seconds)
    ]  # fmt: skip
    rows.append(["<b>total</b>", "", f"<b>{sum(seconds):.1f}</b>", "", ""])
    return section("timings", "Stage timings", table(["stage", "status", "seconds", "", "finished"], rows, "grid timings"))


def missing_section(missing: "list[str]") -> str:
    if not missing:
        return section("missing", "Not produced", "<p>Every artifact the report looks for was found.</p>")
    items = "".join(f"<li>{esc(m)}</li>" for m in dict.fromkeys(missing))
    return section("missing", "Not produced", f"<p>These artifacts are not in the run folder (their stages did not run, or wrote nothing):</p><ul>{items}</ul>")


NAV = [("scene", "Scene"), ("training", "Training"), ("views", "Novel views"), ("bench", "Speed/error"),
       ("mesh", "Mesh"), ("cameras", "Cameras"), ("timings", "Timings"), ("missing", "Not produced")]  # fmt: skip


def header(title: str, run_dir: Path, source: object, chain: "list[str]") -> str:
    source = source or "in-memory input"
    chain = " → ".join(chain) or "unknown"
    when = datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    nav = "".join(f'<a href="#{a}">{esc(t)}</a>' for a, t in NAV)
    return (f"<header><div class='inner'><h1>{esc(title)}</h1><p class='meta'>input <code>{esc(source)}</code><br>"
            f"run folder <code>{esc(run_dir.resolve())}</code><br>chain {esc(chain)} · generated {esc(when)}</p>"
            f"<nav>{nav}</nav></div></header>")  # fmt: skip


def default_title(source: object, run_dir: Path) -> str:
    return f"nerfpipe report: {Path(str(source)).stem if source else run_dir.resolve().name}"


def mesh_evaluation(page: Page, mesh: "dict | None") -> "dict | None":
    """Geometry metrics against a reference: a metrics file of the mesh stage, or mesh.json itself."""
    path = page.find(page.item("mesh_evaluation").candidates())
    data = read_json(path) if path is not None else None
    if data is None and mesh is not None and "fscore" in mesh:
        data = mesh
    return data


def guarded(page: Page, anchor: str, what: str, build) -> str:
    """``build()``, or a note when an artifact holds data of an unexpected shape (the page still gets written)."""
    try:
        return build()
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
        page.missing.append(f"{what} (unexpected content: {type(exc).__name__}: {exc})")
        return section(anchor, what.capitalize(), not_produced(f"{what} (unexpected content, see the end)"))


def build_html(page: Page) -> str:
    """The whole page for ``page.run_dir``; missing artifacts end up in ``page.missing``."""
    run = read_json(page.run_dir / "run.json") or {}
    scene = page.json("scene")
    check = page.json("check")
    sfm = page.optional_json("sfm")
    metrics = page.json("metrics")
    mesh = page.json("mesh")
    evaluation = mesh_evaluation(page, mesh)
    source = run.get("source") or (scene or {}).get("input")
    title = page.config.title or default_title(source, page.run_dir)
    chain = [str(s) for s in run.get("chain", [])] if isinstance(run.get("chain"), list) else []
    body = [
        guarded(page, "figures", "key figures", lambda: key_figures(metrics, check, {**(mesh or {}), **(evaluation or {})})),
        guarded(page, "scene", "scene", lambda: scene_section(scene, check, sfm)),
        guarded(page, "training", "training", lambda: training_section(page, metrics)),
        guarded(page, "views", "novel views", lambda: views_section(page)),
        guarded(page, "bench", "speed against error", lambda: bench_section(page)),
        guarded(page, "mesh", "mesh", lambda: mesh_section(page, mesh, evaluation)),
        guarded(page, "cameras", "cameras", lambda: cameras_section(page)),
        guarded(page, "others", "other outputs", lambda: others_section(page)),
        guarded(page, "timings", "stage timings", lambda: timings_section(stage_markers(page.run_dir, chain))),
    ]
    body.append(missing_section(page.missing))
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<title>{esc(title)}</title><style>{CSS}</style></head><body>{header(title, page.run_dir, source, chain)}"
            f"<main>{''.join(body)}</main></body></html>\n")  # fmt: skip


def write_report(run_dir: "str | Path", config: "ReportConfig | None" = None, out: "str | Path | None" = None) -> Path:
    """Write the report of ``run_dir`` atomically to ``out`` (default ``run_dir/report.html``)."""
    from nerfpipe.pipeline.stages import atomic_path

    run_dir = Path(run_dir)
    out = run_dir / REPORT_FILE if out is None else Path(out)
    page = Page(run_dir, config or ReportConfig(), out_dir=out.parent)
    text = build_html(page)
    with atomic_path(out) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return out


CSS = """
:root { --ink:#1d2330; --muted:#5b6475; --line:#dde2ea; --bg:#f5f7fa; --card:#fff; --accent:#2f6fde; --good:#1b8a4b; --bad:#c62828; }
* { box-sizing:border-box; }
body { margin:0; background:var(--bg); color:var(--ink); font:15px/1.5 system-ui,-apple-system,"Segoe UI",Roboto,"DejaVu Sans",sans-serif; }
main { max-width:1120px; margin:0 auto; padding:0 20px 40px; }
header { background:#1d2330; color:#fff; margin:0 0 18px; padding:22px 0 12px; }
header .inner { max-width:1120px; margin:0 auto; padding:0 20px; }
header h1 { margin:0 0 6px; font-size:26px; font-weight:650; }
header .meta { margin:0 0 10px; color:#c5cbd6; font-size:13px; }
header code { color:#fff; background:rgba(255,255,255,0.12); }
nav a { color:#9fc1ff; text-decoration:none; margin-right:16px; font-size:13px; }
h2 { font-size:19px; margin:0 0 12px; padding-bottom:6px; border-bottom:2px solid var(--line); }
h3 { font-size:15px; margin:4px 0 8px; color:var(--muted); font-weight:600; }
section { background:var(--card); border:1px solid var(--line); border-radius:10px; padding:16px 20px; margin:0 0 18px; }
code { font:12px ui-monospace,"DejaVu Sans Mono",monospace; background:#eef1f6; padding:1px 4px; border-radius:4px; color:var(--ink); word-break:break-all; }
.cards { display:flex; flex-wrap:wrap; gap:12px; margin:0 0 18px; }
.card { flex:1 1 110px; max-width:260px; background:var(--card); border:1px solid var(--line); border-left:4px solid var(--accent); border-radius:8px; padding:10px 14px; }
.card.good { border-left-color:var(--good); } .card.bad { border-left-color:var(--bad); }
.card .v { font-size:23px; font-weight:650; white-space:nowrap; } .card .v small { font-size:13px; color:var(--muted); font-weight:400; }
.card .k { color:var(--muted); font-size:13px; }
.cols { display:grid; grid-template-columns:1fr 1fr; gap:8px 32px; align-items:start; }
@media (max-width:800px) { .cols { grid-template-columns:1fr; } }
table { border-collapse:collapse; font-size:13.5px; }
table.kv { width:100%; margin-bottom:10px; }
table.kv th { text-align:left; font-weight:500; color:var(--muted); padding:3px 14px 3px 0; width:45%; vertical-align:top; }
table.kv td { padding:3px 0; font-variant-numeric:tabular-nums; word-break:break-word; }
table.kv tr + tr { border-top:1px solid #eef1f5; }
table.grid { width:100%; margin:6px 0 12px; }
table.grid th { text-align:left; background:#eef1f6; padding:6px 10px; font-weight:600; }
table.grid td { padding:5px 10px; border-top:1px solid var(--line); font-variant-numeric:tabular-nums; }
table.grid tbody tr:nth-child(even) { background:#fafbfd; }
table.timings td:nth-child(4) { width:40%; }
.bar { height:10px; background:var(--accent); border-radius:5px; min-width:2px; }
figure { margin:10px 0; }
figure img { display:block; max-width:100%; height:auto; border:1px solid var(--line); border-radius:6px; background:#fff; }
figure.gif img { width:320px; image-rendering:auto; background:#000; }
figure.square img { max-width:640px; }
figcaption { font-size:12.5px; color:var(--muted); margin-top:5px; }
.row { display:flex; flex-wrap:wrap; gap:24px; }
.absent { display:inline-block; margin:6px 0; padding:8px 12px; border:1px dashed #b8c0cc; border-radius:6px; color:var(--muted); background:#fafbfc; font-size:13px; }
.status { margin:0 0 8px; font-weight:600; } .status.good { color:var(--good); } .status.bad { color:var(--bad); }
.note { font-size:13px; color:var(--muted); }
pre { background:#f3f5f8; padding:10px; border-radius:6px; overflow-x:auto; font-size:12px; }
"""
