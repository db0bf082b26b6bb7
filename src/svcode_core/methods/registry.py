"""Every reconstruction method and model architecture by name: the one list of them.

The command line (``--method``), the napari plugin, training, the benchmark, the footprint
measurement and the model files all take their names from here, so a method is added in
one place. Each method also owns the table of its options (:class:`Option`): their types,
defaults, bounds, flags and help. ``svcode reconstruct``'s flags, the checks the
reconstructors and solvers make and the plugin's option widgets are all made from it.
This module imports nothing of the package at import time: any module may use it.

Examples
--------
>>> METHODS
('svcode', 'admm', 'wiener', 'rl', 'multiwiener', 'fouriernet')
>>> method("fouriernet").architecture, method("fouriernet").precisions
('SVFourierNet', ('fp32', 'bf16'))
>>> method_of_architecture("MultiWienerNet")
'multiwiener'
>>> method("admm").defaults["iterations"], method("rl").defaults["iterations"]
(50, 10)
>>> method("wiener").option("balance").flag
'--wiener-balance'
"""

from __future__ import annotations

import importlib
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

__all__ = [
    "ARCHITECTURES",
    "DEFAULT_RANK",
    "LEARNED",
    "LEARNED_METHODS",
    "METHODS",
    "METHOD_TITLES",
    "MODEL_BASED",
    "MODEL_BASED_METHODS",
    "SVCODE",
    "TRAINABLE_METHODS",
    "Method",
    "Option",
    "check_method",
    "method",
    "method_of_architecture",
    "reconstructor_class",
]

#: the families of methods (:attr:`Method.family`)
SVCODE = "svcode"
MODEL_BASED = "model-based"
LEARNED = "learned"


