"""Ground-truth objects for simulation and training: fluorescence-like phantoms on an S×S grid.

Every generator returns a float32 ``size × size`` array in ``[0, 1]`` with a dark (zero)
background, and draws all its randomness from the :class:`numpy.random.Generator` it is
given, so a seed fixes the object. Kinds:

* ``beads``: point emitters (sub-pixel to several pixels) over wide ranges of density and
  brightness;
* ``cells``: Voronoi-packed cells with bright membranes, nuclei and textured cytoplasm;
* ``vessels``: branching curvilinear trees of tapering width, plus thin capillaries;
* ``neurons``: somata with dendrite-like processes on a brain-section-like background;
* ``skimage``: random crops, rotations and flips of real images bundled inside
  scikit-image (the Hubble deep field: point and extended emitters on a dark sky; the retina
  fundus photograph: its vessel tree, extracted as a bright-on-dark map). Nothing is
  downloaded: scikit-image's fluorescence samples (``human_mitosis``, ``cells3d``, ``kidney``)
  are not bundled with the wheel and are not used;
* ``isolated-cells``: a few large cells alone in a dark field (textured ellipses);
* ``mixed``: one of the first five chosen at random, or a blend of two;
  ``mixed-isolated`` the same with ``isolated-cells`` among the choices.

Spots and curvilinear structures are sums of pixel-integrated Gaussians (exact box
integration via ``erf``), so sub-pixel emitters are anti-aliased. A structure of radius
``r`` pixels uses the Gaussian of the same second moment as a disk, ``sigma = r / 2``.
Densities are given per ``100 × 100`` pixels; lengths in pixels at ``size = 384`` and scaled
with ``size`` (radii of beads are absolute).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
from scipy import special

__all__ = [
    "HELD_OUT_IMAGES",
    "KINDS",
    "beads",
    "cells",
    "from_image",
    "held_out_image",
    "isolated_cells",
    "make_object",
    "mixed",
    "neurons",
    "normalize_object",
    "skimage_crop",
    "vessels",
]

REFERENCE_SIZE = 384  # the size at which the structure lengths below are given
_AREA = 1e4  # densities are per 100 × 100 pixels
_MAX_SPLAT = 2_000_000  # pixels rendered per vectorised batch (bounds memory)
_MAX_TREE_POINTS = 1_000_000  # centre-line samples rendered together (bounds memory)

Range = float | tuple[float, float]


# ------------------------------------------------------------------------- helpers
def _check_size(size: int) -> None:
    if not isinstance(size, (int, np.integer)) or isinstance(size, bool) or size < 8:
        raise ValueError(f"size must be an integer >= 8, got {size!r}")


def _as_range(value: Range, name: str) -> tuple[float, float]:
    pair = (value, value) if np.isscalar(value) else tuple(np.ravel(value))
    if len(pair) != 2:
        raise ValueError(f"{name} must be a number > 0 or a (min, max) pair, got {value!r}")
    low, high = pair
    if not (np.isfinite(low) and np.isfinite(high) and 0 < low <= high):
        raise ValueError(f"{name} must be a number > 0 or a (min, max) pair, got {value!r}")
    return float(low), float(high)


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float], n=None):
    return np.exp(rng.uniform(np.log(bounds[0]), np.log(bounds[1]), n))


def _count(rng: np.random.Generator, density: Range, size: int, name: str) -> int:
    """A Poisson number (at least 1) of items at a log-uniformly drawn density."""
    rate = _log_uniform(rng, _as_range(density, name)) * size * size / _AREA
    return max(1, int(rng.poisson(rate)))


def _to_unit(img: np.ndarray) -> np.ndarray:
    """Clip at 0 and divide by the maximum (zeros stay zeros); float32."""
    img = np.clip(img, 0, None)
    peak = img.max()
    return (img / peak if peak > 0 else img).astype(np.float32)


def _smooth_noise(rng: np.random.Generator, size: int, sigma: float) -> np.ndarray:
    """Gaussian-filtered white noise with unit standard deviation."""
    from scipy import ndimage

    field = ndimage.gaussian_filter(rng.standard_normal((size, size)), sigma, mode="wrap")
    return field / max(field.std(), 1e-12)


def _pixel_profile(centres: np.ndarray, sigmas: np.ndarray, half: int):
    """1-D pixel-integrated Gaussians, peak 1 when centred: (first pixel, weights)."""
    first = np.round(centres).astype(np.int64) - half
    pixels = first[:, None] + np.arange(2 * half + 1)
    scale = np.sqrt(2.0) * sigmas[:, None]
    mass = special.erf((pixels + 0.5 - centres[:, None]) / scale) - special.erf(
        (pixels - 0.5 - centres[:, None]) / scale
    )
    return first, mass / (2 * special.erf(0.5 / scale))


def _render_spots(
    size: int, centres: np.ndarray, sigmas: np.ndarray, amplitudes: np.ndarray
) -> np.ndarray:
    """Sum of pixel-integrated Gaussian spots, each of peak ``amplitude`` when centred.

    Each spot is rendered in a window reaching at least ``4 sigma + 1`` pixels from its
    centre, so less than ``2 erfc(2 sqrt(2))`` ≈ 1.3e-4 of its mass is cut. Spots are
    grouped by window half-width and rendered in vectorised batches with ``np.bincount``
    on a canvas padded by twice the largest window.
    """
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    halves = np.ceil(4 * sigmas + 1).astype(np.int64)  # tails beyond 4 sigma: < 1e-4
    reach = int(halves.max(initial=1))  # spots farther than this outside cannot touch
    inside = np.all((centres >= -reach) & (centres <= size - 1 + reach), axis=1)
    pad = 2 * reach + 1
    side = size + 2 * pad
    canvas = np.zeros(side * side)
    for half in np.unique(halves[inside]):
        chosen = np.flatnonzero(inside & (halves == half))
        width = 2 * half + 1
        for batch in np.array_split(chosen, 1 + chosen.size * width**2 // _MAX_SPLAT):
            row0, rows = _pixel_profile(centres[batch, 0], sigmas[batch], half)
            col0, cols = _pixel_profile(centres[batch, 1], sigmas[batch], half)
            weights = amplitudes[batch, None, None] * rows[:, :, None] * cols[:, None, :]
            offsets = np.arange(width)
            index = (row0[:, None, None] + pad + offsets[None, :, None]) * side + (
                col0[:, None, None] + pad + offsets[None, None, :]
            )
            canvas += np.bincount(index.ravel(), weights.ravel(), minlength=side * side)
    return canvas.reshape(side, side)[pad:-pad, pad:-pad]


def _tree_branches(
    rng: np.random.Generator,
    start: np.ndarray,
    heading: float,
    radius: float,
    length: float,
    depth: int,
    wiggle: float = 0.08,
    min_radius: float = 0.5,
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Centre-line samples of a random branching tree of tapering radius, branch by branch.

    Each branch is a smooth random walk (heading diffuses by ``wiggle`` rad per √px);
    children sprout along it with a smaller radius and a shorter length, down to ``depth``
    levels or ``min_radius``. Yields, per branch, points ``(n, 2)``, radii ``(n,)`` and the
    sample spacing ``(n,)`` needed to render a line of constant cross-section.
    """
    stack = [(np.asarray(start, dtype=np.float64), heading, radius, length, depth)]
    while stack:
        origin, angle, r0, span, level = stack.pop()
        r1 = max(min_radius, r0 * rng.uniform(0.6, 0.9))  # taper along the branch
        step = max(0.25, 0.5 * min(r0, r1) / 2)
        n = max(2, int(span / step))
        angles = angle + np.cumsum(rng.normal(0.0, wiggle * np.sqrt(step), n))
        path = origin + np.cumsum(step * np.stack([np.sin(angles), np.cos(angles)], 1), 0)
        taper = np.linspace(r0, r1, n)
        yield path, taper, np.full(n, step)
        if level == 0:
            continue
        for _ in range(rng.poisson(1.0 + span / 80.0)):
            k = rng.integers(n // 5, n)
            child = taper[k] * rng.uniform(0.45, 0.85)
            if child >= min_radius:
                turn = rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 1.2)
                stack.append((path[k], angles[k] + turn, child, span * rng.uniform(0.35, 0.75),
                              level - 1))


