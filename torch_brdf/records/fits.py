"""Saved fits: the BRDF manifold's GPLVM (:class:`GPLVMFit`) and the inverse-design SRBF fit (:class:`FitResult`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch

from .codec import Member, Record

__all__ = ["GPLVM_FIT_KIND", "INVERSE_FIT_KIND", "FitResult", "GPLVMFit"]

GPLVM_FIT_KIND = "gplvm-fit"
INVERSE_FIT_KIND = "inverse-fit"


@dataclass(frozen=True)
class GPLVMFit(Record):
    """Result of :func:`fit_gplvm` (frozen).

    Attributes:
        latents: (N, Q) float64 optimised latents :math:`X`.
        lengthscale, mu: kernel hyperparameters used (Eq. 5).
        jitter: extra diagonal added to K beyond ``mu`` to factorise it (0 when none was needed);
            interpolation uses :math:`\\mu + \\text{jitter}` consistently.
        loglik: (T,) float64 log-likelihood after each accepted iteration, starting with the
            initial latents; non-decreasing.
        d: number of columns of Z. data_scale: the factor ``S`` was divided by (1 = none).
        method: optimiser. iterations: accepted iterations. rejected: rejected steps.
        seconds: wall-clock time of the optimisation (informative only).
        names: optional row labels (material names).
    """

    latents: torch.Tensor
    lengthscale: float
    mu: float
    jitter: float
    loglik: torch.Tensor
    d: int
    data_scale: float = 1.0
    method: str = "lbfgs"
    iterations: int = 0
    rejected: int = 0
    seconds: float = 0.0
    names: tuple[str, ...] = ()
    meta: dict[str, Any] = field(default_factory=dict)

    kind = GPLVM_FIT_KIND
    version = 1
    schema: ClassVar[dict[str, Member]] = {"latents": Member("f", 2, finite=True), "loglik": Member("f", 1)}

    @property
    def q(self) -> int:
        return self.latents.shape[1]

    @property
    def n(self) -> int:
        return self.latents.shape[0]

    @property
    def final_loglik(self) -> float:
        return float(self.loglik[-1])

    @property
    def mu_effective(self) -> float:
        """:math:`\\mu` plus the jitter: the diagonal shift of the K that interpolation inverts."""
        return self.mu + self.jitter

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Latents, log-likelihood trace and settings for :meth:`save` (atomic, checksummed, no pickle)."""
        meta = {
            "lengthscale": self.lengthscale, "mu": self.mu, "jitter": self.jitter, "d": self.d,
            "data_scale": self.data_scale, "method": self.method, "iterations": self.iterations,
            "rejected": self.rejected, "seconds": self.seconds, "names": list(self.names), "meta": self.meta,
        }  # fmt: skip
        return {"latents": self.latents.numpy(), "loglik": self.loglik.numpy()}, meta

    @classmethod
    def from_arrays(cls, arrays, m) -> GPLVMFit:
        """The fit of :meth:`to_arrays` output (``load(path)``)."""
        x = torch.from_numpy(np.asarray(arrays["latents"], dtype=np.float64))
        ll = torch.from_numpy(np.asarray(arrays["loglik"], dtype=np.float64))
        if x.ndim != 2 or not bool(torch.isfinite(x).all()):
            raise ValueError("latents must be a finite (N, Q) array")
        return cls(
            x, float(m["lengthscale"]), float(m["mu"]), float(m["jitter"]), ll, int(m["d"]),
            float(m["data_scale"]), str(m["method"]), int(m["iterations"]), int(m["rejected"]),
            float(m["seconds"]), tuple(m.get("names", ())), dict(m.get("meta", {})),
        )  # fmt: skip


@dataclass(frozen=True)
class FitResult(Record):
    """Result of :func:`fit`.

    Attributes:
        coefficients: (J, 3) float64 SRBF coefficients of :math:`p(h)` per channel.
        kd: (3,) diffuse albedo used; f0: (3,) Fresnel :math:`F_0` of the record.
        objective: weighted sum of squares (all channels).
        violation: largest violation of :math:`c \\ge 0` and the energy rows (0 unconstrained).
        iterations: solver iterations (interior point or ADMM), summed over the channel problems.
        seconds: solve time (normal equations + QPs).
        constrained: whether the constraints were imposed.
        max_energy: :math:`\\max_l \\rho_d + \\sum_j g_j^l c_j` over channels (<= 1 when constrained).
    """

    coefficients: torch.Tensor
    kd: torch.Tensor
    f0: torch.Tensor
    objective: float
    violation: float
    iterations: int
    seconds: float
    constrained: bool
    max_energy: float
    meta: dict = field(default_factory=dict)

    kind = INVERSE_FIT_KIND
    version = 1
    schema: ClassVar[dict[str, Member]] = {
        "coefficients": Member("f", 2, finite=True),
        "kd": Member("f", 1, finite=True),
        "f0": Member("f", 1, finite=True),
    }

    def record_coefficients(self) -> torch.Tensor:
        """(J + 1, 3) coefficients for the transfer record: SRBF part and :math:`\\rho_d` last."""
        return torch.cat((self.coefficients, self.kd[None]), 0)

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Coefficients, albedo, F0 and the solve's figures for :meth:`save`."""
        arrays = {"coefficients": self.coefficients.numpy(), "kd": self.kd.numpy(), "f0": self.f0.numpy()}
        meta = {
            "objective": self.objective,
            "violation": self.violation,
            "iterations": self.iterations,
            "seconds": self.seconds,
            "constrained": self.constrained,
            "max_energy": self.max_energy,
            "meta": self.meta,
        }
        return arrays, meta

    @classmethod
    def from_arrays(cls, arrays, meta) -> FitResult:
        """The fit of :meth:`to_arrays` output (float64)."""
        t = {k: torch.from_numpy(v.copy()).double() for k, v in arrays.items()}
        return cls(
            t["coefficients"],
            t["kd"],
            t["f0"],
            float(meta["objective"]),
            float(meta["violation"]),
            int(meta["iterations"]),
            float(meta["seconds"]),
            bool(meta["constrained"]),
            float(meta["max_energy"]),
            dict(meta.get("meta", {})),
        )