@dataclass(frozen=True)
class Option:
    """One keyword option of a method: the single place of its type, default and bounds.

    Attributes
    ----------
    name : str
        Keyword argument of the method's reconstructor.
    kind : {int, float, bool, str}
        Type of its values.
    default : object
        Its value when not given; ``None`` where it is decided when the method runs (the
        help says how).
    flag : str
        Its ``svcode reconstruct`` flag (a ``bool`` option's flag sets ``not default``).
    help : str
        For people: the flag's help and the widget's tooltip; ``{default}`` and
        ``{fixed}`` stand for those values (in the flag's units).
    minimum : float, optional
        Smallest value accepted; ``above`` refuses the minimum itself.
    above : bool
    choices : tuple of str
        The values accepted (``str`` options).
    unit : str
        Unit of its values, for messages (``"pixels"``).
    metavar : str, optional
        The flag's value in ``--help``.
    label : str
        The plugin widget's label.
    widget : str
        The plugin's name of its widget; default ``name``.
    advanced : bool
        Only a flag, no widget in the plugin.
    ceiling : bool
        The default is a ceiling (the system's own value when smaller): the plugin's
        widget offers 0, "the default", instead of it.
    auto : str
        For options that also take ``"auto"``: what it does (the plugin's tick box).
    fixed : float, optional
        The number the plugin offers when ``"auto"`` is not ticked.
    flag_unit, flag_scale, flag_kind :
        The flag's unit, factor (keyword value = flag value × ``flag_scale``) and type
        where they differ from the keyword's (MiB, GiB of bytes).
    rule : str
        What a value must be, where the bounds would say it badly.

    Examples
    --------
    >>> option = Option("rho", float, 0.1, "--rho", "starting penalty", minimum=0, above=True)
    >>> option.check(0.5)
    >>> option.check(0.0, flag=True)
    Traceback (most recent call last):
    ...
    ValueError: --rho must be a finite number > 0, got 0
    """

    name: str
    kind: type
    default: Any
    flag: str
    help: str
    minimum: float | None = None
    above: bool = False
    choices: tuple[str, ...] = ()
    unit: str = ""
    metavar: str | None = None
    label: str = ""
    widget: str = ""
    advanced: bool = False
    ceiling: bool = False
    auto: str = ""
    fixed: float | None = None
    flag_unit: str = ""
    flag_scale: int = 1
    flag_kind: type | None = None
    rule: str = ""

    def describe(self) -> str:
        """The help text with its default filled in (in the flag's units)."""
        default = self.default
        if isinstance(default, int) and not isinstance(default, bool):
            default //= self.flag_scale
        shown = f"{default:g}" if isinstance(default, float) else default
        return self.help.format(default=shown, fixed=self.fixed)

    def words(self, flag: bool = False) -> str:
        """What a value must be, e.g. ``">= 1 (pixels)"``; ``flag``: a value of the flag
        (already of its type, in its units)."""
        kind = (self.flag_kind or self.kind) if flag else self.kind
        unit = self.flag_unit if flag and self.flag_unit else self.unit
        if self.choices:
            text = "one of " + ", ".join(self.choices)
        elif kind is bool:
            text = "True or False"
        else:
            sign = ">" if self.above else ">="
            bound = "" if self.minimum is None else f"{sign} {self.minimum:g}"
            prefix = "a finite number" if kind is float else "" if flag else "a whole number"
            text = self.rule or f"{prefix} {bound}".strip()
        text += f" ({unit})" if unit else ""
        return text + (" or 'auto'" if self.auto else "")

    def check(self, value: Any, flag: bool = False) -> None:
        """Raise :class:`ValueError` unless ``value`` is one of this option's values.

        ``None`` passes where the default is ``None``; ``flag``: ``value`` is the flag's,
        and the message names the flag.
        """
        if (value is None and self.default is None) or (self.auto and value == "auto"):
            return
        kind = (self.flag_kind or self.kind) if flag else self.kind
        label = self.flag if flag else self.name
        shown = f"{value:g}" if isinstance(value, float) else repr(value)
        if not _of_kind(value, kind):
            words = self.words(flag).replace("a finite number", "a number")
            raise ValueError(f"{label} must be {words}, got {shown}")
        if self.choices:
            valid = value in self.choices
        elif kind in (int, float):
            valid = math.isfinite(value) and (
                self.minimum is None
                or (value > self.minimum if self.above else value >= self.minimum)
            )
        else:
            valid = True
        if not valid:
            raise ValueError(f"{label} must be {self.words(flag)}, got {shown}")

    def from_flag(self, value: Any) -> Any:
        """The keyword value of a value given to the flag (``True``: the flag given)."""
        if self.kind is bool:
            return not self.default
        if self.flag_scale != 1:
            return int(value * self.flag_scale)
        return value

    def to_flag(self, value: Any) -> list[str]:
        """The ``svcode reconstruct`` arguments that give the keyword value ``value``.

        Examples
        --------
        >>> method("svcode").option("mask_cache_bytes").to_flag(2**29)
        ['--mask-cache', '512']
        >>> method("svcode").option("skip_empty").to_flag(False)
        ['--no-skip']
        """
        if self.kind is bool:
            return [] if bool(value) == self.default else [self.flag]
        if self.flag_scale != 1:
            value = (self.flag_kind or self.kind)(value / self.flag_scale)
        text = f"{value:g}" if isinstance(value, float) else str(value)
        return [self.flag, text]


def _of_kind(value: Any, kind: type) -> bool:
    if isinstance(value, bool):
        return kind is bool
    if kind is int:
        return isinstance(value, numbers.Integral)
    if kind is float:
        return isinstance(value, numbers.Real)
    return isinstance(value, kind)


