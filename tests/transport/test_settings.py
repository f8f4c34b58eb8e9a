"""The producers' settings objects: frozen, checked when built, equal and hashed by value, and
a key that changes with every field (the resume keys are built from it)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from torch_brdf.errors import SceneError, ShapeError, ValueRangeError
from torch_brdf.records.polynomial import ObjectBasis, Series
from torch_brdf.scene.builtin import cornell_box
from torch_brdf.transport import PathTraceSettings, VisibilitySettings, path_trace, precompute_visibility
from torch_brdf.transport.polynomial import LobeMixture, PolynomialSettings, precompute_polynomial

#: one other value per field of PolynomialSettings (each must change the key)
OTHER = {
    "series": "8,1",
    "spp": torch.full((4, 4), 3),
    "bases": {"left": {"J": 2}},
    "mixture": LobeMixture(),
    "env_point_lights": 8,
    "light_samples": 2,
    "tile_rows": 2,
    "group": 1,
    "fixed": ("left",),
    "guides": False,
    "storage": "float16",
}


def test_polynomial_settings_are_values():
    a = PolynomialSettings("4,1", spp=8)
    b = PolynomialSettings(series=Series((4, 1)), spp=8)
    assert a == b and hash(a) == hash(b) and a.series == Series((4, 1))
    assert PolynomialSettings().series.bands == (64, 1, 1, 1) and PolynomialSettings().spp == 64
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.spp = 4
    m = torch.full((4, 4), 2)
    assert PolynomialSettings(spp=m) == PolynomialSettings(spp=m.clone())  # a map compares by value
    assert PolynomialSettings(spp=m).uniform and not PolynomialSettings(spp=torch.arange(1, 17).reshape(4, 4)).uniform
    assert a.replace(spp=4).spp == 4 and a.spp == 8


def test_every_field_changes_the_key():
    base = PolynomialSettings("4,1", spp=2)
    assert set(OTHER) == {f.name for f in dataclasses.fields(PolynomialSettings)}
    keys = {str(base.key())}
    for name, value in OTHER.items():
        keys.add(str(base.replace(**{name: value}).key()))
    assert len(keys) == len(OTHER) + 1
    basis = ObjectBasis(J=2, spacing="sqrt")
    assert base.replace(bases=[basis, None]).key()["bases"] == [basis.spec(), None]
    v = VisibilitySettings()
    assert len({str(v.key())} | {str(dataclasses.replace(v, **c).key()) for c in _vis_changes()}) == 6
    p = PathTraceSettings()
    changes = ({"spp": 2}, {"max_bounces": 2}, {"chunk": 99}, {"mis": False})
    assert len({str(p.key())} | {str(dataclasses.replace(p, **c).key()) for c in changes}) == 5


def _vis_changes():
    graded = ({"supersample": 2, "bits": 6}, {"supersample": 2, "bits": 2})
    return ({"resolution": 32}, {"block": 8}, *graded, {"chunk": 9})


@pytest.mark.parametrize(
    ("fields", "setting", "error"),
    [
        ({"series": "4,x"}, "series", ValueRangeError),
        ({"series": "1000000000,1"}, "series", ValueRangeError),
        ({"spp": 0}, "spp", ValueRangeError),
        ({"spp": torch.ones(4, 4) * 2}, "spp", ShapeError),  # a float map
        ({"spp": torch.zeros(4, 4, dtype=torch.long)}, "spp", ValueRangeError),
        ({"bases": {"left": {"Q": 1}}}, "bases", SceneError),
        ({"bases": [1]}, "bases", ValueRangeError),
        ({"mixture": "lobes"}, "mixture", ValueRangeError),
        ({"light_samples": 0}, "light_samples", ValueRangeError),
        ({"tile_rows": -1}, "tile_rows", ValueRangeError),
        ({"fixed": "left"}, "fixed", ValueRangeError),
        ({"guides": 1}, "guides", ValueRangeError),
        ({"storage": "float64"}, "storage", ValueRangeError),
    ],
)
def test_polynomial_settings_refuse_bad_values(fields, setting, error):
    with pytest.raises(error) as info:
        PolynomialSettings(**fields)
    assert info.value.setting == setting


def test_visibility_and_path_settings_refuse_bad_values():
    for fields, setting in (
        ({"resolution": 40}, "resolution"),  # not a multiple of the block
        ({"resolution": 2**20}, "resolution"),
        ({"bits": 3}, "bits"),
        ({"supersample": 2}, "supersample"),  # graded maps need bits
        ({"chunk": 0}, "chunk"),
    ):
        with pytest.raises(ValueRangeError) as info:
            VisibilitySettings(**fields)
        assert info.value.setting == setting
    for fields, setting in (({"spp": 0}, "spp"), ({"max_bounces": True}, "max_bounces"), ({"mis": "no"}, "mis")):
        with pytest.raises(ValueRangeError) as info:
            PathTraceSettings(**fields)
        assert info.value.setting == setting


def test_settings_given_one_by_one_are_refused_clearly():
    sc = cornell_box(8)
    with pytest.raises(TypeError, match=r"PolynomialSettings\(series='64,1,1,1', spp=64\).*got spp"):
        precompute_polynomial(sc, spp=4)
    with pytest.raises(TypeError, match="got '4,1'"):
        precompute_polynomial(sc, "4,1")
    with pytest.raises(TypeError, match="the planner"):
        precompute_polynomial(sc, plan="auto", error=0.1)
    with pytest.raises(TypeError, match="VisibilitySettings"):
        precompute_visibility(sc, 32)
    with pytest.raises(TypeError, match="PathTraceSettings"):
        path_trace(sc, spp=4)


def test_an_spp_map_must_fit_the_camera():
    sc = cornell_box(8)
    with pytest.raises(ShapeError, match=r"shape \(8, 8\)"):
        precompute_polynomial(sc, PolynomialSettings("2,1", spp=torch.full((4, 4), 2)), progress=False)
