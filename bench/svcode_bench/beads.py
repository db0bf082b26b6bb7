"""Bead counting: how many beads of a known field a reconstruction finds, and how wide.

The seed paper images fluorescent beads from sparse to dense and reports how many it
recovers and how sharp they come out. Here :func:`bead_phantom` scatters equal beads at a
chosen density and keeps their centres; :func:`detect_beads` takes the local maxima of a
reconstruction that stand out of its background (Otsu's threshold); :func:`score_beads`
pairs them one to one with the true beads (a bead is found when a detection lies within
its radius) and fits each found bead's width.

Sizes follow :mod:`svcode_core.phantoms`: a bead of radius ``r`` pixels is the
pixel-integrated Gaussian of ``sigma = r / 2`` (the Gaussian with the second moment of a
disk of radius ``r``), rendered by the same code. A 10-µm bead is about half an object
pixel on ``cm2-mini`` (20.3 µm), so the instrument cannot show it smaller than its own
resolution; the default ``sigma`` of 1 px (radius 2 px, FWHM 2.4 px) stands for such a
bead as the finest spot the object grid draws without aliasing.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, optimize, special
from skimage.feature import peak_local_max
from skimage.filters import threshold_otsu

from svcode_core.phantoms import _render_spots

__all__ = [
    "BEAD_SIGMA",
    "BeadPhantom",
    "BeadScore",
    "bead_phantom",
    "detect_beads",
    "fit_bead_sigma",
    "match_beads",
    "score_beads",
]

#: default bead width (Gaussian sigma, object pixels): radius 2 px in the phantoms' terms
BEAD_SIGMA = 1.0
_AREA = 1e4  # densities are per 100 × 100 pixels, as in :mod:`svcode_core.phantoms`


@dataclass(frozen=True)
class BeadPhantom:
    """A field of beads with its ground truth.

    Attributes
    ----------
    image : numpy.ndarray
        float32 ``(size, size)`` in ``[0, 1]``, dark background.
    centres : numpy.ndarray
        ``(n, 2)`` bead centres (row, column) in pixels, sub-pixel.
    sigmas : numpy.ndarray
        ``(n,)`` Gaussian widths in pixels.
    """

    image: np.ndarray
    centres: np.ndarray
    sigmas: np.ndarray

    @property
    def radii(self) -> np.ndarray:
        """Bead radii, ``2 sigma`` (the disk of the same second moment)."""
        return 2.0 * self.sigmas


def bead_phantom(
    size: int,
    density: float,
    seed: int | np.random.Generator | None = 0,
    sigma: float = BEAD_SIGMA,
    brightness: float = 1.0,
    min_separation: float | None = None,
) -> BeadPhantom:
    """Equal beads at random sub-pixel positions, ``density`` per 100 × 100 pixels.

    The count is ``round(density · size² / 10⁴)`` (exact, not Poisson, so every seed has the
    same density). Centres are uniform over the field less one bead radius at each edge,
    and no two closer than ``min_separation`` (default: two radii, beads that do not
    overlap), placed one by one by rejection.

    Parameters
    ----------
    size : int
        Side of the square grid.
    density : float
        Beads per 100 × 100 pixels (>= 0).
    seed : int, numpy.random.Generator or None
        Fixes the positions.
    sigma : float
        Gaussian width of every bead in pixels.
    brightness : float
        Peak value of a bead, in ``(0, 1]``.
    min_separation : float or None
        Smallest distance between two centres in pixels (0: fully random placement).

    Returns
    -------
    BeadPhantom

    Examples
    --------
    >>> field = bead_phantom(100, density=5, seed=1)
    >>> field.image.shape, len(field.centres), float(field.radii[0])
    ((100, 100), 5, 2.0)
    >>> bool(abs(field.image.max() - 1) < 0.05)
    True
    """
    if not np.isfinite(density) or density < 0:
        raise ValueError(f"density must be a number >= 0, got {density!r}")
    if not (0 < brightness <= 1) or not sigma > 0:
        raise ValueError(f"need sigma > 0 and brightness in (0, 1], got {sigma!r}, "
                         f"{brightness!r}")
    rng = np.random.default_rng(seed)
    radius = 2.0 * sigma
    separation = 2.0 * radius if min_separation is None else float(min_separation)
    count = int(round(density * size * size / _AREA))
    low, high = radius - 0.5, size - 0.5 - radius
    centres = np.empty((0, 2))
    tries = 0
    while len(centres) < count:
        if tries > 100 * count + 1000:
            raise ValueError(f"cannot place {count} beads {separation:g} px apart in "
                             f"{size}×{size} pixels; lower the density or min_separation")
        tries += 1
        candidate = rng.uniform(low, high, 2)
        if np.all(np.hypot(*(centres - candidate).T) >= separation):
            centres = np.vstack([centres, candidate])
    sigmas = np.full(count, float(sigma))
    image = np.clip(_render_spots(size, centres, sigmas, np.full(count, brightness)), 0, None)
    return BeadPhantom((image / max(1.0, image.max())).astype(np.float32), centres, sigmas)


def detect_beads(
    image: np.ndarray, sigma: float = BEAD_SIGMA, threshold: float | None = None,
    min_distance: int = 1,
) -> np.ndarray:
    """Bead positions in an image: the local maxima that stand out of the background.

    The image is smoothed with a Gaussian of ``sigma / 2`` (single-pixel noise spikes do
    not count as beads, close pairs stay apart) and its median, the background over a field
    that beads leave mostly dark, is subtracted. A detection is a local maximum of that
    (within ``min_distance`` pixels) at or above the threshold: by default Otsu's threshold
    of its positive part, which splits bead pixels from background whatever the image's
    scale and is not pulled up by a few artefacts brighter than the beads (as a fraction of
    the maximum is); or ``threshold`` times its maximum.

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W)`` reconstruction, any scale.
    sigma : float
        The beads' width in pixels.
    threshold : float or None
        Fraction of the brightest (smoothed, background-subtracted) pixel; None: Otsu.
    min_distance : int
        Passed to :func:`skimage.feature.peak_local_max`.

    Returns
    -------
    numpy.ndarray
        ``(m, 2)`` float positions (row, column), brightest first; empty when the image
        holds nothing above its background.

    Examples
    --------
    >>> field = bead_phantom(64, density=10, seed=0)
    >>> len(detect_beads(field.image)), len(field.centres)
    (4, 4)
    >>> detect_beads(np.zeros((32, 32))).shape
    (0, 2)
    """
    smooth = ndimage.gaussian_filter(np.asarray(image, dtype=np.float64), sigma / 2)
    level = smooth - np.median(smooth)
    peak = level.max(initial=0.0)
    if not np.isfinite(peak) or peak <= 0:
        return np.empty((0, 2))
    if threshold is None:
        # Otsu between the background (everything at or below the median, set to 0)
        # and what rises above it; negative ringing has no say in where beads are
        cut = float(threshold_otsu(np.clip(level, 0.0, None)))
    else:
        cut = threshold * peak
    found = peak_local_max(level, min_distance=min_distance, threshold_abs=max(cut, 0.0),
                           exclude_border=False)
    found = found[level[tuple(found.T)] > 0]  # a flat zero background holds no beads
    return found.astype(np.float64).reshape(-1, 2)


def match_beads(
    found: np.ndarray, centres: np.ndarray, tolerance: float | np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Pair detections with true beads one to one, each within its bead's ``tolerance``.

    Hungarian matching on the distances, with pairs farther than the tolerance priced
    above any set of allowed ones: the most beads are paired first, and among such
    pairings the one of least total distance is taken.

    Returns
    -------
    (numpy.ndarray, numpy.ndarray)
        Indices into ``centres`` and into ``found`` of the matched pairs.

    Examples
    --------
    >>> truth = np.array([[10.0, 10.0], [10.0, 20.0]])
    >>> match_beads(np.array([[10.4, 19.5], [40.0, 40.0]]), truth, 2.0)
    (array([1]), array([0]))
    """
    found = np.asarray(found, dtype=np.float64).reshape(-1, 2)
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    if not len(found) or not len(centres):
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    reach = np.broadcast_to(np.asarray(tolerance, dtype=np.float64), (len(centres),))
    distance = np.hypot(*(centres[:, None, :] - found[None, :, :]).transpose(2, 0, 1))
    allowed = distance <= reach[:, None]
    # a forbidden pair costs more than any pairing of allowed ones could add up to
    penalty = 2.0 * (reach.max() + 1.0) * (min(distance.shape) + 1)
    rows, cols = optimize.linear_sum_assignment(np.where(allowed, distance, penalty))
    keep = allowed[rows, cols]
    return rows[keep].astype(np.int64), cols[keep].astype(np.int64)