@dataclass(frozen=True)
class Method:
    """One reconstruction method.

    Attributes
    ----------
    name : str
        Its ``--method`` name.
    title : str
        For people (menus, reports).
    label : str
        Short name in tables and figures.
    family : {"svcode", "model-based", "learned"}
        SV-CoDe; solvers of the forward model (no training); trained baselines.
    precisions : tuple of str
        The ``precision`` values it accepts, the default first.
    options : tuple of Option
        Its own keyword options, besides ``device`` and ``precision``: the one table of
        their defaults and bounds.
    architecture : str or None
        The model class its model files hold (trained methods).
    reconstructor : str
        Its reconstructor class, ``"module:Class"`` relative to :mod:`svcode_core.methods`
        (:func:`reconstructor_class`).
    caveat : str
        What its output cannot be read for, said where the method is chosen; empty if
        nothing.
    """

    name: str
    title: str
    label: str
    family: str
    precisions: tuple[str, ...]
    options: tuple[Option, ...] = ()
    architecture: str | None = None
    reconstructor: str = ""
    caveat: str = ""

    @property
    def needs_weights(self) -> bool:
        """Whether it runs from a model file (SV-CoDe falls back on a bundled one)."""
        return self.architecture is not None

    @property
    def defaults(self) -> Mapping[str, Any]:
        """Each option's default, of the options that have one here (``rank`` is a
        ceiling: the system's own ``K`` when that is smaller)."""
        return MappingProxyType({o.name: o.default for o in self.options
                                 if o.default is not None})  # fmt: skip

    def option(self, name: str) -> Option:
        """Its option ``name``.

        Raises
        ------
        ValueError
            For a name that is not one of its options.
        """
        for option in self.options:
            if option.name == name:
                return option
        raise ValueError(f"{self.name}: no option {name!r}")

    def check(self, options: Mapping[str, Any]) -> None:
        """Raise :class:`ValueError` for an option it does not take or a value out of
        bounds (``None`` values pass: they mean the default).

        Examples
        --------
        >>> method("rl").check({"iterations": 0})
        Traceback (most recent call last):
        ...
        ValueError: iterations must be a whole number >= 1, got 0
        """
        names = [option.name for option in self.options]
        unknown = sorted(set(options) - set(names))
        if unknown:
            raise ValueError(f"{self.name}: unknown option(s) {unknown}; it accepts {names}")
        for name, value in options.items():
            if value is not None:
                self.option(name).check(value)


#: the model-based methods' default low-rank order ``K``: at most this, the system's own
#: ``K`` when that is smaller
DEFAULT_RANK = 3

