"""Camera: primary rays through pixel centres, projection, jitter, aspect ratio, bad input."""

from __future__ import annotations

import math

import pytest
import torch

from torch_brdf.errors import CameraError, TorchBRDFError
from torch_brdf.scene import Camera

#: the published Cornell box camera: looking along +z with +y up
CORNELL = {"origin": (278.0, 273.0, -800.0), "target": (278.0, 273.0, 0.0), "up": (0.0, 1.0, 0.0), "fov_deg": 39.3}


def _oblique(width: int, height: int, fov_deg: float = 50.0) -> Camera:
    """A camera in a general pose (no axis-aligned shortcuts)."""
    return Camera((1.0, 2.0, 3.0), (4.0, -1.0, 7.5), (0.1, 1.0, -0.2), fov_deg, width, height)


def _forward(cam: Camera) -> torch.Tensor:
    f = torch.tensor(cam.target, dtype=torch.float64) - torch.tensor(cam.origin, dtype=torch.float64)
    return f / f.norm()


def _angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle between unit vectors (P, 3) and (3,), accurate near 0 (atan2 of |cross|, dot)."""
    b = b.expand_as(a)
    return torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1))


def test_frame_is_orthonormal_and_follows_pose():
    cam = _oblique(7, 5)
    F = cam.frame
    torch.testing.assert_close(F @ F.T, torch.eye(3, dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close(F[2], _forward(cam), atol=1e-12, rtol=0)
    up = torch.tensor(cam.up, dtype=torch.float64)
    assert float(F[1] @ up) > 0, "camera up must lean towards the given up vector"
    # right = forward x up (the documented convention)
    r = torch.linalg.cross(F[2], up)
    torch.testing.assert_close(F[0], r / r.norm(), atol=1e-12, rtol=0)


@pytest.mark.parametrize(("width", "height"), [(7, 5), (1, 1), (3, 9), (15, 15)])
def test_centre_pixel_of_odd_image_looks_along_forward(width, height):
    cam = _oblique(width, height)
    o, d = cam.generate_rays(dtype=torch.float64)
    assert o.shape == d.shape == (width * height, 3)
    centre = (height // 2) * width + width // 2
    torch.testing.assert_close(d[centre], _forward(cam), atol=1e-14, rtol=0)
    torch.testing.assert_close(o, torch.tensor(cam.origin, dtype=torch.float64).expand(width * height, 3))


def test_generate_rays_are_unit_row_major_through_pixel_centres():
    cam = _oblique(6, 4)
    o, d = cam.generate_rays()
    assert d.dtype == torch.float32 and o.dtype == torch.float32
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(24), atol=1e-6, rtol=0)
    raster = cam.project(o.double() + 3.0 * d.double())
    r, c = torch.meshgrid(torch.arange(4.0), torch.arange(6.0), indexing="ij")
    want = torch.stack((c.reshape(-1) + 0.5, r.reshape(-1) + 0.5), -1).double()
    torch.testing.assert_close(raster, want, atol=1e-4, rtol=0)


@pytest.mark.parametrize("fov_deg", [20.0, 39.3, 90.0, 150.0])
@pytest.mark.parametrize(("width", "height"), [(7, 5), (8, 4), (3, 9)])
def test_top_and_bottom_edge_midpoints_make_half_fov_with_forward(fov_deg, width, height):
    cam = _oblique(width, height, fov_deg)
    _, d = cam.rays_through([width / 2, width / 2], [0.0, float(height)], dtype=torch.float64)
    ang = _angle(d, _forward(cam))
    torch.testing.assert_close(ang, torch.full((2,), math.radians(fov_deg) / 2, dtype=torch.float64))
    up = cam.frame[1]
    assert float(d[0] @ up) > 0 > float(d[1] @ up), "row 0 is the top of the image"


@pytest.mark.parametrize(("width", "height"), [(8, 4), (4, 8), (640, 480)])
def test_aspect_ratio_keeps_pixels_square(width, height):
    fov = 40.0
    cam = _oblique(width, height, fov)
    f = _forward(cam)
    # left/right edge midpoints: horizontal half angle from tan(h) = aspect * tan(v)
    _, d = cam.rays_through([0.0, float(width)], [height / 2, height / 2], dtype=torch.float64)
    want = math.atan(width / height * math.tan(math.radians(fov) / 2))
    torch.testing.assert_close(_angle(d, f), torch.full((2,), want, dtype=torch.float64))
    # one pixel right of the centre and one pixel down make the same angle with forward
    _, d = cam.rays_through([width / 2 + 1, width / 2], [height / 2, height / 2 + 1], dtype=torch.float64)
    a = _angle(d, f)
    torch.testing.assert_close(a[0], a[1], atol=1e-13, rtol=0)


def test_raster_x_runs_to_the_camera_right():
    cam = _oblique(9, 5)
    xs = torch.linspace(0, 9, 10, dtype=torch.float64)
    _, d = cam.rays_through(xs, torch.full_like(xs, 2.5), dtype=torch.float64)
    along_right = d @ cam.frame[0]
    assert bool((along_right.diff() > 0).all())
    assert float(along_right[0]) < 0 < float(along_right[-1])


def test_cornell_camera_puts_plus_x_on_the_left():
    cam = Camera(**CORNELL, width=64, height=64)
    _, d = cam.rays_through([0.0, 64.0, 32.0, 32.0], [32.0, 32.0, 0.0, 64.0], dtype=torch.float64)
    assert float(d[0, 0]) > 0, "the left edge of the image looks towards +x"
    assert float(d[1, 0]) < 0, "the right edge of the image looks towards -x"
    assert float(d[2, 1]) > 0 > float(d[3, 1]), "+y is up"
    # red wall (x ~ 556) on the left, green wall (x = 0) on the right, ceiling on top
    px = cam.project(torch.tensor([[550.0, 274.0, 400.0], [0.0, 274.0, 400.0], [278.0, 548.8, 400.0]]))
    assert float(px[0, 0]) < 32 < float(px[1, 0])
    assert float(px[2, 1]) < 32


@pytest.mark.parametrize(("width", "height"), [(7, 5), (32, 18)])
def test_project_inverts_rays_through(gen, width, height):
    cam = _oblique(width, height, 60.0)
    n = 500
    x = torch.rand(n, generator=gen, dtype=torch.float64) * width
    y = torch.rand(n, generator=gen, dtype=torch.float64) * height
    t = 0.5 + 100 * torch.rand(n, generator=gen, dtype=torch.float64)
    o, d = cam.rays_through(x, y, dtype=torch.float64)
    raster = cam.project(o + t[:, None] * d)
    torch.testing.assert_close(raster, torch.stack((x, y), -1), atol=1e-9, rtol=0)


def test_project_behind_camera_is_inf():
    cam = _oblique(8, 8)
    f = _forward(cam)
    o = torch.tensor(cam.origin, dtype=torch.float64)
    pts = torch.stack((o - 2 * f, o - 0.5 * f + 3 * cam.frame[0], o + 5 * f))  # behind, behind, in front
    px = cam.project(pts)
    assert bool(torch.isinf(px[:2]).all()) and not bool(torch.isnan(px).any())
    torch.testing.assert_close(px[2], torch.tensor([4.0, 4.0], dtype=torch.float64))
    # exactly in the camera plane (axis-aligned camera, so no rounding): also inf
    flat = Camera((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), width=8, height=8)
    assert bool(torch.isinf(flat.project(torch.tensor([[1.0, 2.0, 0.0]]))).all())


def test_jitter_stays_in_pixel_and_is_reproducible():
    cam = _oblique(6, 5)

    def rays(seed):
        g = torch.Generator().manual_seed(seed)
        return cam.generate_rays(jitter=True, generator=g, dtype=torch.float64)

    o1, d1 = rays(7)
    o2, d2 = rays(7)
    _, d3 = rays(8)
    assert torch.equal(d1, d2) and torch.equal(o1, o2)
    assert not torch.allclose(d1, d3)
    raster = cam.project(o1 + d1)
    r, c = torch.meshgrid(torch.arange(5.0), torch.arange(6.0), indexing="ij")
    cell = torch.stack((c.reshape(-1), r.reshape(-1)), -1).double()
    frac = raster - cell
    assert bool(((frac > -1e-9) & (frac < 1 + 1e-9)).all()), "a jittered ray left its pixel"
    # the samples spread over the pixel rather than sitting at the centre
    assert float((frac - 0.5).abs().max()) > 0.3
    assert float(frac.std()) > 0.15


def test_with_size_keeps_pose_and_fov():
    cam = _oblique(7, 5, 33.0)
    big = cam.with_size(20, 10)
    assert (big.width, big.height) == (20, 10)
    assert (big.origin, big.target, big.up, big.fov_deg) == (cam.origin, cam.target, cam.up, cam.fov_deg)
    torch.testing.assert_close(big.frame, cam.frame)
    assert (cam.width, cam.height) == (7, 5)


@pytest.mark.parametrize(
    "kwargs",
    [
        pytest.param({"origin": (0, 0, 0), "target": (0, 5, 0), "up": (0, 1, 0)}, id="up-parallel"),
        pytest.param({"origin": (0, 0, 0), "target": (0, 5, 0), "up": (0, -2, 0)}, id="up-antiparallel"),
        pytest.param({"origin": (1, 2, 3), "target": (1, 2, 3)}, id="origin-equals-target"),
        pytest.param({"origin": (0, 0, 0), "target": (0, 0, 1), "up": (0, 0, 0)}, id="zero-up"),
        pytest.param({"origin": (0, 0, 0), "target": (0, 0, 1), "fov_deg": 0.0}, id="fov-0"),
        pytest.param({"origin": (0, 0, 0), "target": (0, 0, 1), "fov_deg": 180.0}, id="fov-180"),
        pytest.param({"origin": (0, 0, 0), "target": (0, 0, 1), "fov_deg": -10.0}, id="fov-negative"),
        pytest.param({"origin": (0, 0, 0), "target": (0, 0, 1), "fov_deg": float("nan")}, id="fov-nan"),
        pytest.param({"origin": (0, 0, 0), "target": (0, 0, 1), "width": 0}, id="width-0"),
        pytest.param({"origin": (0, 0, 0), "target": (0, 0, 1), "height": 0}, id="height-0"),
        pytest.param({"origin": (0, 0, 0), "target": (0, 0, 1), "width": -4, "height": 4}, id="width-negative"),
    ],
)
def test_degenerate_cameras_raise_camera_error(kwargs):
    with pytest.raises(CameraError):
        Camera(**kwargs)


def test_non_finite_origin_is_rejected():
    with pytest.raises(TorchBRDFError, match="origin"):
        Camera((float("nan"), 0.0, 0.0), (0.0, 0.0, 1.0))
