"""Reconstruct dock widget: tiled SV-CoDe reconstruction in a worker thread, cancellable."""

from __future__ import annotations

from collections.abc import Generator
from typing import Any

import napari
import numpy as np
from magicgui.widgets import CheckBox, ComboBox, Container, PushButton, SpinBox
from napari.qt.threading import GeneratorWorker, thread_worker
from napari.utils import progress
from napari.utils.notifications import show_info

from svcode_core.reconstruct import (
    PRECISIONS,
    FrameProgress,
    ReconstructionResult,
    Reconstructor,
    check_frame_shape,
)

from .._layers import (
    current_index,
    layer_metadata,
    layer_system,
    notify_error,
    object_translate,
)
from .._resources import available_devices, cached_model
from ._choosers import ModelChooser, image_layer_box

__all__ = ["ReconstructWidget", "reconstruct_frames"]

RECONSTRUCTION = "reconstruction"
DEMIXED = "demixed views"


def reconstruct_frames(
    reconstructor: Reconstructor, frames: np.ndarray, first: int = 0, return_views: bool = False
) -> Generator[FrameProgress | tuple[int, ReconstructionResult], None, None]:
    """Reconstruct frame ``first`` of a ``(T, H, W)`` stack, then the others in order.

    Yields the core's :class:`~svcode_core.reconstruct.FrameProgress` after every batch of
    tiles and ``(frame index, ReconstructionResult)`` when a frame is done. Closing the
    generator stops it after the current batch.
    """
    order = [first, *(index for index in range(len(frames)) if index != first)]
    for index in order:
        result = yield from reconstructor.iter_reconstruct(frames[index], return_views)
        yield index, result


