"""Average the weights of several fine-tunings of one model (a uniform model soup).

Every file must hold the same network for the same system: runs fine-tuned from one
starting point stay close enough in weight space that their mean is a model of its own,
often better on data none of them was tuned for. The output is written like any model
file (``save_model``); the training records and the checks measured on one model (its
bf16 precision check) are left out, the ingredients recorded under ``extra`` instead:
measure the soup before trusting it (``bench/precision.py --record`` for its precision).

Usage (from the repository root):
    python training/soup.py A.safetensors B.safetensors [...] --out SOUP.safetensors
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from svcode_core.config import SystemConfig
from svcode_core.methods.model_file import load_model, save_model


def soup(paths: list[Path]) -> tuple[torch.nn.Module, SystemConfig]:
    """The first file's network with the mean of every file's floating-point tensors (in
    float64, stored in each tensor's own dtype), and its system."""
    models = [load_model(path) for path in paths]  # each file checked against its config
    model, system = models[0]
    for path, (other, other_system) in zip(paths[1:], models[1:], strict=True):
        if other.model_config != model.model_config or other_system != system:
            raise SystemExit(f"soup: {path} holds another network or system than {paths[0]}")
    states = [other.state_dict() for other, _ in models]
    model.load_state_dict({
        key: (sum(state[key].double() for state in states) / len(states)).to(value.dtype)
        if value.is_floating_point() else value
        for key, value in states[0].items()
    })
    return model, system


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("weights", type=Path, nargs="+", help="model files (at least two)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if len(args.weights) < 2:
        parser.error("give at least two model files")
    model, system = soup(args.weights)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    ingredients = [path.name if path.parent.name == "weights" else str(path)
                   for path in args.weights]  # fmt: skip
    save_model(args.out, model, system, extra={"soup": ingredients})
    print(f"{args.out}: the mean of {len(args.weights)} models")


if __name__ == "__main__":
    main()
