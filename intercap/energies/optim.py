"""The one optimiser loop the fitting stages share: L-BFGS.

As SMPLify-X: a stage declares which variables move and a closure that returns
the weighted energy; `minimise` runs L-BFGS steps (torch's, with strong Wolfe
line search; on CUDA the batched one below, whose Armijo search reads the host
far less often) until the relative decrease of the energy between steps falls
below `ftol`, the largest gradient entry below `gtol`, or `max_steps` is
reached. A monitor callback sees every step (progress display, correspondence
updates). `minimise_per_frame` runs the same loop for a batch of independent
problems (the body's frames), one L-BFGS per frame in the same tensors.
`AdamRows` is Adam for such batches (the object's pose fits), each row its own
problem. On CUDA both can replay each evaluation (energy and gradients) from one
recorded CUDA graph (`gradient_evaluator`).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np
import torch

log = logging.getLogger(__name__)


@dataclass
class MinimiseResult:
    energy: float  # energy after the last step
    steps: int
    evaluations: int  # closure calls, line search included
    stopped: str  # "ftol", "gtol", "max_steps" or "nonfinite"


# aten operations whose result the host needs before it can go on (a value read back, a shape that depends
# on data, a linear-algebra result checked): on a GPU each waits for every kernel queued before it, and none
# may run inside a recorded CUDA graph
HOST_WAITS = frozenset({"_local_scalar_dense", "nonzero", "masked_select", "unique_dim", "_unique2",
                        "unique_consecutive", "equal", "is_nonzero", "bincount", "histc", "_linalg_check_errors",
                        "repeat_interleave"})

_graph_failures: list[str] = []  # why recordings failed in this process (the first is logged as a warning)


def gradient_evaluator(variables: list[torch.Tensor], energy_fn: Callable[[], torch.Tensor],
                       graph: bool = False) -> Callable[[], tuple[torch.Tensor, list[torch.Tensor]]]:
    """A function returning `energy_fn()` (detached) and its sum's gradients for `variables` at
    their current values.

    With `graph` on CUDA, the first call runs eagerly and records the evaluation as a CUDA graph;
    later calls replay it: one launch for the thousands of small kernels a fitting step's
    forward and backward issue (a GPU's time per step is their launches, ~28 us each). The graph
    reads the variables and whatever else `energy_fn` reads where they were when it was recorded,
    so the caller changes those in place only (`copy_`), and `energy_fn` must not wait on the GPU
    (no `.item()`, `nonzero`, boolean indexing, nothing made on or copied from the CPU;
    tests/host_waits.py checks the body's and the global stage's on the CPU). A recording that
    fails is logged (the process's first failure as a warning) and the evaluation stays eager."""

    def eager() -> tuple[torch.Tensor, list[torch.Tensor]]:
        with torch.enable_grad():
            energy = energy_fn()
            grads = torch.autograd.grad(energy.sum(), variables, allow_unused=True)
        return energy.detach(), [torch.zeros_like(v) if g is None else g for v, g in zip(variables, grads)]

    if not graph or not variables[0].is_cuda:
        return eager
    recorded = {}

    def replay() -> tuple[torch.Tensor, list[torch.Tensor]]:
        if "graph" not in recorded:
            side = torch.cuda.Stream()  # warm-up on a side stream, as torch.cuda.graph asks
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                first = eager()
            torch.cuda.current_stream().wait_stream(side)
            stream = torch.cuda.current_stream()
            try:
                recorded["graph"] = torch.cuda.CUDAGraph()
                with torch.cuda.graph(recorded["graph"], capture_error_mode="thread_local"):
                    recorded["outputs"] = eager()
            except Exception as error:  # noqa: BLE001 - any failure to record leaves the eager path
                torch.cuda.set_stream(stream)  # a failed capture does not restore it
                torch.cuda.synchronize()
                reason = (str(error).strip().splitlines() or [type(error).__name__])[0]
                (log.debug if _graph_failures else log.warning)("CUDA graph not recorded, evaluating eagerly: %s",
                                                                reason)
                _graph_failures.append(reason)
                recorded["graph"] = None
            return first
        if recorded["graph"] is None:
            return eager()
        recorded["graph"].replay()
        energy, grads = recorded["outputs"]
        return energy.clone(), [g.clone() for g in grads]

    return replay


def minimise(
    variables: Iterable[torch.Tensor],
    energy_fn: Callable[[], torch.Tensor],
    max_steps: int = 30,
    inner_iterations: int = 10,
    ftol: float = 1e-6,
    gtol: float = 1e-7,
    history_size: int = 20,
    monitor: Callable[[int, float], None] | None = None,
    graph: bool = False,
    line_search: str = "auto",
    max_line_search: int = 4,
) -> MinimiseResult:
    """Minimise the scalar `energy_fn()` over `variables` (leaf tensors, requires_grad set here);
    `graph`: evaluations replay a CUDA graph (`gradient_evaluator`).

    `line_search`: "strong_wolfe" is torch's L-BFGS (SMPLify-X's); "armijo" is `minimise_per_frame`'s
    L-BFGS with the whole problem as its one row, backtracking at most `max_line_search` trials an
    iteration; "auto": Armijo on CUDA, strong Wolfe elsewhere. The strong Wolfe search reads the energy,
    the slope and its tests on the host at every trial, so a GPU idles while the host decides; Armijo's
    reads one flag per trial. Both reach the same accuracy on the 150-frame bench (BENCHMARKS.md)."""
    variables = list(variables)
    if line_search == "auto":
        line_search = "armijo" if variables[0].is_cuda else "strong_wolfe"
    if line_search == "armijo":
        return _lbfgs_rows(variables, lambda: energy_fn().reshape(1), max_steps, inner_iterations, ftol, gtol,
                           history_size, max_line_search, monitor, graph, one_problem=True)
    if line_search != "strong_wolfe":
        raise ValueError(f"line_search must be 'strong_wolfe' or 'armijo', not {line_search!r}")
    variables = [v.requires_grad_(True) for v in variables]
    energy_and_gradients = gradient_evaluator(variables, energy_fn, graph)
    optimiser = torch.optim.LBFGS(
        variables, lr=1.0, max_iter=inner_iterations, history_size=history_size,
        line_search_fn="strong_wolfe", tolerance_grad=gtol, tolerance_change=1e-12,
    )
    evaluations = 0

    def closure():
        nonlocal evaluations
        evaluations += 1
        energy, grads = energy_and_gradients()
        for v, g in zip(variables, grads):
            v.grad = g
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


def minimise_per_frame(
    variables: Iterable[torch.Tensor],
    energy_fn: Callable[[], torch.Tensor],
    max_steps: int = 30,
    inner_iterations: int = 10,
    ftol: float = 1e-6,
    gtol: float = 1e-7,
    history_size: int = 20,
    max_line_search: int = 1,
    monitor: Callable[[int, float], None] | None = None,
    graph: bool = False,
) -> MinimiseResult:
    """`minimise` for B independent problems at once: every variable's first dimension is the frame
    and `energy_fn()` returns each frame's energy (B,), which depends on that frame's rows only.

    Each frame runs its own L-BFGS (its own history, step length and stopping), batched as tensors:
    one evaluation serves all frames, so a batch costs the kernels of one problem however many
    frames it holds, and a frame's result does not depend on the batch it is fitted in (one L-BFGS
    over the batch's sum stops on the sum's decrease and shares one step length, so larger batches
    fit each frame worse: 150 frames at 30 fps in 32-frame batches, surface 6.2 -> 5.8 mm at the
    same cost, BENCHMARKS.md). The line search is Armijo's backtracking with quadratic
    interpolation, per frame, `max_line_search` trials per iteration: with one, every iteration
    costs one evaluation, and a frame whose trial failed stays and tries the shorter step at the
    next. A frame whose step-start energy falls by no more than `ftol` between steps, or whose
    largest gradient entry is below `gtol`, stops moving. `graph`: as `minimise`'s."""
    return _lbfgs_rows(variables, energy_fn, max_steps, inner_iterations, ftol, gtol, history_size,
                       max_line_search, monitor, graph)


def _lbfgs_rows(variables, energy_fn, max_steps, inner_iterations, ftol, gtol, history_size, max_line_search,
                monitor, graph, one_problem: bool = False) -> MinimiseResult:
    """`minimise_per_frame`'s L-BFGS; `one_problem`: all variables together are one row (B = 1)."""
    variables = [v.requires_grad_(True) for v in variables]
    energy_and_gradients = gradient_evaluator(variables, energy_fn, graph)
    B = 1 if one_problem else int(variables[0].shape[0])
    sizes = [v.numel() if one_problem else v[0].numel() for v in variables]
    x = torch.cat([v.detach().reshape(B, -1) for v in variables], 1)
    evaluations = 0

    def place(point: torch.Tensor) -> None:
        """The variables take the values of `point` (B, n)."""
        with torch.no_grad():
            for v, part in zip(variables, point.split(sizes, 1)):
                v.copy_(part.view_as(v))

    def evaluate(point: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        nonlocal evaluations
        evaluations += 1
        place(point)
        f, grads = energy_and_gradients()
        return f, torch.cat([d.reshape(B, -1) for d in grads], 1)

    # (s, y, rho s, rho y) with rho = 1 / s.y per frame (0 for a pair not kept), oldest first
    history: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]] = []
    scale = torch.full((B,), math.nan, dtype=x.dtype, device=x.device)  # s.y / y.y of the newest good pair
    moving = torch.ones(B, dtype=torch.bool, device=x.device)
    previous = torch.full((B,), math.inf, dtype=x.dtype, device=x.device)
    stopped, step = "max_steps", 0
    for step in range(1, max_steps + 1):
        f, g = evaluate(x)  # the step's energy (correspondences may have changed since the last step)
        finite = torch.isfinite(f)
        moving &= finite & (g.abs().amax(1) >= gtol)
        settled = (previous - f) <= ftol * torch.maximum(torch.maximum(previous.abs(), f.abs()), torch.ones_like(f))
        moving &= ~(settled & torch.isfinite(previous))
        if not bool(moving.any()):
            stopped = "nonfinite" if not bool(finite.all()) else "ftol"
            break
        previous = torch.where(finite, f, previous)
        inner = moving.clone()
        trial = torch.ones_like(f)  # each frame's next trial step length
        for _ in range(inner_iterations):
            # the direction: the two-loop recursion of each frame's own history
            # (each pair's rho folded into rho s and rho y: five kernels a pair, not eleven)
            q = -g
            alphas = []
            for s, y, rho_s, _ in reversed(history):
                a = row_dot(rho_s, q)
                q = torch.addcmul(q, a[:, None], y, value=-1.0)
                alphas.append(a)
            first = torch.clamp(1.0 / g.abs().sum(1).clamp(min=1e-30), max=1.0)  # torch's first step: |g|_1 <= 1
            q = q * torch.where(torch.isnan(scale), first, scale)[:, None]
            for (s, y, _, rho_y), a in zip(history, reversed(alphas)):
                q = torch.addcmul(q, (a - row_dot(rho_y, q))[:, None], s)
            d = torch.where(inner[:, None], q, torch.zeros_like(q))
            slope = (g * d).sum(1)
            uphill = inner & (slope >= 0)  # not a descent direction (a poor history): steepest descent
            d = torch.where(uphill[:, None], -g * first[:, None], d)
            slope = (g * d).sum(1)
            # per-frame backtracking line search (Armijo), trial steps for all frames in one evaluation
            length = trial.clone()
            pending = inner.clone()
            f_new, g_new = f, g
            for trial_index in range(max_line_search):
                f_try, g_try = evaluate(x + length[:, None] * d)
                ok = pending & torch.isfinite(f_try) & (f_try <= f + 1e-4 * length * slope)
                f_new = torch.where(ok, f_try, f_new)
                g_new = torch.where(ok[:, None], g_try, g_new)
                pending &= ~ok
                excess = torch.nan_to_num(f_try - f - length * slope, nan=math.inf, posinf=math.inf)
                shrunk = -slope * length**2 / (2 * excess.clamp(min=1e-30))  # minimum of the quadratic through them
                length = torch.where(pending, torch.minimum(torch.maximum(shrunk, 0.1 * length), 0.5 * length), length)
                if trial_index + 1 < max_line_search and not bool(pending.any()):  # (the last trial: no GPU wait)
                    break
            taken = inner & ~pending
            trial = torch.where(taken, torch.ones_like(trial), length)  # a frame still backtracking goes on next time
            length = torch.where(taken, length, torch.zeros_like(length))
            s = length[:, None] * d
            y = g_new - g
            sy = (s * y).sum(1)
            good = taken & (sy > 1e-10)
            rho = torch.where(good, 1.0 / sy.clamp(min=1e-10), torch.zeros_like(sy))[:, None]
            history.append((s, y, rho * s, rho * y))
            if len(history) > history_size:
                history.pop(0)
            scale = torch.where(good, sy / (y * y).sum(1).clamp(min=1e-30), scale)
            x = x + s
            inner &= (g_new.abs().amax(1) >= gtol) & ~(taken & ((f - f_new).abs() <= 1e-12 * f.abs().clamp(min=1.0)))
            inner &= trial > 1e-10  # a frame no step length lowers has arrived (or its energy is not finite)
            f, g = f_new, g_new
            if not bool(inner.any()):
                break
        if monitor is not None:
            monitor(step, float(f.sum()))
    place(x)
    with torch.no_grad():
        final = float(energy_fn().sum())
    return MinimiseResult(final, step, evaluations, stopped)


def row_dot(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """(B, n), (B, n) -> (B,) the rows' dot products, as one batched product (one kernel)."""
    return torch.bmm(u.unsqueeze(1), v.unsqueeze(2)).view(-1)


class AdamRows:
    """torch.optim.Adam's update for parameters whose rows are separate problems (P rows each): a
    row keeps its own step count and step-size scale (`scale`, 1 at first), and a step moves only
    the rows named. With one row it is Adam itself."""

    def __init__(self, params: list[torch.Tensor], lrs: list[float], rows: int,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.params, self.lrs, self.betas, self.eps = params, lrs, betas, eps
        self.moments = [(torch.zeros_like(p), torch.zeros_like(p)) for p in params]
        self.count, self.scale = np.zeros(rows, int), np.ones(rows)

    @torch.no_grad()
    def step(self, rows: np.ndarray) -> None:
        """One step of `rows` along the gradients in the parameters' .grad, which it then clears."""
        b1, b2 = self.betas
        self.count[rows] += 1
        n = self.count[rows]
        dev, dtype = self.params[0].device, self.params[0].dtype
        size = torch.as_tensor(self.scale[rows] / (1 - b1 ** n), dtype=dtype, device=dev)[:, None]
        root = torch.as_tensor(np.sqrt(1 - b2 ** n), dtype=dtype, device=dev)[:, None]
        at = slice(None) if len(rows) == len(self.count) else torch.as_tensor(rows, device=dev)
        for p, lr, (m, v) in zip(self.params, self.lrs, self.moments):
            g = p.grad[at]
            m[at] = m[at].lerp(g, 1 - b1)
            v[at] = v[at] * b2 + (1 - b2) * g * g
            p[at] = p[at] - (lr * size) * m[at] / (v[at].sqrt() / root + self.eps)
            p.grad = None
