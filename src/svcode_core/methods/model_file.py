"""Safe model files: safetensors weights plus the model and system configurations.

A model file is a plain safetensors file whose string metadata holds the JSON model
configuration (:class:`~svcode_core.network.config.ModelConfig` for SV-CoDe and its
stages, :class:`~svcode_core.methods.learned.MultiWienerConfig` or
:class:`~svcode_core.methods.learned.FourierNetConfig` for the learned baselines), the JSON
:class:`~svcode_core.config.SystemConfig` the model was trained for, the architecture
name and optional JSON ``extra`` information. Loading never unpickles anything: the
header is checked first (a safetensors file starts with an 8-byte little-endian header
length followed by a JSON header), so pickles, ``torch.save`` zip archives and truncated
files are refused with an error that says what the file is.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file
from torch import nn

from ..config import PIXEL_SIZE_FIELDS, SystemConfig
from ..network.config import ModelConfig
from ..network.models import DemixNet, ReconNet, SVCoDe
from .base import resolve_device
from .learned.models import LEARNED_MODELS

__all__ = [
    "FORMAT", "load_model", "read_model_metadata", "record_extra", "record_pool_window",
    "save_model",
]

FORMAT = "svcode-model-1"
_MAX_HEADER = 100 * 2**20


@dataclass(frozen=True)
class _Architecture:
    """How to rebuild a stored model: its configuration class and constructor."""

    config: type
    build: Callable[[Any, SystemConfig], nn.Module]


def _svcode_family(cls: type) -> _Architecture:
    return _Architecture(ModelConfig, lambda config, system: cls(config))


def _architectures() -> dict[str, _Architecture]:
    """Every architecture a model file may hold, by class name: SV-CoDe and its two
    stages, and the learned baselines."""
    return {
        **{cls.__name__: _svcode_family(cls) for cls in (SVCoDe, DemixNet, ReconNet)},
        **{name: _Architecture(cls.config_class, cls) for name, cls in LEARNED_MODELS.items()},
    }


def save_model(
    path: str | Path, model: nn.Module, system: SystemConfig, extra: dict[str, Any] | None = None
) -> Path:
    """Write the weights and both configurations to a safetensors file.

    Parameters
    ----------
    path : str or Path
        Destination (conventionally ``*.safetensors``).
    model : SVCoDe, DemixNet, ReconNet, MultiWienerNet or SVFourierNet
    system : SystemConfig
        The instrument the model was trained for.
    extra : dict, optional
        JSON-serialisable information (training history, metrics, ...).

    Returns
    -------
    Path
    """
    name = type(model).__name__
    architectures = _architectures()
    if name not in architectures:
        raise TypeError(f"model must be one of {sorted(architectures)}, got {name}")
    if not isinstance(system, SystemConfig):
        raise TypeError(f"system must be a SystemConfig, got {type(system).__name__}")
    metadata = {
        "format": FORMAT,
        "architecture": name,
        "model_config": model.model_config.to_json(),
        "system_config": system.validate().to_json(),
        "extra": json.dumps(extra if extra is not None else {}),
    }
    state = {k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}
    path = Path(path)
    save_file(state, str(path), metadata=metadata)
    return path


def read_model_metadata(path: str | Path) -> dict[str, Any]:
    """Check a model file's header and return its metadata without loading weights.

    Returns
    -------
    dict
        ``architecture`` (str), ``model_config`` (the architecture's configuration),
        ``system`` (SystemConfig) and ``extra`` (dict).

    Raises
    ------
    ValueError
        If the file is a pickle, a zip archive, truncated, or not an SV-CoDe model file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model file not found: {path}")
    header = _read_header(path)
    meta = header.get("__metadata__") or {}
    if meta.get("format") != FORMAT:
        raise ValueError(f"{path}: a safetensors file, but not an SV-CoDe model ({FORMAT})")
    architecture = _architectures().get(meta.get("architecture"))
    if architecture is None:
        raise ValueError(f"{path}: unknown architecture {meta.get('architecture')!r}")
    return {
        "architecture": meta["architecture"],
        "model_config": architecture.config.from_json(meta["model_config"]),
        "system": SystemConfig.from_json(meta["system_config"]),
        "extra": json.loads(meta.get("extra", "{}")),
    }


def record_extra(path: str | Path, **items: Any) -> None:
    """Add ``items`` to a model file's ``extra`` metadata, the weights kept bit for bit (the
    file is replaced whole, never left half written)."""
    _rewrite_metadata(path, lambda meta: {
        **meta, "extra": json.dumps({**json.loads(meta.get("extra", "{}")), **items})})


def record_pool_window(path: str | Path, window: int) -> None:
    """Set an SV-CoDe model file's :attr:`~svcode_core.network.config.ModelConfig.pool_window`,
    the weights kept bit for bit: an inference setting (training on patches of at most
    ``window`` pixels pools alike either way), chosen for a model by measuring it."""
    config = read_model_metadata(path)["model_config"]
    if not isinstance(config, ModelConfig):
        raise ValueError(f"{path}: a {type(config).__name__} model has no channel attention "
                         "to pool")
    text = config.replace(pool_window=window).to_json()  # a valid window, or a clear error
    _rewrite_metadata(path, lambda meta: {**meta, "model_config": text})


def _rewrite_metadata(path: str | Path, update: Callable[[dict], dict]) -> None:
    path = Path(path)
    read_model_metadata(path)  # a model file, or a clear error
    header = _read_header(path)["__metadata__"]
    state = load_file(str(path), device="cpu")
    partial = path.with_name(path.name + ".partial")
    save_file(state, str(partial), metadata=update(header))
    partial.replace(path)


#: System fields a model does not depend on: the chief rays only say where the sub-views
#: are cut, and a model sees the sub-views with coordinates relative to them, so it applies
#: unchanged to a system whose chief rays moved (calibrated, self-registered, nudged).
PLACEMENT_FIELDS = ("chief_rays",)
#: The forward model's description (measured PSFs, their rank): what the model-based
#: methods invert, never an input of a network, so a calibrated system keeps its model.
FORWARD_MODEL_FIELDS = ("psf_model", "rank", "rank_tolerance")
#: Every system field a model may differ in from the system it runs on (the pixel sizes
#: label the data and change no computation).
FREE_FIELDS = PLACEMENT_FIELDS + FORWARD_MODEL_FIELDS + PIXEL_SIZE_FIELDS


def load_model(
    path: str | Path,
    system: SystemConfig | None = None,
    device: torch.device | str = "cpu",
) -> tuple[nn.Module, SystemConfig]:
    """Load a model file written by :func:`save_model`, bit for bit, in eval mode.

    Parameters
    ----------
    path : str or Path
    system : SystemConfig, optional
        The instrument the caller will use the model on; a model trained for a different
        system (other than in :data:`FREE_FIELDS`) is refused.
    device : torch.device or str

    Returns
    -------
    (model, system)
        The model (architecture recorded in the file) and its training system.

    Raises
    ------
    ValueError
        Not a safetensors model file (pickle, zip, truncated), a system that differs
        (listing the fields), or tensors whose names or shapes do not fit the config.
    """
    device = resolve_device(device)  # an unavailable device is refused before any work
    meta = read_model_metadata(path)
    stored: SystemConfig = meta["system"]
    if system is not None:
        placed = system.replace(**{name: getattr(stored, name) for name in FREE_FIELDS})
        differences = _differences(placed.to_dict(), stored.to_dict())
        if differences:
            raise ValueError(
                f"{path}: the model was trained for system {stored.name!r}, which differs "
                f"from {system.name!r} in {len(differences)} field(s): " + "; ".join(differences)
            )
    model = _architectures()[meta["architecture"]].build(meta["model_config"], stored)
    state = load_file(str(path), device="cpu")
    expected = model.state_dict()
    problems = [f"missing {k}" for k in expected if k not in state]
    problems += [f"unexpected {k}" for k in state if k not in expected]
    problems += [
        f"{k}: file {tuple(v.shape)} vs model {tuple(expected[k].shape)}"
        for k, v in state.items()
        if k in expected and v.shape != expected[k].shape
    ]
    if problems:
        raise ValueError(f"{path}: weights do not fit the stored model config: "
                         + "; ".join(problems[:10]))
    dtypes = {v.dtype for v in state.values() if v.is_floating_point()}
    if len(dtypes) == 1:
        model.to(dtypes.pop())
    model.load_state_dict(state, strict=True)
    # what the file says of reduced precision (read by methods.svcode.auto_precision) and
    # of the overlap its tiles need (read by methods.svcode.plan_tiles)
    model.precision_check = meta["extra"].get("precision_check", {})
    model.overlap_check = meta["extra"].get("overlap_check", {})
    return model.to(device).eval(), stored


def _read_header(path: Path) -> dict[str, Any]:
    size = path.stat().st_size
    with path.open("rb") as handle:
        start = handle.read(9)  # a safetensors header is a JSON object: byte 8 is "{"
        if start[:1] == b"\x80" and start[8:9] != b"{":
            raise ValueError(f"{path}: a Python pickle, refused (unpickling can run code); "
                             "convert it to safetensors in a trusted environment")
        if start[:4] == b"PK\x03\x04":
            raise ValueError(f"{path}: a zip archive as written by torch.save, refused "
                             "(it holds pickles); convert it to safetensors")
        if len(start) < 8:
            raise ValueError(f"{path}: truncated or empty ({size} bytes), not a safetensors file")
        length = int.from_bytes(start[:8], "little")
        handle.seek(8)
        if length > min(size - 8, _MAX_HEADER):
            raise ValueError(f"{path}: truncated or not a safetensors file (header of "
                             f"{length} bytes announced, file has {size} bytes)")
        raw = handle.read(length)
    try:
        header = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise ValueError(f"{path}: not a safetensors file (header is not JSON)") from None
    if not isinstance(header, dict):
        raise ValueError(f"{path}: not a safetensors file (header is not a JSON object)")
    data_end = max(
        (v["data_offsets"][1] for k, v in header.items() if k != "__metadata__"), default=0
    )
    if 8 + length + data_end != size:
        raise ValueError(f"{path}: truncated or corrupt: the header describes "
                         f"{8 + length + data_end} bytes, the file has {size}")
    return header


def _differences(given: Any, stored: Any, prefix: str = "") -> list[str]:
    """Dotted names of the fields that differ between two JSON-like values."""
    if isinstance(given, dict) and isinstance(stored, dict):
        out = []
        for key in sorted(set(given) | set(stored)):
            name = f"{prefix}.{key}" if prefix else key
            out += _differences(given.get(key), stored.get(key), name)
        return out
    if given != stored:
        return [f"{prefix} (given {_short(given)}, model trained for {_short(stored)})"]
    return []


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."
