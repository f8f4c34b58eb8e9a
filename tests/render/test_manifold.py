from __future__ import annotations

import pytest
import torch

from tests.conftest import RTOL
from tests.manifold.common import SMALL_GRID, small_family
from torch_brdf.errors import SceneError, ShapeError
from torch_brdf.manifold.materials import material_record, sphere_scene, with_material
from torch_brdf.render.manifold import blend, render_rows


def test_blending_equals_rendering_the_blend_for_direct_light():
    """Seed Eq. 8: with one bounce and a fixed seed the renderer is linear in a non-negative table."""
    obs, _ = small_family(3)
    scene = sphere_scene(12)
    imgs = render_rows(scene, "sample", obs.z, SMALL_GRID, spp=1, max_bounces=1, progress=False)
    w = torch.tensor([0.2, 0.5, 0.3], dtype=torch.float64)
    rec = material_record(imgs, obs.names)
    assert rec.values.shape == (3, 3, 144) and rec.basis.startswith("materials:3:")
    blended = blend(rec, w)
    ref = render_rows(scene, "sample", (w @ obs.z.double())[None], SMALL_GRID, spp=1, max_bounces=1, progress=False)
    assert float(ref.abs().max()) > 0
    torch.testing.assert_close(blended, ref[0], rtol=10 * RTOL[torch.float32], atol=1e-6)


def test_gi_blend_drops_only_multiple_bounces_on_the_material():
    """One-hot weights reproduce each GI render exactly; a mixture differs (the L2+ paths)."""
    obs, _ = small_family(2)
    scene = sphere_scene(8)
    imgs = render_rows(scene, "sample", obs.z, SMALL_GRID, spp=1, max_bounces=3, progress=False)
    rec = material_record(imgs)
    torch.testing.assert_close(blend(rec, torch.tensor([0.0, 1.0])), imgs[1], rtol=0, atol=0)


def test_affine_record_is_exact_for_any_weights():
    """With the black-material render as constant part, extrapolating weights (sum != 1) stay exact."""
    obs, _ = small_family(2)
    scene = sphere_scene(10)
    rows = torch.cat([obs.z, torch.zeros_like(obs.z[:1])])
    imgs = render_rows(scene, "sample", rows, SMALL_GRID, spp=1, max_bounces=1, progress=False)
    w = torch.tensor([0.9, 0.6], dtype=torch.float64)  # sum 1.5: the plane would be scaled by 1.5 without it
    ref = render_rows(scene, "sample", (w @ obs.z.double())[None], SMALL_GRID, spp=1, max_bounces=1, progress=False)
    affine = blend(material_record(imgs[:2], constant=imgs[2]), w)
    torch.testing.assert_close(affine, ref[0], rtol=10 * RTOL[torch.float32], atol=1e-6)
    plain = blend(material_record(imgs[:2]), w)
    assert float((plain - ref[0]).abs().max()) > 0.1 * float(ref[0].abs().max())


def test_bad_inputs():
    rec = material_record(torch.zeros(2, 4, 4, 3))
    with pytest.raises(ShapeError):
        blend(rec, torch.ones(3))
    with pytest.raises(ShapeError):
        material_record(torch.zeros(4, 4, 3))
    with pytest.raises(SceneError):
        with_material(sphere_scene(8), "nope", {"type": "lambert"})
