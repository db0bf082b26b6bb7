"""Sample data: simulated raw CM² frames with their ground truth, made on demand.

Each sample is simulated the first time it is asked for (phantom, SV forward model,
sensor noise; a fixed seed) and kept in memory for the session.
"""

from __future__ import annotations

import functools

from svcode_core.config import SystemConfig
from svcode_core.phantoms import make_object
from svcode_core.physics.simulate import Simulation

from ._layers import in_micrometres, layer_metadata, object_translate, placement, show_scale_bar
from ._resources import simulator

__all__ = [
    "SAMPLE_KINDS",
    "make_beads_sample",
    "make_cells_sample",
    "make_paper_cells_sample",
    "make_vessels_sample",
    "sample_layers",
]

SAMPLE_KINDS = ("beads", "cells", "vessels")
SAMPLE_SYSTEM = "cm2-mini"
#: the paper-scale sample's system: a 3000 × 4000 frame, about a minute to simulate
PAPER_SYSTEM = "cm2-v2"
SAMPLE_SEED = 0


@functools.lru_cache(maxsize=6)
def _simulate(kind: str, system: SystemConfig) -> Simulation:
    obj = make_object(kind, system.sub_view_size, SAMPLE_SEED)
    return simulator(system).simulate(obj, seed=SAMPLE_SEED)


def sample_layers(kind: str, system: SystemConfig | None = None) -> list[tuple]:
    """Layer data for a simulated frame of ``kind``: ground truth (hidden) and raw frame.

    Parameters
    ----------
    kind : {"beads", "cells", "vessels"}
    system : SystemConfig, optional
        Default: the ``cm2-mini`` preset.

    Returns
    -------
    list of napari layer-data tuples
        The ground truth on the object grid, placed over the raw frame, and the raw frame;
        both record the system and one scene id (``svcode_scene``) in their metadata and
        are in object-space µm (the current viewer's scale bar is shown).
    """
    if kind not in SAMPLE_KINDS:
        raise ValueError(f"unknown sample {kind!r}; choose one of {', '.join(SAMPLE_KINDS)}")
    system = system or SystemConfig.preset(SAMPLE_SYSTEM)
    scene = _simulate(kind, system)
    scene_id = f"sample {kind} {system.name} seed {SAMPLE_SEED}"  # links truth and frame
    truth = {
        "name": f"{kind} ground truth",
        **placement(system, 2, object_translate(system)),
        "metadata": layer_metadata(system, "object", scene=scene_id),
        "colormap": "magma",
        "visible": False,
    }
    raw = {
        "name": f"{kind} raw",
        **placement(system, 2),
        "metadata": layer_metadata(system, "measurement", scene=scene_id),
        "colormap": "gray",
    }
    if in_micrometres(raw):
        show_scale_bar()
    return [(scene.object, truth, "image"), (scene.measurement, raw, "image")]


def make_beads_sample() -> list[tuple]:
    """Simulated ``cm2-mini`` frame of fluorescent beads with its ground truth."""
    return sample_layers("beads")


def make_cells_sample() -> list[tuple]:
    """Simulated ``cm2-mini`` frame of cells with its ground truth."""
    return sample_layers("cells")


def make_vessels_sample() -> list[tuple]:
    """Simulated ``cm2-mini`` frame of vessels with its ground truth."""
    return sample_layers("vessels")


def make_paper_cells_sample() -> list[tuple]:
    """Simulated paper-scale ``cm2-v2`` frame of cells (3000 × 4000) with its ground truth:
    about a minute to simulate on a laptop's processor."""
    return sample_layers("cells", SystemConfig.preset(PAPER_SYSTEM))