def _box_gauss(x: np.ndarray, centre: float, sigma: float) -> np.ndarray:
    """A unit-mass Gaussian integrated over each unit pixel centred at ``x``."""
    scale = np.sqrt(2.0) * sigma
    return 0.5 * (special.erf((x + 0.5 - centre) / scale) - special.erf((x - 0.5 - centre) / scale))


def fit_bead_sigma(image: np.ndarray, position: Iterable[float],
                   sigma: float = BEAD_SIGMA, others: np.ndarray | None = None) -> float:
    """The width of the bead at ``position``: a least-squares fit of one spot.

    The model is a round pixel-integrated Gaussian (the phantoms' rendering) on a flat
    offset, with free centre, height and width, fitted over the ``(2h + 1)²`` window around
    ``position`` (``h = ceil(3 sigma)``, cut at the image edge), less the pixels nearer to
    one of ``others`` (the other detections) than to ``position``, so that a neighbour's
    core does not pass for this bead's tail. On the phantom itself it returns the drawn
    ``sigma``; a blurred reconstruction gives a larger one.

    Examples
    --------
    >>> field = bead_phantom(32, density=10, seed=2, sigma=1.3)
    >>> round(fit_bead_sigma(field.image, field.centres[0], 1.3), 3)
    1.3
    """
    image = np.asarray(image, dtype=np.float64)
    row, col = (int(round(v)) for v in position)
    half = int(np.ceil(3 * sigma))
    r0, r1 = max(row - half, 0), min(row + half + 1, image.shape[0])
    c0, c1 = max(col - half, 0), min(col + half + 1, image.shape[1])
    rows, cols = np.arange(r0, r1, dtype=np.float64), np.arange(c0, c1, dtype=np.float64)
    keep = np.ones((len(rows), len(cols)), dtype=bool)
    if others is not None and len(others):
        grid_r, grid_c = np.meshgrid(rows, cols, indexing="ij")
        own = np.hypot(grid_r - row, grid_c - col)
        for other in np.asarray(others, dtype=np.float64).reshape(-1, 2):
            if other[0] != row or other[1] != col:
                keep &= own <= np.hypot(grid_r - other[0], grid_c - other[1])
    patch = image[r0:r1, c0:c1][keep]

    def residual(p: np.ndarray) -> np.ndarray:
        cr, cc, s, height, offset = p
        spot = np.outer(_box_gauss(rows, cr, s), _box_gauss(cols, cc, s))[keep]
        return offset + height * spot - patch

    base = float(np.median(patch))
    mass = max(float(patch.sum() - base * patch.size), 1e-12)
    start = [row, col, sigma, mass, base]
    lower = [row - 1.5, col - 1.5, 0.1, 0.0, -np.inf]
    upper = [row + 1.5, col + 1.5, 3.0 * half, np.inf, np.inf]
    fit = optimize.least_squares(residual, start, bounds=(lower, upper), x_scale="jac")
    return float(fit.x[2])