# The model-based defaults sit at the knee of the work–precision curve of the committed
# benchmark (bench/results/regimes.md, realistic regime, one CPU thread, cm2-mini):
# LSV-ADMM at K = 3, 50 iterations, λ from the frame: 28.03 dB in 11.6 s a frame, against
# 28.31 dB in 772 s at the system's K (15) and up to 200 iterations with the fixed λ;
# Wiener's balance 1e-3..0.1 score within 0.1 dB of each other in every regime, and
# Richardson–Lucy's 10 iterations within 0.01 dB of 30 or above them, at a third of the time.
# The help quotes what the slower settings buy.
_RANK = Option(
    "rank", int, DEFAULT_RANK, "--rank", minimum=1, metavar="K", label="rank K", ceiling=True,
    help="low-rank order K of the forward model (default {default}, or the system's K when "
    "smaller; LSV-ADMM at cm2-mini's K = 15 with up to 200 iterations gained 0.28 dB on the "
    "realistic benchmark for 67x the time)",
)  # fmt: skip
_MEMORY_BUDGET = Option(
    "memory_budget", int, None, "--memory-budget", minimum=0, above=True, rule="positive",
    unit="bytes", flag_unit="GiB", flag_scale=2**30, flag_kind=float, metavar="GIB",
    advanced=True,
    help="memory of the forward model's kept spectra and working chunks (default 1 GiB; "
    "cm2-v2 at its K needs about 4 to run LSV-ADMM within 8 GiB)",
)  # fmt: skip
_SVCODE_OPTIONS = (
    Option("tile_size", int, None, "--tile", minimum=1, unit="pixels", metavar="P",
           label="tile size", widget="tile",
           help="tile side P (default: planned within 1 GiB: the whole sub-view when it fits)"),
    Option("stride", int, None, "--stride", minimum=1, unit="pixels", metavar="S",
           advanced=True,
           help="tile stride (default: planned; P/2 with --tile)"),
    Option("batch_size", int, None, "--batch-size", minimum=1, unit="tiles",
           label="batch size", widget="batch",
           help="tiles per model call, more: faster, more memory (default: planned)"),
    Option("skip_empty", bool, True, "--no-skip", label="skip empty tiles", widget="skip",
           help="skip the tiles without signal above the sensor's noise (the default; "
           "--no-skip runs every tile)"),
    Option("mask_cache_bytes", int, 2**30, "--mask-cache", minimum=0,
           unit="bytes; 0 recomputes the masks", flag_unit="MiB; 0 recomputes the masks",
           flag_scale=2**20, metavar="MIB", advanced=True,
           help="memory for frozen coordinate masks, kept for the next tile and frame; 0 to "
           "recompute them (default: {default} MiB; the bundled cm2-mini model needs 614 for its "
           "whole-sub-view tile)"),
    Option("pool_window", int, None, "--pool-window", minimum=0, unit="pixels", metavar="PX",
           advanced=True,
           help="channel attention pools over PX pixels around each pixel (the training "
           "patch, 96 for the bundled model) instead of the whole tile, so tiles of any size "
           "agree with the whole sub-view; about 1.3x the time (default: as the model file "
           "says)"),
    Option("refine_periphery", int, 0, "--refine-periphery", minimum=0, unit="iterations",
           metavar="N", label="refine periphery", widget="refine",
           help="refine the field's periphery (outer ring, edge strips) with N LSV-ADMM "
           "iterations started from the network's reconstruction, blended in from half the "
           "field radius outwards; 10 raised the bundled model's held-out scores in every "
           "regime for 2-3x the time (default: {default}, none)"),
)  # fmt: skip
_ADMM_OPTIONS = (
    _RANK,
    _MEMORY_BUDGET,
    Option("iterations", int, 50, "--iterations", minimum=1, label="iterations",
           help="at most this many (default {default}: 0.17 dB above 20 on the realistic "
           "benchmark, for 2.6x the time)"),
    Option("tv_weight", float, "auto", "--tv-weight", minimum=0, metavar="LAMBDA|auto",
           label="TV weight λ", auto="λ from each frame's noise", fixed=1e-4,
           help="TV weight lambda, or auto: from each frame's noise and level, better for "
           "dim frames (default {default}; the fixed {fixed:g} scored 1.5 dB lower at low "
           "light, 0.3 dB on the realistic benchmark, in the same time)"),
    Option("rho", float, 0.1, "--rho", minimum=0, above=True, advanced=True,
           help="starting penalty (default {default})"),
    Option("tolerance", float, 1e-4, "--tolerance", minimum=0, advanced=True,
           help="relative residual to stop at (default {default}; 0 runs every iteration)"),
    Option("cg_iterations", int, 1, "--cg-iterations", minimum=1, advanced=True,
           help="CG steps per x-update (default {default})"),
)  # fmt: skip
_WIENER_OPTIONS = (
    _RANK,
    _MEMORY_BUDGET,
    Option("balance", float, 0.1, "--wiener-balance", minimum=0, above=True, label="balance",
           help="Laplacian regularisation weight (default {default}; 1e-2 and 1e-3 scored "
           "within 0.1 dB of it in every regime, in the same time)"),
    Option("boundary", str, "reflect", "--wiener-boundary", choices=("reflect", "periodic"),
           label="boundary", help="view boundary handling (default {default})"),
)  # fmt: skip
_RL_OPTIONS = (
    _RANK,
    _MEMORY_BUDGET,
    Option("iterations", int, 10, "--iterations", minimum=1, label="iterations",
           help="this many (default {default}: 30 scored at most 0.01 dB higher in any "
           "regime, at 3x the time)"),
)  # fmt: skip
_DECONVOLUTION = ".baselines:DeconvolutionReconstructor"
_CROSSTALK = ("approximate intensities: each view also holds its neighbours' crosstalk, "
              "which this method does not model; its output is divided by its response to a "
              "uniform object, so only a uniform scene comes out in the object's units")
