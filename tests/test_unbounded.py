"""Unbounded real captures: scene contraction against its per-point reference, disparity samples,
the field behind the box (renders, learns, leaves the box's own rendering alone where it is opaque),
and the per-image colour corrections (zero-mean, identity at evaluation)."""

import math
from pathlib import Path

import pytest
import torch

from nerfpipe.data.cameras import Cameras
from nerfpipe.data.rays import RayBundle
from nerfpipe.fields.background import BackgroundField, BackgroundFieldConfig
from nerfpipe.fields.fast_field import direction_encoding
from nerfpipe.functional.contraction import _contract_reference, contract, disparity_samples, to_box_coordinates
from nerfpipe.models.base import RenderOutputs, SceneInfo
from nerfpipe.models.fast import FRONT_MIN_IMAGES, FastConfig
from nerfpipe.training.runs import load_model_state


def test_contract_matches_reference_and_bounds(dtype, device, tol):
    g = torch.Generator().manual_seed(0)
    x = (torch.randn(500, 3, generator=g, dtype=dtype) * torch.logspace(-1, 4, 500, dtype=dtype)[:, None]).to(device)
    y = contract(x)
    torch.testing.assert_close(y, _contract_reference(x), **tol(dtype))
    inside = x.abs().amax(-1) <= 1
    torch.testing.assert_close(y[inside], x[inside])  # identity in the box
    assert bool((y.abs().amax(-1) < 2.0 + 1e-6).all())  # all of space inside [-2, 2]^3
    # monotonic along rays from the centre: farther points stay farther
    r = torch.linspace(0.1, 1e5, 1000, dtype=dtype, device=device)[:, None] * torch.tensor([0.3, -0.5, 0.8], dtype=dtype, device=device)
    n = contract(r).abs().amax(-1)
    assert bool((n[1:] >= n[:-1] - 1e-6).all())


def test_contract_gradcheck_float64():
    x = torch.tensor([[0.2, -0.3, 0.1], [3.0, 1.0, -2.0], [-0.5, 7.0, 0.0]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(contract, (x,))


def test_to_box_coordinates_maps_box_to_unit_cube():
    aabb = torch.tensor([[-1.0, 0.0, 2.0], [3.0, 1.0, 4.0]])
    assert to_box_coordinates(aabb, aabb).tolist() == [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]


def test_disparity_samples_tile_the_span():
    t0 = torch.tensor([1.0, 2.5])
    jitter = torch.rand(2, 16, generator=torch.Generator().manual_seed(1))
    t, d = disparity_samples(t0, 1e4, 16, jitter)
    torch.testing.assert_close(d.sum(-1), 1e4 - t0)  # the intervals tile [t_start, t_far]
    starts = t0[:, None] + torch.cat([torch.zeros(2, 1), d.cumsum(-1)[:, :-1]], dim=-1)
    assert bool(((t >= starts) & (t <= starts + d)).all())  # each sample inside its interval
    inv = 1.0 / (starts + d)  # interval ends are evenly spaced in disparity
    steps = torch.cat([1.0 / t0[:, None], inv], dim=-1).diff(dim=-1)
    torch.testing.assert_close(steps, steps[:, :1].expand_as(steps))


def _rays(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    o = torch.tensor([0.0, 0.0, 4.0]).expand(n, 3).clone()
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    return RayBundle(origins=o, directions=d, cam_idx=torch.randint(0, 4, (n,), generator=g), z_scale=torch.ones(n))


def _fit_wall(field, opt, target, steps: int = 150):
    """Train ``field`` towards a wall of colour ``target`` behind the box (plus its proposal loss, when it
    has one); returns its evaluation render of fresh rays and the proposal loss of every step."""
    from nerfpipe.estimators.occupancy import ray_aabb_intersect

    def render(rays):
        t_exit = ray_aabb_intersect(rays.origins, rays.directions, field.aabb)[1]
        return field(rays.origins, rays.directions, direction_encoding(rays.directions), t_exit, torch.zeros(len(t_exit), 3))

    proposals = []
    for step in range(steps):
        out = render(_rays(512, step))
        loss = ((out.rgb - target) ** 2).mean()
        if out.proposal is not None:
            loss = loss + out.proposal.mean()
            proposals.append(float(out.proposal.mean()))
        opt.zero_grad()
        loss.backward()
        opt.step()
    field.eval()
    with torch.no_grad():
        return render(_rays(256, 999)), proposals


def test_background_field_learns_a_wall_behind_the_box():
    """A wall of one colour at z = -6 (behind the box [-1, 1]^3) is learned, and its depth found."""
    torch.manual_seed(0)
    field = BackgroundField(BackgroundFieldConfig(levels=(16, 32), num_samples=32), torch.tensor([[-1.0] * 3, [1.0] * 3]))
    opt = torch.optim.Adam([{"params": field.density_grid.parameters(), "lr": 0.5}, {"params": field.mlp.parameters(), "lr": 1e-2},
                            {"params": field.feature_grid.parameters(), "lr": 0.5}])
    target = torch.tensor([0.9, 0.2, 0.1])
    out, _ = _fit_wall(field, opt, target)
    assert float((out.rgb - target).abs().max()) < 0.05
    assert float(out.acc.mean()) > 0.95


def _model(num_images=4, focal_spread=1.0, **kw):
    info = SceneInfo(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]), near=0.5, far=10.0, num_images=num_images, pixels_per_image=100, unbounded=True, focal_spread=focal_spread)
    return FastConfig(preset="small", **kw).setup(info)


def test_real_capture_defaults_and_synthetic_defaults():
    info = dict(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]), near=0.5, far=10.0, num_images=4, pixels_per_image=100)
    real = FastConfig(preset="small").setup(SceneInfo(**info, unbounded=True, focal_spread=1.0))
    session = FastConfig(preset="small").setup(SceneInfo(**info, unbounded=True, focal_spread=0.02))
    assert session.behind is not None and session.appearance is None  # one camera: no colour corrections
    synthetic = FastConfig(preset="small").setup(SceneInfo(**info, has_alpha=True))
    on_black = FastConfig(preset="small").setup(SceneInfo(**info))  # e.g. the CS180 lego: no alpha, no points
    assert real.behind is not None and real.appearance is not None
    assert real.sky is not None and real.sky.shape == (4, 16, 32, 3) and session.sky is None  # the sky residual: photo collections
    assert synthetic.behind is None and synthetic.appearance is None
    assert on_black.behind is None and on_black.appearance is None


def test_fine_levels_learning_rates():
    """The coarsest level learns at grid_lr; the finer levels' colour features at fine_feature_lr, their density at
    fine_density_lr (default grid_lr), real and synthetic scenes alike. Every parameter is in exactly one group, and one
    Adam step moves a fine vertex by at most about its group's rate, the coarsest by about grid_lr."""
    info = dict(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]), near=0.5, far=10.0, num_images=40, pixels_per_image=10**6)

    def lrs(model):
        by_param = {id(p): g["lr"] for g in model.param_groups() for p in g["params"]}
        grids = [model.field.density_grid.tables, model.field.feature_grid.tables]
        return [[by_param[id(t)] for t in tables] for tables in grids]

    real = FastConfig(preset="small").setup(SceneInfo(**info, unbounded=True, focal_spread=0.02))
    synthetic = FastConfig(preset="small").setup(SceneInfo(**info, has_alpha=True))
    chosen = FastConfig(preset="small", fine_density_lr=0.2, fine_feature_lr=0.3).setup(SceneInfo(**info, unbounded=True, focal_spread=0.02))
    for model in (real, synthetic):
        g, f = model.cfg.grid_lr, model.cfg.fine_feature_lr
        assert f < g and lrs(model) == [[g, g, g], [g, f, f]]
    assert lrs(chosen) == [[chosen.cfg.grid_lr, 0.2, 0.2], [chosen.cfg.grid_lr, 0.3, 0.3]]
    for model in (real, synthetic, chosen):
        params = [id(p) for g in model.param_groups() for p in g["params"]]
        assert sorted(params) == sorted(id(p) for p in model.parameters() if p.requires_grad)
    # the second level is the finest active one at the start (coarse to fine)
    chosen.train()
    opt = torch.optim.Adam(chosen.param_groups())
    tables = [chosen.field.density_grid.tables, chosen.field.feature_grid.tables]
    before = [[t.detach().clone() for t in level] for level in tables]
    out = chosen.get_outputs(_rays(256), torch.zeros(256, 3))
    chosen.get_losses(out, torch.full((256, 3), 0.8))["rgb"].backward()
    opt.step()
    moved = [[float((t.detach() - b).abs().max()) for t, b in zip(level, old)] for level, old in zip(tables, before)]
    (d0, d1, _), (f0, f1, _) = moved
    assert d0 > 0.5 * chosen.cfg.grid_lr and 0.1 < d1 <= 0.201, moved
    assert f0 > 0.5 * chosen.cfg.grid_lr and 0.15 < f1 <= 0.301, moved


