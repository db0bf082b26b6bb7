"""Which model a training run builds: the configuration of every trainable method.

SV-CoDe is configured by :class:`~svcode_core.network.ModelConfig` (presets ``mini`` and
``reference``, and the ablations of :data:`ABLATIONS`); each learned baseline by the
configuration class of its model (:data:`~svcode_core.methods.learned.LEARNED_MODELS`).
The method names are those of :mod:`svcode_core.methods.registry`.
"""

from __future__ import annotations

from pathlib import Path

from ..methods import registry
from ..methods.learned import LEARNED_MODELS, FourierNetConfig, MultiWienerConfig
from ..network import ModelConfig
from .settings import ABLATIONS

__all__ = ["ABLATIONS", "AnyModelConfig", "config_class", "model_config_from",
           "with_svcode_options"]

AnyModelConfig = ModelConfig | MultiWienerConfig | FourierNetConfig


def config_class(method: str) -> type:
    """The configuration class of trainable ``method``.

    Examples
    --------
    >>> config_class("svcode").__name__, config_class("fouriernet").__name__
    ('ModelConfig', 'FourierNetConfig')
    """
    if method not in registry.TRAINABLE_METHODS:
        raise ValueError(f"method: {method!r} is not trained; trainable methods are "
                         f"{', '.join(registry.TRAINABLE_METHODS)}")  # fmt: skip
    if method in registry.LEARNED_METHODS:
        return LEARNED_MODELS[registry.method(method).architecture].config_class
    return ModelConfig


def model_config_from(spec: str, ablation: str = "none", method: str = "svcode",
                      lens_context: int = 0, padding: str | None = None,
                      view_margin: int | None = None) -> AnyModelConfig:
    """The configuration of ``method`` from ``"mini"``, ``"reference"`` (SV-CoDe only) or a
    JSON file, with the SV-CoDe options (:func:`with_svcode_options`).

    Examples
    --------
    >>> model_config_from("mini", "no-pe").positional_encoding
    False
    """
    cls = config_class(method)
    if cls is not ModelConfig:
        if spec == "mini":
            config = cls().validate()
        else:
            path = _config_file(spec, "neither mini nor")
            config = cls.from_json(path.read_text(encoding="utf-8"))
    elif spec in ("mini", "reference"):
        config = getattr(ModelConfig, spec)()
    else:
        path = _config_file(spec, "neither mini, reference nor")
        config = ModelConfig.from_json(path.read_text(encoding="utf-8"))
    return with_svcode_options(config, method, ablation, lens_context, padding, view_margin)


def with_svcode_options(config: AnyModelConfig, method: str, ablation: str = "none",
                        lens_context: int = 0, padding: str | None = None,
                        view_margin: int | None = None) -> AnyModelConfig:
    """``config`` with an ablation (:data:`ABLATIONS`), the lens context of reach
    ``lens_context`` (0: none; :attr:`~svcode_core.network.ModelConfig.lens_context`,
    :attr:`~svcode_core.network.ModelConfig.context_reach`), the convolutions'
    ``padding`` and the ``view_margin`` (``None``: the configuration's) applied; they
    belong to SV-CoDe and are refused for the configuration of another method. A reach
    shorter than the one ``config`` already has is refused too.

    Examples
    --------
    >>> with_svcode_options(ModelConfig.mini(), "svcode", lens_context=2).views_per_lens
    11
    """
    asked = [flag for flag, on in (("--ablation", ablation != "none"),
                                   ("--lens-context", lens_context),
                                   ("--padding", padding is not None),
                                   ("--view-margin", view_margin is not None)) if on]
    if not isinstance(config, ModelConfig):
        if asked:
            verb = "applies" if len(asked) == 1 else "apply"
            raise ValueError(f"{' and '.join(asked)} {verb} to SV-CoDe, not to --method {method}")
        return config
    config = config.replace(**ABLATIONS[ablation])
    if padding is not None:
        config = config.replace(padding=padding)
    if view_margin is not None:
        config = config.replace(view_margin=view_margin)
    if not lens_context:
        return config
    if config.lens_context and lens_context < config.context_reach:
        raise ValueError(f"--lens-context {lens_context}: the network configuration already "
                         f"has the lens context of reach {config.context_reach}, which a "
                         "shorter reach would drop; leave --lens-context out or give "
                         f"{config.context_reach} or more")  # fmt: skip
    return config.replace(lens_context=True, context_reach=int(lens_context))


def _config_file(spec: str, presets: str) -> Path:
    path = Path(spec)
    if not path.is_file():
        raise FileNotFoundError(f"--model-config {spec!r}: {presets} an existing JSON file")
    return path