class ReconstructWidget(Container):
    """Reconstruct a raw CM² frame or stack with a bundled or user model.

    Runs in a worker thread with napari's progress bar; *Cancel* stops within one batch of
    tiles. Adds a ``"reconstruction"`` layer (``(S, S)`` or ``(T, S, S)``) and, if asked,
    ``"demixed views"`` (``(9, S, S)`` or ``(9, T, S, S)``: the lens axis first, so a
    stack's frame axis stays aligned with the raw stack), placed over the raw frame.
    """

    def __init__(self, napari_viewer: napari.viewer.Viewer) -> None:
        self._viewer = napari_viewer
        self._layer = image_layer_box(napari_viewer, "raw layer")
        self._model = ModelChooser()
        self._device = ComboBox(label="device", choices=available_devices())
        self._precision = ComboBox(label="precision", choices=list(PRECISIONS), value="fp32")
        self._tile = SpinBox(label="tile size", min=0, max=8192, value=0,
                             tooltip="tile side in pixels; 0 uses the system's patch size")
        self._batch = SpinBox(label="batch size", min=1, max=1024, value=8)
        self._skip = CheckBox(text="skip empty tiles", value=True)
        self._views = CheckBox(text="add the demixed views", value=False)
        self._run = PushButton(text="Reconstruct")
        self._cancel = PushButton(text="Cancel", enabled=False)
        super().__init__(widgets=[
            self._layer, self._model, self._device, self._precision, self._tile, self._batch,
            self._skip, self._views, self._run, self._cancel,
        ])
        self._run.changed.connect(self.start)
        self._cancel.changed.connect(self.cancel)
        self.worker: GeneratorWorker | None = None
        self.frames_done = 0
        self._state: dict[str, Any] = {}

    # ------------------------------------------------------------------ set-up
    def _reconstructor(self, layer: napari.layers.Image) -> Reconstructor:
        system = layer_system(layer.metadata)
        path = self._model.model_path(system.name if system else None)
        model, trained_for = cached_model(path, system)
        if system is None:
            show_info(f"Layer {layer.name!r} has no system configuration; using the model's "
                      f"training system {trained_for.name!r}.")
        tile = self._tile.value or None
        self._state["model"] = {
            "path": str(path), "architecture": type(model).__name__, "system": trained_for.name,
            "device": self._device.value, "precision": self._precision.value,
            "tile_size": tile, "batch_size": self._batch.value, "skip_empty": self._skip.value,
        }
        return Reconstructor(
            model, trained_for, device=self._device.value, precision=self._precision.value,
            tile_size=tile, batch_size=self._batch.value, skip_empty=self._skip.value,
        )

    @staticmethod
    def _frames(layer: napari.layers.Image, reconstructor: Reconstructor) -> np.ndarray:
        frames = np.asarray(layer.data)
        if layer.rgb or frames.ndim not in (2, 3):
            raise ValueError(f"layer {layer.name!r} has shape {frames.shape}; expected a raw "
                             "grey frame (H×W) or a frame stack (T×H×W)")
        check_frame_shape(frames.shape[-2:], reconstructor.system)
        bad = frames.size - np.count_nonzero(np.isfinite(frames))
        if bad:
            raise ValueError(f"layer {layer.name!r} holds {bad} NaN or Inf values")
        return frames if frames.ndim == 3 else frames[None]

    def start(self) -> GeneratorWorker | None:
        """Check the inputs and start the reconstruction worker (errors become notices)."""
        layer = self._layer.value
        if layer is None:
            notify_error("No raw image layer to reconstruct.",
                         "open a raw CM² frame (File ▸ Open) or a sample (File ▸ Open Sample)")
            return None
        try:
            reconstructor = self._reconstructor(layer)
        except (ValueError, FileNotFoundError) as err:
            notify_error(err, "choose a model trained for this system, or set the layer's "
                              "system in the Calibration widget")
            return None
        try:
            frames = self._frames(layer, reconstructor)
        except ValueError as err:
            notify_error(err, "open the raw sensor frame of this system (or set the right "
                              "system in Calibration); replace NaN/Inf pixels, e.g. by 0")
            return None
        first = current_index(layer, self._viewer.dims.point)[0] if frames.shape[0] > 1 else 0
        self._prepare_outputs(layer, reconstructor, frames.shape[0])
        self.frames_done = 0
        total = frames.shape[0] * len(reconstructor.grid)
        self._state["progress"] = progress(total=total, desc="SV-CoDe reconstruction")
        worker = thread_worker(reconstruct_frames, start_thread=False)(
            reconstructor, frames, first, self._views.value
        )
        worker.yielded.connect(self._on_yielded)
        worker.aborted.connect(self._on_aborted)
        worker.finished.connect(self._on_finished)
        self.worker = worker
        self._run.enabled, self._cancel.enabled = False, True
        worker.start()
        return worker

    def _prepare_outputs(self, layer: napari.layers.Image, rec: Reconstructor, count: int) -> None:
        size = rec.system.sub_view_size
        self._state.update(
            system=rec.system,
            count=count,
            tiles=len(rec.grid),
            translate=(*layer.translate[:-2], *object_translate(rec.system)),
            recon=np.zeros((count, size, size), dtype=np.float32),
            views=np.zeros((9, count, size, size), dtype=np.float32) if self._views.value
            else None,
        )

    # ---------------------------------------------------------------- running
    def cancel(self) -> None:
        """Ask the worker to stop after the batch of tiles it is running."""
        if self.worker is not None:
            self.worker.quit()
        self._cancel.enabled = False

    def _on_yielded(self, item: FrameProgress | tuple[int, ReconstructionResult]) -> None:
        state = self._state
        if isinstance(item, FrameProgress):
            fraction = item.tiles_done / item.tiles_total if item.tiles_total else 1.0
            bar = state["progress"]
            bar.n = int(state["tiles"] * (self.frames_done + fraction))
            bar.set_description(f"SV-CoDe frame {self.frames_done + 1}/{state['count']}")
            bar.refresh()
            return
        index, result = item
        self.frames_done += 1
        state["recon"][index] = result.reconstruction
        if state["views"] is not None:
            state["views"][:, index] = result.views
        self._show()

    def _show(self) -> None:
        state = self._state
        single = state["count"] == 1
        meta = layer_metadata(state["system"], RECONSTRUCTION, state["model"])
        self._put_layer(RECONSTRUCTION, state["recon"][0] if single else state["recon"],
                        state["translate"], meta, colormap="magma")
        if state["views"] is not None:
            views = state["views"][:, 0] if single else state["views"]
            meta = layer_metadata(state["system"], "demixed", state["model"])
            self._put_layer(DEMIXED, views, (0.0, *state["translate"]), meta, colormap="gray",
                            visible=False)

    def _put_layer(self, name: str, data: np.ndarray, translate: tuple, meta: dict,
                   **kwargs: Any) -> None:
        layers = self._viewer.layers
        if name in layers and layers[name].ndim == data.ndim:
            layer = layers[name]
            layer.data = data
            layer.translate = translate
            layer.metadata = meta
        else:
            if name in layers:
                layers.remove(name)
            layer = self._viewer.add_image(data, name=name, translate=translate,
                                           metadata=meta, **kwargs)
        if self.frames_done == 1:
            layer.reset_contrast_limits()

    def _on_aborted(self) -> None:
        show_info(f"Reconstruction cancelled after {self.frames_done} of "
                  f"{self._state['count']} frames.")

    def _on_finished(self) -> None:
        self._state["progress"].close()
        self._run.enabled, self._cancel.enabled = True, False