def test_learning_rates_follow_the_batch():
    """The fast model's rates are given for ``lr_reference_rays`` rays a step: a step of four times as many takes every
    group's twice as large; a quarter as many, the batch unknown (None) or ``lr_reference_rays=0`` keep them."""
    from nerfpipe.models.fast import LR_REFERENCE_RAYS

    info = dict(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]), near=0.5, far=10.0, num_images=40, pixels_per_image=10**6)
    for scene in (SceneInfo(**info, unbounded=True, focal_spread=0.02), SceneInfo(**info, has_alpha=True)):
        model = FastConfig(preset="small", lr_reference_rays=LR_REFERENCE_RAYS).setup(scene)
        given = [g["lr"] for g in model.param_groups()]
        assert given == [g["lr"] for g in model.param_groups(LR_REFERENCE_RAYS)] and len(given) >= 4
        assert [g["lr"] for g in model.param_groups(4 * LR_REFERENCE_RAYS)] == pytest.approx([2 * lr for lr in given])
        assert [g["lr"] for g in model.param_groups(LR_REFERENCE_RAYS // 4)] == given  # smaller batches: as given (not measured)
        fixed = FastConfig(preset="small", lr_reference_rays=0).setup(scene)
        assert [g["lr"] for g in fixed.param_groups(4 * LR_REFERENCE_RAYS)] == given
    # by default: bounded scenes scaled, real captures (measured no better at 16,384 rays) not
    bounded = FastConfig(preset="small").setup(SceneInfo(**info, has_alpha=True))
    real = FastConfig(preset="small").setup(SceneInfo(**info, unbounded=True, focal_spread=0.02))
    assert bounded.lr_reference_rays == LR_REFERENCE_RAYS and real.lr_reference_rays is None
    assert bounded.param_groups(4 * LR_REFERENCE_RAYS)[0]["lr"] == pytest.approx(2 * bounded.cfg.grid_lr)
    assert real.param_groups(4 * LR_REFERENCE_RAYS)[0]["lr"] == real.cfg.grid_lr


def test_real_captures_take_density_from_the_coarsest_levels_and_colour_from_all():
    """Real captures (a field behind the box): density from DENSITY_LEVELS_REAL levels (the finer density tables change
    nothing), colour from every level; synthetic scenes, a real capture without the field behind the box (as the demo
    runs) and an explicit option as set; a checkpoint from before the option keeps every level."""
    from nerfpipe.models.fast import DENSITY_LEVELS_REAL

    info = dict(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]), near=0.5, far=10.0, num_images=4, pixels_per_image=100)
    real = FastConfig(preset="small", coarse_to_fine_every=0).setup(SceneInfo(**info, unbounded=True, focal_spread=0.02))
    synthetic = FastConfig(preset="small", coarse_to_fine_every=0).setup(SceneInfo(**info, has_alpha=True))
    one = FastConfig(preset="small", coarse_to_fine_every=0, density_levels=1).setup(SceneInfo(**info, unbounded=True, focal_spread=0.02))
    levels = len(real.field.density_grid.tables)
    assert DENSITY_LEVELS_REAL < levels and real.field.density_levels == int(real.density_levels) == DENSITY_LEVELS_REAL
    bounded = FastConfig(preset="small", coarse_to_fine_every=0, background_field=False).setup(SceneInfo(**info, unbounded=True, focal_spread=0.02))
    assert synthetic.field.density_levels == bounded.field.density_levels == levels and one.field.density_levels == 1
    pts, dirs = torch.rand(500, 3) * 2 - 1, torch.nn.functional.normalize(torch.randn(500, 3), dim=-1)
    for model in (real, synthetic):
        with torch.no_grad():
            for t in [*model.field.density_grid.tables, *model.field.feature_grid.tables]:
                t.normal_(0.0, 0.5)
            sigma, rgb = model.field.density(pts), model.field.rgb(pts, dirs)
            model.field.density_grid.tables[-1].add_(1.0)
            model.field.feature_grid.tables[-1].add_(1.0)
            same_sigma = torch.equal(model.field.density(pts), sigma)
            assert not torch.allclose(model.field.rgb(pts, dirs), rgb)  # colour reads the finest level
        assert same_sigma == (model is real)
    # the training pass (corners of every level, then density from them) agrees with the density pass
    with torch.no_grad():
        torch.testing.assert_close(real.field.density_from_corners(real.field.corners(pts)), real.field.density(pts))
    old = {k: v for k, v in real.state_dict().items() if k != "density_levels"}
    fresh = FastConfig(preset="small", coarse_to_fine_every=0).setup(SceneInfo(**info, unbounded=True, focal_spread=0.02))
    load_model_state(fresh, old, Path("old.safetensors"), "fast")  # as `load_run` and resume load it
    assert fresh.field.density_levels == levels


def test_appearance_codes_are_zero_mean_and_identity_in_evaluation():
    model = _model()
    with torch.no_grad():
        model.appearance.normal_(0.0, 0.2)
    rays = _rays(64)
    model.eval()
    with torch.no_grad():
        evaluated = model.get_outputs(rays, torch.zeros(64, 3)).rgb
        # the mean correction over the images is the identity: averaging the per-image colours gives back the plain render
        per_image = [model._corrected(evaluated, torch.full((64,), i)) for i in range(4)]
    torch.testing.assert_close(torch.stack(per_image).mean(0), evaluated, atol=1e-6, rtol=0)
    assert float((per_image[0] - evaluated).abs().max()) > 1e-3  # and a single image's correction is not


def test_robust_trim_leaves_each_batchs_largest_colour_errors_out():
    """``robust_trim``: from ``behind_from`` on, the colour loss is the squared error of the batch's rays but its
    largest ``robust_trim`` share, over the rays kept (a trimmed least squares), and the rays left out get no gradient;
    before that step, and in evaluation, the plain mean squared error."""
    from nerfpipe.models.base import RenderOutputs
    from nerfpipe.models.fast import ROBUST_TRIM

    assert _model().robust_trim == ROBUST_TRIM and _model(focal_spread=0.02).robust_trim == 0.0  # a collection / one camera
    with pytest.raises(ValueError, match="robust_trim"):
        FastConfig(robust_trim=1.0)
    model = _model(robust_trim=0.25)
    model.train()
    gen = torch.Generator().manual_seed(0)
    rgb = torch.rand(8, 3, generator=gen).requires_grad_(True)
    target = (rgb.detach() + 0.05 * torch.randn(8, 3, generator=gen)).index_add(0, torch.tensor([1, 5]), torch.full((2, 3), 0.6))
    out = RenderOutputs(rgb=rgb, depth=torch.zeros(8), acc=torch.zeros(8))
    model._step = model.cfg.behind_from - 1
    assert torch.allclose(model.get_losses(out, target)["rgb"], torch.mean((rgb - target) ** 2))
    model._step = model.cfg.behind_from
    loss = model.get_losses(out, target)["rgb"]
    kept = torch.tensor([0, 2, 3, 4, 6, 7])  # 6 of 8: the two largest errors left out
    assert torch.allclose(loss, torch.mean((rgb[kept] - target[kept]) ** 2))
    loss.backward()
    assert torch.equal(rgb.grad[torch.tensor([1, 5])], torch.zeros(2, 3))
    assert torch.allclose(rgb.grad[kept], 2 * (rgb - target).detach()[kept] / 18)
    model.eval()
    assert torch.allclose(model.get_losses(out, target)["rgb"], torch.mean((rgb - target) ** 2))
    # a captured CUDA step is captured again when the trim starts, on a scene without a field behind the box too
    info = SceneInfo(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]), near=0.5, far=10.0, num_images=4, pixels_per_image=100, has_alpha=True)
    for trim in (0.1, 0.0):
        bounded = FastConfig(preset="small", fixed_shapes=True, robust_trim=trim).setup(info)
        bounded.train()
        assert bounded.behind is None
        keys = []
        for step in (bounded.cfg.behind_from - 1, bounded.cfg.behind_from):
            bounded._step = step
            keys.append(bounded.graph_key()[6])  # the flag of what starts at behind_from
        assert keys == ([False, True] if trim else [False, False]), (trim, keys)


