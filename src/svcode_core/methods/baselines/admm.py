"""LSV-ADMM: model-based CM² reconstruction with the full low-rank operator.

Solves

    min_x  ½‖A x − y‖² + λ TV(x)   subject to  x ≥ 0

with ``A`` the complete CM² forward model (:class:`~svcode_core.physics.cm2.CM2Operator`: nine
low-rank SV lens blurs, placement at the chief rays, sensor truncation), ``y`` the
zero-padded raw frame and ``TV`` the isotropic total variation with forward differences
(Neumann boundary). Torch throughout, so it runs on CUDA as well as on the CPU.

Splitting
---------
Three constraints, each with its own split variable and scaled dual:
``z₁ = A x`` (data), ``z₂ = ∇x`` (TV), ``z₃ = x`` (positivity). With penalties
``ρ·c_i`` the z-updates are closed form (a per-pixel average with the data, the isotropic
soft threshold, a clamp at 0), and the x-update solves

    (AᵀA + c₂ ∇ᵀ∇ + c₃ I) x = Aᵀ(z₁ − d₁) + c₂ ∇ᵀ(z₂ − d₂) + c₃ (z₃ − d₃).

``AᵀA`` is neither diagonal nor diagonalised by one FFT (spatially varying blur, sum over
lenses, truncation), so no closed form exists; the system is solved inexactly by a few
conjugate-gradient (CG) iterations warm-started at the previous ``x``. The weights
``c₂ = ‖A‖²/8`` and ``c₃ = ‖A‖²`` (``‖∇‖² ≤ 8``; ``‖A‖`` by power iteration) bound the
system's condition number by 3, so each CG step cuts the error by ≥ 3.7×, whatever the
operator: one step per ADMM iteration (the default) suffices in practice (inexact ADMM).
``A x`` is carried along by linearity (``A(x + αp) = Ax + α Ap``) so each CG step costs
one ``A`` and one ``Aᵀ``, and an ADMM iteration ``(n_cg + 1)`` adjoints and ``n_cg``
forwards.

Residuals, stopping and adaptive ρ
----------------------------------
Every ``check_every`` iterations the primal residual ``r = ‖(K x − z)‖_c`` and the dual
residual ``s = ρ‖Σ c_i K_iᵀ(z_i − z_i^prev)‖`` (Boyd et al. 2011, §3.3, in the
``c``-weighted norm) are computed; iteration stops when both are below ``tolerance``
relative to ``max(‖Kx‖, ‖z‖)`` and ``ρ Σ_i ‖c_i K_iᵀ d_i‖`` (the terms one by one: their
sum vanishes at the optimum because ``x`` has no objective term of its own). With
``adaptive_rho`` the common ``ρ`` is balanced when ``r`` and ``s`` differ by more than 10×
(Boyd §3.4.1), by the factor ``sqrt(r / s)`` clipped to ``[0.1, 10]`` (Wohlberg 2017) and
the scaled duals rescaled, so a starting ``ρ`` anywhere in ``[1e-4, 1e4]`` reaches its
working range within about 40 iterations.

The returned estimate is ``z₃`` (exactly non-negative). The objective is recorded every
iteration at the ``x`` iterate (cheap: ``A x`` is known).

Settings (:func:`settings_for`, the same for every system): the fixed ``λ = 1e-4`` from a
sweep ``λ ∈ {1e-5, 1e-4}`` on three benchmark scenes at 80 iterations (objects in ``[0, 1]``,
default sensor noise; the two agree within 0.05 dB, the data term dominates at this noise
level) on ``cm2-mini``, ``ρ = 0.1`` where the adaptive ``ρ`` settles on those scenes;
``cm2-v2`` uses the same values (‖A‖ ≈ 3 × mean transmission at both scales, since
every PSF is normalised to the lens's transmission), not separately tuned. The method's
defaults (:mod:`~svcode_core.methods.registry`: 50 iterations, the frame's own ``λ``)
are those of the benchmark's knee; the fixed ``λ`` is kept for comparisons and for the
solvers run inside other methods.

The TV weight from the frame (``tv_weight="auto"``, :func:`auto_tv_weight`)
----------------------------------------------------------------------------
A fixed ``λ`` suits one noise level only: at 200 photons a pixel it leaves LSV-ADMM
fitting the noise (its PSNR falls after 20 iterations in the benchmark). With Gaussian
noise of variance ``σ²`` the TV-regularised maximum a posteriori estimate has ``λ = β σ²``, where
the prior's ``β`` is the inverse of the object's scale. The frame gives both: ``σ̂`` by
:func:`~svcode_core.physics.noise.estimate_noise_std` and the scale by the frame's mean
``m``, so ``λ = γ σ̂² / m``; for shot noise ``σ̂² / m`` is the noise gain (the inverse
photon count per unit intensity), and ``λ`` scales with the frame as the object does.
``γ`` = :data:`AUTO_TV_GAIN` (2) was chosen on 8 validation objects of the training data
imaged at 200 photons a pixel (the ``low-light`` departures), with the default noise and
by the ``realistic`` instrument, comparing ``λ`` ∈ {1e-4, 1e-3, 3e-3, 1e-2} after 50
iterations (``bench/admm_tv_weight.py``): at low light the best ``λ`` over ``σ̂² / m`` has
median 2.0 (1e-2 best in 6 of 8 frames, +1.3 dB over 1e-4 on the mean); for the realistic
frames 1e-3 to 3e-3 are best (+0.25 dB), ``γ`` = 2 giving about 2e-3; at the default
noise ``γ`` = 2 gives about 1.6e-4, where 1e-4 to 1e-3 agree within 0.1 dB (1e-2 loses 0.4).
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Callable, Generator
from dataclasses import dataclass, field

import numpy as np
import torch

from ...config import SystemConfig
from ...physics.cm2 import CM2Operator
from ...physics.geometry import crop_to_sensor, pad_sensor_frame
from ...physics.noise import estimate_noise_std
from .. import registry
from ..tiling import exhaust

__all__ = [
    "AUTO_TV_GAIN",
    "AdmmResult",
    "AdmmSettings",
    "LsvAdmm",
    "gradient",
    "gradient_adjoint",
    "auto_tv_weight",
    "operator_norm",
    "settings_for",
    "total_variation",
]

RHO_BALANCE = 3.0
RHO_STEP = 10.0
#: ``γ`` of :func:`auto_tv_weight` (module docstring)
AUTO_TV_GAIN = 2.0
_ADMM = registry.method("admm")
_DEFAULTS = _ADMM.defaults


@dataclass(frozen=True)
class AdmmSettings:
    """Knobs of :class:`LsvAdmm` (see the module docstring).

    ``tv_weight`` is the fixed ``λ`` (the ``fixed`` of the method's option); the method's
    default is each frame's own (``"auto"``, :mod:`~svcode_core.methods.registry`), the
    other knobs are its defaults.
    """

    tv_weight: float = _ADMM.option("tv_weight").fixed
    rho: float = _DEFAULTS["rho"]
    iterations: int = _DEFAULTS["iterations"]
    tolerance: float = _DEFAULTS["tolerance"]
    cg_iterations: int = _DEFAULTS["cg_iterations"]
    adaptive_rho: bool = True
    check_every: int = 10


def settings_for(system: SystemConfig) -> AdmmSettings:
    """The settings for ``system``: those tuned on ``cm2-mini``, for every system (see the
    module docstring)."""
    return AdmmSettings()


def auto_tv_weight(frame: np.ndarray) -> float:
    """The TV weight ``λ = γ σ̂² / m`` for a raw sensor frame (module docstring): ``σ̂`` its
    estimated noise, ``m`` its mean, ``γ`` = :data:`AUTO_TV_GAIN`; 0 for a frame without
    signal.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> frame = rng.poisson(200 * np.full((120, 160), 0.25)) / 200  # 200 photons at 1
    >>> round(auto_tv_weight(frame), 3)  # about 2 / 200
    0.01
    >>> round(auto_tv_weight(1000 * frame) / auto_tv_weight(frame))  # in other units
    1000
    """
    mean = float(np.mean(frame, dtype=np.float64))
    if not mean > 0:
        return 0.0
    return AUTO_TV_GAIN * estimate_noise_std(frame) ** 2 / mean


@dataclass
class AdmmResult:
    """Outcome of :meth:`LsvAdmm.solve`.

    Attributes
    ----------
    x : torch.Tensor
        Non-negative estimate ``(S, S)``.
    objective : list of float
        ``½‖Ax − y‖² + λ TV(x)`` after every iteration.
    primal_residual, dual_residual : list of float
        Relative residuals at every check (every ``check_every`` iterations and the last).
    rho : list of float
        ``ρ`` in force after every check.
    iterations : int
        Iterations run.
    converged : bool
        Whether the tolerance was met (else the iteration count ran out).
    tv_weight : float
        The ``λ`` solved with (the frame's own with ``tv_weight="auto"``).
    """

    x: torch.Tensor
    objective: list[float] = field(default_factory=list)
    primal_residual: list[float] = field(default_factory=list)
    dual_residual: list[float] = field(default_factory=list)
    rho: list[float] = field(default_factory=list)
    iterations: int = 0
    converged: bool = False
    tv_weight: float = 0.0


def gradient(x: torch.Tensor) -> torch.Tensor:
    """Forward differences ``(..., 2, H, W)`` (rows, cols); zero across the last row/col."""
    grad = x.new_zeros(*x.shape[:-2], 2, *x.shape[-2:])
    grad[..., 0, :-1, :] = x[..., 1:, :] - x[..., :-1, :]
    grad[..., 1, :, :-1] = x[..., :, 1:] - x[..., :, :-1]
    return grad


def gradient_adjoint(grad: torch.Tensor) -> torch.Tensor:
    """Exact adjoint of :func:`gradient` (minus the divergence), ``(..., H, W)``."""
    rows, cols = grad[..., 0, :, :], grad[..., 1, :, :]
    out = torch.zeros_like(rows)
    out[..., :-1, :] -= rows[..., :-1, :]
    out[..., 1:, :] += rows[..., :-1, :]
    out[..., :, :-1] -= cols[..., :, :-1]
    out[..., :, 1:] += cols[..., :, :-1]
    return out


def _magnitude(grad: torch.Tensor) -> torch.Tensor:
    return torch.sqrt(grad[..., 0, :, :] ** 2 + grad[..., 1, :, :] ** 2)


def total_variation(x: torch.Tensor) -> torch.Tensor:
    """Isotropic total variation ``Σ |∇x|`` (a scalar tensor per image)."""
    return _magnitude(gradient(x)).sum(dim=(-2, -1))


def _soft_threshold(grad: torch.Tensor, threshold: float) -> torch.Tensor:
    """Proximal map of ``threshold · Σ |g|`` (isotropic group shrinkage)."""
    norm = _magnitude(grad)[..., None, :, :].clamp(min=torch.finfo(grad.dtype).tiny)
    return grad * (1.0 - threshold / norm).clamp(min=0.0)


def _dot(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a * b).sum())


#: ``operator_norm``'s estimates per operator and iteration count: a solver is built for
#: every run of the widget or a folder, on an operator the core keeps (1.4 s on cm2-mini)
_NORMS: weakref.WeakKeyDictionary[CM2Operator, dict[int, float]] = weakref.WeakKeyDictionary()


def operator_norm(operator: CM2Operator, iterations: int = 10) -> float:
    """Estimate ``‖A‖₂`` by power iteration on ``AᵀA`` started from a uniform object.

    A uniform object is close to the top singular vector of a non-negative blur, so a few
    iterations give the norm to a few per cent (it only sets the ADMM penalty weights).
    The estimate is kept for the operator's lifetime.
    """
    known = _NORMS.setdefault(operator, {})
    if iterations not in known:
        known[iterations] = _power_iteration(operator, iterations)
    return known[iterations]


def _power_iteration(operator: CM2Operator, iterations: int) -> float:
    size = operator.system.sub_view_size
    dtype, device = operator.lenses.dtype, operator.lenses.device
    x = torch.ones(size, size, dtype=dtype, device=device) / size
    value = 0.0
    for _ in range(iterations):
        x = operator.adjoint(operator.forward(x))
        value = float(x.norm())
        if value == 0.0:
            return 0.0
        x = x / value
    return math.sqrt(value)


class LsvAdmm:
    """LSV-ADMM solver for one CM² operator (the module docstring has the maths).

    Parameters
    ----------
    operator : CM2Operator
        Forward model; the solver runs in its dtype (float32/float64) and on its device.
    tv_weight : float or "auto"
        ``λ`` (≥ 0; 0 gives non-negative least squares), or ``"auto"`` for each frame's own
        (:func:`auto_tv_weight` of the frame's sensor part, module docstring).
    rho : float
        Starting penalty ``ρ`` (> 0).
    cg_iterations : int
        CG steps per x-update.
    adaptive_rho : bool
        Residual balancing of ``ρ``.
    check_every : int
        Iterations between residual checks (stopping test and ρ update).

    Examples
    --------
    >>> from svcode_core.config import SystemConfig
    >>> tiny = SystemConfig.tiny()  # sensor 60 × 80, sub-views 48 × 48
    >>> op = CM2Operator.from_system(tiny)
    >>> frame = op.forward(torch.rand(48, 48, dtype=op.lenses.dtype))  # padded frame
    >>> result = LsvAdmm(op, tv_weight=1e-4).solve(frame, iterations=10)
    >>> tuple(result.x.shape), bool(result.x.min() >= 0)
    ((48, 48), True)
    >>> result = LsvAdmm(op, tv_weight="auto").solve(frame, iterations=10)
    >>> result.tv_weight > 0  # this frame's λ
    True
    """

    def __init__(
        self,
        operator: CM2Operator,
        tv_weight: float | str,
        rho: float = _DEFAULTS["rho"],
        cg_iterations: int = _DEFAULTS["cg_iterations"],
        adaptive_rho: bool = True,
        check_every: int = 10,
    ) -> None:
        if not isinstance(operator, CM2Operator):
            raise TypeError(f"operator must be a CM2Operator, got {type(operator).__name__}")
        options = {"tv_weight": tv_weight, "rho": rho, "cg_iterations": cg_iterations}
        for name, value in options.items():
            _ADMM.option(name).check(value)
        if not isinstance(check_every, int) or check_every < 1:
            raise ValueError(f"check_every must be a positive integer, got {check_every!r}")
        self.operator = operator
        self.tv_weight = tv_weight if tv_weight == "auto" else float(tv_weight)
        self.rho = float(rho)
        self.cg_iterations = cg_iterations
        self.adaptive_rho = adaptive_rho
        self.check_every = check_every
        norm = operator_norm(operator)
        if norm == 0.0:
            raise ValueError("the operator is zero (no lens transmits light): nothing to invert")
        self.weights = (1.0, norm**2 / 8.0, norm**2)  # c₁, c₂, c₃

    def _adjoint(self, parts: list[torch.Tensor]) -> torch.Tensor:
        """``Σ c_i K_iᵀ v_i`` for ``parts = [v₁ (frame), v₂ (gradient field), v₃ (object)]``.

        Leading batch axes are allowed (the same on every part).
        """
        _, c_tv, c_id = self.weights
        return self.operator.adjoint(parts[0]) + c_tv * gradient_adjoint(parts[1]) + c_id * parts[2]

    def _frame(self, frame: torch.Tensor) -> torch.Tensor:
        system = self.operator.system
        dtype, device = self.operator.lenses.dtype, self.operator.lenses.device
        if not isinstance(frame, torch.Tensor):
            raise TypeError(f"frame must be a torch.Tensor, got {type(frame).__name__}")
        if tuple(frame.shape) != tuple(system.padded_shape):
            raise ValueError(
                f"frame must be the padded sensor frame {system.padded_shape}, got "
                f"{tuple(frame.shape)}"
            )
        if not frame.is_floating_point() or not bool(torch.isfinite(frame).all()):
            raise ValueError("frame must be a floating-point frame without NaN or Inf values")
        frame = frame.to(device=device, dtype=dtype)
        return pad_sensor_frame(crop_to_sensor(frame, system), system)

    def _tv_weight(self, frame: torch.Tensor) -> float:
        """``λ`` for a checked padded frame: the fixed one, or the frame's own."""
        if self.tv_weight != "auto":
            return self.tv_weight
        sensor = crop_to_sensor(frame, self.operator.system)
        return auto_tv_weight(sensor.detach().to("cpu", torch.float64).numpy())

    def objective(self, x: torch.Tensor, frame: torch.Tensor) -> float:
        """``½‖A x − y‖² + λ TV(x)`` for an object ``x`` and a padded frame ``y``."""
        y = self._frame(frame)
        residual = self.operator.forward(x) - y
        return 0.5 * _dot(residual, residual) + self._tv_weight(y) * float(total_variation(x))

    def solve(
        self,
        frame: torch.Tensor,
        x0: torch.Tensor | None = None,
        iterations: int = _DEFAULTS["iterations"],
        tolerance: float = _DEFAULTS["tolerance"],
        callback: Callable[[int, torch.Tensor], None] | None = None,
    ) -> AdmmResult:
        """Reconstruct one padded sensor frame (:meth:`iter_solve` run to the end).

        Parameters
        ----------
        frame : torch.Tensor
            Padded frame ``system.padded_shape`` (values outside the sensor are ignored).
        x0 : torch.Tensor, optional
            Warm start ``(S, S)`` (e.g. the result of a previous frame); default zeros.
        iterations : int
            Largest number of iterations.
        tolerance : float
            Relative primal and dual residual at which to stop (0: run all iterations).
        callback : callable, optional
            ``callback(iteration, estimate)`` after every iteration (estimate = ``z₃``).

        Returns
        -------
        AdmmResult

        Raises
        ------
        FloatingPointError
            If the iteration produces a non-finite objective (it never should).
        """
        return exhaust(self.iter_solve(frame, x0, iterations, tolerance, callback))

    def iter_solve(
        self,
        frame: torch.Tensor,
        x0: torch.Tensor | None = None,
        iterations: int = _DEFAULTS["iterations"],
        tolerance: float = _DEFAULTS["tolerance"],
        callback: Callable[[int, torch.Tensor], None] | None = None,
    ) -> Generator[int, None, AdmmResult]:
        """Generator form of :meth:`solve`: yields the number of iterations done after every
        iteration and returns the :class:`AdmmResult`; closing it stops between iterations.
        """
        _ADMM.option("iterations").check(iterations)
        _ADMM.option("tolerance").check(tolerance)
        op, c_tv = self.operator, self.weights[1]
        y = self._frame(frame)
        tv_weight = self._tv_weight(y)
        size = op.system.sub_view_size
        if x0 is None:
            x = y.new_zeros(size, size)
            ax = torch.zeros_like(y)
        else:
            if tuple(x0.shape) != (size, size) or not bool(torch.isfinite(x0).all()):
                raise ValueError(f"x0 must be a finite ({size}, {size}) object")
            x = x0.to(dtype=y.dtype, device=y.device).clone()
            ax = op.forward(x)
        z = [ax.clone(), gradient(x), x.clamp(min=0)]
        d = [torch.zeros_like(v) for v in z]
        rho = self.rho
        result = AdmmResult(x=z[2], tv_weight=tv_weight)
        for iteration in range(1, iterations + 1):
            # x-update: warm-started CG on the normal equations
            r = self._adjoint([z[0] - d[0] - ax, z[1] - d[1] - gradient(x), z[2] - d[2] - x])
            p, rr = r.clone(), _dot(r, r)
            for _ in range(self.cg_iterations):
                if rr <= torch.finfo(x.dtype).tiny:
                    break
                ap = op.forward(p)
                mp = self._adjoint([ap, gradient(p), p])
                alpha = rr / _dot(p, mp)
                x, ax, r = x + alpha * p, ax + alpha * ap, r - alpha * mp
                rr, rr_old = _dot(r, r), rr
                p = r + (rr / rr_old) * p
            # z- and dual updates
            grad = gradient(x)
            previous = z
            z = [
                (y + rho * (ax + d[0])) / (1.0 + rho),
                _soft_threshold(grad + d[1], tv_weight / (rho * c_tv)),
                (x + d[2]).clamp(min=0),
            ]
            image = [ax, grad, x]
            d = [di + ki - zi for di, ki, zi in zip(d, image, z, strict=True)]
            misfit = ax - y
            value = 0.5 * _dot(misfit, misfit) + tv_weight * float(_magnitude(grad).sum())
            if not math.isfinite(value):
                raise FloatingPointError(
                    f"LSV-ADMM diverged at iteration {iteration} (objective {value}); "
                    "check the frame and the operator"
                )
            result.objective.append(value)
            result.iterations = iteration
            if callback is not None:
                callback(iteration, z[2])
            yield iteration
            if iteration % self.check_every and iteration != iterations:
                continue
            primal, dual, scale_primal, scale_dual = self._residuals(image, z, previous, d, rho)
            result.primal_residual.append(primal / scale_primal if scale_primal else 0.0)
            result.dual_residual.append(dual / scale_dual if scale_dual else 0.0)
            if result.primal_residual[-1] <= tolerance and result.dual_residual[-1] <= tolerance:
                result.converged = True
                result.rho.append(rho)
                break
            if self.adaptive_rho and (primal > RHO_BALANCE * dual or dual > RHO_BALANCE * primal):
                ratio = math.sqrt(primal / dual) if dual > 0 else RHO_STEP
                factor = min(max(ratio, 1.0 / RHO_STEP), RHO_STEP)
                rho *= factor
                d = [di / factor for di in d]
            result.rho.append(rho)
        result.x = z[2]
        return result

    def _residuals(
        self,
        image: list[torch.Tensor],
        z: list[torch.Tensor],
        previous: list[torch.Tensor],
        d: list[torch.Tensor],
        rho: float,
    ) -> tuple[float, float, float, float]:
        """Primal and dual residuals and their scales (module docstring), c-weighted."""
        c = self.weights
        primal = sum(ci * _dot(k - zi, k - zi) for ci, k, zi in zip(c, image, z, strict=True))
        size_k = sum(ci * _dot(k, k) for ci, k in zip(c, image, strict=True))
        size_z = sum(ci * _dot(zi, zi) for ci, zi in zip(c, z, strict=True))
        # Σ c_i K_iᵀ Δz_i; the scale sums the norms of the terms c_i K_iᵀ d_i one by one (their
        # sum tends to 0 at the optimum, since x carries no objective term of its own)
        changes = [zi - pi for zi, pi in zip(z, previous, strict=True)]
        data_change, data_dual = self.operator.adjoint(torch.stack([changes[0], d[0]]))
        dual = data_change + c[1] * gradient_adjoint(changes[1]) + c[2] * changes[2]
        terms = (data_dual, c[1] * gradient_adjoint(d[1]), c[2] * d[2])
        scale = sum(float(term.norm()) for term in terms)
        return (
            math.sqrt(primal),
            rho * float(dual.norm()),
            math.sqrt(max(size_k, size_z)),
            (rho * scale),
        )
