"""Planning the precomputation: the BRDF series and each object's editable basis.

:class:`Series` and :class:`ObjectBasis` travel with the saved record
(:mod:`torch_brdf.records.polynomial`); :func:`plan_bases` chooses the bases of a scene.
"""

from __future__ import annotations

from typing import Any

from ...errors import SceneError
from ...records.polynomial import ObjectBasis, Series
from ...scene.scene import Scene

__all__ = ["ObjectBasis", "Series", "plan_bases"]


def plan_bases(
    scene: Scene, series: Series, overrides: dict[str, dict[str, Any]] | None = None
) -> list[ObjectBasis | None]:
    """Choose each object's basis from its material: model only what the scene requires.

    * fixed objects (``editable=False``): None (their full BRDF is baked into path weights);
    * Lambertian materials: one band (an editable diffuse colour; its equivalent albedo is
      its albedo);
    * Blinn-Phong / Phong of exponent ``n``: ``series.eye`` bands of theta_h with spacing
      ``lobe:n`` (bands adapted to that lobe, 1.4% projection error at J = 64, n = 100);
    * anything else: ``series.eye`` bands of theta_h with MERL's ``sqrt`` spacing.

    ``overrides`` maps object names to :class:`ObjectBasis` fields (``J``, ``spacing``,
    ``quotient``, ``fresnel``, ``variable``), e.g. to make a diffuse wall glossy-editable.
    """
    overrides = dict(overrides or {})
    unknown = sorted(set(overrides) - {o.name for o in scene.objects})
    if unknown:
        raise SceneError(f"basis overrides name unknown objects: {unknown}")
    fields = ("J", "spacing", "quotient", "fresnel", "variable")
    for name, spec in overrides.items():
        if not isinstance(spec, dict):
            raise SceneError(f"basis override of {name!r} must be a table of {list(fields)}; got {spec!r}")
        bad = sorted(set(spec) - set(fields))
        if bad:
            raise SceneError(f"basis override of {name!r}: unknown keys {bad} (known: {list(fields)})")
    out: list[ObjectBasis | None] = []
    for obj in scene.objects:
        if not obj.editable:
            if obj.name in overrides:
                raise SceneError(f"object {obj.name!r} is fixed (editable=False); it has no basis to override")
            out.append(None)
            continue
        mat = scene.materials[obj.material]
        kind = mat.get("type")
        if kind == "lambert":
            spec: dict[str, Any] = {"J": 1, "spacing": "uniform"}
        elif kind in ("blinn_phong", "phong"):
            spec = {"J": series.eye, "spacing": f"lobe:{float(mat.get('exponent', 20.0)):g}"}
        else:
            spec = {"J": series.eye, "spacing": "sqrt"}
        spec.update(overrides.get(obj.name, {}))
        spec["J"] = int(min(spec["J"], series.eye)) if "J" not in overrides.get(obj.name, {}) else int(spec["J"])
        spec["second"] = min(series.second, spec["J"])
        out.append(ObjectBasis(**spec))
    return out