def test_per_image_rows_are_gathered_with_a_backward_that_adds_in_order():
    """:func:`nerfpipe.models.fast._per_image`: the rows of advanced indexing, and gradients that are the same bit for
    bit from call to call on two threads (advanced indexing's backward, ``index_put_`` with ``accumulate``, differed in
    the last bits from call to call there, and two trainings of a photo collection drifted apart from the first step)."""
    from nerfpipe.models.fast import _per_image

    gen = torch.Generator().manual_seed(0)
    values, idx, grad = torch.randn(8, 12, generator=gen), torch.randint(8, (4, 1024), generator=gen), torch.randn(4096, 12, generator=gen)

    def backward(gather):
        leaf = values.clone().requires_grad_(True)
        gather(leaf).backward(grad)
        return leaf.grad

    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        assert torch.equal(_per_image(values, idx), values[idx.reshape(-1)])
        first = backward(lambda t: _per_image(t, idx))
        assert torch.allclose(first, backward(lambda t: t[idx.reshape(-1)]), rtol=1e-5, atol=1e-5)
        assert all(torch.equal(first, backward(lambda t: _per_image(t, idx))) for _ in range(20))
    finally:
        torch.set_num_threads(threads)


def test_appearance_absorbs_a_per_image_exposure():
    """Two images of one grey scene, one 30 % darker: the codes learn the ratio, evaluation shows the mean."""
    torch.manual_seed(0)
    model = _model(num_images=2, appearance_lr=1e-2, background_field=False)
    model.train()
    opt = torch.optim.Adam(model.param_groups())
    for step in range(120):
        rays = _rays(256, step)
        rays.cam_idx = torch.randint(0, 2, (256,), generator=torch.Generator().manual_seed(step))
        gain = torch.where(rays.cam_idx == 0, 1.0, 0.7)[:, None]
        target = 0.6 * gain * torch.ones(256, 3)
        out = model.get_outputs(rays, torch.zeros(256, 3))
        loss = sum(model.get_losses(out, target).values())
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    rgb = model.get_outputs(_rays(64, 500), torch.zeros(64, 3)).rgb.detach()
    c = model.appearance.detach() - model.appearance.detach().mean(0)
    gains = [float(torch.eye(3)[0] @ (torch.eye(3) + c[i, :9].view(3, 3)) @ torch.ones(3) / 3 + c[i, 9]) for i in range(2)]
    assert gains[1] < gains[0]  # the darker image got the darker correction
    assert 0.42 + 0.03 < float(rgb.mean()) < 0.6 - 0.03  # evaluation shows the mean exposure, not one image's


def test_track_rays_pass_through_their_points(scene_path):
    """Rays through COLMAP keypoints of colmap_mouse pass by their 3D points at the reprojection error."""
    from nerfpipe.data_adapters import load
    from nerfpipe.training.pixel_sampler import PixelSampler

    scene = load(scene_path("colmap_mouse"))
    sampler = PixelSampler(scene, "train", "black", track_rays=256)
    tracks = sampler.tracks
    num_obs = len(scene.points.track_camera)
    assert 0.8 * num_obs * len(scene.splits["train"]) / len(scene.cameras) < len(tracks) <= num_obs
    batch = sampler.sample(1024, torch.Generator().manual_seed(0))
    depth = batch.depth
    assert int(torch.isnan(depth).sum()) == 1024 - 256 and bool((depth[-256:] > 0).all())
    # the point at distance t along each track ray is within ~2 px (angle) of a sparse point
    pts = batch.rays.origins[-256:] + depth[-256:, None] * batch.rays.directions[-256:]
    d = torch.cdist(pts.double(), scene.points.xyz.double()).amin(dim=1) / depth[-256:].double()
    assert float(d.median()) < 1.5 / 1400  # focal length ~1400 px


def test_depth_loss_rewards_stopping_at_the_point_and_punishes_fog():
    model = _model(background_field=False)
    t = torch.linspace(0.5, 5.0, 100)
    target = torch.tensor([3.0, 3.0, float("nan")])
    eps = model.cfg.depth_tolerance * float((model.object_box[1] - model.object_box[0]).norm())

    def loss(w0, w1):
        w = torch.cat([w0, w1, torch.zeros(100)])
        extras = dict(weights=w, t_mids=t.repeat(3), ray_indices=torch.arange(3).repeat_interleave(100), t_exit=torch.full((3,), 4.0))
        return float(model._depth_loss(extras, target))

    at_point = torch.where((t - 3.0).abs() <= eps, 1.0, 0.0)
    at_point = at_point / at_point.sum()
    fog = torch.full((100,), 1.0 / 100)
    assert loss(at_point, at_point) == 0.0
    assert loss(fog, fog) > 0.9  # 44 % in front, 2 % in the window
    behind_box = torch.tensor([3.0, 4.5, float("nan")])  # a point outside the box: only the space in front counts
    w = torch.cat([torch.zeros(100), torch.zeros(100), torch.zeros(100)])
    extras = dict(weights=w, t_mids=t.repeat(3), ray_indices=torch.arange(3).repeat_interleave(100), t_exit=torch.full((3,), 4.0))
    assert float(model._depth_loss(extras, behind_box)) == 0.5  # ray 0 must stop at 3 and does not; ray 1 is free
    none = torch.full((3,), float("nan"))
    assert float(model._depth_loss(extras, none)) == 0.0  # no ray with a point: nothing to ask


def test_depth_loss_leaves_a_margin_in_front_of_the_window():
    """Weight between the window and ``depth_front_margin`` windows in front of the point (a surface a sparse point
    lies a little behind) costs only the window's miss; weight further in front costs as free space too."""
    model = _model(background_field=False)
    eps = model.cfg.depth_tolerance * float((model.object_box[1] - model.object_box[0]).norm())
    margin = model.cfg.depth_front_margin
    assert margin > 1
    target = torch.tensor([3.0])

    def loss(at: float) -> float:  # all of the ray's weight at distance ``at``
        extras = dict(weights=torch.ones(1), t_mids=torch.tensor([at]), ray_indices=torch.zeros(1, dtype=torch.long), t_exit=torch.full((1,), 4.0))
        return float(model._depth_loss(extras, target))

    assert loss(3.0) == 0.0
    assert loss(3.0 - (1 + margin) / 2 * eps) == 1.0  # inside the margin: the window missed, no free space broken
    assert loss(3.0 - 1.5 * margin * eps) == 2.0  # in front of the margin: both


def test_depth_loss_and_the_field_behind_the_box_read_nothing_back_from_the_device():
    """Issue 13: the real-capture terms of a training step add no host sync (no branch on a tensor, no boolean
    index, no box size read back every step), forward and backward."""
    from nerfpipe.training.opcount import DispatchCounter

    model = _model()
    model.train()
    t = torch.linspace(0.5, 5.0, 50)
    w = torch.full((150,), 0.01, requires_grad=True)
    extras = dict(weights=w, t_mids=t.repeat(3), ray_indices=torch.arange(3).repeat_interleave(50), t_exit=torch.full((3,), 4.0))
    n = 8
    origins = torch.tensor([[0.0, 0.0, -3.0]]).expand(n, 3)
    directions = torch.tensor([[0.0, 0.0, 1.0]]).expand(n, 3)
    target = torch.tensor([3.0, 4.5, float("nan")])

    def behind():
        return model.behind(origins, directions, torch.zeros(n, 16), torch.full((n,), 4.0), torch.zeros(n, 3), codes=torch.zeros(n, model.behind.code_dim))

    behind()  # the grid's constants are built on the first call (then cached): the steady state is counted
    with DispatchCounter() as c:
        model._depth_loss(extras, target).backward()
        behind().rgb.sum().backward()
    assert c.syncs == 0, dict(c.sync_ops)


@pytest.mark.parametrize("front", [False, True])
def test_a_real_capture_training_step_in_fixed_shapes_reads_back_twice_on_the_cpu(front):
    """Issue 13: with the marching in shapes known on the host (CUDA's default), a whole training step of a real
    capture (box, field behind the box, depth loss, colour corrections, image codes), forward and backward, reads
    back the number of samples kept and, on the CPU, of the occupied intervals. The field behind the box then renders
    every ray, and so does its part in front of the box where it is read (``behind.front``)."""
    from nerfpipe.training.opcount import DispatchCounter

    model = _model(fixed_shapes=True, behind=BackgroundFieldConfig(front=front))
    assert model.front == front
    model.train()
    model._step = model.cfg.behind_from  # the field behind the box is on
    rays, bg = _rays(64, 3), torch.zeros(64, 3)
    target, depth = torch.rand(64, 3), torch.where(torch.arange(64) % 2 == 0, 3.5, float("nan"))

    def step():
        out = model.get_outputs(rays, bg)
        sum(model.get_losses(out, target, depth).values()).backward()
        return out

    step()  # constants built on the first call
    with DispatchCounter() as c:
        out = step()
    assert {"rgb", "depth"} <= set(model.get_losses(out, target, depth)) and out.num_samples > 0
    # on the CPU a second: the occupied intervals gathered before their density (a GPU's eager step evaluates every
    # interval instead, and its CUDA graph packs them into slots: test_a_real_capture_training_step_with_sample_slots...)
    assert dict(c.sync_ops) == {"aten.nonzero": 2}, dict(c.sync_ops)
    model.cfg.fixed_shapes = False  # the rounds read back more: the count sees them
    with DispatchCounter() as c:
        step()
    assert c.syncs > 2, dict(c.sync_ops)


