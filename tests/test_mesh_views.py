"""mesh_views.png: four ray-cast views, shaded and coloured."""

import numpy as np

from nerfpipe.mesh.container import TriangleMesh
from nerfpipe.mesh.views import look_at, orbit_cameras, render_views, write_views


def coloured_box() -> TriangleMesh:
    import trimesh

    b = trimesh.creation.box(extents=(1.0, 0.6, 0.4))
    return TriangleMesh(b.vertices, b.faces, np.tile(np.array([[230, 20, 20]], np.uint8), (len(b.vertices), 1)))


def test_look_at_uses_opencv_axes():
    m = look_at(np.array([0.0, -3.0, 0.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(m[:3, 2], [0, 1, 0])  # +z forward
    np.testing.assert_allclose(m[:3, 1], [0, 0, -1])  # +y down
    np.testing.assert_allclose(m[:3, 0], [1, 0, 0])  # +x right


def test_orbit_cameras_see_the_whole_mesh():
    mesh = coloured_box()
    cams = orbit_cameras(mesh, size=64)
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.3, 0.3) for z in (-0.2, 0.2)])

    for i in range(len(cams)):
        uv, z = _project(cams, i, corners)
        assert (z > 0).all() and (uv >= 0).all() and (uv <= 64).all()


def test_the_views_keep_to_the_arc_the_photographs_were_taken_from():
    mesh = coloured_box()
    arc = np.radians(np.linspace(-60, 60, 7))  # a wall-mounted object: photographed from its front only
    seen_from = np.stack([3 * np.cos(arc), 3 * np.sin(arc), np.ones(7)], -1)
    cams = orbit_cameras(mesh, size=64, seen_from=seen_from)
    az = np.degrees(np.arctan2(cams.centers[:, 1].numpy(), cams.centers[:, 0].numpy()))
    np.testing.assert_allclose(az, [-45, -15, 15, 45], atol=1e-6)  # spread over the 120-degree arc, none behind
    around = np.radians(np.linspace(0, 360, 9)[:-1])  # photographed all round: the usual four sides
    ring = np.stack([3 * np.cos(around), 3 * np.sin(around), np.ones(8)], -1)
    np.testing.assert_allclose(orbit_cameras(mesh, size=64, seen_from=ring).world_from_cam, orbit_cameras(mesh, size=64).world_from_cam)


def _project(cams, i, pts):
    cam_from_world = np.linalg.inv(cams.world_from_cam[i].numpy())
    p = pts @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    uv = p[:, :2] / p[:, 2:] * cams.fx[i].item() + cams.cx[i].item()
    return uv, p[:, 2]


def test_render_views_grid_and_colours(tmp_path):
    img = render_views(coloured_box(), size=48)
    assert img.shape == (96, 192, 3)
    assert (img[0, 0] == 1.0).all()  # background corner
    for k in range(4):
        shaded, coloured = img[:48, 48 * k : 48 * (k + 1)], img[48:, 48 * k : 48 * (k + 1)]
        fg = (shaded < 0.99).any(-1)
        assert 0.05 < fg.mean() < 0.9
        assert np.allclose(shaded[fg][:, 0], shaded[fg][:, 1])  # front faces grey
        red = coloured[fg]
        assert (red[:, 0] > 2 * red[:, 1]).mean() > 0.99  # the vertex colour shows
    path = write_views(coloured_box(), tmp_path / "mesh_views.png", size=32)
    import imageio.v3 as iio

    assert iio.imread(path).shape == (64, 128, 3)


def test_back_faces_are_tinted():
    m = coloured_box()
    flipped = TriangleMesh(m.vertices, m.faces[:, ::-1].copy())
    img = render_views(flipped, size=32)[:32]
    fg = (img < 0.99).any(-1)
    assert (img[fg][:, 0] > img[fg][:, 1]).all()
