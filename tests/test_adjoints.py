"""Every linear operator of the package against its adjoint: ⟨A x, y⟩ = ⟨x, Aᵀ y⟩.

One list, :func:`linear_operators`, names each operator with its adjoint and the shapes of
``x`` and ``y``; one test checks them all in float32 and float64. A new operator with an
adjoint belongs in the list.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import pytest
import torch
from test_cm2 import gaussian_psfs
from test_lowrank import random_operator

from svcode_core.config import SystemConfig
from svcode_core.methods.baselines.admm import gradient, gradient_adjoint
from svcode_core.physics.cm2 import CM2Operator
from svcode_core.physics.geometry import (
    crop_to_sensor,
    extract_sub_views,
    pad_sensor_frame,
    place_sub_views,
)

TOLERANCE = {torch.float32: 1e-5, torch.float64: 1e-12}


class Linear(NamedTuple):
    """``forward: x → y`` and ``adjoint: y → x`` with the shapes of ``x`` and ``y``."""

    forward: Callable[[torch.Tensor], torch.Tensor]
    adjoint: Callable[[torch.Tensor], torch.Tensor]
    x_shape: tuple[int, ...]
    y_shape: tuple[int, ...]


def linear_operators() -> dict[str, Callable[[SystemConfig, torch.dtype], Linear]]:
    """Every linear operator with an adjoint: name → builder for a system and a dtype."""

    def cm2(system: SystemConfig, dtype: torch.dtype) -> Linear:
        op = CM2Operator.from_psfs(system, gaussian_psfs(system), rank=3, dtype=dtype)
        size = system.sub_view_size
        return Linear(op.forward, op.adjoint, (2, size, size), (2, *system.padded_shape))

    def crop(system: SystemConfig, dtype: torch.dtype) -> Linear:
        return Linear(lambda f: crop_to_sensor(f, system), lambda s: pad_sensor_frame(s, system),
                      tuple(system.padded_shape), tuple(system.sensor_shape))  # fmt: skip

    def views(margin: int) -> Callable[[SystemConfig, torch.dtype], Linear]:
        def build(system: SystemConfig, dtype: torch.dtype) -> Linear:
            side = system.sub_view_size + 2 * margin
            return Linear(lambda f: extract_sub_views(f, system, margin),
                          lambda v: place_sub_views(v, system, margin),
                          (2, *system.padded_shape), (2, 9, side, side))  # fmt: skip
        return build

    def lowrank(shape: tuple[int, int], kernel: tuple[int, int],
                lenses: int | None) -> Callable[[SystemConfig, torch.dtype], Linear]:  # fmt: skip
        def build(system: SystemConfig, dtype: torch.dtype) -> Linear:
            op = random_operator(shape, kernel, lenses=lenses, dtype=dtype)
            out = (2, 3, *shape) if lenses is None else (2, 3, lenses, *shape)
            return Linear(op.forward, op.adjoint, (2, 3, *shape), out)
        return build

    operators = {
        "CM2Operator": cm2,
        "crop_to_sensor / pad_sensor_frame": crop,
        "extract_sub_views / place_sub_views": views(0),
        "extract_sub_views / place_sub_views, margin 4": views(4),
        "TV gradient": lambda system, dtype: Linear(gradient, gradient_adjoint,
                                                    (3, 17, 12), (3, 2, 17, 12)),
    }  # fmt: skip
    # the low-rank blur: odd and even sizes, a kernel larger than the image, batched lenses
    for shape, kernel, lenses in [((20, 20), (5, 5), None), ((17, 23), (5, 9), None),
                                  ((12, 9), (7, 3), None), ((5, 6), (9, 11), None),
                                  ((11, 14), (5, 3), 3)]:  # fmt: skip
        name = f"LowRankSVOperator {shape}, kernel {kernel}, lenses {lenses}"
        operators[name] = lowrank(shape, kernel, lenses)
    return operators


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", list(linear_operators()))
def test_adjoint_dot_product(tiny_system, name, dtype):
    op = linear_operators()[name](tiny_system, dtype)
    generator = torch.Generator().manual_seed(0)
    x = torch.randn(op.x_shape, generator=generator, dtype=dtype)
    y = torch.randn(op.y_shape, generator=generator, dtype=dtype)
    ax, aty = op.forward(x), op.adjoint(y)
    assert tuple(ax.shape) == op.y_shape and tuple(aty.shape) == op.x_shape
    lhs = (ax.double() * y.double()).sum()
    rhs = (x.double() * aty.double()).sum()
    scale = ax.double().norm() * y.double().norm()
    assert abs(lhs - rhs) / scale <= TOLERANCE[dtype]