def test_fitted_colour_psnr_sees_through_exposure_but_not_through_errors():
    from nerfpipe.training.evaluation import fitted_colour_psnr, score

    g = torch.Generator().manual_seed(0)
    gt = torch.rand(40, 60, 3, generator=g)
    darker = 0.7 * gt + 0.05  # a different exposure of the same picture
    assert score(darker, gt)[0] < 20 and fitted_colour_psnr(darker, gt) > 60
    wrong_right = darker.clone()
    wrong_right[:, 30:] = torch.rand(40, 30, 3, generator=g)  # the scored half is wrong: no fit can hide it
    assert fitted_colour_psnr(wrong_right, gt) < 15
    from nerfpipe.training.evaluation import colour_fitted

    shown = colour_fitted(darker, gt)  # the whole view through the map, as held_out.png shows it with colour corrections
    assert shown.shape == gt.shape and torch.allclose(shown.float(), gt, atol=1e-5)


def test_background_distortion_matches_the_pairwise_formula():
    """The field behind the box reports mip-NeRF 360's distortion of its weights (all pairs, in the
    disparity-uniform sample coordinate) in training only, and it has gradients."""
    aabb = torch.tensor([[-1.0] * 3, [1.0] * 3])
    cfg = BackgroundFieldConfig(levels=(8,), num_samples=6, distortion_weight=0.1, init_density=1.0)
    field = BackgroundField(cfg, aabb)
    with torch.no_grad():
        field.density_grid.tables[0].normal_()
    rays = _rays(5)
    t0 = torch.full((5,), 3.5)
    args = (rays.origins, rays.directions, torch.zeros(5, 16), t0, torch.zeros(5, 3))
    out = field(*args, generator=torch.Generator().manual_seed(0))
    assert out.distortion is not None and out.distortion.shape == (5,)
    out.distortion.sum().backward()
    assert float(field.density_grid.tables[0].grad.abs().sum()) > 0
    # reference: recompute the weights with the same jitter, then the O(S^2) sum
    from nerfpipe.functional.contraction import disparity_samples
    from nerfpipe.functional.volrend import render_weights

    jitter = torch.rand((5, 6), generator=torch.Generator().manual_seed(0))
    t, deltas = disparity_samples(t0, field.t_far, 6, jitter)
    deltas = field._contracted_lengths(rays.origins, rays.directions, t0, deltas)
    points = (rays.origins[:, None, :] + t[..., None] * rays.directions[:, None, :]).reshape(-1, 3)
    with torch.no_grad():
        w, _ = render_weights(field.density(points).view(5, 6), deltas)
        mids = (torch.arange(6) + 0.5) / 6
        ref = (w[:, :, None] * w[:, None, :] * (mids[:, None] - mids[None, :]).abs()).sum((-1, -2)) + (w**2).sum(-1) / 18
    torch.testing.assert_close(out.distortion.detach(), ref, rtol=1e-4, atol=1e-6)
    field.eval()
    assert field(*args).distortion is None


def test_outer_weight_loss_matches_the_overlap_reference_and_trains_only_the_coarse_weights():
    from nerfpipe.fields.background import _outer_weight_loss_reference, outer_weight_loss

    g = torch.Generator().manual_seed(3)
    edges = torch.rand(4, 7, generator=g).sort(-1).values
    edges[0] = torch.tensor([0.0, 0.1, 0.25, 0.5, 0.5, 0.9, 1.0])  # edges on coarse boundaries, an empty interval
    fine = torch.rand(4, 6, generator=g).requires_grad_()
    coarse = (torch.rand(4, 4, generator=g) * 0.3).requires_grad_()
    loss = outer_weight_loss(edges, fine, coarse)
    ref = _outer_weight_loss_reference(edges, fine, coarse)
    torch.testing.assert_close(loss, ref)
    (g1,) = torch.autograd.grad(loss.sum(), coarse)
    (g2,) = torch.autograd.grad(ref.sum(), coarse)
    torch.testing.assert_close(g1, g2)
    assert float(loss.detach().sum()) > 0
    assert torch.autograd.grad(outer_weight_loss(edges, fine, coarse).sum(), fine, allow_unused=True)[0] is None
    # coarse weights of 1 everywhere bound any fine weights (an empty interval has none): no loss
    small = fine.detach() / 10
    small[0, 3] = 0.0
    assert float(outer_weight_loss(edges, small, torch.ones(4, 4)).abs().max()) == 0.0


def test_background_field_with_a_fine_field_learns_a_wall_behind_the_box():
    """With a proposal (the coarse density) and a fine field, the wall at z = -6 is learned; the
    proposal loss falls as the coarse weights learn to bound the fine ones."""
    torch.manual_seed(0)
    cfg = BackgroundFieldConfig(levels=(8,), num_samples=16, fine_levels=(16, 64), fine_samples=16, fine_log2_rows=12)
    field = BackgroundField(cfg, torch.tensor([[-1.0] * 3, [1.0] * 3]))
    assert field.fine_density_grid.hash_rows == [None, 1 << 12]  # the 64^3 level is hashed
    opt = torch.optim.Adam([{"params": field.grid_parameters(), "lr": 0.5}, {"params": field.mlp.parameters(), "lr": 1e-2}])
    target = torch.tensor([0.9, 0.2, 0.1])
    out, proposals = _fit_wall(field, opt, target)
    assert out.proposal is None  # evaluation: no losses
    assert float((out.rgb - target).abs().max()) < 0.05
    assert float(out.acc.mean()) > 0.95
    assert sum(proposals[-10:]) < 0.5 * max(proposals)


def test_the_colour_behind_the_box_is_computed_only_for_rays_that_show_it():
    """Rays the box hides (transmittance at most BEHIND_SEEN) keep the given background; the others get
    exactly what the field behind the box renders for them alone."""
    from nerfpipe.models.fast import BEHIND_SEEN

    model = _model()
    model.eval()
    with torch.no_grad():
        model.behind.density_grid.tables[0].normal_(generator=torch.Generator().manual_seed(1))
    rays = _rays(4, 5)
    code = direction_encoding(rays.directions)
    t_exit = model._behind_start(rays)
    bg = torch.full((4, 3), 0.25)
    acc = torch.tensor([1.0, 1.0 - BEHIND_SEEN / 2, 0.5, 0.0])
    codes = model._image_codes(rays)  # this model has image codes (a photo collection): the mean one in evaluation
    with torch.no_grad():
        got = model._behind(rays, code, t_exit, bg, acc, {}, codes)
        full = model._in_front(rays, code, model.behind(rays.origins, rays.directions, code, t_exit, bg, codes=codes).rgb, codes)
    torch.testing.assert_close(got[:2], bg[:2])
    torch.testing.assert_close(got[2:], full[2:])
    assert float((full[2:] - bg[2:]).abs().max()) > 0.01  # the field behind the box does show there


def test_the_field_in_front_of_the_box_reads_the_intervals_of_a_ray_that_misses_the_box():
    """``BackgroundField.front`` cut nowhere is the field's own rendering from the same start (values and gradients);
    cut at or before its start it is empty; cut in between, its transmittance is the product over the cut intervals
    (a slow loop: each interval's midpoint, its contracted length)."""
    torch.manual_seed(3)
    box = torch.tensor([[-1.0] * 3, [1.0] * 3])
    field = BackgroundField(BackgroundFieldConfig(), box).double()
    with torch.no_grad():
        for t in [*field.density_grid.tables, *field.feature_grid.tables]:
            t.normal_()
    field.eval()
    rays = _rays(16, 4)
    o, d = rays.origins.double(), rays.directions.double()
    code, start = direction_encoding(d), torch.full((16,), 0.5, dtype=torch.float64)
    out = field(o, d, code, start, torch.zeros(16, 3, dtype=torch.float64))
    rgb, trans = field.front(o, d, code, start, torch.full_like(start, float("inf")))
    torch.testing.assert_close(rgb, out.rgb)
    torch.testing.assert_close(trans, 1.0 - out.acc)
    params = list(field.parameters())
    g_front = torch.autograd.grad((rgb * torch.arange(1.0, 4.0)).sum() + trans.sum(), params)
    g_field = torch.autograd.grad((out.rgb * torch.arange(1.0, 4.0)).sum() - out.acc.sum(), params)
    for a, b in zip(g_front, g_field):
        torch.testing.assert_close(a, b)
    with torch.no_grad():
        rgb, trans = field.front(o, d, code, start, start * 0.5)
        assert float(rgb.abs().max()) == 0.0 and float((trans - 1.0).abs().max()) == 0.0
        t_end = torch.linspace(0.8, 6.0, 16, dtype=torch.float64)
        _, trans = field.front(o, d, code, start, t_end)
        edges = field.t_far / (1.0 + (field.t_far / 0.5 - 1.0) * (1.0 - torch.linspace(0.0, 1.0, field.cfg.num_samples + 1, dtype=torch.float64)))
        for i in range(16):
            optical = 0.0
            for a, b in zip(edges[:-1].tolist(), edges[1:].tolist()):
                b = min(b, float(t_end[i]))
                if b <= a:
                    break
                ends = contract(to_box_coordinates(o[i] + torch.tensor([[a], [b]], dtype=torch.float64) * d[i], box.double()))
                optical += float(field.density(o[i : i + 1] + 0.5 * (a + b) * d[i])) * float((ends[1] - ends[0]).norm())
            assert abs(float(trans[i]) - math.exp(-optical)) < 1e-9


