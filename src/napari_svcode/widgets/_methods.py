"""The method chooser of the Reconstruct widget: a method and its own options.

Every method of ``svcode reconstruct --method`` is offered
(:data:`svcode_core.methods.METHODS`); only the chosen method's options are shown. Their
widgets are made from the methods' tables of options
(:class:`svcode_core.methods.registry.Option`: label, bounds, default, help as tooltip;
the advanced options are flags of ``svcode reconstruct`` only). The panel turns its values
into the keyword arguments of :func:`svcode_core.methods.build_reconstructor` and estimates
what a run would cost from the core's tiling (:func:`svcode_core.methods.svcode.tile_plan`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psutil
from magicgui.widgets import (
    CheckBox,
    ComboBox,
    Container,
    FileEdit,
    FloatSpinBox,
    Label,
    SpinBox,
)
from magicgui.widgets.bases import ValueWidget

from svcode_core.config import SystemConfig
from svcode_core.methods import LEARNED_METHODS, METHOD_TITLES, METHODS, registry
from svcode_core.methods.cost import duration, iteration_seconds, tile_seconds
from svcode_core.methods.registry import SVCODE, Option
from svcode_core.methods.svcode import tile_plan

from .._resources import cached_model
from ._choosers import ModelChooser

__all__ = ["Cost", "MethodPanel"]

#: runs estimated to take longer ask first
LONG_RUN_SECONDS = 15 * 60
#: runs estimated to need more than this share of the free memory ask first
MEMORY_SHARE = 0.8
#: the largest whole number and number an option widget offers, and a number's step
WHOLE_MAX, NUMBER_MAX, NUMBER_STEP = 100_000, 10.0, 1e-5


@dataclass
class Cost:
    """What a run is estimated to take: ``seconds`` and ``memory`` (bytes), with reasons."""

    seconds: float
    memory: int
    detail: str

    def warning(self) -> str | None:
        """A one-line warning when the run would take very long or not fit in memory."""
        available = psutil.virtual_memory().available
        if self.memory > MEMORY_SHARE * available:
            return (f"needs about {self.memory / 2**30:.1f} GiB, {available / 2**30:.1f} GiB "
                    f"free ({self.detail})")  # fmt: skip
        if self.seconds > LONG_RUN_SECONDS:
            return f"would take about {duration(self.seconds)} ({self.detail})"
        return None


def _key(option: Option) -> str:
    """The panel's name of the widget of ``option``."""
    return option.widget or option.name


def _auto_key(option: Option) -> str:
    """The name of the tick box of an option that also takes ``"auto"`` (``tv_auto``)."""
    return _key(option).split("_")[0] + "_auto"


def _zero_is_default(option: Option) -> bool:
    """Whether the widget of a whole-number option offers 0 for "the default": where 0 is
    no value of the option."""
    return option.kind is int and option.minimum is not None and option.minimum >= 1


def _start(option: Option) -> Any:
    """The value the widget of ``option`` shows at first: its default."""
    if option.kind is float and not isinstance(option.default, float):
        return option.fixed  # a word ("auto") is the tick box's
    if _zero_is_default(option) and (option.default is None or option.ceiling):
        return 0
    return option.default


def _tooltip(option: Option) -> str:
    return option.describe() + ("; 0: the default" if _zero_is_default(option) else "")


def _option_widget(option: Option) -> ValueWidget:
    """The widget of ``option``, at its default, its help as tooltip."""
    common = {"name": _key(option), "tooltip": _tooltip(option)}
    if option.kind is bool:
        return CheckBox(text=option.label, value=option.default, **common)
    if option.choices:
        return ComboBox(label=option.label, choices=list(option.choices),
                        value=option.default, **common)  # fmt: skip
    if option.kind is int:
        low = 0 if _zero_is_default(option) else int(option.minimum or 0)
        return SpinBox(label=option.label, min=low, max=WHOLE_MAX, value=_start(option),
                       **common)  # fmt: skip
    return FloatSpinBox(label=option.label, min=float(option.minimum or 0.0), max=NUMBER_MAX,
                        step=NUMBER_STEP, value=_start(option), **common)  # fmt: skip


