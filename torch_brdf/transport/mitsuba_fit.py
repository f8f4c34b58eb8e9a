r"""The peer of :func:`torch_brdf.render.fit_image`: Mitsuba 3's differentiable path tracer.

The same inverse task as the polynomial fit: recover the Blinn-Phong ``kd`` and
``ks`` (RGB, exponent fixed) of one material of a scene from a target image, by Mitsuba's
optimisation loop: every step re-renders the scene with path replay backpropagation
(``prb`` integrator, Vicini et al. 2021) in ``llvm_ad_rgb``, back-propagates the weighted
mean squared error and takes one :class:`mi.ad.Adam` step, the values clamped to [0, 1].

The material is the bridge's Blinn-Phong Python BSDF
(:mod:`torch_brdf.transport.mitsuba`: our formula, checked there against our path tracer)
with ``kd`` and ``ks`` exposed as differentiable parameters, so both sides fit the same model.
Its sampling mixture weight stays the one of the starting material (a valid importance
sampler for every kd, ks; only the variance changes).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import ShapeError, ValueRangeError
from ..scene import Scene
from .mitsuba import BLINN_PHONG_PLUGIN, _blinn_phong_class, set_variant, to_mitsuba_dict

__all__ = ["MitsubaBlinnPhongFit", "MitsubaTrajectory"]

_DIFF_REGISTERED: set[str] = set()


def _register_differentiable(mi) -> None:
    """Register the bridge's Blinn-Phong BSDF with ``kd``/``ks`` traversed as differentiable
    (same evaluation and sampling; it replaces the plain registration for this variant)."""
    if mi.variant() in _DIFF_REGISTERED:
        return
    base = _blinn_phong_class(mi)

    class DifferentiableBlinnPhong(base):
        def traverse(self, callback):
            callback.put("kd", self.kd, mi.ParamFlags.Differentiable)
            callback.put("ks", self.ks, mi.ParamFlags.Differentiable)

        def parameters_changed(self, keys):
            pass

    mi.register_bsdf(BLINN_PHONG_PLUGIN, lambda props: DifferentiableBlinnPhong(props))
    _DIFF_REGISTERED.add(mi.variant())


@dataclass(frozen=True)
class MitsubaTrajectory:
    """What :meth:`MitsubaBlinnPhongFit.fit` returns.

    Attributes:
        kd: (steps + 1, C) kd before the first and after every step.
        ks: (steps + 1, C) ks likewise.
        seconds: (steps + 1,) wall-clock seconds of the loop up to each entry (0 first).
        losses: (steps,) the weighted MSE of each step's own noisy render.
    """

    kd: np.ndarray
    ks: np.ndarray
    seconds: np.ndarray
    losses: np.ndarray = field(repr=False)


class MitsubaBlinnPhongFit:
    """A loaded differentiable Mitsuba scene whose ``material`` (Blinn-Phong) is fitted.

    Args:
        scene: our scene; ``scene.materials[material]`` must be a Blinn-Phong dict (its kd, ks
            are only the initial values of the scene description).
        material: the material key of the fitted objects.
        max_bounces: surface vertices per path (``prb``'s ``max_depth`` is one more).
        variant: Mitsuba variant (``llvm_ad_rgb``: needs LLVM 19, Debian's ``libllvm19``).
    Raises:
        ImportError: Mitsuba is not installed.
        ValueRangeError: the material is not Blinn-Phong or no object uses it.
    """

    def __init__(self, scene: Scene, material: str, max_bounces: int = 4, variant: str = "llvm_ad_rgb"):
        if scene.materials.get(material, {}).get("type") != "blinn_phong":
            raise ValueRangeError(f"material {material!r} must be a Blinn-Phong material dict")
        self.mi = mi = set_variant(variant)
        _register_differentiable(mi)
        desc = to_mitsuba_dict(scene, 1, max_bounces)
        desc["integrator"] = {"type": "prb", "max_depth": int(max_bounces) + 1}
        self.scene = mi.load_dict(desc)
        self.params = mi.traverse(self.scene)
        objs = [f"obj_{i}." for i, o in enumerate(scene.objects) if o.material == material]
        self.keys = {
            p: [k for k in self.params.keys() if k.startswith(tuple(objs)) and k.endswith(f".{p}")]
            for p in ("kd", "ks")
        }
        if not self.keys["kd"]:
            raise ValueRangeError(f"no object of the scene uses material {material!r}")
        self.height, self.width = scene.camera.height, scene.camera.width

    def _set(self, kd, ks) -> None:
        mi = self.mi
        for p, v in (("kd", kd), ("ks", ks)):
            c = np.broadcast_to(np.asarray(v, dtype=np.float64), (3,))
            for k in self.keys[p]:
                self.params[k] = mi.Color3f(*[float(x) for x in c])
        self.params.update()

    def render(self, kd, ks, spp: int, seed: int = 0) -> torch.Tensor:
        """(H, W, 3) float32: Mitsuba's render with the material at ``kd``, ``ks`` (scalar or RGB)."""
        self._set(kd, ks)
        img = self.mi.render(self.scene, seed=int(seed), spp=int(spp))
        return torch.from_numpy(np.array(img, dtype=np.float32)[..., :3].copy())

    def fit(
        self,
        target,
        weights=None,
        kd0=0.5,
        ks0=0.0,
        steps: int = 100,
        spp: int = 16,
        lr: float = 0.02,
        seed: int = 0,
    ) -> MitsubaTrajectory:
        """Mitsuba's loop: ``steps`` x (render at ``spp`` with prb, weighted MSE, backward, Adam).

        Args:
            target: (H, W, 3) target image.
            weights: (H, W) painted-pixel weights >= 0 (default all ones); the loss is
                :math:`\\sum_p w_p \\|I_p - T_p\\|^2 / (3\\sum_p w_p)`.
            kd0: start of ``kd`` (scalar or RGB).
            ks0: start of ``ks`` (scalar or RGB).
            steps: Adam steps.
            spp: samples per pixel per step.
            lr: learning rate.
            seed: step ``i`` renders with seed ``seed + i + 1``.
        Returns:
            :class:`MitsubaTrajectory`; the kernels are compiled by one untimed 1-spp
            differentiable step before the clock starts.
        """
        import drjit as dr

        mi = self.mi
        t = torch.as_tensor(target, dtype=torch.float32)
        if t.shape != (self.height, self.width, 3):
            raise ShapeError(f"Expected target of shape ({self.height}, {self.width}, 3); got {tuple(t.shape)}")
        w = torch.ones(self.height, self.width) if weights is None else torch.as_tensor(weights, dtype=torch.float32)
        if w.shape != (self.height, self.width) or bool((w < 0).any()):
            raise ShapeError(f"Expected weights >= 0 of shape ({self.height}, {self.width}); got {tuple(w.shape)}")
        tgt = mi.TensorXf(t.numpy())
        wt = mi.TensorXf(np.repeat(w.numpy()[..., None], 3, -1) / (3.0 * float(w.sum())))
        self._set(kd0, ks0)
        opt = mi.ad.Adam(lr=lr)
        for p in ("kd", "ks"):
            for k in self.keys[p]:
                opt[k] = self.params[k]
        self.params.update(opt)

        def step(s, n):
            img = mi.render(self.scene, self.params, seed=s, spp=n)
            loss = dr.sum(wt * dr.square(img - tgt), axis=None)
            dr.backward(loss)
            return loss

        step(seed, 1)  # compile the kernels (not timed); the gradient is dropped below
        opt = mi.ad.Adam(lr=lr)
        for p in ("kd", "ks"):
            for k in self.keys[p]:
                opt[k] = self.params[k]
        self.params.update(opt)
        key_kd, key_ks = self.keys["kd"][0], self.keys["ks"][0]
        kd = [np.array(self.params[key_kd]).ravel().copy()]
        ks = [np.array(self.params[key_ks]).ravel().copy()]
        secs, losses = [0.0], []
        t0 = time.perf_counter()
        for i in range(steps):
            loss = step(seed + i + 1, spp)
            opt.step()
            for p in ("kd", "ks"):
                for k in self.keys[p]:
                    opt[k] = dr.clip(opt[k], 0.0, 1.0)
            self.params.update(opt)
            losses.append(float(np.array(loss).ravel()[0]))
            kd.append(np.array(self.params[key_kd]).ravel().copy())
            ks.append(np.array(self.params[key_ks]).ravel().copy())
            secs.append(time.perf_counter() - t0)
        return MitsubaTrajectory(np.stack(kd), np.stack(ks), np.array(secs), np.array(losses))