def test_rays_either_side_of_the_box_outline_see_the_same_surroundings():
    """Two rays a hair apart, one that just misses the (empty) box and one that just crosses it, see the same
    haze of the field behind the box: the one that crosses reads the field in front of the box too
    (``BackgroundFieldConfig.front``); without it the haze between the camera and the box is missing from it and
    the box's outline shows."""
    model = _model(behind_from=0, behind=BackgroundFieldConfig(num_samples=96, front=True))
    model.eval()
    with torch.no_grad():  # a uniform haze of one colour: two partitions of a ray differ only by their chords' error
        model.behind.density_grid.tables[0].fill_(2.0)
        model.behind.feature_grid.tables[0].zero_()
        model.behind.mlp[-1].weight.zero_()
        model.behind.mlp[-1].bias.fill_(2.0)
    o = torch.tensor([[0.0, 0.0, 4.0]]).expand(2, 3)
    d = torch.nn.functional.normalize(torch.tensor([[1.0 - 1e-4, 0.0, -3.0], [1.0 + 1e-4, 0.0, -3.0]]), dim=-1)
    rays = RayBundle(origins=o, directions=d, cam_idx=torch.zeros(2, dtype=torch.long), z_scale=torch.ones(2))
    code = direction_encoding(d)

    def render():
        with torch.no_grad():
            return model._over_surroundings(rays, torch.zeros(2, 3), torch.zeros(2), torch.zeros(2, 3), code, model._behind_start(rays), {})

    from nerfpipe.estimators.occupancy import ray_aabb_intersect

    t_in, t_out = ray_aabb_intersect(o, d, model.object_box)
    assert bool(t_out[0] >= t_in[0]) and not bool(t_out[1] >= t_in[1])  # one crosses the box, one misses it
    seamless = render()
    assert float((seamless[0] - seamless[1]).abs().max()) < 0.005  # 0.0018: the chords of two partitions
    model.front = False
    assert float((render()[0] - render()[1]).abs().max()) > 0.04  # 0.054


def test_the_appearance_fit_composites_as_get_outputs_does():
    """The fit's fast path (the box rendered once, the surroundings and the correction at every step) renders what
    get_outputs renders under a fitted view's appearance."""
    model = _model(num_images=3, behind_from=0)
    torch.manual_seed(2)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.3 * torch.randn_like(p))
    model.eval()
    rays = _rays(256, 7)
    model._view_appearance = 0.2 * torch.randn(12 + model.image_codes.shape[1])
    try:
        with torch.no_grad():
            want = model.get_outputs(rays, torch.full((256, 3), 0.5)).rgb
            code = direction_encoding(rays.directions)
            *_, rgb, _, acc = model._in_box(rays, code)
            got = model._over_surroundings(rays, rgb, acc, torch.full((256, 3), 0.5), code, model._behind_start(rays), {})
    finally:
        model._view_appearance = None
    assert float(acc.max()) > 0.05 and float(acc.min()) < 0.95
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)


def test_image_codes_learn_each_photographs_sky_and_a_held_out_view_fits_its_own():
    """Two photographs of one scene under different skies (no colour map relates them: one sky's colour
    varies left to right, the other's the opposite way): the image codes learn both; evaluation shows the
    mean, and fitting a held-out view's code to some of its pixels (NeRF-W's protocol) renders the rest in
    its own light, leaving the trained model unchanged."""
    from nerfpipe.training.evaluation import appearance_fitted_view

    torch.manual_seed(0)
    model = _model(num_images=2, background_field=False, appearance_fit_steps=80, sky_residual=0)  # the codes alone (the
    # per-image sky residual would take part of each sky, which a held-out view's fit cannot then reproduce)
    assert model.image_codes is not None and model.image_codes.shape == (2, 8)

    def sky(rays):
        x = rays.directions[:, :1]
        return torch.where(rays.cam_idx[:, None] == 0, torch.tensor([0.2, 0.4, 0.8]) + 0.5 * x, torch.tensor([0.7, 0.6, 0.4]) - 0.5 * x).clamp(0, 1)

    model.train()
    opt = torch.optim.Adam(model.param_groups())
    for step in range(200):
        rays = _rays(512, step)
        rays.cam_idx = rays.cam_idx % 2
        loss = sum(model.get_losses(model.get_outputs(rays, torch.zeros(512, 3)), sky(rays)).values())
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    held_out = _rays(1024, 1000)
    held_out.cam_idx = torch.zeros(1024, dtype=torch.long)
    target = sky(held_out)
    fit, test = held_out[:512], held_out[512:]
    before = {k: v.clone() for k, v in model.state_dict().items()}
    with torch.no_grad():
        mean_err = float(((model.get_outputs(test, torch.zeros(512, 3)).rgb - target[512:]) ** 2).mean())
    with model.fitted_appearance(fit, target[:512], torch.zeros(3)) as fitted:
        assert fitted
        with torch.no_grad():
            fitted_err = float(((model.get_outputs(test, torch.zeros(512, 3)).rgb - target[512:]) ** 2).mean())
    assert fitted_err < 0.2 * mean_err and fitted_err < 2e-3, (fitted_err, mean_err)
    assert model._view_appearance is None and all(p.requires_grad for p in model.parameters())
    for k, v in model.state_dict().items():
        torch.testing.assert_close(v, before[k], atol=0, rtol=0)
    plain = _model(num_images=2, background_field=False, appearance=False)  # nothing to fit: no figure
    view = RayBundle(origins=held_out.origins.reshape(32, 32, 3), directions=held_out.directions.reshape(32, 32, 3),
                     cam_idx=held_out.cam_idx.reshape(32, 32), z_scale=held_out.z_scale.reshape(32, 32))
    assert appearance_fitted_view(plain, view, target.reshape(32, 32, 3), torch.zeros(3), 4096) is None
    psnr, render = appearance_fitted_view(model, view, target.reshape(32, 32, 3), torch.zeros(3), 4096)
    assert psnr > 25.0 and render.shape == (32, 32, 3)
    with torch.no_grad():  # the picture: the left half, which the fit saw, is rendered in the fitted appearance too
        mean_view = model.get_outputs(view, torch.zeros(32, 32, 3)).rgb.clamp(0, 1)
    image = target.reshape(32, 32, 3)
    left, mean_left = (float(((x[:, :16] - image[:, :16]) ** 2).mean()) for x in (render, mean_view))
    assert left < 0.2 * mean_left and left < 2e-3, (left, mean_left)


def test_pose_corrections_rotate_rays_about_their_camera_and_stay_zero_mean():
    """Camera refinement: each image's correction rotates its rays' directions about the camera centre
    (Rodrigues' formula as the reference) and moves their origins, after the mean correction over the images
    is removed (the frame of the held-out views stays put); zero corrections leave the rays alone, and the
    corrections learn from the colour loss."""
    model = _model(pose_refine=True)
    model.train()
    rays = _rays(64, 3)
    same = model._refined(rays)
    torch.testing.assert_close(same.origins, rays.origins)
    torch.testing.assert_close(same.directions, rays.directions)
    with torch.no_grad():
        model.pose_deltas.copy_(torch.randn(4, 6, generator=torch.Generator().manual_seed(2)) * 0.1)
    got = model._refined(rays)
    delta = model.pose_deltas.detach() - model.pose_deltas.detach().mean(0)
    for i in range(64):
        w, t = delta[rays.cam_idx[i], :3], delta[rays.cam_idx[i], 3:]
        theta, k, v = w.norm(), w / w.norm(), rays.directions[i]
        rodrigues = v * theta.cos() + torch.linalg.cross(k, v) * theta.sin() + k * (k @ v) * (1 - theta.cos())
        torch.testing.assert_close(got.directions[i], rodrigues, atol=1e-5, rtol=0)
        torch.testing.assert_close(got.origins[i], rays.origins[i] + t)
    shifted = model.pose_deltas.detach() + torch.tensor([0.3, -0.2, 0.1, 1.0, 2.0, 3.0])  # the same for every image
    with torch.no_grad():
        model.pose_deltas.copy_(shifted)
    torch.testing.assert_close(model._refined(rays).directions, got.directions, atol=1e-6, rtol=0)
    out = model.get_outputs(rays, torch.zeros(64, 3))
    out.rgb.sum().backward()
    assert float(model.pose_deltas.grad.abs().sum()) > 0


