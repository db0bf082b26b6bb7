"""Shift-invariant deconvolution baselines: Wiener and Richardson–Lucy per view, then fusion.

The classical approach that ignores the spatial variance of the PSF and the crosstalk
between lenses (design.md §4):

1. cut the nine ``S × S`` sub-views out of the zero-padded raw frame; sub-view ``ℓ`` is
   co-registered with the object grid for lens ``ℓ`` by construction (it is centred on the
   chief ray), so no further registration is needed;
2. deconvolve sub-view ``ℓ`` with **one** PSF, lens ``ℓ``'s PSF at the object centre
   ``r = 0`` (``Σ_k w_{ℓ,k}(0) h_{ℓ,k}`` of the low-rank model), its small negative
   values from the rank truncation set to 0, normalised to unit sum
   (:func:`unit_centre_psfs`).
   Because lens ``ℓ``'s image of pixel ``r`` carries the lens's transmission ``T_ℓ(r)``
   (vignetting: the PSF's total energy there), the deconvolved view estimates
   ``T_ℓ(r) x(r)``;
3. fuse by least squares over the lenses that see each pixel::

       x(r) = Σ_ℓ c_ℓ(r) T_ℓ(r) d_ℓ(r) / Σ_ℓ c_ℓ(r) T_ℓ(r)²

   with ``d_ℓ`` the deconvolved views and ``c_ℓ(r) ∈ {0, 1}`` whether that pixel of
   sub-view ``ℓ`` lies on the sensor. This corrects vignetting and weights each view by its
   signal; pixels that no lens sees with at least ``1e-6`` of the best total weight are 0;
4. bring the result to the object's units: divide it by the same reconstruction of the
   frame a uniform object of value 1 gives (through the operator), pixel by pixel. Each
   sub-view also holds the light its neighbours' lenses cast into it (the crosstalk these
   methods do not model), so without this step the fused image is several times the
   object (about 4.5× on average for ``cm2-mini``, 2.7× in the centre and more towards
   the edges); with it, a uniform object comes back as itself. No single scale fits every
   scene, because the crosstalk lands elsewhere than the object that casts it: an
   extended scene (tissue, cells) comes out near its own level, an isolated bright object
   at about a third of it on ``cm2-mini`` (its flux divided by the response there).

The per-view filters follow scikit-image's conventions exactly, so that on a truly
shift-invariant image they agree with it:

* :func:`wiener_deconvolve` = ``skimage.restoration.wiener(image, psf, balance,
  clip=False)``: ``conj(H) / (|H|² + balance·|L|²)`` with ``L`` the discrete Laplacian,
  circular (periodic) boundary. ``boundary="reflect"`` first mirrors each view by the
  kernel size, which removes most wrap-around artefacts at the view's edges;
* :func:`richardson_lucy_deconvolve` = ``skimage.restoration.richardson_lucy(image, psf,
  num_iter, clip=False)``: start at 0.5 everywhere, linear convolution with zero boundary,
  ``1e-12`` added to the blurred estimate before the division. Negative readings are set to
  0 first (RL needs non-negative data).
"""

from __future__ import annotations

import functools
from collections.abc import Generator

import torch

from ...physics.cm2 import CM2Operator
from ...physics.geometry import extract_sub_views, pad_sensor_frame
from ...physics.lowrank import fft_shape
from .. import registry
from ..tiling import exhaust

__all__ = [
    "ShiftInvariantDeconvolution",
    "centre_psfs",
    "fuse_views",
    "iter_richardson_lucy",
    "lens_transmission",
    "richardson_lucy_deconvolve",
    "unit_centre_psfs",
    "wiener_deconvolve",
]

RL_EPSILON = 1e-12
FUSION_FLOOR = 1e-6
_WIENER, _RL = registry.method("wiener"), registry.method("rl")
#: the Wiener filter's boundary handling (its ``boundary`` option's choices)
BOUNDARIES = _WIENER.option("boundary").choices


