"""What makes the CPU wait on a GPU, seen on the CPU: evaluations recorded as CUDA graphs
(`optim.gradient_evaluator`) must issue none of it."""
from __future__ import annotations

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from intercap.energies import optim


class HostWaits(TorchDispatchMode):
    """Records what makes the CPU wait on a GPU or copy to it: a value read back, a shape that
    depends on data, a linear-algebra result checked, data or a scalar copied from the host, a
    tensor made without a device (on the CPU, in a GPU run). None of it may run inside a
    recorded CUDA graph, so the body's and the global stage's evaluations must issue none. Seen
    on the CPU: aten operations as dispatched, torch's factories as called."""

    WAITING = optim.HOST_WAITS

    # torch factories that, called without a device, make a CPU tensor on a GPU run: indexing a CUDA
    # tensor with one copies it from the host (anny's interpolation did: `torch.arange(batch)`)
    FACTORIES = ("arange", "zeros", "ones", "empty", "full", "eye", "linspace", "tensor", "as_tensor", "rand", "randn")

    def __init__(self):
        super().__init__()
        self.seen = []
        self.host_scalars = {}  # id -> 0-dim tensor made from a Python number (host memory on a GPU run), kept
        # alive so that its id is not reused

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        boolean_index = name in ("index", "index_put", "index_put_") and any(
            isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (args[1] or ()))
        from_host = name == "lift_fresh" and args[0].dim() > 0  # torch.tensor(list), x.new_tensor(list)
        # a number written into one element (`x[i, j] = 1.0`) is copied from the host; into several, filled
        scalar_copied = name == "copy_" and id(args[1]) in self.host_scalars
        if name in self.WAITING or boolean_index or from_host or scalar_copied:
            self.seen.append(name)
        out = func(*args, **(kwargs or {}))
        if name == "lift_fresh" and args[0].dim() == 0:
            self.host_scalars[id(out)] = out
        return out

    def __enter__(self):
        self.factories = {name: getattr(torch, name) for name in self.FACTORIES}
        for name, make in self.factories.items():
            setattr(torch, name, self._watched_factory(name, make))
        return super().__enter__()

    def __exit__(self, *exc):
        for name, make in self.factories.items():
            setattr(torch, name, make)
        return super().__exit__(*exc)

    def _watched_factory(self, name, make):
        def watched(*args, **kwargs):
            keeps_device = name == "as_tensor" and isinstance(args[0], torch.Tensor)
            if kwargs.get("device") is None and not keeps_device:
                self.seen.append(f"torch.{name} without a device")
            return make(*args, **kwargs)
        return watched


def watch_evaluations(monkeypatch) -> tuple[HostWaits, list[list]]:
    """Run the fits as where graphs are recorded (`optim.records_graphs`: the dense nearest-point
    search, depth pairs of fixed size) and watch every function they would record (`optim.recorded`;
    nothing is recorded here), its calls after its first (the first runs eagerly on a GPU too, and
    fills the caches there): returns the `HostWaits` they share and, per evaluation (energy and
    gradients: the functions whose name says they evaluate), the list of its calls. The L-BFGS's
    other parts (direction, verdict, step) and the correspondence refreshes are watched too."""
    waits, evaluators = HostWaits(), []

    def watched(fn, enabled, device):
        if not enabled:
            return fn
        calls = []
        if "evaluat" in fn.__name__:
            evaluators.append(calls)

        def run_watched():
            calls.append(1)
            if len(calls) == 1:
                return fn()
            with waits:
                return fn()
        return run_watched

    monkeypatch.setattr(optim, "records_graphs", lambda device: True)
    monkeypatch.setattr(optim, "recorded", watched)
    return waits, evaluators