def _grown_tree(size: int, rng: np.random.Generator, *args: Any, **kwargs: Any) -> np.ndarray:
    """Grow a tree (:func:`_tree_branches` arguments) and render it at brightness 1.

    Branches are rendered in groups of at least :data:`_MAX_TREE_POINTS` samples as they
    grow, so memory does not grow with the tree (large fields grow trees of tens of
    millions of samples).
    """
    img = np.zeros((size, size))
    group: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def render() -> None:
        tree = tuple(np.concatenate(part) for part in zip(*group, strict=True))
        img[...] += _render_tree(size, tree, 1.0)
        group.clear()

    for branch in _tree_branches(rng, *args, **kwargs):
        group.append(branch)
        if sum(len(b[1]) for b in group) >= _MAX_TREE_POINTS:
            render()
    if group:
        render()
    return img


def _render_tree(size: int, tree, brightness: float) -> np.ndarray:
    """Render centre-line samples as tubes whose cross-section peaks at ``brightness``."""
    points, radii, steps = tree
    sigmas = radii / 2
    # A line of spots spaced ``step`` sums to (1 / step) × the 1-D integral of one
    # spot's profile, which is 1 / erf(0.5 / (√2 σ)) for the peak-1 pixel-integrated form.
    amplitudes = brightness * steps * special.erf(0.5 / (np.sqrt(2) * sigmas))
    return _render_spots(size, points, sigmas, amplitudes)