def test_rays_from_downscaled_photographs_keep_their_points_and_colours(scene_path):
    """``max_side``: training pixels are the area means of the photographs at that size, and the rays through the
    keypoints (scaled with them) still pass by their 3D points, at the smaller images' reprojection error."""
    from nerfpipe.data_adapters import load
    from nerfpipe.training.pixel_sampler import PixelSampler, area_resize

    scene = load(scene_path("colmap_mouse"))
    sampler = PixelSampler(scene, "train", "black", track_rays=256, max_side=480)
    cams = sampler.cameras
    assert {(int(w), int(h)) for w, h in zip(cams.width, cams.height)} <= {(480, 360), (360, 480)}
    assert len(sampler) == int((cams.width * cams.height).sum())
    first = torch.from_numpy(scene.images.load(int(scene.splits["train"][0])))
    small = area_resize(first, int(cams.width[0]), int(cams.height[0]))
    block = first[:4, :4].float().mean((0, 1))  # a 4x4 block of the 1920-pixel photograph is one pixel at 480
    assert (small[0, 0].float() - block).abs().max() <= 0.5
    assert torch.equal(sampler.pixels[: small.numel() // 3], small.reshape(-1, 3))
    batch = sampler.sample(1024, torch.Generator().manual_seed(0))
    depth = batch.depth[-256:]
    pts = batch.rays.origins[-256:] + depth[:, None] * batch.rays.directions[-256:]
    d = torch.cdist(pts.double(), scene.points.xyz.double()).amin(dim=1) / depth.double()
    assert float(d.median()) < 1.5 / 1400  # within ~1.5 full-size pixels (~0.4 at 480) of a sparse point
    assert len(sampler.tracks) > 0.8 * len(scene.points.track_camera) * len(scene.splits["train"]) / len(scene.cameras)


def _fog_everywhere(model) -> list:
    """``model`` in training mode, seeded, every density table at 1 (fog everywhere); its density tables."""
    model.train()
    model.generator = torch.Generator().manual_seed(0)
    grids = list(model.field.density_grid.parameters())
    with torch.no_grad():
        for g in grids:
            g.fill_(1.0)
    return grids


def _descend(loss_fn, params, steps: int = 30) -> None:
    """``steps`` Adam steps (rate 0.1) on ``loss_fn()`` over ``params``."""
    opt = torch.optim.Adam(params, lr=0.1)
    for _ in range(steps):
        loss = loss_fn()
        opt.zero_grad()
        loss.backward()
        opt.step()


def test_sparsity_clears_density_no_photograph_needs_and_is_on_for_real_captures():
    from nerfpipe.data.orbit import camera_arc, look_at
    from nerfpipe.models.fast import SPARSITY_MIN_ARC, SPARSITY_REAL, SPARSITY_UNTIL

    box = torch.tensor([[-1.0] * 3, [1.0] * 3])

    def ring(start_deg, end_deg, n=12):
        a = torch.deg2rad(torch.linspace(start_deg, end_deg, n))
        eye = torch.stack([4 * torch.cos(a), 4 * torch.sin(a), torch.full_like(a, 2.0)], -1)
        return Cameras.create(look_at(eye, torch.zeros_like(eye), torch.tensor([0.0, 0.0, 1.0])), 100.0, 100.0, 50.0, 50.0, 100, 100)

    assert camera_arc(ring(0, 330), box.mean(0)) == pytest.approx(2 * math.pi)  # an object all round
    assert camera_arc(ring(-60, 60), box.mean(0)) == pytest.approx(math.radians(120))  # a half-open arc: from the first to the last
    assert camera_arc(ring(-60, 60)[:2], box.mean(0)) == 0.0
    info = dict(aabb=box, near=0.5, far=10.0, pixels_per_image=100, unbounded=True)
    weight = lambda **kw: FastConfig(preset="small").setup(SceneInfo(**{**info, "num_images": 20, **kw})).sparsity_weight  # noqa: E731
    assert weight(arc=2 * math.pi) == weight(arc=SPARSITY_MIN_ARC) == SPARSITY_REAL > 0  # all round; one side of an object
    assert FastConfig(preset="small").setup(SceneInfo(**info, num_images=20, arc=2 * math.pi)).stats()["sparsity_weight"] == SPARSITY_REAL  # in metrics.json
    assert weight(arc=math.radians(63)) == 0.0  # a facade's in-box surfaces would thin
    assert weight(arc=2 * math.pi, num_images=200) == SPARSITY_REAL  # many views leave fog too (the room scene: +3.3 dB)
    no_field = FastConfig(preset="small", background_field=False).setup(SceneInfo(**info, num_images=20, arc=2 * math.pi))
    assert no_field.sparsity_weight == 0.0  # nothing behind the box to take the surroundings (the demo's object on white)
    assert weight(arc=2 * math.pi, unbounded=False, has_alpha=True) == 0.0
    model = _model(sparsity_weight=1.0)
    grids = _fog_everywhere(model)
    probe = torch.rand(4096, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1
    with torch.no_grad():
        fog0 = float(model.field.density(probe).mean())
    first = float(model._sparsity())
    assert first == pytest.approx(float((-torch.expm1(-model.field.density(probe) * model.step_size)).mean()), rel=0.05)
    _descend(model._sparsity, grids)
    with torch.no_grad():
        assert float(model.field.density(probe).mean()) < 0.5 * fog0
        assert float(model._sparsity()) < 0.5 * first
    out = RenderOutputs(rgb=torch.zeros(2, 3), depth=torch.zeros(2), acc=torch.zeros(2))
    assert "sparsity" in model.get_losses(out, torch.zeros(2, 3))
    model.eval()
    assert "sparsity" not in model.get_losses(out, torch.zeros(2, 3))
    # on for the first SPARSITY_UNTIL steps only (it clears the fog, then would thin plain surfaces into holes)
    model.train()
    assert model.sparsity_until == SPARSITY_UNTIL and model.stats()["sparsity_until"] == SPARSITY_UNTIL
    for step, on in ((SPARSITY_UNTIL - 1, True), (SPARSITY_UNTIL, False)):
        model._before_step(step)
        assert ("sparsity" in model.get_losses(out, torch.zeros(2, 3))) == on, step
    assert _model(sparsity_weight=1.0, sparsity_until=10).sparsity_until == 10


def test_distortion_loss_is_on_for_real_captures_and_gathers_each_rays_weights():
    """Real captures with the field behind the box train with the box's distortion loss by default (the fog a
    few-view capture grows in the box), less of it the more photographs they have; synthetic scenes do not. The loss is the packed distortion of the training rays' weights, and descending it
    gathers a ray's spread weights."""
    from nerfpipe.functional.packed import distortion_loss_packed
    from nerfpipe.models.fast import DISTORTION_REAL, DISTORTION_FULL_IMAGES, SPARSITY_MIN_ARC

    info = dict(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]), near=0.5, far=10.0, num_images=20, pixels_per_image=100, unbounded=True)
    weight = lambda **kw: FastConfig(preset="small").setup(SceneInfo(**{**info, **kw})).distortion_weight  # noqa: E731
    assert weight(arc=2 * math.pi) == weight(arc=SPARSITY_MIN_ARC) == DISTORTION_REAL > 0  # 20 training images
    assert weight(arc=2 * math.pi, num_images=DISTORTION_FULL_IMAGES) == DISTORTION_REAL
    assert weight(arc=2 * math.pi, num_images=2 * DISTORTION_FULL_IMAGES) == pytest.approx(DISTORTION_REAL / 4)  # more photographs, less prior
    assert weight(arc=math.radians(63)) == DISTORTION_REAL  # a facade: the sky's fog in front of it too
    assert weight(arc=2 * math.pi, unbounded=False, has_alpha=True) == 0.0  # synthetic, no field behind the box
    assert FastConfig(preset="small", background_field=False).setup(SceneInfo(**info, arc=2 * math.pi)).distortion_weight == 0.0
    assert FastConfig(preset="small", distortion_weight=0.0).setup(SceneInfo(**info, arc=2 * math.pi)).distortion_weight == 0.0
    around = FastConfig(preset="small").setup(SceneInfo(**info, arc=2 * math.pi))
    assert around.stats()["distortion_weight"] == DISTORTION_REAL  # in metrics.json
    around.train()
    out = around.get_outputs(_rays(256), torch.zeros(256, 3))
    loss = around.get_losses(out, torch.full((256, 3), 0.5))["distortion"].detach()
    assert float(loss) == pytest.approx(DISTORTION_REAL * float(out.extras["distortion"].detach())) and float(loss) > 0
    around.eval()
    with torch.no_grad():
        assert "distortion" not in around.get_losses(around.get_outputs(_rays(64), torch.zeros(64, 3)), torch.zeros(64, 3))
    # what the loss does to one ray: weights spread evenly along it gather about one place
    edges = torch.linspace(0.0, 1.0, 33)
    mids, one_ray = 0.5 * (edges[1:] + edges[:-1]), torch.zeros(32, dtype=torch.long)
    logits = torch.zeros(32, requires_grad=True)
    opt = torch.optim.Adam([logits], lr=0.05)

    def spread(w):  # the weights' standard deviation along the ray
        p = w / w.sum()
        return float(((p * (mids - (p * mids).sum()) ** 2).sum()).sqrt())

    before = spread(torch.softmax(logits, -1).detach())
    for _ in range(200):
        loss = distortion_loss_packed(0.8 * torch.softmax(logits, -1), edges[:-1], edges[1:], one_ray, 1).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert spread(torch.softmax(logits, -1).detach()) < 0.25 * before


def test_evidence_sparsity_clears_the_box_away_from_the_sparse_points_where_the_sparsity_is_off():
    """Facades and photo collections (cameras on one side: no sparsity loss, which would thin their surfaces) get the
    sparsity loss only where SfM saw no surface: farther than ``evidence_radius`` from every sparse point. Density near
    the points stays; the fog far from them goes."""
    from nerfpipe.models.fast import EVIDENCE_SPARSITY, evidence_at, evidence_grid

    box = torch.tensor([[-1.0] * 3, [1.0] * 3])
    points = torch.stack([torch.linspace(-0.5, 0.5, 60), torch.zeros(60), torch.zeros(60)], -1)  # a rod of points along x
    info = dict(aabb=box, near=0.5, far=10.0, num_images=20, pixels_per_image=100, unbounded=True, points=points)
    weight = lambda **kw: FastConfig(preset="small").setup(SceneInfo(**{**info, **kw})).evidence_sparsity_weight  # noqa: E731
    assert weight(arc=math.radians(63)) == EVIDENCE_SPARSITY > 0  # a facade
    assert weight(arc=2 * math.pi) == 0.0  # an object all round: the sparsity loss everywhere instead
    assert weight(arc=math.radians(63), points=points[:10]) == 0.0  # too few points to say where surfaces are
    assert weight(arc=math.radians(63), points=None) == 0.0
    assert weight(arc=math.radians(63), unbounded=False, has_alpha=True, points=None) == 0.0  # synthetic: no field behind the box
    assert FastConfig(preset="small").setup(SceneInfo(**info, arc=1.0)).stats()["evidence_sparsity_weight"] == EVIDENCE_SPARSITY

    grid = evidence_grid(points, box, 0.05)  # 0.05 of the diagonal (3.46): 0.17, six 1/32 cells (and the cell a point lies in)
    probe = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.1, -0.1], [0.8, 0.0, 0.0], [0.0, 0.4, 0.0], [0.9, 0.9, 0.9], [5.0, 0.0, 0.0]])
    assert evidence_at(grid, box, probe).tolist() == [True, True, False, False, False, False]

    model = FastConfig(preset="small").setup(SceneInfo(**info, arc=1.0))
    grids = _fog_everywhere(model)
    near = points[::6] + 0.02
    far = torch.rand(2048, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1
    far = far[~evidence_at(model.evidence, box, far)]
    with torch.no_grad():
        near0, far0 = float(model.field.density(near).mean()), float(model.field.density(far).mean())
    _descend(lambda: model._sparsity(away_from_points=True), grids)
    with torch.no_grad():
        assert float(model.field.density(far).mean()) < 0.5 * far0
        assert float(model.field.density(near).mean()) > 0.8 * near0
    out = RenderOutputs(rgb=torch.zeros(2, 3), depth=torch.zeros(2), acc=torch.zeros(2))
    assert "evidence_sparsity" in model.get_losses(out, torch.zeros(2, 3)) and "sparsity" not in model.get_losses(out, torch.zeros(2, 3))


def test_a_real_capture_training_step_with_sample_slots_reads_nothing_back():
    """Issue 13: with the samples packed into slots known beforehand (what the trainer's CUDA graph sets), the same
    step reads nothing back, so it can be captured whole; it trains as the step that reads the count back."""
    from nerfpipe.training.opcount import DispatchCounter

    model = _model(fixed_shapes=True)
    model.train()
    model._step = model.cfg.behind_from
    rays, bg = _rays(64, 3), torch.zeros(64, 3)
    target, depth = torch.rand(64, 3), torch.where(torch.arange(64) % 2 == 0, 3.5, float("nan"))

    def step(seed):
        model.zero_grad(set_to_none=True)
        model.generator = torch.Generator().manual_seed(seed)
        out = model.get_outputs(rays, bg)
        sum(model.get_losses(out, target, depth).values()).backward()
        return out, {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}

    ref, ref_grads = step(0)
    n, intervals = model.sample_count().tolist()
    assert n == ref.num_samples > 0 and intervals >= n
    model.sample_capacity = (n + 1000, intervals + 3000)
    with DispatchCounter() as c:
        got, grads = step(0)
    assert c.syncs == 0, dict(c.sync_ops)
    assert got.num_samples == n + 1000 and model.sample_count().tolist() == [n, intervals]
    torch.testing.assert_close(got.rgb, ref.rgb, rtol=1e-6, atol=1e-7)
    assert grads.keys() == ref_grads.keys()
    for name in grads:
        torch.testing.assert_close(grads[name], ref_grads[name], rtol=1e-5, atol=1e-9)


def test_a_run_written_before_the_field_in_front_of_the_box_loads_as_it_trained():
    """A stored model config without ``behind.front`` (a run written before session 48) loads with it off, as it
    trained; one that has it keeps its value; the config's own default is None (decided by the training images)."""
    from nerfpipe.training.runs import _options_since
    from nerfpipe.util.configs import from_dict, to_dict

    assert FastConfig().behind.front is None  # by the training images (test_the_field_in_front_of_the_box_is_read_...)
    stored = to_dict(FastConfig())
    del stored["behind"]["front"]
    _options_since(FastConfig, stored)
    assert from_dict(FastConfig, stored).behind.front is False
    stored = to_dict(FastConfig(behind=BackgroundFieldConfig(front=True)))
    _options_since(FastConfig, stored)
    assert from_dict(FastConfig, stored).behind.front is True
    stored = {"preset": "small"}  # no table of the field behind the box at all
    _options_since(FastConfig, stored)
    assert from_dict(FastConfig, stored).behind.front is False
    assert not _model(num_images=FRONT_MIN_IMAGES, behind=BackgroundFieldConfig(front=False)).front


def test_a_run_written_before_the_rule_of_20_photographs_keeps_its_rule():
    """A stored model config without ``front_min_images`` (a run written before session 54, when the field in front
    of the box was read from 32 training images on) loads with that rule: a capture of 20 training images renders
    without it, as it trained; a new config reads it from :data:`FRONT_MIN_IMAGES` on."""
    from nerfpipe.models.fast import FRONT_MIN_IMAGES_BEFORE
    from nerfpipe.training.runs import _options_since
    from nerfpipe.util.configs import from_dict, to_dict

    assert FRONT_MIN_IMAGES < 20 < FRONT_MIN_IMAGES_BEFORE
    stored = to_dict(FastConfig())
    del stored["front_min_images"]
    _options_since(FastConfig, stored)
    old = from_dict(FastConfig, stored)
    assert old.front_min_images == FRONT_MIN_IMAGES_BEFORE
    info = SceneInfo(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]), near=0.5, far=10.0, num_images=20, pixels_per_image=100, unbounded=True, focal_spread=1.0)
    assert not old.setup(info).front and FastConfig().setup(info).front


