"""The ``report`` stage: report.html from any subset of a run's artifacts, embedded images that
decode to the very files, relative links for large ones, and the page loaded in headless Chromium
(every image decoded, screenshot not blank)."""

import base64
import html
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from nerfpipe.outputs.colormap import ERROR_MAX
from nerfpipe.pipeline.report import REPORT_FILE, ReportConfig, fmt, write_report
from nerfpipe.pipeline.stages import DEFAULT_CHAIN, Pipeline, stages

IMAGES = {
    "train/psnr.png": "PSNR curves", "train/progress.png": "validation view during training",
    "render/orbit.gif": "orbit (colour)", "render/depth_orbit.gif": "orbit (depth)",
    "bench/psnr_vs_seconds.png": "val PSNR against training seconds", "mesh/mesh_views.png": "mesh from four views",
    "train/cameras.png": "training cameras, rays and samples",
    "train/held_out.png": f"held-out views: photograph, render, error (turbo, 0 to {ERROR_MAX} RMS)",
}  # fmt: skip
METRICS = {"val_psnr": 23.4567, "val_ssim": 0.8123, "train_seconds": 61.5, "iterations": 812, "model": "fast",
           "model_params": 1234567, "model_mb": 4.71, "samples_per_ray": 37.5, "video": {"frames": 8}}  # fmt: skip
MESH = {"method": "mc", "faces": 50210, "vertices": 25107, "faces_simplified": 50210, "fscore": 0.8765, "chamfer_l1": 0.0123}


# ---------------------------------------------------------------- a run folder with real small artifacts


def _pattern(w: int, h: int, seed: int) -> np.ndarray:
    """A colourful uint8 image (gradients plus a disc), different per seed."""
    y, x = np.mgrid[0:h, 0:w] / max(w, h)
    disc = ((x - 0.5) ** 2 + (y - 0.5) ** 2 < 0.1).astype(float)
    img = np.stack([x, y, 0.5 + 0.5 * np.sin(6 * x + seed)], -1) * 0.7 + 0.3 * disc[..., None]
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def _write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


def _write_images(run: Path, big_cameras: bool) -> None:
    import imageio.v3 as iio

    from nerfpipe.outputs.plots import plot_psnr
    from nerfpipe.outputs.video import write_gif

    (run / "train").mkdir(parents=True)
    plot_psnr({"train": [[i, 0.1 * i, 10 + i ** 0.5] for i in range(1, 50)], "val": [[0, 0, 9.0], [49, 4.9, 16.0]]}, run / "train" / "psnr.png")
    frames = [np.roll(_pattern(48, 40, 0), 6 * k, axis=1) for k in range(8)]
    write_gif(frames, run / "render" / "orbit.gif", 10.0)
    write_gif([f[..., ::-1] for f in frames], run / "render" / "depth_orbit.gif", 10.0)
    for i, rel in enumerate(["train/progress.png", "bench/psnr_vs_seconds.png", "mesh/mesh_views.png", "train/held_out.png"]):
        (run / rel).parent.mkdir(parents=True, exist_ok=True)
        iio.imwrite(run / rel, _pattern(120 + 10 * i, 60, i + 1))
    rng = np.random.default_rng(0)  # noise does not compress: a PNG of several hundred kB
    cams = rng.integers(0, 256, (400, 400, 3), dtype=np.uint8) if big_cameras else _pattern(80, 80, 9)
    iio.imwrite(run / "train" / "cameras.png", cams)