_ALL = (
    Method(SVCODE, "SV-CoDe (network)", "SV-CoDe", SVCODE, ("auto", "fp32", "bf16", "fp16"),
           _SVCODE_OPTIONS, "SVCoDe", ".svcode:Reconstructor"),
    Method("admm", "LSV-ADMM (TV)", "LSV-ADMM", MODEL_BASED, ("fp32", "fp64"), _ADMM_OPTIONS,
           reconstructor=".baselines:AdmmReconstructor"),
    Method("wiener", "Wiener (per view, fused)", "Wiener", MODEL_BASED, ("fp32", "fp64"),
           _WIENER_OPTIONS, reconstructor=_DECONVOLUTION, caveat=_CROSSTALK),
    Method("rl", "Richardson-Lucy (per view, fused)", "Richardson-Lucy", MODEL_BASED,
           ("fp32", "fp64"), _RL_OPTIONS, reconstructor=_DECONVOLUTION, caveat=_CROSSTALK),
    Method("multiwiener", "MultiWienerNet (learned)", "MultiWienerNet", LEARNED,
           ("fp32", "bf16"), architecture="MultiWienerNet",
           reconstructor=".learned.reconstruct:LearnedReconstructor"),
    Method("fouriernet", "SV-FourierNet (learned)", "SV-FourierNet", LEARNED,
           ("fp32", "bf16"), architecture="SVFourierNet",
           reconstructor=".learned.reconstruct:LearnedReconstructor"),
)  # fmt: skip
_BY_NAME = {entry.name: entry for entry in _ALL}

#: every method of ``svcode reconstruct --method``
METHODS: tuple[str, ...] = tuple(_BY_NAME)
MODEL_BASED_METHODS: tuple[str, ...] = tuple(m.name for m in _ALL if m.family == MODEL_BASED)
LEARNED_METHODS: tuple[str, ...] = tuple(m.name for m in _ALL if m.family == LEARNED)
#: the methods ``svcode train --method`` trains
TRAINABLE_METHODS: tuple[str, ...] = (SVCODE, *LEARNED_METHODS)
METHOD_TITLES: dict[str, str] = {m.name: m.title for m in _ALL}
#: model class stored in a model file → its method
ARCHITECTURES: dict[str, str] = {m.architecture: m.name for m in _ALL if m.architecture}


def check_method(name: str) -> None:
    """Raise :class:`ValueError` unless ``name`` is one of :data:`METHODS`."""
    if name not in _BY_NAME:
        raise ValueError(f"method: {name!r} is not one of {', '.join(METHODS)}")


def method(name: str) -> Method:
    """The entry of method ``name``.

    Raises
    ------
    ValueError
        For a name that is not one of :data:`METHODS`.
    """
    check_method(name)
    return _BY_NAME[name]


def reconstructor_class(name: str) -> type:
    """The reconstructor class of method ``name``, imported on first use.

    Examples
    --------
    >>> reconstructor_class("admm").__name__
    'AdmmReconstructor'
    """
    module, _, cls = method(name).reconstructor.partition(":")
    return getattr(importlib.import_module(module, __package__), cls)


def method_of_architecture(architecture: str) -> str:
    """The method whose model files hold ``architecture`` (a model class name).

    Raises
    ------
    ValueError
        For a class that is no method's model (e.g. one SV-CoDe stage alone).
    """
    if architecture not in ARCHITECTURES:
        raise ValueError(f"a {architecture} is not the model of any method "
                         f"({', '.join(ARCHITECTURES)})")  # fmt: skip
    return ARCHITECTURES[architecture]
