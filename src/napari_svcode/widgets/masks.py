"""Coordinate-mask dock widget: one CoordGate mask over the field, computed on request."""

from __future__ import annotations

from pathlib import Path

import napari
import numpy as np
from magicgui.widgets import ComboBox, Container, PushButton, SpinBox
from napari.qt.threading import FunctionWorker
from napari.utils.notifications import show_info

from svcode_core.config import SystemConfig

from .._layers import layer_metadata, notify_error, object_translate, placement
from .._resources import cached_model
from .._workers import function_worker
from ._choosers import ModelChooser

__all__ = ["MaskWidget", "block_help", "layer_help", "stage_help"]

_STAGES = {
    "demix": "demix: the demixing network (the nine raw sub-views → nine demixed views)",
    "recon": "recon: the reconstruction network (the demixed views → the object)",
}
_LAYERS = {
    "conv1": "1×1 convolution that widens the features (c → 2c) before the 3×3 one",
    "conv2": "3×3 depth-wise convolution (the spatial filter of the block)",
    "conv3": "1×1 convolution after the channel attention, back to c channels",
    "conv4": "1×1 convolution that widens the features of the feed-forward part",
    "conv5": "1×1 convolution at the end of the feed-forward part",
}


def stage_help(stage: str | None) -> str:
    """Help text for a network stage (``"demix"`` or ``"recon"``)."""
    return _STAGES.get(stage or "", "the network stage: demix or recon")


def block_help(block: str | None) -> str:
    """Help text for a block name such as ``"view"``, ``"enc1.0"``, ``"dec0.1"``, ``"middle.0"``."""
    name, _, index = (block or "").partition(".")
    if name == "view":
        return "view: the first block, run on each lens's view with lens-specific masks"
    for prefix, where in (("enc", "encoder"), ("dec", "decoder")):
        if name.startswith(prefix) and name[len(prefix):].isdigit():
            level = int(name[len(prefix):])
            return (f"{block}: {where} level {level} (features at 1/{2 ** level} of the tile "
                    f"size), block {index}")
    if name == "middle":
        return f"{block}: bottleneck block {index} (the coarsest features)"
    return "the CoDe block: view, encL.i (encoder), middle.i, decL.i (decoder)"


def layer_help(layer: str | None) -> str:
    """Help text for a gated convolution of a block (``"conv1"`` ... ``"conv5"``)."""
    return _LAYERS.get(layer or "", "the gated convolution of the block (conv1 … conv5)")