def _render_somata(
    size: int, centres: np.ndarray, radii: np.ndarray, amplitudes: np.ndarray,
    rng: np.random.Generator,
) -> np.ndarray:
    """Elliptic, flat-topped blobs ``exp(-ρ⁴)`` with a dimmer (nucleus-excluding) centre."""
    img = np.zeros((size, size))
    for (cr, cc), r, a in zip(centres, radii, amplitudes, strict=True):
        half = int(np.ceil(2 * r)) + 1
        r0, c0 = int(round(cr)) - half, int(round(cc)) - half
        rr, cc_ = np.mgrid[max(r0, 0):min(r0 + 2 * half + 1, size),
                           max(c0, 0):min(c0 + 2 * half + 1, size)]
        if rr.size == 0:
            continue
        theta, aspect = rng.uniform(0, np.pi), rng.uniform(0.7, 1.0)
        dv, du = rr - cr, cc_ - cc
        along = (dv * np.cos(theta) + du * np.sin(theta)) / r
        across = (-dv * np.sin(theta) + du * np.cos(theta)) / (r * aspect)
        rho2 = along**2 + across**2
        body = np.exp(-(rho2**2)) * (1 - rng.uniform(0.2, 0.7) * np.exp(-((rho2 / 0.3) ** 2)))
        img[rr, cc_] += a * body
    return img


# ----------------------------------------------------------------- generators
def beads(
    size: int,
    rng: np.random.Generator,
    density: Range = (0.3, 100.0),
    radius: Range = (0.3, 8.0),
    brightness: Range = (1e-2, 1.0),
    log_brightness: bool = True,
) -> np.ndarray:
    """Fluorescent beads: anti-aliased Gaussian spots at random sub-pixel positions.

    Parameters
    ----------
    size : int
        Side of the square grid.
    rng : numpy.random.Generator
        Source of randomness.
    density : float or (float, float)
        Beads per 100 × 100 pixels; a range is sampled log-uniformly per frame and the
        count is Poisson (at least 1). The default spans about 4 to 1500 beads at 384².
    radius : float or (float, float)
        Bead radius in pixels (Gaussian ``sigma = radius / 2``), log-uniform per bead.
    brightness : float or (float, float)
        Peak value of a bead, per bead, in ``(0, 1]``; ranges down to ``1e-3`` and below
        are fine (the default keeps most beads visible next to the brightest).
    log_brightness : bool
        Sample brightness log-uniformly (default) rather than uniformly.

    Returns
    -------
    numpy.ndarray
        float32 ``(size, size)`` in ``[0, 1]``. Brightness is absolute (a frame of dim beads
        stays dim) unless overlapping beads exceed 1, in which case the frame is divided by
        its maximum.
    """
    _check_size(size)
    n = _count(rng, density, size, "density")
    low, high = _as_range(brightness, "brightness")
    if high > 1:
        raise ValueError(f"brightness must lie in (0, 1], got {brightness!r}")
    centres = rng.uniform(-0.5, size - 0.5, (n, 2))
    radii = _log_uniform(rng, _as_range(radius, "radius"), n)
    values = _log_uniform(rng, (low, high), n) if log_brightness else rng.uniform(low, high, n)
    img = np.clip(_render_spots(size, centres, radii / 2, values), 0, None)
    return (img / max(1.0, img.max())).astype(np.float32)


