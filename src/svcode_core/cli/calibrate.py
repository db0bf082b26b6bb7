"""``svcode calibrate``: a calibrated system from a point-source scan."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING

from . import SUMMARIES, add_system_arguments, chosen_system

if TYPE_CHECKING:
    import numpy as np


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svcode calibrate``."""
    parser = subparsers.add_parser(
        "calibrate",
        help=SUMMARIES["calibrate"],
        description=(
            "Fit the chief rays, the lens array's shift and rotation, the per-lens PSFs on "
            "the system's PSF grid, the vignetting and the low-rank order from a scan of a "
            "point source (one raw frame per position). Writes OUT/system.json with the PSF "
            "stack it refers to (psfs.tif), calibration.json, report.txt and report.png; "
            "give OUT/system.json to --system of every other command."
        ),
    )
    parser.add_argument("scan", type=Path, metavar="SCAN.tif", help="N×H×W raw frames")
    parser.add_argument("--positions", type=Path, required=True, metavar="POS.csv",
                        help="the source position of each frame, in the scan's order: "
                        "header 'row,col' then object pixels (fractions allowed), or "
                        "header 'x_um,y_um' then stage micrometres from the field's centre "
                        "(scaled by --pixel-size); the frames of a repeated position are "
                        "averaged")  # fmt: skip
    parser.add_argument("--pixel-size", type=float, metavar="UM",
                        help="object-space pixel size in micrometres (sensor pixel over "
                        "magnification), for positions in micrometres (default: the "
                        "system's object_pixel_um)")  # fmt: skip
    add_system_arguments(parser, default=None, what="the nominal system (sensor, grid, "
                         "starting values)", default_text="required")  # fmt: skip
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--dark", type=Path, metavar="DARK.tif",
                        help="dark frame or stack (averaged) to subtract; default: each "
                        "frame's median")  # fmt: skip
    parser.add_argument("--tolerance", type=float,
                        help="low-rank tolerance: PSF energy fraction left out "
                        "(default: the system's rank_tolerance)")  # fmt: skip
    parser.add_argument("--saturation", type=float,
                        help="reading at which a pixel saturates (default: the full scale "
                        "of integer frames, else the system's noise.saturation)")  # fmt: skip
    parser.set_defaults(func=run)


def _scan(path: Path) -> np.ndarray:
    """The scan's frames ``(N, H, W)``, memory-mapped where the TIFF allows: a paper-scale
    scan of 4 frames per position is 15 GB, and the calibration reads it a frame at a time."""
    import numpy as np

    from ..io import mapped_tiff, read_tiff

    frames = mapped_tiff(path)
    if frames is None:  # compressed, scattered or unreadable (read_tiff names the problem)
        frames = np.asarray(read_tiff(path)[0])
    return frames[None] if frames.ndim == 2 else frames


def run(args: argparse.Namespace) -> int:
    """Calibrate and write the files; print a summary."""
    # scipy.stats and scikit-image's feature module: only when calibrating
    import numpy as np

    from ..evaluation.figures import calibration_figure
    from ..io import read_tiff
    from ..physics.calibration import calibrate, read_positions, save_calibration

    nominal = chosen_system(args)
    if nominal is None:
        raise ValueError("give the nominal system: --system NAME or FILE.json")
    frames = _scan(args.scan)
    pixel_size = nominal.object_pixel_um if args.pixel_size is None else args.pixel_size
    positions = read_positions(args.positions, pixel_size, size=nominal.sub_view_size,
                               frames=len(frames))  # fmt: skip
    dark = None if args.dark is None else np.asarray(read_tiff(args.dark)[0])
    start = time.perf_counter()
    calibration = calibrate(frames, positions, nominal, dark=dark, tolerance=args.tolerance,
                            saturation=args.saturation)  # fmt: skip
    files = save_calibration(calibration, args.out, nominal)
    files["figure"] = calibration_figure(args.out / "report.png", calibration, frames)
    seconds = time.perf_counter() - start
    shift = calibration.array_shift
    print(f"calibrated {nominal.name} from {len(frames)} frames in {seconds:.1f} s: array "
          f"shift ({shift[0]:+.2f}, {shift[1]:+.2f}) px, rotation "
          f"{calibration.array_rotation_deg:+.3f} deg, K = {max(calibration.ranks)} "
          f"-> {files['system']}")
    return 0
