"""The one optimiser loop the fitting stages share: L-BFGS with strong Wolfe line search.

As SMPLify-X: a stage declares which variables move and a closure that
returns the weighted energy; `minimise` runs L-BFGS steps until the relative
decrease of the energy between steps falls below `ftol`, the largest gradient
entry below `gtol`, or `max_steps` is reached. A monitor callback sees every
step (progress display, correspondence updates).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Iterable

import torch


@dataclass
class MinimiseResult:
    energy: float  # energy after the last step
    steps: int
    evaluations: int  # closure calls, line search included
    stopped: str  # "ftol", "gtol", "max_steps" or "nonfinite"


def minimise(
    variables: Iterable[torch.Tensor],
    energy_fn: Callable[[], torch.Tensor],
    max_steps: int = 30,
    inner_iterations: int = 10,
    ftol: float = 1e-6,
    gtol: float = 1e-7,
    history_size: int = 20,
    monitor: Callable[[int, float], None] | None = None,
) -> MinimiseResult:
    """Minimise the scalar `energy_fn()` over `variables` (leaf tensors, requires_grad set here)."""
    variables = [v.requires_grad_(True) for v in variables]
    optimiser = torch.optim.LBFGS(
        variables, lr=1.0, max_iter=inner_iterations, history_size=history_size,
        line_search_fn="strong_wolfe", tolerance_grad=gtol, tolerance_change=1e-12,
    )
    evaluations = 0

    def closure():
        nonlocal evaluations
        evaluations += 1
        optimiser.zero_grad(set_to_none=False)
        energy = energy_fn()
        energy.backward()
        return energy

    previous = math.inf
    stopped = "max_steps"
    step = 0
    for step in range(1, max_steps + 1):
        energy = float(optimiser.step(closure).detach())
        if not math.isfinite(energy):
            stopped = "nonfinite"
            break
        if monitor is not None:
            monitor(step, energy)
        if previous < math.inf and (previous - energy) <= ftol * max(abs(previous), abs(energy), 1.0):
            stopped = "ftol"
            break
        gradients = [v.grad.abs().max() for v in variables if v.grad is not None]
        if gradients and float(torch.stack(gradients).max()) < gtol:
            stopped = "gtol"
            break
        previous = energy
    with torch.no_grad():
        final = float(energy_fn())
    return MinimiseResult(final, step, evaluations, stopped)
