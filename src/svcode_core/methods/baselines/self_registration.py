"""Chief-ray self-registration of a raw frame: reconstruct, register, rebuild, repeat.

:func:`~svcode_core.physics.registration.register_views` measures how far each lens's sub-view
sits from where the forward model puts it, given an object estimate. A first
reconstruction with misregistered lenses blurs their disagreement into the estimate, so
one round finds only part of the drift; each round here reconstructs with the operator
the last round moved (LSV-ADMM, a few iterations at low rank), registers the residual
offsets and adds them up.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from ...config import N_LENSES, SystemConfig
from ...physics.calibration import fit_array
from ...physics.cm2 import CM2Operator
from ...physics.registration import Registration, register_views, registered_system
from . import BaselineReconstructor, settings_for

__all__ = [
    "MAX_LENS_RESIDUAL_PX",
    "REGISTRATION_FRAMES",
    "SELF_REGISTRATION_ROUNDS",
    "RegistrationRejected",
    "register_recording",
    "self_register",
]

#: rounds of reconstruct → register → rebuild (the third moves offsets by < 0.05 px on
#: ``cm2-mini``, ``bench/results/calibration.md``)
SELF_REGISTRATION_ROUNDS = 3
#: a recording is registered on the mean of its first frames (more signal, same drift)
REGISTRATION_FRAMES = 8
#: a lens further than this from the array's fitted translation and rotation means the
#: registration locked onto the object's own structure (seen on a dense cell scene), not
#: a drift: it is then not applied
MAX_LENS_RESIDUAL_PX = 1.0


class RegistrationRejected(ValueError):
    """Self-registration found offsets no rigid lens array explains; nothing was moved."""


def self_register(
    frame: np.ndarray,
    system: SystemConfig,
    rounds: int = SELF_REGISTRATION_ROUNDS,
    rank: int = 3,
    iterations: int = 10,
    reference: int = 4,
    progress: Callable[[str, float], None] | None = None,
) -> tuple[Registration, SystemConfig, np.ndarray]:
    """Estimate the lens offsets of ``system`` from ``frame`` and move the system by them.

    Parameters
    ----------
    frame : numpy.ndarray
        Raw sensor frame ``system.sensor_shape``.
    system : SystemConfig
        The system believed (its chief rays and PSF model are the start).
    rounds : int
        Reconstruct → register → rebuild rounds (≥ 1).
    rank, iterations : int
        LSV-ADMM's low-rank order and iterations for the intermediate reconstructions.
    reference : int
        Lens whose offset is 0.
    progress : callable, optional
        Called as ``progress(stage, fraction)`` before each round and at the end; an
        exception it raises stops the registration (how a caller cancels).

    Returns
    -------
    (Registration, SystemConfig, numpy.ndarray)
        The summed offsets (relative to ``reference``, as found), the system moved by
        them and its PSFs ``(9, G·G, k, k)`` (:meth:`CM2Operator.from_psfs` builds the
        operator any method uses).

    Raises
    ------
    ValueError
        For a frame of another size or ``rounds < 1``.
    """
    if not isinstance(rounds, int) or rounds < 1:
        raise ValueError(f"rounds must be a positive integer, got {rounds!r}")
    system = system.validate()
    offsets = np.zeros((N_LENSES, 2))
    moved, operator = system, CM2Operator.from_system(system, rank=rank)
    for round_ in range(rounds):
        if progress is not None:
            progress(f"round {round_ + 1} of {rounds}", round_ / rounds)
        # the fixed λ: the registration's thresholds were measured with it
        solver = BaselineReconstructor("admm", moved, operator=operator, iterations=iterations,
                                       tv_weight=settings_for(moved).tv_weight)
        estimate = solver.reconstruct(frame).reconstruction
        found = register_views(frame, moved, estimate, operator, reference)
        offsets = offsets + found.offsets
        moved, psfs = registered_system(system, offsets)
        if round_ < rounds - 1:
            operator = CM2Operator.from_psfs(moved, psfs, rank=rank)
    shift, rotation, residuals = fit_array(offsets, system)
    registration = replace(found, offsets=offsets, shift=shift, rotation_deg=rotation,
                           residuals=residuals)
    if progress is not None:
        progress("done", 1.0)
    return registration, moved, psfs


def register_recording(
    frames: np.ndarray,
    system: SystemConfig,
    folder: str | Path,
    progress: Callable[[str, float], None] | None = None,
) -> tuple[SystemConfig, Registration]:
    """Self-register a recording and write the moved system into ``folder``.

    Parameters
    ----------
    frames : numpy.ndarray
        Raw frames ``(T, H, W)``; the mean of the first :data:`REGISTRATION_FRAMES` is
        registered.
    system : SystemConfig
        The system believed.
    folder : str or Path
        Receives ``system.json`` (its ``psf_model`` the moved PSFs ``psfs.tif``, beside
        it with their positions) and ``registration.json``.
    progress : callable, optional
        Passed to :func:`self_register`.

    Returns
    -------
    (SystemConfig, Registration)
        The moved system (as written) and the offsets found.

    Raises
    ------
    RegistrationRejected
        If a lens sits more than :data:`MAX_LENS_RESIDUAL_PX` from the array fit (the
        message names it); nothing is written.
    """
    from ...io import write_json_atomic
    from ...physics.psf_io import save_psfs

    frame = np.mean(np.asarray(frames[:REGISTRATION_FRAMES], dtype=np.float64), axis=0)
    registration, moved, psfs = self_register(frame, system, progress=progress)
    misfit = np.linalg.norm(registration.residuals, axis=1)
    if misfit.max() > MAX_LENS_RESIDUAL_PX:
        lens = int(misfit.argmax())
        raise RegistrationRejected(
            f"self-registration not applied: lens {lens} would move {misfit[lens]:.1f} px "
            f"away from the rest of the array (at most {MAX_LENS_RESIDUAL_PX} px is a "
            "drift); the scene's own structure misled it, recalibrate with a bead scan")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    psf_file, _ = save_psfs(folder / "psfs.tif", psfs, moved)
    moved = moved.replace(psf_model=str(psf_file.resolve()))
    moved.save(folder / "system.json")
    write_json_atomic(folder / "registration.json", registration.to_dict())
    return moved, registration