def _centred_spectra(kernels: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """Real FFTs (size ``shape``) of odd kernels ``(..., h, w)`` with their centre at (0, 0)."""
    height, width = kernels.shape[-2:]
    padded = kernels.new_zeros(*kernels.shape[:-2], *shape)
    padded[..., :height, :width] = kernels
    padded = torch.roll(padded, shifts=(-(height // 2), -(width // 2)), dims=(-2, -1))
    return torch.fft.rfft2(padded)


def _check_images(images: torch.Tensor, psfs: torch.Tensor) -> None:
    for name, tensor in (("images", images), ("psfs", psfs)):
        if not isinstance(tensor, torch.Tensor) or tensor.dtype not in (
            torch.float32,
            torch.float64,
        ):
            raise ValueError(
                f"{name} must be a float32 or float64 torch.Tensor (FFT-based deconvolution "
                f"has no half-precision path), got {getattr(tensor, 'dtype', type(tensor))}"
            )
        if not bool(torch.isfinite(tensor).all()):
            raise ValueError(f"{name} contains NaN or Inf values")
    if images.ndim < 2 or psfs.ndim < 2 or images.shape[:-2] != psfs.shape[:-2]:
        raise ValueError(
            f"images (..., H, W) and psfs (..., h, w) must share leading axes, got "
            f"{tuple(images.shape)} and {tuple(psfs.shape)}"
        )
    height, width = psfs.shape[-2:]
    if height % 2 == 0 or width % 2 == 0:
        raise ValueError(f"PSF sizes must be odd, got {height}x{width}")


def wiener_deconvolve(
    images: torch.Tensor, psfs: torch.Tensor, balance: float, boundary: str = "periodic"
) -> torch.Tensor:
    """Wiener–Hunt deconvolution with a Laplacian regulariser, one PSF per image.

    Parameters
    ----------
    images : torch.Tensor
        ``(..., H, W)``, float32 or float64.
    psfs : torch.Tensor
        ``(..., h, w)`` with the same leading axes, odd sizes, centre at ``(h//2, w//2)``.
    balance : float
        Regularisation weight (> 0): larger is smoother.
    boundary : {"periodic", "reflect"}
        Periodic is scikit-image's convention; reflect mirrors each image by the kernel size
        before filtering and crops afterwards.

    Returns
    -------
    torch.Tensor
        Same shape and dtype as ``images``.
    """
    _check_images(images, psfs)
    _WIENER.option("balance").check(balance)
    _WIENER.option("boundary").check(boundary)
    rows, cols = images.shape[-2:]
    pad_r, pad_c = (min(psfs.shape[-2], rows - 1), min(psfs.shape[-1], cols - 1))
    if boundary == "reflect":
        flat = images.reshape(-1, 1, rows, cols)
        flat = torch.nn.functional.pad(flat, (pad_c, pad_c, pad_r, pad_r), mode="reflect")
        images = flat.reshape(*images.shape[:-2], *flat.shape[-2:])
    shape = tuple(images.shape[-2:])
    transfer = _centred_spectra(psfs, shape)
    laplacian = psfs.new_tensor([[0.0, -1.0, 0.0], [-1.0, 4.0, -1.0], [0.0, -1.0, 0.0]])
    regulariser = _centred_spectra(laplacian, shape).real
    gain = transfer.conj() / (transfer.abs() ** 2 + balance * regulariser**2)
    result = torch.fft.irfft2(gain * torch.fft.rfft2(images), s=shape)
    if boundary == "reflect":
        result = result[..., pad_r : pad_r + rows, pad_c : pad_c + cols]
    return result


def richardson_lucy_deconvolve(
    images: torch.Tensor, psfs: torch.Tensor, iterations: int
) -> torch.Tensor:
    """Richardson–Lucy deconvolution, one PSF per image, zero boundary.

    Parameters
    ----------
    images : torch.Tensor
        ``(..., H, W)``, float32 or float64; negative values are treated as 0.
    psfs : torch.Tensor
        ``(..., h, w)`` with the same leading axes, odd sizes, non-negative.
    iterations : int
        Number of multiplicative updates (``num_iter`` of scikit-image), at least 1.

    Returns
    -------
    torch.Tensor
        Same shape and dtype as ``images``, non-negative.
    """
    return exhaust(iter_richardson_lucy(images, psfs, iterations))


def iter_richardson_lucy(
    images: torch.Tensor, psfs: torch.Tensor, iterations: int
) -> Generator[int, None, torch.Tensor]:
    """Generator form of :func:`richardson_lucy_deconvolve`: yields the number of updates
    done after every update and returns the estimate; closing it stops between updates."""
    _check_images(images, psfs)
    _RL.option("iterations").check(iterations)
    if bool((psfs < 0).any()):
        raise ValueError("Richardson–Lucy needs non-negative PSFs")
    rows, cols = images.shape[-2:]
    height, width = psfs.shape[-2:]
    shape = fft_shape((rows, cols), (height, width))
    spectra = _centred_spectra(psfs, shape)

    def blur(image: torch.Tensor, spectrum: torch.Tensor) -> torch.Tensor:
        return torch.fft.irfft2(torch.fft.rfft2(image, s=shape) * spectrum, s=shape)[
            ..., :rows, :cols
        ]

    data = images.clamp(min=0)
    estimate = torch.full_like(data, 0.5)
    for iteration in range(1, iterations + 1):
        ratio = data / (blur(estimate, spectra) + RL_EPSILON)
        estimate = estimate * blur(ratio, spectra.conj())
        yield iteration
    return estimate.clamp(min=0)  # FFT round-off can leave tiny negatives


def centre_psfs(operator: CM2Operator) -> torch.Tensor:
    """Each lens's PSF at the object centre, from the low-rank model, ``(9, h, w)``."""
    centre = operator.margin + operator.system.sub_view_size // 2
    pixel = slice(centre, centre + 1)
    weights = operator.lenses.weight_maps(pixel, pixel)[..., 0, 0]  # (9, K)
    return torch.einsum("lk,lkij->lij", weights, operator.lenses.kernels)


def unit_centre_psfs(operator: CM2Operator) -> torch.Tensor:
    """:func:`centre_psfs` clipped at zero and normalised to unit sum, ``(9, h, w)``.

    The rank truncation leaves small negative values, which are set to 0. A lens without
    light at the centre gets a unit impulse (its fusion weight is 0 anyway).
    """
    psfs = centre_psfs(operator).clamp(min=0)
    energy = psfs.sum(dim=(-2, -1), keepdim=True)
    impulse = torch.zeros_like(psfs)
    impulse[:, psfs.shape[-2] // 2, psfs.shape[-1] // 2] = 1.0
    tiny = torch.finfo(psfs.dtype).tiny
    return torch.where(energy > 0, psfs / energy.clamp(min=tiny), impulse)


def lens_transmission(operator: CM2Operator) -> torch.Tensor:
    """Transmission ``T_ℓ(r)`` (total PSF energy) of each lens at every object pixel, (9, S, S)."""
    m, size = operator.margin, operator.system.sub_view_size
    inner = slice(m, m + size)
    return operator.lenses.weight_maps(inner, inner, mix=operator.lenses.kernels.sum(dim=(-2, -1)))


def fuse_views(
    deconvolved: torch.Tensor, transmission: torch.Tensor, coverage: torch.Tensor
) -> torch.Tensor:
    """Least-squares fusion of the nine deconvolved views (module docstring, step 3).

    Parameters
    ----------
    deconvolved : torch.Tensor
        ``(..., 9, S, S)``, each an estimate of ``T_ℓ x``.
    transmission : torch.Tensor
        ``T_ℓ`` ``(9, S, S)``.
    coverage : torch.Tensor
        ``(9, S, S)``, 1 where the sub-view pixel lies on the sensor, else 0.

    Returns
    -------
    torch.Tensor
        ``(..., S, S)``.
    """
    weight = coverage * transmission
    denominator = (weight * transmission).sum(dim=-3)
    seen = denominator > FUSION_FLOOR * denominator.max().clamp(min=torch.finfo(weight.dtype).tiny)
    numerator = (weight * deconvolved).sum(dim=-3)
    return torch.where(seen, numerator / torch.where(seen, denominator, 1.0), 0.0)


class ShiftInvariantDeconvolution:
    """Per-view Wiener or Richardson–Lucy deconvolution of CM² frames, fused into one image.

    Parameters
    ----------
    operator : CM2Operator
        Supplies the geometry, each lens's centre PSF and its transmission map.
    method : {"wiener", "rl"}
    balance : float
        Wiener regularisation weight (default: the method's, :mod:`~svcode_core.methods.registry`).
    iterations : int
        Richardson–Lucy iterations (default: the method's).
    boundary : {"reflect", "periodic"}
        Wiener boundary handling (RL always uses a zero boundary).

    Examples
    --------
    >>> from svcode_core.config import SystemConfig
    >>> tiny = SystemConfig.tiny()  # sensor 60 × 80, sub-views 48 × 48
    >>> op = CM2Operator.from_system(tiny)
    >>> deconv = ShiftInvariantDeconvolution(op, "rl", iterations=5)
    >>> frame = op.forward(torch.rand(48, 48, dtype=op.lenses.dtype))  # padded frame
    >>> deconv(frame).shape
    torch.Size([48, 48])
    """

    def __init__(
        self,
        operator: CM2Operator,
        method: str,
        balance: float = _WIENER.defaults["balance"],
        iterations: int = _RL.defaults["iterations"],
        boundary: str = _WIENER.defaults["boundary"],
    ) -> None:
        if method not in ("wiener", "rl"):
            raise ValueError(f"method must be 'wiener' or 'rl', got {method!r}")
        self.operator = operator
        self.method = method
        self.balance = balance
        self.iterations = iterations
        self.boundary = boundary
        self.psfs = unit_centre_psfs(operator)
        self.transmission = lens_transmission(operator)
        system = operator.system
        sensor = torch.ones(system.sensor_shape, dtype=self.psfs.dtype, device=self.psfs.device)
        self.coverage = extract_sub_views(pad_sensor_frame(sensor, system), system)

    @property
    def steps(self) -> int:
        """The steps :meth:`iter_solve` reports for a frame: RL's iterations; Wiener's 1."""
        return 1 if self.method == "wiener" else self.iterations

    def deconvolve_views(self, views: torch.Tensor) -> torch.Tensor:
        """Deconvolve nine sub-views ``(..., 9, S, S)`` with their lenses' centre PSFs."""
        return exhaust(self._iter_deconvolve(views))

    def _iter_deconvolve(self, views: torch.Tensor) -> Generator[int, None, torch.Tensor]:
        psfs = self.psfs.expand(*views.shape[:-2], *self.psfs.shape[-2:])
        if self.method == "wiener":
            return wiener_deconvolve(views, psfs, self.balance, self.boundary)
        return (yield from iter_richardson_lucy(views, psfs, self.iterations))

    def __call__(self, frame: torch.Tensor) -> torch.Tensor:
        """Reconstruct from a padded sensor frame ``(..., H_pad, W_pad)`` → ``(..., S, S)``."""
        return exhaust(self.iter_solve(frame))

    def iter_solve(self, frame: torch.Tensor) -> Generator[int, None, torch.Tensor]:
        """Generator form of calling it: yields the RL iterations done after every one
        (nothing for Wiener) and returns the reconstruction; closing it stops between them."""
        views = extract_sub_views(frame, self.operator.system)
        deconvolved = yield from self._iter_deconvolve(views)
        fused = fuse_views(deconvolved, self.transmission, self.coverage)
        flat = self.flat_response
        return torch.where(flat > 0, fused / torch.where(flat > 0, flat, 1.0), 0.0)

    @functools.cached_property
    def flat_response(self) -> torch.Tensor:
        """Steps 1–3 applied to the frame of a uniform object of value 1 ``(S, S)``: what
        the output is divided by (0 where no lens sees the pixel)."""
        size = self.operator.system.sub_view_size
        ones = torch.ones(size, size, dtype=self.psfs.dtype, device=self.psfs.device)
        with torch.no_grad():
            views = extract_sub_views(self.operator.forward(ones), self.operator.system)
            deconvolved = exhaust(self._iter_deconvolve(views))
            return fuse_views(deconvolved, self.transmission, self.coverage)