def test_the_field_in_front_of_the_box_is_read_where_a_capture_has_many_photographs():
    """``behind.front`` None: on from ``FRONT_MIN_IMAGES`` training images (with fewer its haze costs held-out PSNR),
    never without the field behind the box; given, as given."""
    assert _model(num_images=FRONT_MIN_IMAGES).front and not _model(num_images=FRONT_MIN_IMAGES - 1).front
    assert _model(num_images=4, behind=BackgroundFieldConfig(front=True)).front
    assert not _model(num_images=FRONT_MIN_IMAGES, background_field=False).front
    assert _model(num_images=FRONT_MIN_IMAGES).stats()["behind_front"] == 1.0


def test_sky_residual_is_each_images_bilinear_texture_over_directions_zero_mean_and_off_outside_training():
    """The per-image sky residual (``sky_residual``): the bilinear read of each ray's image's texture (zero-mean over
    the images) at its direction's equirectangular coordinates, against ``grid_sample`` (border padding) as the
    reference, values and gradients; a texture the same for every image reads as zero; evaluation renders without it."""
    model = _model(sky_residual=4)
    model.train()
    rays = _rays(96, 5)
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        model.sky.copy_(torch.randn(model.sky.shape, generator=g))
    got = model._sky_residual(rays)
    got.backward(torch.ones_like(got))
    grad = model.sky.grad.clone()
    sky = model.sky.detach().clone().requires_grad_(True)
    n, rows, cols, _ = sky.shape
    table = (sky - sky.mean(0, keepdim=True)).permute(0, 3, 1, 2)  # [images, 3, rows, cols]
    d = rays.directions
    u = (torch.atan2(d[:, 1], d[:, 0]) / (2 * math.pi) + 0.5) * cols - 0.5
    v = torch.acos(d[:, 2]) / math.pi * rows - 0.5
    grid = torch.stack([(2 * u + 1) / cols - 1, (2 * v + 1) / rows - 1], dim=-1)
    want = torch.stack([torch.nn.functional.grid_sample(table[int(c)][None], grid[i].view(1, 1, 1, 2), align_corners=False,
                                                        padding_mode="border")[0, :, 0, 0] for i, c in enumerate(rays.cam_idx)])
    torch.testing.assert_close(got.detach(), want.detach(), atol=1e-5, rtol=0)
    want.backward(torch.ones_like(want))
    torch.testing.assert_close(grad, sky.grad, atol=1e-5, rtol=0)
    with torch.no_grad():
        model.sky.copy_(torch.randn(1, rows, cols, 3, generator=g).expand(n, -1, -1, -1))
    torch.testing.assert_close(model._sky_residual(rays), torch.zeros(96, 3), atol=1e-6, rtol=0)
    assert any(model.sky is p for group in model.param_groups() for p in group["params"])
    assert _model(focal_spread=0.0).sky is None and _model(sky_residual=0).sky is None  # one camera's session, or off
    with torch.no_grad():
        model.sky.copy_(torch.randn(model.sky.shape, generator=g))
    trained = model.get_outputs(rays, torch.zeros(96, 3)).rgb
    with torch.no_grad():
        model.sky.zero_()
        untextured = model.get_outputs(rays, torch.zeros(96, 3)).rgb
        model.sky.copy_(torch.randn(model.sky.shape, generator=g))
    assert not torch.allclose(trained, untextured, atol=1e-3)  # in training, each image's residual
    model.eval()
    with torch.no_grad():
        evaluated = model.get_outputs(rays, torch.zeros(96, 3)).rgb
        model.sky.zero_()
        plain = model.get_outputs(rays, torch.zeros(96, 3)).rgb
    torch.testing.assert_close(evaluated, plain)  # novel views: the mean (zero)