def cells(
    size: int,
    rng: np.random.Generator,
    density: Range = (1.0, 10.0),
    empty_fraction: Range = (0.01, 0.4),
) -> np.ndarray:
    """Cell-like tissue: warped Voronoi cells with membranes, nuclei and textured cytoplasm.

    Each cell is the part of its (warped) Voronoi region within a random radius of its seed;
    its distance to the nearest cell boundary gives a bright membrane rim and a soft body.
    Per frame, the relative weight of membrane, cytoplasm and nucleus labelling is random
    (from membrane-only to nuclear-only stains); per cell the brightness is log-uniform.

    Parameters
    ----------
    size : int
        Side of the square grid.
    rng : numpy.random.Generator
        Source of randomness.
    density : float or (float, float)
        Cells per 100 × 100 pixels at size 384 (about 15 to 150 cells per frame by default);
        cell size follows from the spacing.
    empty_fraction : float or (float, float)
        Fraction of Voronoi regions left without a cell.

    Returns
    -------
    numpy.ndarray
        float32 ``(size, size)`` in ``[0, 1]``, maximum 1.
    """
    from scipy.spatial import cKDTree

    _check_size(size)
    n = _count(rng, density, REFERENCE_SIZE, "density")
    spacing = size / np.sqrt(n)
    seeds = rng.uniform(0, size, (n, 2))
    radius = spacing * rng.uniform(0.35, 0.65, n)
    grid = np.stack(np.mgrid[0:size, 0:size], -1).reshape(-1, 2).astype(np.float64)
    warp = 0.12 * spacing * np.stack(
        [_smooth_noise(rng, size, spacing / 3).ravel() for _ in range(2)], 1
    )
    dist, label = cKDTree(seeds).query(grid + warp, k=2)
    nearest = label[:, 0]
    gap = np.linalg.norm(seeds[label[:, 1]] - seeds[nearest], axis=1)
    to_edge = (dist[:, 1] ** 2 - dist[:, 0] ** 2) / (2 * np.maximum(gap, 1e-9))
    depth = np.minimum(to_edge, radius[nearest] - dist[:, 0])  # > 0 inside the cell
    rim_width = max(0.7, 0.06 * spacing)
    edge = max(0.6, rim_width / 2)
    body = special.expit(depth / edge)
    rim = np.exp(-0.5 * (depth / rim_width) ** 2) * special.expit((depth + rim_width) / edge)
    nucleus = special.expit((rng.uniform(0.3, 0.5) * radius[nearest] - dist[:, 0]) / edge)
    texture = 1 + 0.35 * _smooth_noise(rng, size, max(1.0, 0.04 * spacing)).ravel()
    weights = rng.dirichlet([0.7, 0.7, 0.7])  # membrane, cytoplasm, nucleus
    present = rng.random(n) >= rng.uniform(*_as_range(empty_fraction, "empty_fraction"))
    level = _log_uniform(rng, (0.15, 1.0), n) * present
    img = level[nearest] * (
        weights[0] * rim + (weights[1] * body + weights[2] * nucleus * body) * texture
    )
    return _to_unit(img.reshape(size, size))


def vessels(
    size: int,
    rng: np.random.Generator,
    trees: Range = (2.0, 6.0),
    radius: Range = (1.5, 6.0),
    capillaries: Range = (5.0, 40.0),
) -> np.ndarray:
    """Vasculature: branching, tapering, wiggling vessel trees and a faint capillary mesh.

    Parameters
    ----------
    size : int
        Side of the square grid.
    rng : numpy.random.Generator
        Source of randomness.
    trees : float or (float, float)
        Number of large trees per frame (log-uniform, rounded, at least 1). Trees enter from
        the border or start inside the field.
    radius : float or (float, float)
        Radius in pixels at size 384 of the trunk of each tree.
    capillaries : float or (float, float)
        Number of small, thin, dim trees per frame.

    Returns
    -------
    numpy.ndarray
        float32 ``(size, size)`` in ``[0, 1]``, maximum 1.
    """
    _check_size(size)
    scale = size / REFERENCE_SIZE
    img = np.zeros((size, size))
    radius = _as_range(radius, "radius")
    for _ in range(max(1, round(_log_uniform(rng, _as_range(trees, "trees"))))):
        start = rng.uniform(0, size, 2)
        heading = rng.uniform(0, 2 * np.pi)
        if rng.random() < 0.6:  # enter from a border, heading inwards
            side = rng.integers(4)
            start[side % 2] = 0.0 if side < 2 else size - 1.0
            heading = np.arctan2(size / 2 - start[0], size / 2 - start[1]) + rng.normal(0, 0.4)
        trunk = max(0.6, _log_uniform(rng, radius) * scale)
        tree = _grown_tree(size, rng, start, heading, trunk, size * rng.uniform(0.5, 1.2), depth=4)
        img += tree * rng.uniform(0.4, 1.0)
    for _ in range(round(_log_uniform(rng, _as_range(capillaries, "capillaries")))):
        tree = _grown_tree(size, rng, rng.uniform(0, size, 2), rng.uniform(0, 2 * np.pi),
                           rng.uniform(0.5, 1.0), size * rng.uniform(0.05, 0.2), depth=2,
                           wiggle=0.15)
        img += tree * rng.uniform(0.05, 0.3)
    return _to_unit(img)