class MethodPanel(Container):
    """A method and its options; only the chosen method's options are visible.

    Each option widget is named as the option's ``widget`` in its table (e.g. ``tile``,
    ``iterations``; ``tv_auto`` ticks ``"auto"``) and reached as an attribute.

    Parameters
    ----------
    label : str
        Label of the method box.
    method : str
        The method chosen at first.
    """

    def __init__(self, label: str = "method", method: str = "svcode") -> None:
        self.method = ComboBox(
            label=label,
            value=method,
            choices=[(METHOD_TITLES[name], name) for name in METHODS],
            tooltip="the reconstruction method (svcode reconstruct --method)",
        )
        self.model = ModelChooser()
        self.weights = FileEdit(
            label="model file",
            mode="r",
            filter="*.safetensors",
            tooltip="a model trained with svcode train --method ...",
        )
        self.precision = ComboBox(
            label="precision", choices=list(registry.method(method).precisions)
        )
        self._widgets = {"model": self.model, "weights": self.weights,
                         "precision": self.precision}  # fmt: skip
        #: widget name → the option whose value it shows
        self._shows: dict[str, Option] = {}
        for name in METHODS:  # one widget per name, shared by the methods (rank)
            for option in registry.method(name).options:
                if option.advanced or _key(option) in self._widgets:
                    continue
                widget = self._widgets[_key(option)] = _option_widget(option)
                self._shows[_key(option)] = option
                if option.auto:
                    box = CheckBox(
                        name=_auto_key(option),
                        text=option.auto,
                        value=option.default == "auto",
                        tooltip=option.describe(),
                    )
                    box.changed.connect(lambda on, w=widget: setattr(w, "enabled", not on))
                    widget.enabled = not box.value
                    self._widgets[_auto_key(option)] = box
        self.caveat = Label(value="")
        self.caveat.native.setWordWrap(True)
        super().__init__(widgets=[self.method, self.caveat, *self._widgets.values()],
                         labels=True)
        self.margins = (0, 0, 0, 0)
        self.method.changed.connect(self._show_options)
        self._show_options(self.method.value)

    # ---------------------------------------------------------------- showing
    def _shown(self, method: str) -> list[str]:
        """The widgets of ``method``, in order."""
        entry = registry.method(method)
        names = ["model"] if entry.family == SVCODE else ["weights"] if entry.needs_weights else []
        names.append("precision")
        for option in entry.options:
            if not option.advanced:
                names += [_key(option), *([_auto_key(option)] if option.auto else [])]
        return names

    def _show_options(self, method: str) -> None:
        shown = self._shown(method)
        for name, widget in self._widgets.items():
            widget.visible = name in shown
        entry = registry.method(method)
        for option in entry.options:  # a widget another method's option showed: this one's
            if not option.advanced and self._shows[_key(option)] != option:
                widget = self._widgets[_key(option)]
                widget.value, widget.tooltip = _start(option), _tooltip(option)
                self._shows[_key(option)] = option
        self.precision.choices = list(entry.precisions)
        self.precision.value = entry.precisions[0]
        self.caveat.value = f"⚠ {entry.caveat}" if entry.caveat else ""
        self.caveat.visible = bool(entry.caveat)

    # ---------------------------------------------------------------- values
    def options(self) -> dict[str, Any]:
        """Keyword arguments of :func:`~svcode_core.methods.build_reconstructor` (without
        ``device``, ``weights`` and ``model``): the shown options' values (``None``: the
        default; an option at 0 that is 0 by default, e.g. no refinement, is left out)."""
        values: dict[str, Any] = {"precision": self.precision.value}
        for option in registry.method(self.method.value).options:
            if option.advanced:
                continue
            value = self._widgets[_key(option)].value
            if option.auto and self._widgets[_auto_key(option)].value:
                value = "auto"
            elif option.kind is int and value == 0 and _zero_is_default(option):
                value = None
            elif option.kind is int and value == 0 == option.default:
                continue
            values[option.name] = value
        return values

    def weights_path(self, system_name: str | None = None) -> Path | None:
        """The model file of the method: SV-CoDe's (bundled or chosen), a learned baseline's
        (``None`` when none is chosen), ``None`` for the model-based baselines.

        Raises
        ------
        ValueError
            SV-CoDe without a bundled model or chosen file.
        """
        method = self.method.value
        if method == "svcode":
            return self.model.model_path(system_name)
        if method in LEARNED_METHODS:
            path = Path(self.weights.value)
            return path if path.is_file() else None
        return None

    def _model(self, system: SystemConfig) -> Any:
        """SV-CoDe's model for ``system`` (what the run loads, cached), ``None`` when it
        cannot be loaded (the run says why)."""
        try:
            return cached_model(self.weights_path(system.name), system)[0]
        except (OSError, ValueError):
            return None

    def cost(self, system: SystemConfig, frames: int, device: str, views: bool) -> Cost:
        """Rough time and memory of reconstructing ``frames`` frames of ``system``: SV-CoDe's
        tiles and working memory as the core plans them (:func:`tile_plan`)."""
        entry, options = registry.method(self.method.value), self.options()
        size = system.sub_view_size
        memory = frames * size * size * 4 * (10 if views else 1)
        per_iteration = iteration_seconds(size, device)
        if entry.family == SVCODE:
            model = self._model(system)
            try:
                plan = tile_plan(
                    model,
                    system,
                    options["precision"],
                    options.get("tile_size"),
                    None,
                    options.get("batch_size"),
                    device=device,
                )
            except ValueError:  # the core refuses the tile size when the run starts
                return Cost(0.0, memory, "")
            per_frame = len(plan.grid)
            tiles = per_frame * frames
            work = None if model is None else model.working_bytes_per_pixel()
            seconds = tile_seconds(tiles, plan.grid.patch, work, device)
            memory += entry.defaults["mask_cache_bytes"] + plan.working_bytes
            detail = f"{tiles:,} tile{'s' * (tiles > 1)}" if frames == 1 else (
                f"{tiles:,} tiles: {per_frame:,} a frame × {frames} frames")  # fmt: skip
            refine = options.get("refine_periphery", 0) * frames
            if refine:
                seconds += refine * per_iteration
                detail += f" and {refine:,} refinement iterations"
            return Cost(seconds, memory, detail)
        if "iterations" in options:
            iterations = (options["iterations"] or entry.defaults["iterations"]) * frames
            return Cost(iterations * per_iteration, memory, f"{iterations:,} iterations")
        return Cost(0.1 * frames, memory, f"{frames} frames")

    def describe(self) -> str:
        """The method's title."""
        return METHOD_TITLES[self.method.value]