def _write_figures(run: Path) -> None:
    _write_json(run / "run.json", {"source": "/data/lego_200x200.npz", "chain": ["load", "check", "train", "render", "report"]})
    _write_json(run / "scene.json", {"input": "/data/lego_200x200.npz", "adapter": "cs180-npz", "num_cameras": 170,
                                     "splits": {"train": 100, "val": 10}, "image_sizes": [[200, 200]], "near": 2.0, "far": 6.0,
                                     "aabb": [[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]]})  # fmt: skip
    _write_json(run / "check.json", {"num_cameras": 170, "kornia_max_px": 4.9e-13, "roundtrip_max_px": 5.1e-13, "failures": []})
    _write_json(run / "train" / "metrics.json", METRICS)
    _write_json(run / "render" / "orbit.json", {"frames": 8, "size": [48, 40], "depth_mapping": "turbo colormap from 2.1 to 4.9"})
    _write_json(run / "mesh" / "mesh.json", MESH)
    rows = [{"preset": p, "budget_s": 20.0, "train_s": 20.3, "iterations": 100, "val_psnr": v, "val_ssim": 0.7,
             "model_mb": 3.0, "samples_per_ray": 40.0} for p, v in (("vanilla", 18.25), ("fast-small", 24.75))]  # fmt: skip
    _write_json(run / "bench" / "table.json", {"scene": "lego_200x200", "rows": rows})
    for i, (name, seconds) in enumerate((("load", 0.2), ("check", 1.3), ("train", 75.0), ("render", 12.0))):
        _write_json(run / "stages" / f"{name}.done.json", {"stage": name, "status": "ran", "seconds": seconds,
                                                          "finished": f"2026-01-01T10:0{i}:00", "finished_at": 1000.0 + i})  # fmt: skip


@pytest.fixture
def full_run(tmp_path) -> Path:
    run = tmp_path / "run"
    _write_images(run, big_cameras=False)
    _write_figures(run)
    return run


def _run_report(run: Path, **options) -> str:
    Pipeline(["report"], {"report": options}).run(None, run, resume=False)
    return (run / REPORT_FILE).read_text()


def _img_sources(page: str) -> "dict[str, str]":
    """alt -> src of every <img>."""
    return {html.unescape(alt): src for src, alt in re.findall(r'<img src="([^"]*)" alt="([^"]*)">', page)}


# ---------------------------------------------------------------- the page


def test_report_is_last_in_the_default_chain():
    assert DEFAULT_CHAIN[-1] == "report"
    spec = stages()["report"]
    assert spec.requires == () and spec.produces == (REPORT_FILE,)


def test_full_run_embeds_every_image_and_figure(full_run):
    page = _run_report(full_run)
    sources = _img_sources(page)
    assert set(sources) == set(IMAGES.values())
    for rel, alt in IMAGES.items():
        mime, data = re.fullmatch(r"data:(image/\w+);base64,(.*)", sources[alt]).groups()
        assert base64.b64decode(data) == (full_run / rel).read_bytes()
        assert mime == ("image/gif" if rel.endswith(".gif") else "image/png")
    for value in [*(METRICS[k] for k in ("val_psnr", "val_ssim", "iterations", "model_params")), MESH["fscore"], MESH["faces"]]:
        assert fmt(value) in page
    assert "<b>24.75</b>" in page and "<b>18.25</b>" not in page  # best PSNR of the budget in bold
    assert "not produced" not in page and "Every artifact the report looks for was found" in page
    timings = page[page.index('id="timings"') :]
    assert [timings.index(f"<td>{s}</td>") for s in ("load", "check", "train", "render")] == sorted(
        timings.index(f"<td>{s}</td>") for s in ("load", "check", "train", "render"))
    assert "<b>88.5</b>" in timings  # total seconds
    assert "http://" not in page and "https://" not in page  # no external resources
    assert json.loads((full_run / "stages" / "report.done.json").read_text())["status"] == "ran"
    assert not list(full_run.rglob(".tmp-*"))


def test_missing_and_broken_artifacts_are_listed(tmp_path):
    run = tmp_path / "run"
    _write_json(run / "scene.json", {"input": "/data/x.npz", "num_cameras": 3})
    (run / "check.json").write_text("{not json")
    page = _run_report(run)
    missing = page[page.index('id="missing"') :]
    for what in ("training metrics", "PSNR curves", "orbit (colour)", "orbit (depth)", "mesh from four views",
                 "training cameras", "speed-against-error table"):  # fmt: skip
        assert what in missing
    assert "convention check (check.json: unreadable)" in missing
    assert "scene summary" not in missing and "<img" not in page
    assert "nerfpipe report: x" in page


