"""What makes the CPU wait on a GPU, seen on the CPU: evaluations recorded as CUDA graphs
(`optim.gradient_evaluator`) must issue none of it."""
from __future__ import annotations

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from intercap.energies import optim


class HostWaits(TorchDispatchMode):
    """Records the aten operations that make the CPU wait on a GPU (a value read back, a shape that
    depends on data, a linear-algebra result checked, data copied from the host): none may run
    inside a recorded CUDA graph, so the body's evaluation must issue none. Seen on the CPU."""

    WAITING = {"_local_scalar_dense", "nonzero", "masked_select", "unique_dim", "_unique2", "unique_consecutive",
               "equal", "is_nonzero", "bincount", "histc", "_linalg_check_errors", "repeat_interleave"}

    def __init__(self):
        super().__init__()
        self.seen = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        boolean_index = name in ("index", "index_put", "index_put_") and any(
            isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (args[1] or ()))
        from_host = name == "lift_fresh" and args[0].dim() > 0  # torch.tensor(list); a scalar written in place is a fill
        if name in self.WAITING or boolean_index or from_host:
            self.seen.append(name)
        return func(*args, **(kwargs or {}))


def watch_evaluations(monkeypatch) -> tuple[HostWaits, list[list]]:
    """Watch every `gradient_evaluator`'s calls after its first (the first runs eagerly on a GPU too,
    and fills the caches there; the rest are recorded): returns the `HostWaits` they share and, per
    evaluator made, the list of its calls."""
    waits, evaluators = HostWaits(), []
    real = optim.gradient_evaluator

    def watched(variables, energy_fn, graph=False):
        evaluate, calls = real(variables, energy_fn, graph), []
        evaluators.append(calls)

        def evaluate_watched():
            calls.append(1)
            if len(calls) == 1:
                return evaluate()
            with waits:
                return evaluate()
        return evaluate_watched

    monkeypatch.setattr(optim, "gradient_evaluator", watched)
    return waits, evaluators

