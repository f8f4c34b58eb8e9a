r"""The BRDF base class, constrained parameters and the model registry.

Conventions (stated once, kept everywhere):

* ``eval(wi, wo, frame)`` returns the BRDF value :math:`f_r(\omega_i, \omega_o)` in 1/sr,
  RGB, **without** the cosine (pbrt's convention), shape ``(*B, 3)``.
* Directions are unit vectors pointing away from the surface. With ``frame=None`` they are
  already local (z = normal, see :mod:`torch_brdf.frame`); with a :class:`Frame` they are
  world-space and are rotated into it. ``f = 0`` when either direction is at or below the
  horizon (one-sided, reflection only).
* ``sample(wo, frame, u)`` draws ``wi`` from a density over solid angle and returns
  ``(wi, pdf)``; ``u`` is ``(*B, 2)`` uniforms in [0, 1). ``pdf = 0`` marks an invalid
  sample (below the horizon); then ``wi`` is still a finite unit vector.
* Parameters are stored raw (``raw_<name>``) and exposed through a transform
  (:class:`Positive`, :class:`Clamped`), like gpytorch's ``raw_lengthscale``; gradients
  flow to the raw tensors. Assigning ``model.<name> = value`` goes through the inverse
  transform and updates ``raw_<name>`` in place (gpytorch's ``lengthscale.setter``);
  out-of-range values raise :class:`~torch_brdf.errors.ValueRangeError`. Computation
  follows the dtype of the directions.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from ..errors import ShapeError, TorchBRDFError, ValueRangeError
from ..frame import Frame
from ..sphere.warps import cosine_hemisphere_pdf, square_to_cosine_hemisphere


class Positive:
    """``value = softplus(raw) + lower`` (strictly positive, smooth)."""

    def __init__(self, lower: float = 0.0):
        self.lower = float(lower)

    def forward(self, raw: torch.Tensor) -> torch.Tensor:
        return F.softplus(raw) + self.lower

    def inverse(self, value: torch.Tensor) -> torch.Tensor:
        v = value - self.lower
        if bool((v <= 0).any()):
            raise ValueRangeError(f"value must be > {self.lower}; got min {float(value.min())}")
        return v + torch.log(-torch.expm1(-v))


class Clamped:
    """``value = clamp(raw, lo, hi)``: exact at the bounds (albedo 0 and 1), gradient 0
    outside — the projected-constraint style of the fits."""

    def __init__(self, lo: float = 0.0, hi: float = 1.0):
        self.lo, self.hi = float(lo), float(hi)

    def forward(self, raw: torch.Tensor) -> torch.Tensor:
        return raw.clamp(self.lo, self.hi)

    def inverse(self, value: torch.Tensor) -> torch.Tensor:
        if bool(((value < self.lo) | (value > self.hi)).any()):
            raise ValueRangeError(f"value must lie in [{self.lo}, {self.hi}]; got {value.tolist()}")
        return value


_REGISTRY: dict[str, type[BRDF]] = {}


def register(name: str) -> Callable[[type[BRDF]], type[BRDF]]:
    """Class decorator: make a model creatable by ``create(name, ...)``."""

    def deco(cls: type[BRDF]) -> type[BRDF]:
        if name in _REGISTRY:
            raise ValueError(f"BRDF model {name!r} registered twice")
        _REGISTRY[name] = cls
        cls.model_name = name
        return cls

    return deco


def available() -> list[str]:
    """Names of the registered BRDF models."""
    return sorted(_REGISTRY)


def model_class(name: str) -> type[BRDF]:
    """The class registered as ``name`` (e.g. to list its parameters)."""
    if name not in _REGISTRY:
        raise ValueRangeError(f"unknown BRDF model {name!r}; available: {available()}")
    return _REGISTRY[name]


def model_parameters(name: str) -> list[str] | None:
    """The keyword parameters of model ``name``'s constructor (without ``self``), or None when
    it takes any keyword (``**kwargs``): what a material table of that type may hold besides
    ``type`` (the scene description's check and ``torch-brdf edit --set OBJECT.type=``).

    Raises:
        ValueRangeError: an unknown model.
    """
    import inspect

    params = inspect.signature(model_class(name).__init__).parameters.values()
    if any(p.kind is p.VAR_KEYWORD for p in params):
        return None
    return [p.name for p in params if p.name != "self" and p.kind is not p.VAR_POSITIONAL]


def create(spec: str | dict[str, Any], **params: Any) -> BRDF:
    """A BRDF from a registry name and parameters, or from a material dict
    ``{"type": name, **params}`` (the scene description's material tables)."""
    if isinstance(spec, dict):
        params = {**{k: v for k, v in spec.items() if k != "type"}, **params}
        spec = spec.get("type", "")
    if spec not in _REGISTRY:
        raise ValueRangeError(f"unknown BRDF model {spec!r}; available: {available()}")
    try:
        return _REGISTRY[spec](**params)
    except TorchBRDFError:
        raise
    except (TypeError, ValueError) as exc:  # an unknown keyword, a ragged list, ...
        raise ValueRangeError(f"bad parameters for BRDF model {spec!r}: {exc}") from exc


def _check_dirs(w: torch.Tensor, name: str) -> torch.Tensor:
    if not isinstance(w, torch.Tensor) or w.ndim < 1 or w.shape[-1] != 3 or not w.is_floating_point():
        got = f"{tuple(w.shape)} {w.dtype}" if isinstance(w, torch.Tensor) else repr(type(w))
        raise ShapeError(f"Expected {name} to be a floating tensor of shape (..., 3); got {got}")
    return w


class ConstrainedModule(nn.Module):
    """An ``nn.Module`` whose constrained parameters are stored raw behind a transform:
    :meth:`register_constrained` makes the Parameter ``raw_<name>`` that is read as
    ``self.<name>`` (gpytorch's ``raw_lengthscale`` pattern). BRDFs and half-vector
    distributions share it."""

    def __init__(self):
        super().__init__()
        self._constraints: dict[str, Positive | Clamped] = {}

    # -- parameters ------------------------------------------------------------------------
    def register_constrained(self, name: str, value, transform: Positive | Clamped, shape=()) -> None:
        """Store ``value`` as the Parameter ``raw_<name>`` behind ``transform``; the model
        reads it as ``self.<name>``. ``shape=(3,)`` broadcasts a scalar to RGB."""
        v = torch.as_tensor(value, dtype=torch.get_default_dtype())
        if not bool(torch.isfinite(v).all()):
            raise ValueRangeError(f"{type(self).__name__}.{name} must be finite; got {value!r}")
        try:
            v = v.expand(shape).clone() if shape else v.reshape(())
        except RuntimeError as exc:
            raise ShapeError(
                f"{type(self).__name__}.{name}: expected a scalar or shape {shape}; got {value!r}"
            ) from exc
        self._constraints[name] = transform
        self.register_parameter("raw_" + name, nn.Parameter(self._inverse(name, v)))

    def _inverse(self, name: str, value: torch.Tensor) -> torch.Tensor:
        """The raw value of ``value`` for constraint ``name``; a refusal names the parameter
        (the transforms alone said "value must lie in [0.0, 1.0]" without saying which)."""
        try:
            return self._constraints[name].inverse(value)
        except ValueRangeError as exc:
            raise ValueRangeError(f"{type(self).__name__}.{name}: {exc}") from None

    def __getattr__(self, name: str):
        cons = self.__dict__.get("_constraints")
        if cons is not None and name in cons:
            return cons[name].forward(super().__getattr__("raw_" + name))
        return super().__getattr__(name)

    def __setattr__(self, name: str, value) -> None:
        cons = self.__dict__.get("_constraints")
        if cons is not None and name in cons:
            self.set_constrained(name, value)
        else:
            super().__setattr__(name, value)

    def set_constrained(self, name: str, value) -> None:
        """Assign a constrained parameter through its inverse transform (gpytorch's
        ``lengthscale.setter``): ``model.<name> = value`` calls this. The Parameter
        ``raw_<name>`` is updated in place, so it stays the same Parameter (optimisers and
        ``state_dict`` see the new value) with its dtype, device and ``requires_grad``.

        Args:
            name: a name given to :meth:`register_constrained`.
            value: a scalar or a tensor broadcastable to the parameter's shape.
        Raises:
            ValueRangeError: ``value`` is not finite or outside the transform's range
                (e.g. a negative exponent, an albedo above 1); the parameter is unchanged.
            ShapeError: ``value`` does not broadcast to the parameter's shape.
        """
        raw = super().__getattr__("raw_" + name)
        v = torch.as_tensor(value).detach().to(device=raw.device, dtype=raw.dtype)
        if not bool(torch.isfinite(v).all()):
            raise ValueRangeError(f"{type(self).__name__}.{name} must be finite; got {value!r}")
        try:
            v = v.expand(raw.shape)
        except RuntimeError as exc:
            raise ShapeError(
                f"{type(self).__name__}.{name}: expected a scalar or shape {tuple(raw.shape)}; got {tuple(v.shape)}"
            ) from exc
        new_raw = self._inverse(name, v)
        with torch.no_grad():
            raw.copy_(new_raw)

    def params(self, dtype: torch.dtype) -> dict[str, torch.Tensor]:
        """The constrained parameters as tensors of ``dtype`` (for the math)."""
        return {k: getattr(self, k).to(dtype) for k in self._constraints}

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={getattr(self, k).detach().tolist()}" for k in self._constraints)


class BRDF(ConstrainedModule):
    """Base class of every BRDF model (see the module docstring for the conventions).

    Subclasses implement :meth:`eval_local` and, for importance sampling,
    :meth:`sample_local` and :meth:`pdf_local` (the default samples the cosine lobe).
    """

    model_name: str = "brdf"
    #: True if f depends on the azimuth of the half vector (needs a tangent frame).
    anisotropic: bool = False

    # -- the interface ---------------------------------------------------------------------
    def eval_local(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """f_r for local directions (*B, 3) -> (*B, 3); 0 below the horizon."""
        raise NotImplementedError

    def sample_local(self, wo: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Draw wi (*B, 3) given wo (*B, 3) and uniforms u (*B, 2); returns (wi, pdf (*B,))."""
        wi = square_to_cosine_hemisphere(u.reshape(-1, 2)).reshape(u.shape[:-1] + (3,))
        return wi, self.pdf_local(wi, wo)

    def pdf_local(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """Solid-angle density (*B,) of :meth:`sample_local`."""
        return torch.where(wo[..., 2] > 0, cosine_hemisphere_pdf(wi[..., 2]), torch.zeros_like(wi[..., 2]))

    def eval(self, wi: torch.Tensor, wo: torch.Tensor, frame: Frame | None = None) -> torch.Tensor:
        """f_r (*B, 3) without the cosine. wi, wo: (*B, 3), local if ``frame`` is None."""
        wi, wo = _check_dirs(wi, "wi"), _check_dirs(wo, "wo")
        if frame is not None:
            wi, wo = frame.to_local(wi), frame.to_local(wo)
        return self.eval_local(wi, wo)

    def sample(self, wo: torch.Tensor, frame: Frame | None, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Importance-sample wi for wo: returns (wi (*B, 3), pdf (*B,)), world-space if ``frame``."""
        wo = _check_dirs(wo, "wo")
        if u.shape != wo.shape[:-1] + (2,):
            raise ShapeError(f"Expected u to have shape {tuple(wo.shape[:-1]) + (2,)}; got {tuple(u.shape)}")
        wl = frame.to_local(wo) if frame is not None else wo
        wi, pdf = self.sample_local(wl, u.to(wl.dtype))
        return (frame.to_world(wi) if frame is not None else wi), pdf

    def pdf(self, wi: torch.Tensor, wo: torch.Tensor, frame: Frame | None = None) -> torch.Tensor:
        """Density (*B,) with which :meth:`sample` draws wi given wo."""
        wi, wo = _check_dirs(wi, "wi"), _check_dirs(wo, "wo")
        if frame is not None:
            wi, wo = frame.to_local(wi), frame.to_local(wo)
        return self.pdf_local(wi, wo)

    def albedo(self, wo: torch.Tensor, n: int = 64) -> torch.Tensor:
        r"""Directional albedo :math:`\int f(\omega_i, \omega_o)\cos\theta_i\,d\omega_i` for
        local wo (*B, 3) -> (*B, 3), by importance sampling on a fixed stratified
        :math:`n \times n` grid of ``u`` (deterministic; exact in expectation)."""
        wo = _check_dirs(wo, "wo")
        g = (torch.arange(n, dtype=wo.dtype) + 0.5) / n
        u = torch.stack(torch.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)  # (n*n, 2)
        wo_b = wo.unsqueeze(-2).expand(*wo.shape[:-1], n * n, 3)
        u_b = u.expand(*wo.shape[:-1], n * n, 2)
        wi, pdf = self.sample_local(wo_b, u_b)
        f = self.eval_local(wi, wo_b)
        w = torch.where(pdf > 0, wi[..., 2].clamp_min(0) / pdf.clamp_min(torch.finfo(wo.dtype).tiny), 0.0)
        return (f * w.unsqueeze(-1)).mean(-2)


def lambert_value(albedo: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    """albedo / pi where both directions are above the horizon, else 0: (*B, 3)."""
    up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    return torch.where(up.unsqueeze(-1), albedo / math.pi, torch.zeros((), dtype=wi.dtype))


@register("lambert")
class Lambert(BRDF):
    """The Lambertian BRDF :math:`\\rho/\\pi`.

    Args:
        albedo: RGB reflectance :math:`\\rho` in [0, 1] (scalar or 3 values), exposed as
            ``reflectance`` (``albedo(wo)`` is the directional albedo of every BRDF).
    """

    def __init__(self, albedo=0.5):
        super().__init__()
        self.register_constrained("reflectance", albedo, Clamped(0.0, 1.0), shape=(3,))

    def eval_local(self, wi, wo):
        return lambert_value(self.reflectance.to(wi.dtype), wi, wo)

    def albedo_exact(self, wo: torch.Tensor) -> torch.Tensor:
        """The exact directional albedo (*B, 3): rho above the horizon, else 0."""
        up = (wo[..., 2] > 0).unsqueeze(-1)
        return torch.where(up, self.reflectance.to(wo.dtype), torch.zeros((), dtype=wo.dtype))
