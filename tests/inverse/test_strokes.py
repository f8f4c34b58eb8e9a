"""Strokes (Eq. 23) on a hand-built record."""

from __future__ import annotations

import math

import pytest
import torch

from torch_brdf.errors import ShapeError, ValueRangeError
from torch_brdf.inverse import Brush, Stroke, paint, stroke_distance, target_from_image
from torch_brdf.render.record import BasisImage


def _record(h=10, w=20):
    """A record covering the left half of an h x w frame (the 'object')."""
    mask = torch.zeros(h, w, dtype=torch.bool)
    mask[:, : w // 2] = True
    return BasisImage.from_dense(torch.ones(2, h, w, 3, dtype=torch.float64), mask=mask, basis="srbf:1+diffuse")


def test_distance_to_polyline():
    pts = torch.tensor([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]], dtype=torch.float64)
    xy = torch.tensor([[5.0, 3.0], [12.0, 5.0], [-3.0, -4.0]], dtype=torch.float64)
    torch.testing.assert_close(stroke_distance(pts, xy), torch.tensor([3.0, 2.0, 5.0], dtype=torch.float64))


def test_eq23_by_hand():
    rec = _record()
    before = torch.full((rec.num_pixels, 3), 0.2, dtype=torch.float64)
    brush = Brush((1.0, 0.5, 0.0), diameter=6.0, kappa=0.3)
    t = paint(rec, before, [Stroke([[2.5, 4.5]], brush)])
    r = torch.div(rec.pixels, rec.width, rounding_mode="floor").double() + 0.5
    c = (rec.pixels % rec.width).double() + 0.5
    d = ((c - 2.5) ** 2 + (r - 4.5) ** 2).sqrt()
    w = torch.where(d <= 3.0, torch.exp(-0.3 * d), 0.0)[:, None]
    want = w * torch.tensor([1.0, 0.5, 0.0], dtype=torch.float64) + (1 - w) * before
    torch.testing.assert_close(t.target, want)
    assert torch.equal(t.painted, d <= 3.0)
    assert torch.equal(t.weight, torch.ones(rec.num_pixels, dtype=torch.float64))


def test_negative_colour_removes_and_scale_multiplies():
    rec = _record()
    before = torch.full((rec.num_pixels, 3), 0.5, dtype=torch.float64)
    dark = paint(rec, before, [Stroke([[1.0, 1.0], [8.0, 8.0]], Brush((-1.0, -1.0, -1.0), 4.0, 0.0))])
    assert bool((dark.target[dark.painted] < 0.5).all()) and bool((dark.target[~dark.painted] == 0.5).all())
    twice = paint(rec, before, [Stroke([[1.0, 1.0]], Brush(diameter=4.0, kappa=0.0, scale=2.0))])
    torch.testing.assert_close(twice.target[twice.painted], torch.full_like(twice.target[twice.painted], 1.0))


def test_display_coordinates_are_scaled():
    rec = _record()
    before = torch.zeros(rec.num_pixels, 3, dtype=torch.float64)
    a = paint(rec, before, [Stroke([[2.5, 4.5]], Brush(diameter=6.0, kappa=0.1))])
    b = paint(rec, before, [Stroke([[10.0, 18.0]], Brush(diameter=24.0, kappa=0.025))], display_size=(80, 40))
    torch.testing.assert_close(a.target, b.target)


def test_keep_weight_and_order():
    rec = _record()
    before = torch.zeros(rec.num_pixels, 3, dtype=torch.float64)
    brush = Brush((1.0, 1.0, 1.0), 4.0, 0.0)
    t = paint(rec, before, [Stroke([[2.0, 2.0]], brush)], keep_weight=0.0)
    assert torch.equal(t.weight, t.painted.double())
    over = paint(rec, before, [Stroke([[2.0, 2.0]], brush), Stroke([[2.0, 2.0]], Brush((0.0, 0, 0), 4.0, 0.0))])
    assert float(over.target.abs().max()) == 0.0  # the later stroke paints over the earlier one


def test_target_image_and_mask():
    rec = _record()
    before = torch.zeros(rec.num_pixels, 3, dtype=torch.float64)
    img = torch.full((20, 40, 3), 0.75, dtype=torch.float64)
    mask = torch.zeros(20, 40)
    mask[0:4, 0:4] = 1.0
    mask[4, 4] = 1.0  # a quarter of solving pixel (2, 2)
    t = target_from_image(rec, before, img, mask)
    assert int(t.painted.sum()) == 5
    torch.testing.assert_close(t.target[t.painted], torch.full((5, 3), 0.75, dtype=torch.float64))
    assert sorted(t.weight[t.painted].tolist()) == [0.25, 1.0, 1.0, 1.0, 1.0]


def test_odd_input():
    rec = _record()
    before = torch.zeros(rec.num_pixels, 3, dtype=torch.float64)
    with pytest.raises(ValueRangeError, match="no strokes"):
        paint(rec, before, [])
    with pytest.raises(ValueRangeError, match="no stroke touches"):
        paint(rec, before, [Stroke([[18.0, 5.0]], Brush(diameter=2.0))])  # right half: not the object
    with pytest.raises(ValueRangeError):
        Brush((math.nan, 0.0, 0.0))
    with pytest.raises(ValueRangeError):
        Stroke([[math.nan, 1.0]])
    with pytest.raises(ShapeError):
        Stroke(torch.zeros(0, 2))
    with pytest.raises(ValueRangeError):
        Brush(diameter=0.0)
    with pytest.raises(ShapeError):
        paint(rec, before[:3], [Stroke([[2.0, 2.0]])])
    with pytest.raises(ValueRangeError):
        target_from_image(rec, before, torch.zeros(10, 20, 3), torch.zeros(10, 20))
