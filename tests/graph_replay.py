"""CUDA graphs' replay, on the CPU: what `optim.recorded` records is re-run as a GPU replays it.

A CUDA graph replays the kernels it recorded on the memory they used then; the Python around them
does not run again. So a recorded function that reads a tensor made anew at each call, keeps a
result in a Python variable, or branches on a value, replays wrongly, silently. `ReplayOnCpu`
records the aten operations a function dispatches with the tensors they read and wrote, and a
replay re-runs each on those same tensors: such a function gives stale results here too, and a
fit replayed so must equal its eager run. As on a GPU, where a recording runs nothing, what the
recorded run wrote in place is put back afterwards: the first call's effect is its warm-up's alone.
"""
from __future__ import annotations

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

from intercap.energies import optim


class ReplayOnCpu(TorchDispatchMode):
    """Records each aten operation dispatched while active: (operation, arguments, outputs); and
    what each tensor written in place held before, to put back (`undo`)."""

    def __init__(self):
        super().__init__()
        self.operations = []
        self.before = {}  # id -> (tensor, its values before the recording's first write)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func.overloadpacket.__name__ in optim.HOST_WAITS:
            raise RuntimeError(f"{func} waits on the device: it cannot be recorded")
        for argument, value in zip(func._schema.arguments, [*args, *[kwargs.get(a.name) for a in
                                                                   func._schema.arguments[len(args):]]]):
            if (isinstance(value, torch.Tensor) and argument.alias_info is not None and argument.alias_info.is_write
                    and id(value) not in self.before):
                self.before[id(value)] = (value, value.detach().clone())
        out = func(*args, **kwargs)
        returns = func._schema.returns
        writes = any(r.alias_info is not None and r.alias_info.is_write for r in returns)
        views = any(r.alias_info is not None and not r.alias_info.is_write for r in returns)
        if not views:  # a view is the same memory at a replay: nothing to redo
            self.operations.append((func, args, kwargs, None if writes else out))
        return out

    def undo(self) -> None:
        with torch.no_grad():
            for tensor, values in self.before.values():
                tensor.copy_(values)

    def replay(self) -> None:
        """Each recorded operation again, on the tensors it had; results into the tensors it made."""
        with torch.no_grad():  # the recording's backward operations are among them
            self._replay()

    def _replay(self) -> None:
        for func, args, kwargs, out in self.operations:
            fresh = func(*args, **kwargs)
            if out is not None:  # not in place: its new result goes where the recording's went
                for made, again in zip(tree_leaves(out), tree_leaves(fresh)):
                    if isinstance(made, torch.Tensor):
                        made.copy_(again)


def record_on_cpu(fn):
    recording = ReplayOnCpu()
    with recording:
        outputs = fn()
    recording.undo()
    return outputs, recording.replay


def replaying_on_cpu(monkeypatch):
    """`optim.recorded` records and replays on the CPU (`ReplayOnCpu`), as a fixture
    (conftest's `replay_on_cpu`): yields the list of replays made."""
    replays = []
    monkeypatch.setattr(optim, "records_graphs", lambda device: True)
    monkeypatch.setattr(optim, "_warm_up", lambda fn: fn())

    def counted_record(fn):
        outputs, replay = record_on_cpu(fn)
        return outputs, lambda: replays.append(1) or replay()

    monkeypatch.setattr(optim, "_record", counted_record)
    monkeypatch.setattr(optim, "_graph_failures", [])
    yield replays
    assert not optim._graph_failures, f"recordings failed: {optim._graph_failures}"