def test_large_image_is_linked_relative_to_the_report(tmp_path):
    run = tmp_path / "run"
    _write_images(run, big_cameras=True)
    out = write_report(run, ReportConfig(max_embed_mb=0.25), out=tmp_path / "elsewhere" / "r.html")
    sources = _img_sources(out.read_text())
    src = sources["training cameras, rays and samples"]
    assert src == "../run/train/cameras.png" and (out.parent / src).resolve() == (run / "train" / "cameras.png").resolve()
    assert all(s.startswith("data:") for alt, s in sources.items() if alt != "training cameras, rays and samples")


# ---------------------------------------------------------------- in a real browser

CHECK_SCRIPT = """<script>
window.addEventListener('load', () => {
  const r = [...document.images].map(i => ({alt: i.alt, complete: i.complete, w: i.naturalWidth, h: i.naturalHeight}));
  const pre = document.createElement('pre'); pre.id = 'imgcheck'; pre.textContent = JSON.stringify(r);
  document.body.appendChild(pre);
});
</script>"""


def _chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        msg = "chromium is not installed (apt-get install -y chromium)"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    return exe


def _chromium_args(exe: str, profile: Path) -> "list[str]":
    return [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
            "--disable-component-update", "--disable-sync", "--hide-scrollbars", f"--user-data-dir={profile}",
            "--virtual-time-budget=5000", "--window-size=1200,2000"]  # fmt: skip


def _image_sizes(run: Path) -> "dict[str, tuple[int, int]]":
    import imageio.v3 as iio

    shapes = {alt: iio.imread(run / rel, index=0 if rel.endswith(".gif") else None).shape for rel, alt in IMAGES.items()}
    return {alt: (shape[1], shape[0]) for alt, shape in shapes.items()}