def test_equirect_lookup_matches_the_one_direction_reference_values_and_gradients(device):
    """:func:`equirect_lookup` against :func:`equirect_lookup_reference` (one texture and per-ray textures), the poles
    and the seam at azimuth +-pi included, and its gradient in the textures against the reference's."""
    from nerfpipe.functional.gather import equirect_lookup, equirect_lookup_reference

    g = torch.Generator().manual_seed(5)
    textures = torch.randn(3, 6, 12, 2, generator=g)
    d = torch.nn.functional.normalize(torch.randn(40, 3, generator=g), dim=-1)
    d = torch.cat([d, torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [-1.0, 1e-7, 0.0], [-1.0, -1e-7, 0.0]])])
    which = torch.randint(0, 3, (len(d),), generator=g)
    got = equirect_lookup(textures.to(device), d.to(device), which.to(device))
    ref_textures = textures.clone().requires_grad_(True)
    want = torch.stack([equirect_lookup_reference(ref_textures[int(k)], tuple(map(float, v))) for v, k in zip(d, which)])
    torch.testing.assert_close(got.detach().cpu(), want.detach(), atol=1e-5, rtol=0)
    upstream = torch.randn(want.shape, generator=g)
    textures_dev = textures.clone().to(device).requires_grad_(True)
    (equirect_lookup(textures_dev, d.to(device), which.to(device)) * upstream.to(device)).sum().backward()
    (want * upstream).sum().backward()
    torch.testing.assert_close(textures_dev.grad.cpu(), ref_textures.grad, atol=1e-5, rtol=0)
    one = equirect_lookup(textures[1], d)  # one texture for every ray
    torch.testing.assert_close(one, equirect_lookup(textures, d, torch.ones(len(d), dtype=torch.long)))
    upper = equirect_lookup(textures[2], d, polar_max=math.pi / 2)  # rows over the upper hemisphere, the last held below
    want = torch.stack([equirect_lookup_reference(textures[2], tuple(map(float, v)), math.pi / 2) for v in d])
    torch.testing.assert_close(upper, want, atol=1e-5, rtol=0)
    below = d[:, 2] < 0
    torch.testing.assert_close(upper[below], equirect_lookup(textures[2, -1:].expand(2, -1, -1), d[below]), atol=1e-6, rtol=0)


def test_sky_map_is_a_shared_texture_behind_everything_in_training_and_renders():
    """The sky map (``sky_map``): on where the sky residual is (photo collections), off elsewhere; added behind
    everything for every image alike, in training and in evaluation renders; learnt (its own parameter group); a
    checkpoint from before it loads without it, and one trained with it rebuilds it from the config's default."""
    from nerfpipe.functional.gather import equirect_lookup
    from nerfpipe.models.fast import SKY_MAP_FADE, SKY_MAP_ROWS

    model = _model()
    assert model.sky_map is not None and model.sky_map.shape == (SKY_MAP_ROWS, 2 * SKY_MAP_ROWS, 3)
    assert _model(focal_spread=0.0).sky_map is None and _model(sky_map=0).sky_map is None
    assert _model(sky_residual=0).sky_map is None and _model(sky_residual=0, sky_map=8).sky_map.shape == (8, 16, 3)
    assert any(model.sky_map is p for group in model.param_groups() for p in group["params"])
    assert model.stats()["sky_map_rows"] == SKY_MAP_ROWS and _model(sky_map=0).stats()["sky_map_rows"] == 0
    down = _rays(64, 2)  # looking down: below the horizon
    up = RayBundle(origins=-down.origins, directions=-down.directions, cam_idx=down.cam_idx, z_scale=down.z_scale)
    g = torch.Generator().manual_seed(4)
    for training in (True, False):
        model.train(training)
        for rays, sky in ((up, True), (down, False)):
            with torch.no_grad():
                model.sky_map.zero_()
                plain = model.get_outputs(rays, torch.full((64, 3), 0.5)).rgb
                model.sky_map.copy_(0.3 * torch.randn(model.sky_map.shape, generator=g))
                mapped = model.get_outputs(rays, torch.full((64, 3), 0.5)).rgb
            assert ((mapped - plain).abs().max() > 1e-3) == sky, (training, sky)
    whole = _model(sky_map_upper=False)
    with torch.no_grad():
        whole.sky_map.copy_(0.3 * torch.randn(whole.sky_map.shape, generator=g))
    torch.testing.assert_close(whole._sky_map(down.directions), equirect_lookup(whole.sky_map, down.directions))
    torch.testing.assert_close(model._sky_map(up.directions), equirect_lookup(model.sky_map, up.directions, polar_max=math.pi / 2)
                               * (up.directions[:, 2:] / SKY_MAP_FADE).clamp(max=1.0))
    state = _model(sky_map=0).state_dict()
    old = _model()
    old.load_state_dict(state)
    assert old.sky_map is None and "sky_map" not in old.state_dict()
    info = SceneInfo(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]), near=0.5, far=10.0, num_images=4, pixels_per_image=100, unbounded=True, focal_spread=1.0)
    assert FastConfig(preset="small").for_checkpoint(state, info).setup(info).sky_map is None
    cfg = FastConfig(preset="small")
    assert cfg.for_checkpoint(model.state_dict(), info) is cfg  # trained with the default: the config as it is
    assert cfg.for_checkpoint(_model(sky_map=8).state_dict(), info).setup(info).sky_map.shape == (8, 16, 3)


def test_a_checkpoint_from_before_the_sky_residual_loads_without_it():
    state = {k: v for k, v in _model(sky_residual=0).state_dict().items()}
    model = _model()
    assert model.sky is not None
    model.load_state_dict(state)
    assert model.sky is None and "sky" not in model.state_dict()
