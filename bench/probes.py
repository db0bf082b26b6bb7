"""What the probe scripts (``ghosts.py``, ``ring_gap.py``, ``exposure.py``,
``resolution.py``, ``precision.py``, ``tile_overlap.py``) share: the reconstructors they
compare, with their labels, and how they write a report."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from svcode_bench.regimes import (
    ADMM_RANK,
    REGIMES,
    SCENES,
    model_label,
    plan_for,
    scene_object,
)
from svcode_core.config import SystemConfig
from svcode_core.methods.base import BaseReconstructor
from svcode_core.methods.build import build_reconstructor
from svcode_core.pretrained import require_bundled_weights

#: raw frame ``(H, W)`` to the ``(S, S)`` object estimate
Reconstruct = Callable[[np.ndarray], np.ndarray]
#: the committed reports
RESULTS = Path(__file__).parent / "results"


def svcode_methods(system: SystemConfig, weights: list[Path], knob: str = "",
                   **options: Any) -> list[tuple[str, Reconstruct]]:
    """The bundled SV-CoDe model, then every file of ``weights``, built with ``options``.

    Labels are the model's family and file (the bundled one by its name, the others by
    their path, relative to the working directory when inside it: the reports name no
    machine's folders), then ``knob`` (what ``options`` set).
    """
    methods = []
    bundled = require_bundled_weights(system)
    for path in [bundled, *weights]:
        reconstructor = build_reconstructor("svcode", system, path, **options)
        name = path.name if path == bundled else _shown(path)
        methods.append((f"{model_label(path)}: {name}{knob}",
                        lambda raw, r=reconstructor: r.reconstruct(raw).reconstruction))
    return methods


def learned_methods(system: SystemConfig, weights: list[Path]) -> list[tuple[str, Reconstruct]]:
    """A trained MultiWienerNet or SV-FourierNet per file of ``weights``, labelled by its
    family and file."""
    from svcode_core.methods import registry
    from svcode_core.methods.model_file import read_model_metadata

    methods = []
    for path in weights:
        method = registry.method_of_architecture(read_model_metadata(path)["architecture"])
        reconstructor = build_reconstructor(method, system, path)
        methods.append((f"{registry.method(method).label}: {_shown(path)}",
                        lambda raw, r=reconstructor: r.reconstruct(raw).reconstruction))
    return methods


def _shown(path: Path) -> str:
    """``path`` relative to the working directory when inside it, else as given."""
    here, resolved = Path.cwd().resolve(), path.resolve()
    return str(resolved.relative_to(here) if resolved.is_relative_to(here) else path)


def admm_method(system: SystemConfig, iterations: int) -> tuple[str, Reconstruct]:
    """:func:`admm_auto` at ``iterations``, as a function of the raw frame."""
    label, admm = admm_auto(system, iterations)
    return label, lambda raw: admm.reconstruct(raw).reconstruction


def admm_iterations(system: SystemConfig) -> int:
    """LSV-ADMM's iterations in the probes: the benchmark plan's most (50; 10 at paper
    scale, where each takes seconds a frame)."""
    return max(plan_for(system).admm_checkpoints)


def admm_auto(system: SystemConfig, iterations: int | None = None
              ) -> tuple[str, BaseReconstructor]:  # fmt: skip
    """LSV-ADMM as the probes run it, with its label: ``K`` = 3, ``iterations`` (default
    :func:`admm_iterations`), λ from each frame (the method's default), no early stop."""
    iterations = iterations or admm_iterations(system)
    return (f"LSV-ADMM K={ADMM_RANK}, {iterations} it, λ auto",
            build_reconstructor("admm", system, rank=ADMM_RANK, iterations=iterations,
                                tolerance=0.0, tv_weight="auto"))


def add_system_argument(parser: argparse.ArgumentParser) -> None:
    """``--system``: the preset or system file measured (default ``cm2-mini``)."""
    parser.add_argument("--system", default="cm2-mini",
                        help="preset or system JSON file (default cm2-mini; cm2-v2 runs the "
                        "paper-scale plan's scenes)")  # fmt: skip


def add_probe_arguments(parser: argparse.ArgumentParser, name: str) -> None:
    """``--weights`` (further SV-CoDe models beside the bundled one), ``--no-admm`` and
    ``--out`` (the report's stem, default ``bench/results/<name>``) of a probe script."""
    parser.add_argument("--weights", type=Path, nargs="*", default=[],
                        help="further SV-CoDe model files (the bundled one always runs)")
    parser.add_argument("--no-admm", action="store_true", help="skip LSV-ADMM")
    parser.add_argument("--out", type=Path, default=RESULTS / name,
                        help=f"output stem (.json and .md; default bench/results/{name})")


def add_check_arguments(parser: argparse.ArgumentParser, what: str, name: str) -> None:
    """``--record`` (write ``what`` into the model file) and ``--out`` (the report's stem,
    default ``bench/results/<name>``) of a script that measures a model file."""
    parser.add_argument("--record", action="store_true", help=f"write {what} into the model file")
    parser.add_argument("--out", type=Path, default=RESULTS / name,
                        help=f"output stem (.json and .md; default bench/results/{name})")


def add_scene_arguments(parser: argparse.ArgumentParser) -> None:
    """``--regimes`` and ``--scenes`` of the benchmark's; by default the plan's for the
    system (:func:`planned_scenes`)."""
    parser.add_argument("--regimes", nargs="+", choices=list(REGIMES),
                        help="default: the benchmark's for the system (every regime; at "
                        "paper scale matched and realistic)")  # fmt: skip
    parser.add_argument("--scenes", nargs="+", choices=[name for name, *_ in SCENES],
                        help="default: the benchmark's for the system (every scene; at "
                        "paper scale cells, neurons, ihc)")  # fmt: skip


def planned_scenes(args: argparse.Namespace, system: SystemConfig) -> tuple[tuple[str, ...],
                                                                            tuple[str, ...]]:
    """``(regimes, scenes)``: those given, else the benchmark plan's for ``system``
    (:func:`svcode_bench.regimes.plan_for`)."""
    plan = plan_for(system)
    return tuple(args.regimes or plan.regimes), tuple(args.scenes or plan.scenes)


def plan_truths(system: SystemConfig) -> dict[str, tuple[int, np.ndarray]]:
    """The benchmark plan's scenes for ``system``, each with its index in
    :data:`~svcode_bench.regimes.SCENES` (the object's seed; the benchmark's noise seed is
    100 + index) and its truth."""
    names = plan_for(system).scenes
    return {name: (index, scene_object(kind, system.sub_view_size, index, params))
            for index, (name, kind, params) in enumerate(SCENES) if name in names}


def earlier_rows(out: Path, system: SystemConfig, script: str) -> list[dict]:
    """The rows of the report at ``out``.json that a ``--merge`` run keeps from ([] when
    there is none); one of another system is refused, before any work is done."""
    earlier = out.with_suffix(".json")
    if not earlier.exists():
        return []
    report = json.loads(earlier.read_text())
    if report.get("system", "cm2-mini") != system.name:
        raise SystemExit(f"{script}: {earlier} measured {report.get('system', 'cm2-mini')}, "
                         f"not {system.name}: give another --out")
    return report["rows"]


def write_report(rows: list[dict], out: Path,
                 write_markdown: Callable[[dict, Path], None], **fields: Any) -> None:
    """``out``.json (the rows, the thread count and ``fields``) and ``out``.md from it."""
    report = {"threads": torch.get_num_threads(), **fields, "rows": rows}
    out.with_suffix(".json").write_text(json.dumps(report, indent=1))
    write_markdown(report, out.with_suffix(".md"))
    print(f"wrote {out.with_suffix('.md')}")
