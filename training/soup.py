"""Average the weights of several fine-tunings of one model (a uniform model soup).

Every file must hold the same network (same configuration, same parameter names and
shapes): runs fine-tuned from one starting point stay close enough in weight space that
their mean is a model of its own, often better on data none of them was tuned for. The
output keeps the first file's network and system; the training record and the checks
measured on one model (its bf16 precision check) are left out, the ingredients recorded
under ``extra`` instead: measure the soup before trusting it (``bench/precision.py
--record`` for its precision).

Usage (from the repository root):
    python training/soup.py A.safetensors B.safetensors [...] --out SOUP.safetensors
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import save_file


def load(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    with safe_open(str(path), "pt") as file:
        return {key: file.get_tensor(key) for key in file.keys()}, file.metadata() or {}


def soup(paths: list[Path]) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """The mean of the files' floating-point tensors (in float64, stored in each tensor's
    own dtype) and the first file's metadata, its ``extra`` reduced to the system, the
    network and the ingredients."""
    first, metadata = load(paths[0])
    total = {key: value.double() for key, value in first.items() if value.is_floating_point()}
    for path in paths[1:]:
        tensors, other = load(path)
        same_network = other.get("model_config") == metadata.get("model_config")
        if not same_network or tensors.keys() != first.keys():
            raise SystemExit(f"soup: {path} holds another network than {paths[0]}")
        for key in total:
            if tensors[key].shape != first[key].shape:
                raise SystemExit(f"soup: {key} is {tuple(tensors[key].shape)} in {path}, "
                                 f"{tuple(first[key].shape)} in {paths[0]}")
            total[key] += tensors[key].double()
    mean = {key: (total[key] / len(paths)).to(value.dtype) if key in total else value
            for key, value in first.items()}
    first_extra = json.loads(metadata.get("extra", "{}") or "{}")
    extra = {key: first_extra[key] for key in ("system", "model_config") if key in first_extra}
    extra["soup"] = [path.name if path.parent.name == "weights" else str(path) for path in paths]
    return mean, {**metadata, "extra": json.dumps(extra)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("weights", type=Path, nargs="+", help="model files (at least two)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if len(args.weights) < 2:
        parser.error("give at least two model files")
    tensors, metadata = soup(args.weights)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_file({key: value.contiguous() for key, value in tensors.items()}, str(args.out),
              metadata=metadata)
    print(f"{args.out}: the mean of {len(args.weights)} models")


if __name__ == "__main__":
    main()
