"""Models shipped inside the package: ``svcode_core/weights/<system name>.safetensors``.

Each bundled model is a :func:`~svcode_core.network.save_model` file (safetensors with its
model configuration and the system it was trained for) and has a model card beside it,
``<system name>.md``, with the training command, data recipe, wall time and validation
scores.
"""

from __future__ import annotations

from pathlib import Path

from .config import SystemConfig

__all__ = ["WEIGHTS_DIR", "bundled_weights", "require_bundled_weights"]

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


def _name(system: SystemConfig | str) -> str:
    return system.name if isinstance(system, SystemConfig) else str(system)


def bundled_weights(system: SystemConfig | str | None = None) -> Path | None:
    """The bundled model file for ``system`` (a configuration or a system name).

    Without ``system``, the first bundled model in alphabetical order. ``None`` when no
    such model is installed.
    """
    found = sorted(WEIGHTS_DIR.glob("*.safetensors")) if WEIGHTS_DIR.is_dir() else []
    if system is not None:
        found = [path for path in found if path.stem == _name(system)]
    return found[0] if found else None


def require_bundled_weights(system: SystemConfig | str) -> Path:
    """Like :func:`bundled_weights`, but raise a ``FileNotFoundError`` that says what to do.

    Raises
    ------
    FileNotFoundError
        If no model is bundled for ``system``.
    """
    path = bundled_weights(system)
    if path is None:
        shipped = sorted(p.stem for p in WEIGHTS_DIR.glob("*.safetensors"))
        raise FileNotFoundError(
            f"no bundled SV-CoDe model for system {_name(system)!r} (bundled: "
            f"{', '.join(shipped) or 'none'}); train one with `svcode dataset` and "
            "`svcode train` and pass it with --weights"
        )
    return path