class MaskWidget(Container):
    """Show the coordinate mask ``M(r)`` of any CoDe layer as an Image layer.

    *Load model* lists the gated layers of the model; choose the stage, block, layer, lens
    (for the lens-specific first block) and channel, then *Show mask*. A mask is computed
    in a worker thread the first time it is asked for and cached; it is placed over the
    raw frame like the reconstruction (masks live on the sub-view grid).
    """

    def __init__(self, napari_viewer: napari.viewer.Viewer) -> None:
        self._viewer = napari_viewer
        self._loaded: tuple | None = None  # (path, model, system, mask layers)
        self._model = ModelChooser()
        self._load = PushButton(text="Load model")
        self._stage = ComboBox(label="stage", choices=self._stages, tooltip=stage_help(None))
        self._block = ComboBox(label="block", choices=self._blocks, tooltip=block_help(None))
        self._gate = ComboBox(label="layer", choices=self._gates, tooltip=layer_help(None))
        self._lens = SpinBox(label="lens", min=0, max=8,
                             tooltip="lens 0–8 (row by row); only the view block has "
                                     "lens-specific masks")
        self._channel = SpinBox(label="channel", min=0, max=0,
                                tooltip="output channel of the layer whose mask is shown")
        self._run = PushButton(text="Show mask")
        super().__init__(widgets=[self._model, self._load, self._stage, self._block, self._gate,
                                  self._lens, self._channel, self._run])
        self._load.changed.connect(self.load_model)
        self._stage.changed.connect(self._block.reset_choices)
        self._block.changed.connect(self._gate.reset_choices)
        self._gate.changed.connect(self._update_channels)
        for box, describe in ((self._stage, stage_help), (self._block, block_help),
                              (self._gate, layer_help)):
            box.changed.connect(lambda value, box=box, describe=describe:
                                setattr(box, "tooltip", describe(value)))
        self._run.changed.connect(self.show_mask)
        self.cache: dict[tuple, np.ndarray] = {}
        self.worker: FunctionWorker | None = None

    # ------------------------------------------------------------- choosing
    def load_model(self) -> None:
        """Load the chosen model and list its gated layers."""
        try:
            path = self._model.model_path()
            model, system = cached_model(path)
        except (ValueError, FileNotFoundError) as err:
            notify_error(err, "choose an SV-CoDe .safetensors model file")
            return
        layers = model.mask_layers()
        if not layers:
            notify_error("This model has no coordinate gates (built with coord_gate=False).",
                         "choose a model trained with coordinate gates")
            return
        self._loaded = (Path(path), model, system, layers)
        self.reset_choices()
        self._update_channels()

    def _infos(self, **match: str) -> list:
        layers = self._loaded[3] if self._loaded else []
        return [info for info in layers
                if all(getattr(info, key) == value for key, value in match.items())]

    # Choices are functions of the loaded model, so napari's reset_choices keeps them.
    def _stages(self, _widget=None) -> list[str]:
        return list(dict.fromkeys(info.stage for info in self._infos()))

    def _blocks(self, _widget=None) -> list[str]:
        infos = self._infos(stage=self._stage.value)
        return list(dict.fromkeys(info.block for info in infos))

    def _gates(self, _widget=None) -> list[str]:
        return [info.layer for info in self._infos(stage=self._stage.value,
                                                   block=self._block.value)]

    def _update_channels(self, *_) -> None:
        info = self._selected()
        if info is not None:
            self._channel.max = info.channels - 1
            self._lens.enabled = info.lenses > 1

    def _selected(self):
        infos = self._infos(stage=self._stage.value, block=self._block.value,
                            layer=self._gate.value)
        return infos[0] if infos else None

    # ------------------------------------------------------------- showing
    def show_mask(self) -> FunctionWorker | None:
        """Add the chosen mask as an Image layer (from the cache, or computed in a worker)."""
        info = self._selected()
        if info is None:
            notify_error("No gated layer chosen.", "press 'Load model' and pick a layer")
            return None
        path, model, system, _ = self._loaded
        lens = self._lens.value if info.lenses > 1 else 0
        key = (str(path), info.stage, info.block, info.layer, lens, self._channel.value)
        if key in self.cache:
            self._add(key, system)
            return None

        def compute() -> np.ndarray:
            return model.coordinate_mask(info.stage, info.block, info.layer,
                                         system.sub_view_size, lens=lens,
                                         channels=key[-1]).cpu().numpy()[0]

        worker = function_worker(compute, lambda mask: self._store(key, mask, system),
                                 "reload the model, or choose another layer")
        self.worker = worker
        worker.start()
        return worker

    def _store(self, key: tuple, mask: np.ndarray, system: SystemConfig) -> None:
        self.cache[key] = mask
        self._add(key, system)

    def _add(self, key: tuple, system: SystemConfig) -> None:
        _, stage, block, layer, lens, channel = key
        name = f"mask {stage}/{block}/{layer} lens {lens} ch {channel}"
        if name in self._viewer.layers:
            show_info(f"{name!r} is already shown")
            return
        mask = self.cache[key]
        low, high = float(mask.min()), float(mask.max())
        self._viewer.add_image(  # contrast from the mask's own range, e.g. 0.48–0.68
            mask, name=name, colormap="viridis",
            contrast_limits=(low, high if high > low else low + 1e-6),
            **placement(system, 2, object_translate(system)),
            metadata=layer_metadata(system, "mask"),
        )