@dataclass(frozen=True)
class BeadScore:
    """Counts and widths of one image (or of several pooled).

    Attributes
    ----------
    n_true, n_found, n_matched : int
        Beads in the truth, detections, and detections paired with a bead.
    size_errors : numpy.ndarray
        Per matched bead, fitted width over true width minus 1 (0: the right size).
    """

    n_true: int
    n_found: int
    n_matched: int
    size_errors: np.ndarray

    @property
    def recall(self) -> float:
        """Fraction of the beads found (NaN without beads)."""
        return self.n_matched / self.n_true if self.n_true else float("nan")

    @property
    def precision(self) -> float:
        """Fraction of the detections that are beads.

        NaN when nothing was detected: no claim was made, so none can be right or wrong,
        and 1 would let an empty reconstruction look perfectly precise in an average. F1
        stays defined (0 when beads were missed).
        """
        return self.n_matched / self.n_found if self.n_found else float("nan")

    @property
    def f1(self) -> float:
        """``2 matched / (true + found)``, the harmonic mean of recall and precision."""
        total = self.n_true + self.n_found
        return 2 * self.n_matched / total if total else float("nan")

    @property
    def size_error(self) -> float:
        """Median relative width error of the found beads, in absolute value."""
        errors = np.abs(self.size_errors)
        return float(np.median(errors)) if errors.size else float("nan")

    @property
    def size_bias(self) -> float:
        """Median signed relative width error (> 0: beads come out wider)."""
        return float(np.median(self.size_errors)) if self.size_errors.size else float("nan")

    @classmethod
    def pooled(cls, scores: Iterable[BeadScore]) -> BeadScore:
        """One score over several images: the counts added, the widths gathered."""
        scores = list(scores)
        errors = [s.size_errors for s in scores]
        return cls(sum(s.n_true for s in scores), sum(s.n_found for s in scores),
                   sum(s.n_matched for s in scores),
                   np.concatenate(errors) if errors else np.empty(0))

    def as_dict(self) -> dict[str, float | int]:
        """The counts and summary figures, for a report."""
        return {"beads": self.n_true, "found": self.n_found, "matched": self.n_matched,
                "recall": self.recall, "precision": self.precision, "f1": self.f1,
                "size_error": self.size_error, "size_bias": self.size_bias}