def test_report_renders_in_headless_chromium(tmp_path):
    exe = _chromium()
    run = tmp_path / "run"
    _write_images(run, big_cameras=True)
    _write_figures(run)
    page = _run_report(run, max_embed_mb=0.25)  # cameras.png is linked, the rest embedded
    probe = run / "probe.html"  # a copy with a script that records how each image decoded
    probe.write_text(page.replace("</body>", CHECK_SCRIPT + "</body>"))
    shot = tmp_path / "shot.png"
    dom = subprocess.Popen([*_chromium_args(exe, tmp_path / "p1"), "--dump-dom", probe.as_uri()], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    subprocess.run([*_chromium_args(exe, tmp_path / "p2"), f"--screenshot={shot}", (run / REPORT_FILE).as_uri()], capture_output=True, timeout=60, check=True)
    out, _ = dom.communicate(timeout=60)
    found = json.loads(html.unescape(re.search(r'<pre id="imgcheck">(.*?)</pre>', out, re.S).group(1)))
    assert {r["alt"] for r in found} == set(IMAGES.values())
    for r in found:
        assert r["complete"] and (r["w"], r["h"]) == _image_sizes(run)[r["alt"]], r
    _assert_not_blank(shot)


def _assert_not_blank(shot: Path) -> None:
    import imageio.v3 as iio

    img = iio.imread(shot)[..., :3].astype(float)
    assert img.shape[:2] == (2000, 1200)
    assert img.std() > 20.0  # a blank page is one colour
    assert len(np.unique(img.reshape(-1, 3)[::7], axis=0)) > 200  # text, plots and photos, not flat boxes


def test_odd_content_is_reported_not_fatal(full_run):
    _write_json(full_run / "train" / "metrics.json", {"val_psnr": "n/a", "iterations": [1, 2]})
    (full_run / "scene.json").write_text("[1, 2, 3]")  # JSON, but not an object
    _write_json(full_run / "bench" / "table.json", {"scene": "x", "rows": ["not a row", {"preset": "p", "budget_s": "?"}]})
    _write_json(full_run / "stages" / "train.done.json", {"stage": "train", "seconds": "long"})
    _write_json(full_run / "render" / "orbit.json", {"frames": 8, "size": 3})
    _write_json(full_run / "run.json", {"source": 5, "chain": "load,train"})
    page = _run_report(full_run)
    assert "scene summary (scene.json: unreadable)" in page
    assert len(_img_sources(page)) == len(IMAGES)  # the pictures are still all there
    assert "<td>p</td>" in page and "n/a" in page


def test_without_a_bench_the_runs_own_validations_are_the_speed_table(tmp_path):
    run = tmp_path / "run"
    _write_json(run / "scene.json", {"input": "/data/x.npz", "num_cameras": 3})
    rows = [{"step": 0, "train_seconds": 0.0, "val_psnr": 8.5, "val_ssim": 0.1, "views": 1},
            {"step": 300, "train_seconds": 155.25, "val_psnr": 28.75, "val_ssim": 0.95, "views": 10}]
    _write_json(run / "train" / "history.json", {"val": rows})
    page = _run_report(run)
    section = page[page.index('id="bench"') : page.index('id="missing"')]
    assert "this run's validations" in section and "28.75" in section and "155.2" in section
    assert "speed-against-error table" not in page[page.index('id="missing"') :]


def test_mesh_metrics_show_the_free_space_violation(full_run):
    """mesh/mesh_metrics.json (the mesh stage's figures against the dataset): the free-space violation is a
    headline card and a row of the mesh section, with its sight-line count."""
    evaluation = {"reference": "sparse points", "points_within_threshold": 0.9688, "free_space_violation": 0.6221,
                  "sight_lines": 25656, "free_space_tau": 0.02684}  # fmt: skip
    _write_json(full_run / "mesh" / "mesh_metrics.json", evaluation)
    page = _run_report(full_run)
    cards = page[page.index('class="card') : page.index('id="mesh"')]
    mesh = page[page.index('id="mesh"') :]
    assert "free-space violation" in cards and fmt(0.6221) in cards
    for value in (0.9688, 0.6221, 25656, 0.02684):
        assert fmt(value) in mesh, value
    assert "free-space violation" in mesh and "sight lines (camera to sparse point)" in mesh


def test_a_figure_linked_out_of_the_run_folder_is_not_embedded(full_run, tmp_path):
    """Run folders are passed around: a figure that is a symlink to a file elsewhere (a key, a photo) must
    not end up base64 in a report the user then shares; the page says why it is absent."""
    secret = tmp_path / "secret.png"
    secret.write_bytes((full_run / "train" / "cameras.png").read_bytes())
    (full_run / "train" / "cameras.png").unlink()
    (full_run / "train" / "cameras.png").symlink_to(secret)
    page = _run_report(full_run)
    assert base64.b64encode(secret.read_bytes()).decode("ascii")[:200] not in page
    assert "not embedded" in page and "cameras.png" in page


# ---------------------------------------------------------------- the report from the stages' declarations


def _views(page_html: str) -> str:
    return page_html[page_html.index('id="views"') : page_html.index('id="bench"')]


def test_renaming_an_artifact_in_a_stage_declaration_moves_it_in_the_report(tmp_path):
    """The report names no stage's files: rename the render stage's colour GIF in its declaration and the
    novel-views section shows the renamed file (and no longer the old name, though it is on disk)."""
    from dataclasses import replace

    from nerfpipe.outputs.video import write_gif
    from nerfpipe.pipeline.report import Page, build_html
    from nerfpipe.pipeline.report_items import Shown, declared

    run = tmp_path / "run"
    write_gif([_pattern(24, 20, 0)] * 2, run / "render" / "orbit.gif", 10.0)
    write_gif([_pattern(24, 20, 5)] * 2, run / "render" / "spin.gif", 10.0)
    specs = dict(stages())
    assert "render/orbit.gif" in _views(build_html(Page(run, items=declared(specs.values()))))
    render = specs["render"]
    shows = tuple(replace(s, files=("render/spin.gif",), title="spin (colour)") if s.role == "colour" else s for s in render.shows)
    specs["render"] = replace(render, shows=shows)
    views = _views(build_html(Page(run, items=declared(specs.values()))))
    spin = base64.b64encode((run / "render" / "spin.gif").read_bytes()).decode()
    assert "render/spin.gif" in views and "spin (colour)" in views and spin in views
    assert "render/orbit.gif" not in views
    specs["render"] = replace(render, shows=shows + (Shown("colour", "image", ("render/x.gif",), "x"),))
    with pytest.raises(ValueError, match="'colour' declared by both 'render' and 'render'"):
        declared(specs.values())


def test_every_section_reads_a_declared_artifact_of_a_stage(tmp_path):
    """No section asks for a role no stage declares, every built-in declaration is read by a section, and
    every declared file lies in what its stage produces; report.py itself names no stage's file."""
    from nerfpipe.pipeline.report import Page, build_html
    from nerfpipe.pipeline.report_items import declared, outside_produces

    specs = dict(stages())
    page = Page(tmp_path, items=declared(specs.values()))
    build_html(page)
    assert page.undeclared == []
    assert set(page.items) <= page.used
    assert {name: outside_produces(spec) for name, spec in specs.items() if outside_produces(spec)} == {}
    source = Path(__import__("nerfpipe.pipeline.report", fromlist=["x"]).__file__).read_text()
    for spec in specs.values():
        for item in spec.shows:
            for f in item.files:
                assert f'"{f}"' not in source and f'"{Path(f).name}"' not in source, f


def test_a_declared_item_no_section_reads_goes_to_other_outputs(tmp_path):
    """A third-party stage shows a picture and a table by declaring them; nothing in the report changes."""
    from dataclasses import replace

    import imageio.v3 as iio

    from nerfpipe.pipeline.report import Page, build_html
    from nerfpipe.pipeline.report_items import Shown, declared

    specs = dict(stages())
    specs["extra"] = replace(specs["check"], name="extra", produces=("extra/out.json",), shows=(
        Shown("extra_image", "image", ("extra/heat.png",), "heat map"), Shown("extra_table", "table", ("extra/out.json",), "extra figures")))
    (tmp_path / "extra").mkdir()
    iio.imwrite(tmp_path / "extra" / "heat.png", _pattern(30, 20, 3))
    _write_json(tmp_path / "extra" / "out.json", {"holes": 3})
    page_html = build_html(Page(tmp_path, items=declared(specs.values())))
    others = page_html[page_html.index('id="others"') : page_html.index('id="timings"')]
    assert "heat map" in others and "extra/heat.png" in others and "<th>holes</th><td>3</td>" in others


def test_psnr_plot_marks_the_appearance_fitted_figure(tmp_path, monkeypatch):
    """Photo collections: the val curves are rendered with the mean appearance, the scored figure is fitted; the plot
    says which is which and shows the scored one."""
    from nerfpipe.outputs import plots

    figs = []
    monkeypatch.setattr(plots, "_save", lambda fig, path: figs.append(fig))
    history = {"train": [[1, 0.1, 9.0], [2, 0.2, 10.0]], "val": [[1, 0.1, 10.0, 0.4, 1], [2, 0.2, 11.0, 0.5, 2]]}
    plots.plot_psnr(history, tmp_path / "psnr.png", (2, 0.2, 16.2159, 2))
    plots.plot_psnr(history, tmp_path / "psnr.png")
    labels = [[t.get_text() for t in fig.legends[0].get_texts()] for fig in figs]  # one legend under both plots
    assert labels[0] == ["train (batch)", "val (1 view, mean appearance)", "val (2 views, mean appearance)",
                         "final, appearance fitted (2 views): 16.22 dB"]
    assert labels[1] == ["train (batch)", "val (1 view)", "val (2 views)"]
    star = figs[0].axes[0].lines[-1]  # against iterations on the left, seconds on the right
    assert (list(star.get_xdata()), list(star.get_ydata())) == ([2], [16.2159])
    assert list(figs[0].axes[1].lines[-1].get_xdata()) == [0.2]
    import matplotlib.pyplot as plt

    for fig in figs:
        plt.close(fig)
