"""Low-rank spatially varying (SV) blur of one or several lenses.

A lens's PSF varies smoothly over the field. Known on a ``G × G`` grid of object
positions, the PSFs are factorised by an SVD into ``K`` basis kernels ``h_k`` and grid
weights ``W_k``; the weights are interpolated to every object pixel as coefficient maps
``w_k(r) = Σ_g φ_g(r) W_k[g]``, so that the PSF of pixel ``r`` is
``PSF(r) ≈ Σ_k w_k(r) h_k`` and the lens image of an object ``x`` is

    v = Σ_k h_k ∗ (w_k ⊙ x)

(:class:`LowRankSVOperator`, FFT convolution, linear with zero boundary, output the
size of the input). With ``K`` equal to the full rank of the PSF grid this equals the
exact per-pixel SV convolution of :func:`svcode_core.physics.reference.sv_convolve_reference`
with the same interpolation basis ``φ``; at smaller ``K`` the difference is the
truncation alone.

Conventions
-----------
* Kernels have odd sizes ``(h, w)`` and act by true convolution with their centre at
  index ``(h // 2, w // 2)``: a unit object pixel at ``p`` gives back the kernel with its
  centre at ``p``.
* PSF grids are arrays ``(G·G, h, w)``; grid node ``g = a·G + b`` sits at normalised
  object position ``(v, u) = (t_a, t_b)`` with ``t = linspace(-1, 1, G)`` (``v`` outer).
* Object pixel ``i`` of an ``S``-pixel axis sits at ``2 i / (S - 1) - 1``
  (:func:`svcode_core.physics.geometry.normalized_coordinates`); margin pixels continue the line
  beyond ``[-1, 1]`` and take the edge value of the interpolated weights.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ..config import DEFAULT_MEMORY_BUDGET
from .geometry import normalized_coordinates

__all__ = [
    "DEFAULT_MEMORY_BUDGET",
    "InterpolatedMaps",
    "ChunkPlan",
    "LowRankSVOperator",
    "PSFDecomposition",
    "coefficient_maps",
    "decompose_psfs",
    "fft_shape",
    "interpolation_basis",
    "plan_chunks",
]

_REAL_DTYPES = (torch.float32, torch.float64)



def _pair(value: int | Sequence[int], name: str) -> tuple[int, int]:
    pair = (value, value) if isinstance(value, (int, np.integer)) else tuple(value)
    if len(pair) != 2 or any(not isinstance(v, (int, np.integer)) or v < 1 for v in pair):
        raise ValueError(f"{name} must be a positive integer or a (rows, cols) pair, got {value!r}")
    return int(pair[0]), int(pair[1])


def _grid_side(n_psfs: int) -> int:
    side = int(round(np.sqrt(n_psfs)))
    if side * side != n_psfs:
        raise ValueError(f"the PSF grid must hold G*G PSFs, got {n_psfs}")
    return side


def interpolation_basis(n_grid: int, size: int, margin: int = 0, order: int = 3) -> np.ndarray:
    """1-D cardinal functions interpolating ``n_grid`` grid nodes onto the pixels of an axis.

    Grid node ``g`` sits at ``linspace(-1, 1, n_grid)[g]``; pixel ``i`` (``-margin ≤ i <
    size + margin``) at ``2 i / (size - 1) - 1``. A value ``f`` known on the nodes is
    interpolated as ``f(i) = Σ_g basis[g, i] f_g``; on a 2-D grid the interpolation is
    the tensor product, ``w(i, j) = Σ_{a,b} basis_rows[a, i] basis_cols[b, j] W[a, b]``.

    Parameters
    ----------
    n_grid : int
        Number of grid nodes ``G`` along the axis (``G = 1``: a constant).
    size : int
        Number of object pixels ``S`` along the axis, at least 2.
    margin : int
        Extra pixels on each side; their coordinates are clamped to ``[-1, 1]``, so they
        take the edge value.
    order : {1, 3}
        1: piecewise-linear tent functions (bilinear in 2-D). 3: cardinal functions of the
        not-a-knot cubic spline, which reproduce cubic polynomials exactly (for ``G ≥ 4``;
        with ``G = 2`` or 3 the spline is the interpolating line or parabola).

    Returns
    -------
    numpy.ndarray
        Float64, shape ``(n_grid, size + 2·margin)``; every column sums to 1.

    Examples
    --------
    >>> interpolation_basis(3, 5, order=1).round(2)
    array([[1. , 0.5, 0. , 0. , 0. ],
           [0. , 0.5, 1. , 0.5, 0. ],
           [0. , 0. , 0. , 0.5, 1. ]])
    """
    if not isinstance(n_grid, (int, np.integer)) or n_grid < 1:
        raise ValueError(f"n_grid must be a positive integer, got {n_grid!r}")
    if not isinstance(margin, (int, np.integer)) or margin < 0:
        raise ValueError(f"margin must be a non-negative integer, got {margin!r}")
    if order not in (1, 3):
        raise ValueError(f"order must be 1 (linear) or 3 (cubic), got {order!r}")
    coords = normalized_coordinates(
        size, start=-margin, length=size + 2 * margin, dtype=torch.float64
    ).numpy()
    coords = np.clip(coords, -1.0, 1.0)
    if n_grid == 1:
        return np.ones((1, coords.size))
    nodes = np.linspace(-1.0, 1.0, n_grid)
    if order == 1:
        position = (coords + 1.0) * (0.5 * (n_grid - 1))
        return np.maximum(0.0, 1.0 - np.abs(position[None, :] - np.arange(n_grid)[:, None]))
    from scipy.interpolate import CubicSpline  # here: it takes 0.3 s to import

    spline = CubicSpline(nodes, np.eye(n_grid), axis=0, bc_type="not-a-knot")
    return np.ascontiguousarray(spline(coords).T)


def coefficient_maps(
    grid_weights: np.ndarray,
    size: int | Sequence[int],
    margin: int = 0,
    order: int = 3,
) -> np.ndarray:
    """Interpolate grid weights ``(K, G_r, G_c)`` to every object pixel.

    Parameters
    ----------
    grid_weights : array_like
        Shape ``(K, G_r, G_c)`` (usually square, ``G_r = G_c = G``).
    size : int or (int, int)
        Object grid size ``S`` (or ``(rows, cols)``) without the margin.
    margin : int
        Extra pixels on every side (edge values, see :func:`interpolation_basis`).
    order : {1, 3}
        Interpolation order, see :func:`interpolation_basis`.

    Returns
    -------
    numpy.ndarray
        Float64 coefficient maps ``w_k``, shape ``(K, rows + 2·margin, cols + 2·margin)``.
    """
    grid_weights = np.asarray(grid_weights, dtype=np.float64)
    if grid_weights.ndim != 3:
        raise ValueError(f"grid_weights must have shape (K, G, G), got {grid_weights.shape}")
    rows, cols = _pair(size, "size")
    basis_rows = interpolation_basis(grid_weights.shape[1], rows, margin, order)
    basis_cols = interpolation_basis(grid_weights.shape[2], cols, margin, order)
    return np.einsum("ai,kab,bj->kij", basis_rows, grid_weights, basis_cols, optimize=True)


@dataclass(frozen=True)
class PSFDecomposition:
    """Rank-``K`` factorisation of one lens's PSF grid, ``PSF_g ≈ Σ_k W_k[g] h_k``.

    Attributes
    ----------
    kernels : numpy.ndarray
        Basis kernels ``h_k``, shape ``(K, h, w)``, unit L2 norm (zero for a zero grid),
        sign chosen so that each kernel's largest-magnitude entry is positive.
    grid_weights : numpy.ndarray
        Weights ``W_k`` on the PSF grid, shape ``(K, G, G)`` (they carry the singular values).
    singular_values : numpy.ndarray
        All singular values of the ``(G·G, h·w)`` PSF matrix, descending.
    captured_energy : numpy.ndarray
        ``captured_energy[K - 1] = Σ_{i<K} σ_i² / Σ σ_i²`` for every possible ``K``
        (1 for a grid without energy).
    """

    kernels: np.ndarray
    grid_weights: np.ndarray
    singular_values: np.ndarray
    captured_energy: np.ndarray

    @property
    def rank(self) -> int:
        """Number of retained components ``K``."""
        return int(self.kernels.shape[0])

    @property
    def energy_fraction(self) -> float:
        """Fraction of the PSF energy captured by the retained ``K`` components."""
        return float(self.captured_energy[self.rank - 1])


def decompose_psfs(
    psfs: np.ndarray, rank: int | None = None, tolerance: float = 1e-2
) -> PSFDecomposition:
    """SVD of a lens's PSF grid into basis kernels and grid weights.

    Parameters
    ----------
    psfs : array_like
        PSFs on a ``G × G`` grid, shape ``(G·G, h, w)`` with odd ``h, w``, ``v``-major
        (see the module docstring).
    rank : int, optional
        Number of components ``K`` (``1 ≤ K ≤ min(G·G, h·w)``). If omitted, the smallest
        ``K`` whose left-out energy fraction ``Σ_{i≥K} σ_i² / Σ σ_i²`` is at most
        ``tolerance``.
    tolerance : float
        In ``[0, 1)``; 0 keeps the full rank.

    Returns
    -------
    PSFDecomposition
        A grid without energy (all PSFs zero) gives ``K`` zero kernels and weights
        (``K = 1`` unless ``rank`` is given), so the operator built from it is zero.

    Raises
    ------
    ValueError
        Wrong shape, even kernel size, NaN/Inf values, ``rank`` or ``tolerance`` out of range.
    """
    psfs = np.asarray(psfs, dtype=np.float64)
    if psfs.ndim != 3:
        raise ValueError(f"psfs must have shape (G*G, h, w), got {psfs.shape}")
    n_psfs, height, width = psfs.shape
    side = _grid_side(n_psfs)
    if height % 2 == 0 or width % 2 == 0:
        raise ValueError(f"PSF sizes must be odd, got {height}x{width}")
    if not np.isfinite(psfs).all():
        raise ValueError("psfs contains NaN or Inf values")
    if not (np.isfinite(tolerance) and 0.0 <= tolerance < 1.0):
        raise ValueError(f"tolerance must be in [0, 1), got {tolerance!r}")
    max_rank = min(n_psfs, height * width)
    if rank is not None and (not isinstance(rank, (int, np.integer)) or not 1 <= rank <= max_rank):
        raise ValueError(f"rank must be an integer in [1, {max_rank}], got {rank!r}")

    u, sigma, vt = np.linalg.svd(psfs.reshape(n_psfs, height * width), full_matrices=False)
    energy = sigma**2
    total = energy.sum()
    if total == 0.0:
        n_keep = 1 if rank is None else int(rank)
        return PSFDecomposition(
            kernels=np.zeros((n_keep, height, width)),
            grid_weights=np.zeros((n_keep, side, side)),
            singular_values=sigma,
            captured_energy=np.ones(max_rank),
        )
    captured = np.minimum(np.cumsum(energy) / total, 1.0)
    # left_out[K] = energy fraction of components K, K+1, ...; exactly 0 for K = max_rank
    left_out = np.append(np.cumsum(energy[::-1])[::-1] / total, 0.0)
    if rank is None:
        rank = int(np.argmax(left_out[1:] <= tolerance)) + 1
    kernels = vt[:rank]
    weights = u[:, :rank] * sigma[:rank]
    peak = kernels[np.arange(rank), np.argmax(np.abs(kernels), axis=1)]
    sign = np.where(peak < 0, -1.0, 1.0)
    return PSFDecomposition(
        kernels=(kernels * sign[:, None]).reshape(rank, height, width),
        grid_weights=(weights * sign).T.reshape(rank, side, side),
        singular_values=sigma,
        captured_energy=captured,
    )


@dataclass(frozen=True)
class InterpolatedMaps:
    """Coefficient maps kept in factored form, formed only where and when they are needed.

    ``w_{ℓ,k}(i, j) = Σ_{a,b} basis_rows[a, i] · grid_weights[ℓ, k, a, b] · basis_cols[b, j]``
    (:func:`coefficient_maps`): ``G_r·G_c`` numbers per map instead of ``H·W``.

    Attributes
    ----------
    grid_weights : array_like
        ``(K, G_r, G_c)`` or ``(L, K, G_r, G_c)``.
    basis_rows : array_like
        ``(G_r, H)``, from :func:`interpolation_basis`.
    basis_cols : array_like
        ``(G_c, W)``.
    """

    grid_weights: torch.Tensor | np.ndarray
    basis_rows: torch.Tensor | np.ndarray
    basis_cols: torch.Tensor | np.ndarray

    def to(self, device: torch.device | str, dtype: torch.dtype) -> InterpolatedMaps:
        """The three factors as tensors on ``device`` in ``dtype``."""
        return InterpolatedMaps(
            *(torch.as_tensor(t).to(device=device, dtype=dtype) for t in self.factors)
        )

    @property
    def factors(self) -> tuple:
        """``(grid_weights, basis_rows, basis_cols)``."""
        return self.grid_weights, self.basis_rows, self.basis_cols


def fft_shape(shape: tuple[int, int], kernel_shape: tuple[int, int]) -> tuple[int, int]:
    """FFT grid of the operator: at least ``(H + h//2, W + w//2)`` and the kernel, 5-smooth."""
    from scipy.fft import next_fast_len  # here: scipy.fft takes 0.3-0.4 s to import

    return tuple(
        next_fast_len(max(size + kernel // 2, kernel), real=True)
        for size, kernel in zip(shape, kernel_shape, strict=True)
    )


@dataclass(frozen=True)
class ChunkPlan:
    """How one application of a :class:`LowRankSVOperator` fits its memory budget.

    Attributes
    ----------
    kept_lenses : int
        Lenses whose kernel spectra are kept (the first ones; as many as fit in half the
        budget, leaving room for one term of one image); the others' are recomputed
        chunk by chunk.
    lenses, components : int
        Lenses and components per chunk: all components of as many lenses as fit, else one
        lens and as many components as fit; at least one of each.
    bytes : int
        Kept spectra plus the working memory of one chunk; exceeds the budget only when
        the kept spectra and one term (of the whole batch) do.
    """

    kept_lenses: int
    lenses: int
    components: int
    bytes: int


def _application_costs(
    shape: tuple[int, int], fft: tuple[int, int], itemsize: int, batch: int
) -> tuple[int, int, int]:
    """Bytes of one half spectrum, and working bytes per lens and per (lens, component) term.

    Per lens: the accumulated (forward) or input (adjoint) spectra and an inverse or forward
    FFT with its padded copy. Per term: its coefficient map, the weighted or correlated
    images with their padded FFT copies and spectra, and the kernel spectrum (counted even
    when kept: the adjoint forms its conjugate product).
    """
    plane = shape[0] * shape[1] * itemsize
    padded = fft[0] * fft[1] * itemsize
    spectrum = fft[0] * (fft[1] // 2 + 1) * 2 * itemsize
    per_lens = batch * (2 * spectrum + padded + plane)
    per_term = plane + batch * (plane + padded + 2 * spectrum) + 2 * spectrum
    return spectrum, per_lens, per_term


def plan_chunks(
    shape: tuple[int, int],
    kernel_shape: tuple[int, int],
    n_lenses: int,
    rank: int,
    dtype: torch.dtype = torch.float32,
    memory_budget: int | None = None,
    batch: int = 1,
) -> ChunkPlan:
    """The chunks of an operator of these sizes applied to ``batch`` images (no allocation).

    Parameters
    ----------
    shape, kernel_shape
        Image ``(H, W)`` and kernel ``(h, w)`` sizes.
    n_lenses, rank
        ``L`` and ``K``.
    dtype
        Real dtype of the operator.
    memory_budget : int, optional
        Bytes; default :data:`DEFAULT_MEMORY_BUDGET`.
    batch : int
        Number of images per application.
    """
    budget = DEFAULT_MEMORY_BUDGET if memory_budget is None else int(memory_budget)
    itemsize = torch.finfo(dtype).bits // 8
    fft = fft_shape(shape, kernel_shape)
    spectrum, per_lens, per_term = _application_costs(shape, fft, itemsize, batch)
    _, lens_one, term_one = _application_costs(shape, fft, itemsize, 1)
    room = max(0, min(budget // 2, budget - lens_one - term_one))
    kept = min(room // (rank * spectrum), n_lenses)
    available = budget - kept * rank * spectrum
    components = int(np.clip((available - per_lens) // per_term, 1, rank))
    lenses = int(np.clip(available // (per_lens + components * per_term), 1, n_lenses))
    work = lenses * (per_lens + components * per_term)
    return ChunkPlan(kept, lenses, components, kept * rank * spectrum + work)


def _check_image(tensor: torch.Tensor, name: str, trailing: tuple[int, ...]) -> None:
    if not isinstance(tensor, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(tensor).__name__}")
    if tensor.ndim < len(trailing) or tuple(tensor.shape[-len(trailing) :]) != trailing:
        dims = ", ".join(str(d) for d in trailing)
        raise ValueError(f"{name} must have shape (..., {dims}), got {tuple(tensor.shape)}")
    if not torch.isfinite(tensor).all():
        raise ValueError(f"{name} contains NaN or Inf values")


def _chunks(total: int, step: int) -> list[slice]:
    return [slice(start, min(start + step, total)) for start in range(0, total, step)]


class LowRankSVOperator:
    """Low-rank SV blur ``v = Σ_k h_k ∗ (w_k ⊙ x)`` of one lens or a stack of lenses.

    Linear convolution with zero boundary, output cropped to the input size ("same"),
    computed with real FFTs on a padded grid of at least ``(H + h//2, W + w//2)`` pixels
    (the least size at which the circular wrap cannot reach the cropped output; at least
    the kernel size), rounded up to a 5-smooth length. The forward pass costs ``K``
    forward FFTs and one inverse FFT per image and lens (the sum over ``k`` is done in the
    Fourier domain); the adjoint one forward FFT and ``K`` inverse FFTs (each ``w_k``
    multiplies in real space after its own inverse transform, so those cannot be merged).

    Lens batching: with kernels ``(L, K, h, w)`` and weights ``(L, K, H, W)`` one operator
    holds ``L`` lenses; :meth:`forward` maps an object ``(..., H, W)`` to the ``L`` lens
    images ``(..., L, H, W)`` and :meth:`adjoint` maps ``(..., L, H, W)`` back to
    ``(..., H, W)``, summing over lenses. With 3-D kernels and weights the lens axis is
    absent from images.

    Memory: lenses and components are independent terms of the sums, so both passes go
    through them in chunks (:meth:`chunking`) whose working memory fits ``memory_budget``.
    Coefficient maps given as :class:`InterpolatedMaps` are formed chunk by chunk from
    the grid weights; kernel spectra are kept for as many lenses as fit in half the budget
    and recomputed per chunk for the others. The chunking changes the order of float
    additions only.

    Parameters
    ----------
    kernels : array_like
        Basis kernels ``(K, h, w)`` or ``(L, K, h, w)``, odd ``h`` and ``w``, centre at
        ``(h // 2, w // 2)``, true convolution.
    weights : array_like or InterpolatedMaps
        Coefficient maps ``(K, H, W)`` or ``(L, K, H, W)``, stored as given (in ``dtype``),
        or their factors, stored instead of the maps.
    dtype : torch.dtype, optional
        ``torch.float32`` or ``torch.float64``; default the dtype of ``weights`` (of its
        grid weights) if it is one of those, else float32.
    device : torch.device or str, optional
        Default: that of ``weights`` (of its grid weights) when it is a tensor, else the CPU.
    memory_budget : int, optional
        Bytes for the kept kernel spectra plus the working memory of one application
        (:meth:`memory_estimate`; the input and output images are the caller's). Default
        :data:`DEFAULT_MEMORY_BUDGET`. A budget smaller than one term still computes,
        one lens and one component at a time.

    Notes
    -----
    Inputs must match the operator's dtype and device (else a ``ValueError`` naming
    :meth:`to`); non-finite inputs raise ``ValueError``.

    Examples
    --------
    >>> op = LowRankSVOperator(torch.ones(1, 3, 3), torch.ones(1, 5, 5))
    >>> op.forward(torch.ones(5, 5))[2].round().tolist()
    [6.0, 9.0, 9.0, 9.0, 6.0]
    """

    def __init__(
        self,
        kernels: torch.Tensor | np.ndarray,
        weights: torch.Tensor | np.ndarray | InterpolatedMaps,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
        memory_budget: int | None = None,
    ) -> None:
        lead = weights.grid_weights if isinstance(weights, InterpolatedMaps) else weights
        if dtype is None:
            dtype = getattr(torch.as_tensor(lead[:0]), "dtype", None)
            dtype = dtype if dtype in _REAL_DTYPES else torch.float32
        if dtype not in _REAL_DTYPES:
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        if device is None:
            device = lead.device if isinstance(lead, torch.Tensor) else "cpu"
        if memory_budget is None:
            memory_budget = DEFAULT_MEMORY_BUDGET
        if not isinstance(memory_budget, (int, np.integer)) or memory_budget < 1:
            raise ValueError(f"memory_budget must be a positive byte count, got {memory_budget!r}")
        kernels = torch.as_tensor(kernels).to(device=device, dtype=dtype)
        if isinstance(weights, InterpolatedMaps):
            maps = weights.to(device, dtype)
            rows, cols = maps.basis_rows, maps.basis_cols
            if rows.ndim != 2 or cols.ndim != 2 or maps.grid_weights.shape[-2:] != (
                rows.shape[0],
                cols.shape[0],
            ):
                raise ValueError(
                    f"grid weights {tuple(maps.grid_weights.shape)} do not match the bases "
                    f"{tuple(rows.shape)} and {tuple(cols.shape)}"
                )
            lead_shape = (*maps.grid_weights.shape[:-2], rows.shape[1], cols.shape[1])
            factors = maps.factors
        else:
            maps = torch.as_tensor(weights).to(device=device, dtype=dtype)
            lead_shape, factors = tuple(maps.shape), (maps,)
        if kernels.ndim not in (3, 4) or len(lead_shape) != kernels.ndim:
            raise ValueError(
                "kernels and weights must be (K, h, w) and (K, H, W), or (L, K, h, w) and "
                f"(L, K, H, W); got {tuple(kernels.shape)} and {lead_shape}"
            )
        if kernels.shape[:-2] != lead_shape[:-2]:
            raise ValueError(
                f"kernels {tuple(kernels.shape)} and weights {lead_shape} disagree "
                "on the number of lenses or components"
            )
        if kernels.shape[-3] < 1:
            raise ValueError("at least one component (K >= 1) is needed")
        height, width = kernels.shape[-2:]
        if height % 2 == 0 or width % 2 == 0:
            raise ValueError(f"kernel sizes must be odd, got {height}x{width}")
        for tensor, name in ((kernels, "kernels"), *((f, "weights") for f in factors)):
            if not torch.isfinite(tensor).all():
                raise ValueError(f"{name} contains NaN or Inf values")
        self.lens_batched = kernels.ndim == 4
        self.kernels = kernels if self.lens_batched else kernels[None]
        if isinstance(maps, InterpolatedMaps) and not self.lens_batched:
            maps = dataclasses.replace(maps, grid_weights=maps.grid_weights[None])
        self._maps = maps if isinstance(maps, InterpolatedMaps) or self.lens_batched else maps[None]
        self._shape = lead_shape[-2:]
        self.memory_budget = int(memory_budget)
        self.fft_shape = fft_shape(self.shape, self.kernel_shape)
        kept = self._plan(1).kept_lenses
        self._spectra = self._kernel_spectra(slice(0, kept), slice(None))

    # ------------------------------------------------------------------ pieces
    @property
    def _spectrum_bytes(self) -> int:
        """Bytes of one complex half spectrum on the FFT grid."""
        return _application_costs(self.shape, self.fft_shape, self.dtype.itemsize, 1)[0]

    def _kernel_spectra(self, lenses: slice, components: slice) -> torch.Tensor:
        """Real FFTs of some kernels, centre moved to index (0, 0), ``(l, k, Hf, Wf//2+1)``.

        As ``rfft2`` of the zero-padded kernels, but the row transforms run over the
        ``h`` kernel rows only (the others are zero).
        """
        height, width = self.kernel_shape
        kernels = self.kernels[lenses, components]
        shift_rows = (torch.arange(height, device=self.device) - height // 2) % self.fft_shape[0]
        shift_cols = (torch.arange(width, device=self.device) - width // 2) % self.fft_shape[1]
        complex_dtype = torch.complex64 if self.dtype == torch.float32 else torch.complex128
        spectra = torch.zeros(
            *kernels.shape[:-2], self.fft_shape[0], self.fft_shape[1] // 2 + 1,
            dtype=complex_dtype, device=self.device,
        )
        if spectra.numel() == 0:  # no lens kept (the FFT libraries reject empty batches)
            return spectra
        padded = kernels.new_zeros(*kernels.shape[:-1], self.fft_shape[1])
        padded[..., shift_cols] = kernels
        spectra[..., shift_rows, :] = torch.fft.rfft(padded, dim=-1)
        return torch.fft.fft(spectra, dim=-2)

    def _spectra_of(self, lenses: slice, components: slice) -> torch.Tensor:
        if lenses.stop <= self._spectra.shape[0]:
            return self._spectra[lenses, components]
        return self._kernel_spectra(lenses, components)

    def _maps_of(self, lenses: slice, components: slice) -> torch.Tensor:
        """Coefficient maps of some lenses and components, ``(l, k, H, W)``."""
        if not isinstance(self._maps, InterpolatedMaps):
            return self._maps[lenses, components]
        return self.weight_maps(lenses=lenses, components=components)

    def weight_maps(
        self,
        rows: slice = slice(None),
        cols: slice = slice(None),
        lenses: slice = slice(None),
        components: slice = slice(None),
        mix: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Coefficient maps on a window, ``(l, k, r, c)``, or mixed over components.

        Parameters
        ----------
        rows, cols, lenses, components : slice
            The window and the lenses and components wanted.
        mix : torch.Tensor, optional
            ``(l, k)`` coefficients: return ``Σ_k mix[ℓ, k] w_{ℓ,k}``, ``(l, r, c)``, formed
            from the mixed grid weights (the interpolation is linear).
        """
        if isinstance(self._maps, InterpolatedMaps):
            grid = self._maps.grid_weights[lenses, components]
            if mix is not None:
                grid = torch.einsum("lkab,lk->lab", grid, mix)
            return self._maps.basis_rows[:, rows].T @ grid @ self._maps.basis_cols[:, cols]
        maps = self._maps[lenses, components, rows, cols]
        return maps if mix is None else torch.einsum("lkij,lk->lij", maps, mix)

    @property
    def weights(self) -> torch.Tensor:
        """All coefficient maps ``(L, K, H, W)`` (formed in full: ``L·K·H·W`` numbers)."""
        return self._maps_of(slice(None), slice(None))

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape ``(H, W)`` of the object and of each lens image."""
        return tuple(self._shape)

    @property
    def kernel_shape(self) -> tuple[int, int]:
        """Kernel shape ``(h, w)``."""
        return tuple(self.kernels.shape[-2:])

    @property
    def rank(self) -> int:
        """Number of components ``K`` (per lens)."""
        return int(self.kernels.shape[-3])

    @property
    def n_lenses(self) -> int:
        """Number of lenses ``L`` (1 for an operator without lens axis)."""
        return int(self.kernels.shape[0])

    @property
    def dtype(self) -> torch.dtype:
        return self.kernels.dtype

    @property
    def device(self) -> torch.device:
        return self.kernels.device

    # --------------------------------------------------------------- memory
    def _plan(self, batch: int) -> ChunkPlan:
        return plan_chunks(
            self.shape, self.kernel_shape, self.n_lenses, self.rank, self.dtype,
            self.memory_budget, batch,
        )

    def _costs(self, batch: int) -> tuple[int, int]:
        """Working bytes per lens and per (lens, component) term (:func:`plan_chunks`)."""
        itemsize = self.dtype.itemsize
        return _application_costs(self.shape, self.fft_shape, itemsize, batch)[1:]

    def chunking(self, batch: int = 1) -> tuple[int, int]:
        """Lenses and components per chunk for ``batch`` images (:class:`ChunkPlan`)."""
        plan = self._plan(batch)
        return plan.lenses, plan.components

    def memory_estimate(self, batch: int = 1) -> int:
        """Bytes the operator holds plus its working peak for ``batch`` images (an estimate).

        Kept spectra, kernels and weights, plus the working memory of the chunks of
        :meth:`chunking`; the input and output images are not counted.
        """
        maps = self._maps.factors if isinstance(self._maps, InterpolatedMaps) else (self._maps,)
        held = sum(t.nelement() * t.element_size() for t in (self.kernels, *maps))
        return held + self._plan(batch).bytes

    # ------------------------------------------------------------------ algebra
    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> LowRankSVOperator:
        """The same operator on another device and/or in another dtype (a new object).

        The kernel spectra are recomputed there. Returns ``self`` when nothing changes.
        """
        device = self.device if device is None else torch.device(device)
        dtype = self.dtype if dtype is None else dtype
        if device == self.device and dtype == self.dtype:
            return self
        squeeze = slice(None) if self.lens_batched else 0
        maps = self._maps
        maps = (
            dataclasses.replace(maps, grid_weights=maps.grid_weights[squeeze])
            if isinstance(maps, InterpolatedMaps)
            else maps[squeeze]
        )
        return LowRankSVOperator(
            self.kernels[squeeze], maps, dtype=dtype, device=device,
            memory_budget=self.memory_budget,
        )

    def _check(self, tensor: torch.Tensor, name: str, trailing: tuple[int, ...]) -> None:
        _check_image(tensor, name, trailing)
        if tensor.dtype != self.dtype or tensor.device != self.device:
            raise ValueError(
                f"{name} is {tensor.dtype} on {tensor.device} but the operator is "
                f"{self.dtype} on {self.device}; convert one of them (see LowRankSVOperator.to)"
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Lens images of object ``x``.

        Parameters
        ----------
        x : torch.Tensor
            Shape ``(..., H, W)``.

        Returns
        -------
        torch.Tensor
            ``(..., L, H, W)`` for a lens-batched operator, else ``(..., H, W)``.
        """
        self._check(x, "x", self.shape)
        rows, cols = self.shape
        images = x.new_empty(*x.shape[:-2], self.n_lenses, rows, cols)
        n_lenses, n_components = self.chunking(int(np.prod(x.shape[:-2])))
        for lenses in _chunks(self.n_lenses, n_lenses):
            total = None
            for components in _chunks(self.rank, n_components):
                weighted = self._maps_of(lenses, components) * x[..., None, None, :, :]
                spectrum = torch.fft.rfft2(weighted, s=self.fft_shape)
                del weighted
                spectrum = spectrum.mul_(self._spectra_of(lenses, components)).sum(dim=-3)
                total = spectrum if total is None else total.add_(spectrum)
                del spectrum
            images[..., lenses, :, :] = torch.fft.irfft2(total, s=self.fft_shape)[
                ..., :rows, :cols
            ]
        return images if self.lens_batched else images.squeeze(-3)

    def adjoint(self, y: torch.Tensor) -> torch.Tensor:
        """Adjoint ``x = Σ_ℓ Σ_k w_{ℓ,k} ⊙ (h_{ℓ,k} ⋆ y_ℓ)`` (correlation, zero boundary).

        Parameters
        ----------
        y : torch.Tensor
            ``(..., L, H, W)`` for a lens-batched operator, else ``(..., H, W)``.

        Returns
        -------
        torch.Tensor
            Shape ``(..., H, W)``.
        """
        rows, cols = self.shape
        if self.lens_batched:
            self._check(y, "y", (self.n_lenses, rows, cols))
        else:
            self._check(y, "y", self.shape)
            y = y[..., None, :, :]
        x = y.new_zeros(*y.shape[:-3], rows, cols)
        n_lenses, n_components = self.chunking(int(np.prod(y.shape[:-3])))
        for lenses in _chunks(self.n_lenses, n_lenses):
            spectrum = torch.fft.rfft2(y[..., lenses, :, :], s=self.fft_shape)[..., None, :, :]
            for components in _chunks(self.rank, n_components):
                product = spectrum * self._spectra_of(lenses, components).conj()
                correlated = torch.fft.irfft2(product, s=self.fft_shape)[..., :rows, :cols]
                del product
                correlated = correlated * self._maps_of(lenses, components)
                x += correlated.sum(dim=(-4, -3))
                del correlated
        return x

    __call__ = forward

    @classmethod
    def from_decomposition(
        cls,
        decompositions: PSFDecomposition | Sequence[PSFDecomposition],
        size: int | Sequence[int],
        margin: int = 0,
        order: int = 3,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
        memory_budget: int | None = None,
    ) -> LowRankSVOperator:
        """Operator of one lens, or of several lenses given a sequence of decompositions.

        Coefficient maps are those of :func:`coefficient_maps`, kept as
        :class:`InterpolatedMaps` (formed when applied); lenses of lower rank are padded
        with zero components up to the largest rank.

        Parameters
        ----------
        decompositions : PSFDecomposition or sequence of PSFDecomposition
        size : int or (int, int)
            Object grid size without the margin; the operator's shape is
            ``size + 2·margin`` per axis.
        margin, order
            As in :func:`coefficient_maps`.
        dtype, device, memory_budget
            Of the operator.
        """
        single = isinstance(decompositions, PSFDecomposition)
        items = [decompositions] if single else list(decompositions)
        if not items:
            raise ValueError("at least one decomposition is needed")
        rank = max(item.rank for item in items)
        kernel_shape = {item.kernels.shape[1:] for item in items}
        if len(kernel_shape) != 1:
            raise ValueError(f"all lenses need the same kernel shape, got {sorted(kernel_shape)}")
        grid_shape = {item.grid_weights.shape[1:] for item in items}
        if len(grid_shape) != 1:
            raise ValueError(f"all lenses need the same PSF grid, got {sorted(grid_shape)}")
        kernels = np.zeros((len(items), rank, *kernel_shape.pop()))
        grid_weights = np.zeros((len(items), rank, *grid_shape.pop()))
        for lens, item in enumerate(items):
            kernels[lens, : item.rank] = item.kernels
            grid_weights[lens, : item.rank] = item.grid_weights
        if single:
            kernels, grid_weights = kernels[0], grid_weights[0]
        rows, cols = _pair(size, "size")
        maps = InterpolatedMaps(
            grid_weights,
            interpolation_basis(grid_weights.shape[-2], rows, margin, order),
            interpolation_basis(grid_weights.shape[-1], cols, margin, order),
        )
        return cls(kernels, maps, dtype=dtype, device=device, memory_budget=memory_budget)