def score_beads(image: np.ndarray, phantom: BeadPhantom, threshold: float | None = None,
                tolerance: float | np.ndarray | None = None,
                measure_size: bool = True) -> BeadScore:
    """Detect beads in ``image``, pair them with ``phantom``'s and fit the found ones' width.

    Parameters
    ----------
    image : numpy.ndarray
        Reconstruction of ``phantom`` (any scale).
    phantom : BeadPhantom
        The truth.
    threshold : float or None
        Detection threshold, see :func:`detect_beads` (None: Otsu).
    tolerance : float, numpy.ndarray or None
        Largest distance from a bead's centre at which it counts as found (default: its
        radius).
    measure_size : bool
        Fit the widths (the slow part); otherwise ``size_errors`` is empty.

    Examples
    --------
    >>> field = bead_phantom(64, density=10, seed=0)
    >>> score = score_beads(field.image, field)
    >>> score.recall, score.precision, round(score.size_error, 6)
    (1.0, 1.0, 0.0)
    """
    sigma = float(np.median(phantom.sigmas)) if len(phantom.sigmas) else BEAD_SIGMA
    found = detect_beads(image, sigma, threshold)
    reach = phantom.radii if tolerance is None else tolerance
    beads, hits = match_beads(found, phantom.centres, reach)
    errors = np.empty(0)
    if measure_size and len(beads):
        errors = np.array([fit_bead_sigma(image, found[h], phantom.sigmas[b], found)
                           / phantom.sigmas[b] - 1.0 for b, h in zip(beads, hits, strict=True)])
    return BeadScore(len(phantom.centres), len(found), len(beads), errors)