def neurons(
    size: int,
    rng: np.random.Generator,
    density: Range = (0.3, 3.0),
    soma_radius: Range = (4.0, 9.0),
    background: Range = (0.02, 0.12),
) -> np.ndarray:
    """Neurons in a brain section: somata with tapering dendrites on a neuropil background.

    Parameters
    ----------
    size : int
        Side of the square grid.
    rng : numpy.random.Generator
        Source of randomness.
    density : float or (float, float)
        Somata per 100 × 100 pixels at size 384 (about 4 to 45 per frame by default).
    soma_radius : float or (float, float)
        Soma radius in pixels at size 384.
    background : float or (float, float)
        Mean level of the neuropil texture relative to a soma.

    Returns
    -------
    numpy.ndarray
        float32 ``(size, size)`` in ``[0, 1]``, maximum 1.
    """
    _check_size(size)
    scale = size / REFERENCE_SIZE
    n = _count(rng, density, REFERENCE_SIZE, "density")
    centres = rng.uniform(0, size, (n, 2))
    radii = np.maximum(1.5, _log_uniform(rng, _as_range(soma_radius, "soma_radius"), n) * scale)
    levels = _log_uniform(rng, (0.3, 1.0), n)
    img = _render_somata(size, centres, radii, levels, rng)
    for centre, r, level in zip(centres, radii, levels, strict=True):
        for angle in rng.uniform(0, 2 * np.pi) + np.linspace(0, 2 * np.pi, rng.integers(3, 8),
                                                             endpoint=False):
            angle += rng.normal(0, 0.3)
            start = centre + 0.8 * r * np.array([np.sin(angle), np.cos(angle)])
            tree = _grown_tree(size, rng, start, angle, rng.uniform(0.25, 0.45) * r,
                               r * rng.uniform(4, 14), depth=2, wiggle=0.12, min_radius=0.4)
            img += tree * (level * rng.uniform(0.2, 0.5))
    texture = sum(w * _smooth_noise(rng, size, s * scale) for w, s in ((0.5, 2), (1, 8), (1, 30)))
    neuropil = np.clip(1 + 0.5 * texture / texture.std(), 0, None) * _log_uniform(
        rng, _as_range(background, "background")
    )
    puncta = beads(size, rng, density=(20.0, 80.0), radius=(0.4, 1.5), brightness=(0.02, 0.15))
    return _to_unit(img + neuropil + puncta)


@functools.cache
def _bundled_images() -> tuple[np.ndarray, ...]:
    """Dark-background maps from images inside scikit-image's data folder (read once)."""
    import skimage.color
    import skimage.data
    import skimage.io
    from scipy import ndimage

    folder = Path(skimage.data.__file__).parent
    paths = [folder / "hubble_deep_field.jpg", folder / "retina.jpg"]
    for path in paths:
        if not path.is_file():
            raise FileNotFoundError(f"scikit-image's bundled sample {path} is missing")
    sky = skimage.color.rgb2gray(skimage.io.imread(paths[0]))
    sky = normalize_object(sky, background_percentile=60.0, upper_percentile=99.95)
    fundus = skimage.io.imread(paths[1])[::2, ::2].astype(np.float64) / 255.0
    green = fundus[..., 1]
    inside = ndimage.distance_transform_edt(fundus[..., 0] > 0.08) > 12
    vessel_map = np.clip(ndimage.gaussian_filter(green, 6) - green, 0, None) * inside
    vessel_map = normalize_object(vessel_map, background_percentile=80.0, upper_percentile=99.9)
    images = [sky, vessel_map]
    for name in TRAINING_PHOTOS:
        image = skimage.io.imread(folder / name)
        grey = skimage.color.rgb2gray(image[..., :3]) if image.ndim == 3 else image / 255.0
        step = max(1, min(grey.shape) // 512)  # keep each map small in memory
        images.append(np.asarray(grey[::step, ::step], dtype=np.float32))
    for image in images:
        image.flags.writeable = False  # shared by every call
    return tuple(images)


TRAINING_PHOTOS = (
    "astronaut.png", "brick.png", "camera.png", "chelsea.png", "coffee.png", "coins.png",
    "grass.png", "gravel.png", "horse.png", "moon.png", "page.png", "rocket.jpg", "text.png",
)  # fmt: skip
"""Photographs inside scikit-image's data folder used as training textures (besides the
Hubble deep field and the retina): grey levels turned into bright-on-dark maps by
:func:`skimage_crop`. Disjoint from :data:`HELD_OUT_IMAGES`, which only benchmarks use."""


def _fluorescence_map(crop: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A grey-level crop as a fluorescence-like map: as is, inverted, or its local
    contrast, with a random share of the dimmest pixels cut to a dark background."""
    from scipy import ndimage

    choice = rng.integers(3)
    if choice == 1:
        crop = crop.max() - crop
    elif choice == 2:
        crop = np.abs(crop - ndimage.gaussian_filter(crop, rng.uniform(2.0, 8.0)))
    return normalize_object(crop, background_percentile=float(rng.uniform(0.0, 80.0)))


def skimage_crop(size: int, rng: np.random.Generator) -> np.ndarray:
    """A random crop, 90° rotation and flip of an image bundled with scikit-image.

    The Hubble deep field and the retina's vessels are used as they are; the photographs
    of :data:`TRAINING_PHOTOS` become bright-on-dark maps (:func:`_fluorescence_map`:
    grey levels, inverted, or local contrast, over a dark background of random extent),
    so the content ranges from sparse to dense. The crop side is 25 % to 100 % of the
    image's short side (so the scale varies), and the crop is resized with anti-aliasing
    to ``size × size``. :data:`HELD_OUT_IMAGES` are never used.

    Returns
    -------
    numpy.ndarray
        float32 ``(size, size)`` in ``[0, 1]``.
    """
    import skimage.transform

    _check_size(size)
    images = _bundled_images()
    image = images[rng.integers(len(images))]
    side = int(min(image.shape) * rng.uniform(0.25, 1.0))
    top = rng.integers(0, image.shape[0] - side + 1)
    left = rng.integers(0, image.shape[1] - side + 1)
    crop = np.rot90(image[top:top + side, left:left + side], rng.integers(4))
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
    resized = skimage.transform.resize(crop, (size, size), order=1, anti_aliasing=True)
    if image is images[0] or image is images[1]:
        return normalize_object(resized, background_percentile=0.0)
    return _fluorescence_map(resized, rng)


def isolated_cells(
    size: int,
    rng: np.random.Generator,
    count: Range = (1.0, 8.0),
    radius: Range = (8.0, 60.0),
) -> np.ndarray:
    """A few large cells alone in a dark field: textured ellipses with soft edges.

    Large bright objects with nothing around them are where the demixing is least
    determined: their light reaches the neighbouring lenses' views one pitch away, and
    with the outer views cut by the sensor edge a copy there can pass for an object of its
    own. Dense content rarely shows this case.

    Parameters
    ----------
    size : int
        Side of the square grid.
    rng : numpy.random.Generator
        Source of randomness.
    count : float or (float, float)
        Number of cells, drawn log-uniformly and rounded.
    radius : float or (float, float)
        Semi-major axis in pixels at size 384 (log-uniform, scaled with ``size``); the
        semi-minor axis is 60–100 % of it.

    Returns
    -------
    numpy.ndarray
        float32 ``(size, size)`` in ``[0, 1]``, maximum 1.

    Examples
    --------
    >>> obj = isolated_cells(96, np.random.default_rng(0))
    >>> obj.shape, float(obj.max()), bool(np.median(obj) < 1e-3)  # mostly dark
    ((96, 96), 1.0, True)
    """
    _check_size(size)
    n = int(round(_log_uniform(rng, _as_range(count, "count"))))
    major = _log_uniform(rng, _as_range(radius, "radius"), n) * size / REFERENCE_SIZE
    minor = major * rng.uniform(0.6, 1.0, n)
    centres = rng.uniform(0, size, (n, 2))
    angles = rng.uniform(0, np.pi, n)
    levels = _log_uniform(rng, (0.3, 1.0), n)
    rows, cols = np.mgrid[0:size, 0:size].astype(np.float64)
    img = np.zeros((size, size))
    for centre, a, b, angle, level in zip(centres, major, minor, angles, levels, strict=True):
        dy, dx = rows - centre[0], cols - centre[1]
        u = dx * np.cos(angle) + dy * np.sin(angle)
        v = -dx * np.sin(angle) + dy * np.cos(angle)
        depth = (1 - np.hypot(u / a, v / b)) * b  # about the distance inside the edge
        body = special.expit(depth / rng.uniform(0.7, 3.0))
        texture = 1 + 0.3 * _smooth_noise(rng, size, max(1.0, 0.1 * b))
        img = np.maximum(img, level * body * texture)
    return _to_unit(img)


MIXED_KINDS = ("beads", "cells", "vessels", "neurons", "skimage")
MIXED_WEIGHTS = (0.2, 0.2, 0.15, 0.15, 0.3)


def mixed(
    size: int,
    rng: np.random.Generator,
    kinds: tuple[str, ...] = MIXED_KINDS,
    weights: tuple[float, ...] = MIXED_WEIGHTS,
) -> np.ndarray:
    """One kind at random (70 %) or a blend of two different kinds (30 %), for diversity;
    30 % of the draws sit on a smooth in-focus background of 5–30 % of the peak.

    ``kinds`` are drawn with probabilities ``weights``; the defaults are the ``mixed``
    kind, and ``mixed-isolated`` adds ``isolated-cells``.

    Returns
    -------
    numpy.ndarray
        float32 ``(size, size)`` in ``[0, 1]``.
    """
    chosen = rng.choice(list(kinds), size=2, replace=False, p=list(weights))
    first = KINDS[str(chosen[0])](size, rng)
    if rng.random() < 0.7:
        out = first
    else:
        weight = rng.uniform(0.3, 0.7)
        out = _to_unit(weight * first + (1 - weight) * KINDS[str(chosen[1])](size, rng))
    if rng.random() < 0.3:  # in-focus autofluorescence: a smooth floor under the structures
        floor = _smooth_noise(rng, size, size / rng.uniform(2.0, 8.0))
        out = _to_unit(out + rng.uniform(0.05, 0.3) * (floor - floor.min()) / np.ptp(floor))
    return out


KINDS: dict[str, Callable[..., np.ndarray]] = {
    "beads": beads,
    "cells": cells,
    "vessels": vessels,
    "neurons": neurons,
    "skimage": skimage_crop,
    "isolated-cells": isolated_cells,
    "mixed": mixed,
    "mixed-isolated": functools.partial(
        mixed, kinds=(*MIXED_KINDS, "isolated-cells"), weights=(0.15, 0.15, 0.12, 0.12, 0.26, 0.2)
    ),
}


def make_object(
    kind: str,
    size: int,
    seed_or_rng: int | np.random.Generator | None = None,
    **params,
) -> np.ndarray:
    """Generate an object of the given kind; the seed fixes the result.

    Parameters
    ----------
    kind : str
        One of :data:`KINDS`: ``"beads"``, ``"cells"``, ``"vessels"``, ``"neurons"``,
        ``"skimage"``, ``"isolated-cells"``, ``"mixed"``, ``"mixed-isolated"``.
    size : int
        Side of the square grid.
    seed_or_rng : int, numpy.random.Generator or None
        Seed, or a generator to draw from (it advances).
    **params
        Keyword arguments of the kind's generator (e.g. ``density`` for beads).

    Returns
    -------
    numpy.ndarray
        float32 ``(size, size)`` in ``[0, 1]``.

    Examples
    --------
    >>> obj = make_object("beads", 64, 0)
    >>> obj.shape, obj.dtype.name, bool(obj.min() >= 0 and obj.max() <= 1)
    ((64, 64), 'float32', True)
    """
    if kind not in KINDS:
        raise ValueError(f"unknown object kind {kind!r}; choose one of {', '.join(KINDS)}")
    return KINDS[kind](size, np.random.default_rng(seed_or_rng), **params)


# ------------------------------------------------------------- real images
def normalize_object(
    img: np.ndarray,
    background_percentile: float = 1.0,
    upper_percentile: float = 100.0,
    background_sigma: float | None = None,
) -> np.ndarray:
    """Suppress the background and stretch the contrast to ``[0, 1]``.

    The background is the ``background_percentile`` of the image or, when
    ``background_sigma`` is given, a smooth lower envelope (Gaussian smoothing of the image
    capped by its own local mean, smoothed again) for uneven illumination. It is subtracted
    and the result clipped at 0; then the image is divided by its ``upper_percentile``
    (100: the maximum; lower values saturate hot pixels) and clipped to 1.

    Parameters
    ----------
    img : array_like
        Image of any shape and numeric dtype.
    background_percentile : float
        Percentile in ``[0, 100)`` taken as the background level.
    upper_percentile : float
        Percentile in ``(background_percentile, 100]`` mapped to 1.
    background_sigma : float, optional
        Scale in pixels of a smooth background estimate, used instead of the percentile.

    Returns
    -------
    numpy.ndarray
        float32, same shape, in ``[0, 1]``; all zeros when nothing is left above the
        background (e.g. a constant image).

    Raises
    ------
    ValueError
        On NaN or Inf values, or percentiles out of range.
    """
    from scipy import ndimage

    img = np.asarray(img, dtype=np.float64)
    if not np.isfinite(img).all():
        raise ValueError("image holds NaN or Inf values")
    if not 0 <= background_percentile < upper_percentile <= 100:
        raise ValueError(
            "percentiles must satisfy 0 <= background_percentile < upper_percentile <= 100, "
            f"got {background_percentile} and {upper_percentile}"
        )
    if img.size == 0:
        return img.astype(np.float32)
    if background_sigma is None:
        background = np.percentile(img, background_percentile)
    else:
        if not background_sigma > 0:
            raise ValueError(f"background_sigma must be > 0, got {background_sigma!r}")
        local_mean = ndimage.gaussian_filter(img, background_sigma, mode="nearest")
        background = ndimage.gaussian_filter(
            np.minimum(img, local_mean), background_sigma, mode="nearest"
        )
    img = np.clip(img - background, 0, None)
    scale = np.percentile(img, upper_percentile)
    if scale <= 0:
        return np.zeros(img.shape, dtype=np.float32)
    return np.clip(img / scale, 0, 1).astype(np.float32)


def from_image(
    image_or_path: np.ndarray | str | Path,
    size: int,
    background_percentile: float = 1.0,
    upper_percentile: float = 100.0,
) -> np.ndarray:
    """An object from any 2-D image: luminance, centre crop, anti-aliased resize, normalise.

    Parameters
    ----------
    image_or_path : array_like, str or Path
        A 2-D grey image, an RGB(A) image ``(rows, cols, 3 or 4)`` (converted to luminance,
        alpha ignored), or the path of a TIFF or PNG (any format scikit-image reads).
    size : int
        Side of the square result.
    background_percentile, upper_percentile : float
        Passed to :func:`normalize_object`.

    Returns
    -------
    numpy.ndarray
        float32 ``(size, size)`` in ``[0, 1]``. A non-square image is first cropped to the
        centred square of its short side (nothing is stretched), then resized with
        ``skimage.transform.resize(anti_aliasing=True)``.

    Raises
    ------
    ValueError
        If the image is not 2-D grey or RGB(A), or holds NaN or Inf.
    """
    import skimage.color
    import skimage.io
    import skimage.transform

    _check_size(size)
    if isinstance(image_or_path, (str, Path)):
        path = Path(image_or_path)
        if path.suffix.lower() in (".tif", ".tiff"):
            image = tifffile.imread(path)
        else:
            image = skimage.io.imread(path)
    else:
        image = image_or_path
    image = np.asarray(image, dtype=np.float64)
    if image.ndim == 3 and image.shape[-1] in (3, 4):
        image = skimage.color.rgb2gray(image[..., :3])
    if image.ndim != 2:
        raise ValueError(
            f"expected a 2-D grey or (rows, cols, 3|4) RGB image, got shape {image.shape}"
        )
    if not np.isfinite(image).all():
        raise ValueError("image holds NaN or Inf values")
    side = min(image.shape)
    top, left = (image.shape[0] - side) // 2, (image.shape[1] - side) // 2
    square = image[top:top + side, left:left + side]
    resized = skimage.transform.resize(square, (size, size), order=1, anti_aliasing=True,
                                       preserve_range=True)
    return normalize_object(resized, background_percentile, upper_percentile)


# ------------------------------------------------------------ held-out test images
#: scikit-image sample files kept out of every training set: benchmark content only.
HELD_OUT_IMAGES = ("cell.png", "ihc.png", "microaneurysms.png")


def _held_out_map(name: str, image: np.ndarray) -> tuple[np.ndarray, float]:
    """A bright-on-dark map of one held-out image and the background percentile to cut."""
    import skimage.color
    from scipy import ndimage

    if name == "ihc.png":  # stained tissue: haematoxylin + DAB optical densities as dye
        stains = skimage.color.rgb2hed(image[..., :3])
        return stains[..., 0] + stains[..., 2], 50.0
    grey = image.astype(np.float64) / 255.0
    if name == "microaneurysms.png":  # dark vessels and lesions on a retina: invert locally
        return np.clip(ndimage.gaussian_filter(grey, 8) - grey, 0, None), 80.0
    return grey, 75.0  # cell.png: a bright cell on a darker field


def held_out_image(name: str, size: int) -> np.ndarray:
    """A held-out scikit-image sample as a dark-background, fluorescence-like object.

    Parameters
    ----------
    name : str
        One of :data:`HELD_OUT_IMAGES`: ``cell.png`` (a cell, bright on its background),
        ``ihc.png`` (immunohistochemistry: the two stains' optical densities, so nuclei and
        membranes glow), ``microaneurysms.png`` (retinal vessels and lesions, inverted
        against a smooth background).
    size : int
        Side of the square result (centre square of the image, anti-aliased resize).

    Returns
    -------
    numpy.ndarray
        float32 ``(size, size)`` in ``[0, 1]``, background at 0 (the given percentile of
        the map is subtracted), the 99.5th percentile at 1.

    Raises
    ------
    ValueError
        For a name not in :data:`HELD_OUT_IMAGES`.
    FileNotFoundError
        If scikit-image does not ship the file.
    """
    import skimage.io

    if name not in HELD_OUT_IMAGES:
        raise ValueError(f"unknown held-out image {name!r}; choose one of "
                         f"{', '.join(HELD_OUT_IMAGES)}")  # fmt: skip
    import skimage.data

    path = Path(skimage.data.__file__).parent / name
    if not path.is_file():
        raise FileNotFoundError(f"scikit-image's bundled sample {path} is missing")
    image, background = _held_out_map(name, skimage.io.imread(path))
    return from_image(image, size, background_percentile=background, upper_percentile=99.5)
