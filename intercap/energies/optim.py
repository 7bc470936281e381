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
problem. On CUDA what they repeat replays recorded CUDA graphs (`recorded`): each
evaluation (energy and gradients, `gradient_evaluator`) and, in the batched L-BFGS,
each part of an iteration (direction, trial verdict, step).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable, Iterable

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


def recorded(fn: Callable[[], object], enabled: bool, device: torch.device) -> Callable[[], object]:
    """`fn` (no arguments: it reads and writes tensors where they are) replayed from a recorded CUDA
    graph where `enabled` on CUDA, else `fn` itself.

    The first call runs `fn` eagerly, then records it; later calls replay the recording (one launch
    for all its kernels: a GPU's time per small kernel is its launch, ~25 us) and return the outputs
    the recording made, the same tensors each time, overwritten by each replay. A replay reads what
    `fn` read when it was recorded, where it was then: the caller changes those tensors in place
    only (`copy_`), and `fn` must not wait on the GPU (no `.item()`, `nonzero`, boolean indexing,
    nothing made on or copied from the CPU; tests/host_waits.py checks the fits' on the CPU, and
    tests/graph_replay.py replays recordings on the CPU). A recording that fails is logged (the
    process's first failure as a warning) and `fn` stays eager."""
    if not enabled or not records_graphs(device):
        return fn
    recording = {}

    def call():
        if "replay" not in recording:
            first = _warm_up(fn)
            try:
                recording["outputs"], recording["replay"] = _record(fn)
            except Exception as error:  # noqa: BLE001 - any failure to record leaves the eager path
                reason = (str(error).strip().splitlines() or [type(error).__name__])[0]
                (log.debug if _graph_failures else log.warning)("CUDA graph not recorded, evaluating eagerly: %s",
                                                                reason)
                _graph_failures.append(reason)
                recording["replay"] = None
            return first
        if recording["replay"] is None:
            return fn()
        recording["replay"]()
        return recording["outputs"]

    return call


def records_graphs(device: torch.device) -> bool:
    """Whether `recorded` records on `device` (CUDA; the tests replay on the CPU too, graph_replay.py):
    what a recorded graph reads must then keep its shape (the body's depth pairs, the object's renders)."""
    return device.type == "cuda"


def _warm_up(fn: Callable[[], object]) -> object:
    """fn() on a side stream, as torch.cuda.graph asks before a recording."""
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        first = fn()
    torch.cuda.current_stream().wait_stream(side)
    return first


def _record(fn: Callable[[], object]) -> tuple[object, Callable[[], None]]:
    """fn's kernels recorded as one CUDA graph: (the outputs of the recorded run, the replay)."""
    stream = torch.cuda.current_stream()
    graph = torch.cuda.CUDAGraph()
    try:
        with torch.cuda.graph(graph, capture_error_mode="thread_local"):
            outputs = fn()
    except Exception:
        torch.cuda.set_stream(stream)  # a failed capture does not restore it
        torch.cuda.synchronize()
        raise
    return outputs, graph.replay


def energy_and_gradients(variables: list[torch.Tensor], energy_fn: Callable[[], torch.Tensor]
                         ) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """`energy_fn()` (detached) and its sum's gradients for `variables` (zeros where unused)."""
    with torch.enable_grad():
        energy = energy_fn()
        grads = torch.autograd.grad(energy.sum(), variables, allow_unused=True)
    return energy.detach(), [torch.zeros_like(v) if g is None else g for v, g in zip(variables, grads)]


def gradient_evaluator(variables: list[torch.Tensor], energy_fn: Callable[[], torch.Tensor],
                       graph: bool = False) -> Callable[[], tuple[torch.Tensor, list[torch.Tensor]]]:
    """A function returning `energy_fn()` (detached) and its sum's gradients for `variables` at
    their current values; with `graph` on CUDA replayed from a recorded graph (`recorded`: the
    caller changes the variables in place)."""
    def evaluation() -> tuple[torch.Tensor, list[torch.Tensor]]:
        return energy_and_gradients(variables, energy_fn)

    evaluate = recorded(evaluation, graph, variables[0].device)
    if evaluate is evaluation:
        return evaluation

    def replay() -> tuple[torch.Tensor, list[torch.Tensor]]:
        energy, grads = evaluate()
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
    `graph`: on CUDA evaluations (with Armijo's search, every part of an iteration) replay recorded
    graphs (`recorded`).

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
            v.grad = g.contiguous()  # torch's L-BFGS flattens them with `view` (a gradient may be a slice)
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
    """`minimise_per_frame`'s L-BFGS; `one_problem`: all variables together are one row (B = 1).

    Its state lives in tensors changed in place only (`RowLBFGS`), and each part of an iteration (the
    direction, an evaluation, a trial's verdict, the step) is a function of that state alone: with `graph`
    on CUDA each replays a recorded graph (`recorded`), so an iteration costs a few launches, not the
    hundred kernels of its bookkeeping. The host reads one flag per iteration (and per extra trial)."""
    state = RowLBFGS(variables, energy_fn, ftol, gtol, history_size, one_problem)
    x, f, moving, inner, pending = state.x, state.f, state.moving, state.inner, state.pending
    evaluations = 0
    evaluate, start, direct, judge, advance = (recorded(part, graph, state.device) for part in (
        state.evaluation, state.start, state.direct, state.judge, state.advance))
    stopped, step = "max_steps", 0
    for step in range(1, max_steps + 1):
        state.point.copy_(x)
        evaluate()
        evaluations += 1
        start()
        if not bool(moving.any()):
            stopped = "nonfinite" if not bool(torch.isfinite(f).all()) else "ftol"
            break
        for _ in range(inner_iterations):
            direct()
            for trial_index in range(max_line_search):  # trial steps for all frames in one evaluation
                evaluate()
                evaluations += 1
                judge()
                if trial_index + 1 < max_line_search and not bool(pending.any()):  # (the last trial: no GPU wait)
                    break
            advance()
            if not bool(inner.any()):
                break
        if monitor is not None:
            monitor(step, float(f.sum()))
    state.place(x)
    with torch.no_grad():
        final = float(energy_fn().sum())
    return MinimiseResult(final, step, evaluations, stopped)


class RowLBFGS:
    """The state of `_lbfgs_rows`' B independent L-BFGS problems, in tensors changed in place only, and
    the parts of an iteration, each a function of that state alone (so `recorded` can replay it)."""

    def __init__(self, variables, energy_fn, ftol: float, gtol: float, history_size: int, one_problem: bool):
        self.variables = variables = [v.requires_grad_(True) for v in variables]
        self.energy_fn, self.ftol, self.gtol = energy_fn, ftol, gtol
        self.device = device = variables[0].device
        self.B = B = 1 if one_problem else int(variables[0].shape[0])
        self.sizes = [v.numel() if one_problem else v[0].numel() for v in variables]
        self.x = x = torch.cat([v.detach().reshape(B, -1) for v in variables], 1)  # where the frames are
        self.point = x.clone()  # where the next evaluation is
        self.f, self.g = f, g = x.new_zeros(B), torch.zeros_like(x)  # energy and gradient at x
        self.f_try, self.g_try = f.clone(), g.clone()  # at point
        self.f_new, self.g_new = f.clone(), g.clone()  # at the accepted trial
        self.d = torch.zeros_like(x)  # the direction
        # scale: s.y / y.y of the newest good pair
        self.slope, self.length, self.scale = f.clone(), f.clone(), torch.full_like(f, math.nan)
        self.trial = torch.ones_like(f)  # each frame's next trial step length
        self.previous = torch.full_like(f, math.inf)  # the energy at the last step's start
        self.moving, self.inner, self.pending = (torch.ones(B, dtype=torch.bool, device=device) for _ in range(3))
        self.memory = PairMemory(B, x.shape[1], history_size, x)

    def place(self, at: torch.Tensor) -> None:
        """The variables take the values of `at` (B, n)."""
        with torch.no_grad():
            for v, part in zip(self.variables, at.split(self.sizes, 1)):
                v.copy_(part.view_as(v))

    def evaluation(self) -> None:
        """f_try, g_try: energy and gradient at `point`."""
        self.place(self.point)
        energy, grads = energy_and_gradients(self.variables, self.energy_fn)
        self.f_try.copy_(energy)
        self.g_try.copy_(torch.cat([grad.reshape(self.B, -1) for grad in grads], 1))

    @torch.no_grad()
    def start(self) -> None:
        """A step starts at x (evaluated: the correspondences may have changed since the last step):
        frames whose energy settled since the last step's start, or whose gradient vanished, stop."""
        f, g, previous, moving = self.f, self.g, self.previous, self.moving
        f.copy_(self.f_try)
        g.copy_(self.g_try)
        finite = torch.isfinite(f)
        moving.logical_and_(finite & (g.abs().amax(1) >= self.gtol))
        settled = (previous - f) <= self.ftol * torch.maximum(torch.maximum(previous.abs(), f.abs()),
                                                              torch.ones_like(f))
        moving.logical_and_(~(settled & torch.isfinite(previous)))
        previous.copy_(torch.where(finite, f, previous))
        self.inner.copy_(moving)
        self.trial.fill_(1.0)

    @torch.no_grad()
    def direct(self) -> None:
        """Each frame's direction from its own history (steepest descent where that is not downhill),
        and its first trial point."""
        g, d, inner, scale = self.g, self.d, self.inner, self.scale
        first = torch.clamp(1.0 / g.abs().sum(1).clamp(min=1e-30), max=1.0)  # torch's first step: |g|_1 <= 1
        q = -self.memory.inverse_hessian_times(g, torch.where(torch.isnan(scale), first, scale))
        q = torch.where(inner[:, None], q, torch.zeros_like(q))
        uphill = inner & ((g * q).sum(1) >= 0)  # not a descent direction (a poor history): steepest descent
        d.copy_(torch.where(uphill[:, None], -g * first[:, None], q))
        self.slope.copy_((g * d).sum(1))
        self.length.copy_(self.trial)
        self.pending.copy_(inner)
        self.f_new.copy_(self.f)
        self.g_new.copy_(g)
        self.point.copy_(self.x + self.length[:, None] * d)

    @torch.no_grad()
    def judge(self) -> None:
        """Armijo's test of each pending frame's trial; a failed one backtracks to the minimum of the
        quadratic through f, the slope and the trial (within [0.1, 0.5] of its length): the next point."""
        f, f_try, length, slope, pending = self.f, self.f_try, self.length, self.slope, self.pending
        ok = pending & torch.isfinite(f_try) & (f_try <= f + 1e-4 * length * slope)
        self.f_new.copy_(torch.where(ok, f_try, self.f_new))
        self.g_new.copy_(torch.where(ok[:, None], self.g_try, self.g_new))
        pending.logical_and_(~ok)
        excess = torch.nan_to_num(f_try - f - length * slope, nan=math.inf, posinf=math.inf)
        shrunk = -slope * length**2 / (2 * excess.clamp(min=1e-30))
        length.copy_(torch.where(pending, torch.minimum(torch.maximum(shrunk, 0.1 * length), 0.5 * length), length))
        self.point.copy_(self.x + length[:, None] * self.d)

    @torch.no_grad()
    def advance(self) -> None:
        """The frames whose trial passed move and remember the pair; a frame still backtracking tries
        its shorter step at the next iteration; frames that arrived stop."""
        f, g, f_new, g_new, inner, trial, length = (self.f, self.g, self.f_new, self.g_new, self.inner, self.trial,
                                                    self.length)
        taken = inner & ~self.pending
        trial.copy_(torch.where(taken, torch.ones_like(trial), length))
        s = torch.where(taken, length, torch.zeros_like(length))[:, None] * self.d
        y = g_new - g
        sy = (s * y).sum(1)
        good = taken & (sy > 1e-10)
        self.memory.push(s, y, good)
        self.scale.copy_(torch.where(good, sy / (y * y).sum(1).clamp(min=1e-30), self.scale))
        self.x.add_(s)
        inner.logical_and_((g_new.abs().amax(1) >= self.gtol)
                           & ~(taken & ((f - f_new).abs() <= 1e-12 * f.abs().clamp(min=1.0))))
        inner.logical_and_(trial > 1e-10)  # a frame no step length lowers has arrived (or its energy is not finite)
        f.copy_(f_new)
        g.copy_(g_new)


class PairMemory:
    """The last `size` step pairs (s, y) of each of B rows, oldest first, and the L-BFGS inverse
    Hessian they define, in Byrd, Nocedal and Schnabel's compact form (1994, eq. 3.1):

        H g = gamma g + S a - gamma Y u,  u = R^-1 S'g,  a = R^-T ((D + gamma Y'Y) u - gamma Y'g)

    with S, Y the pairs as columns, R the upper triangle of S'Y and D its diagonal. This is the
    two-loop recursion's product in a fixed number of batched kernels (about 20, against the
    two-loop's 5 a pair and 200 for 20 pairs): on a GPU, where each kernel costs its launch, the
    direction costs as little as one evaluation's few. A pair not kept (curvature s.y too small)
    and an empty slot are stored as zeros with R's diagonal 1 there: they then add nothing, as a
    pair the two-loop skips."""

    def __init__(self, rows: int, n: int, size: int, like: torch.Tensor):
        self.size = size
        self.pairs = like.new_zeros(rows, 2 * size, n)  # (B, 2m, n): S's m rows, then Y's
        self.gram = like.new_zeros(rows, 2 * size, 2 * size)  # [S; Y] [S; Y]'

    def push(self, s: torch.Tensor, y: torch.Tensor, keep: torch.Tensor) -> None:
        """Appends each row's pair (s, y) (B, n), as zeros where `keep` (B,) is false; the oldest goes."""
        s, y = (torch.where(keep[:, None], v, torch.zeros_like(v))[:, None] for v in (s, y))
        m = self.size
        self.pairs.copy_(torch.cat((self.pairs[:, 1:m], s, self.pairs[:, m + 1:], y), 1))
        self.gram.copy_(torch.bmm(self.pairs, self.pairs.mT))

    def inverse_hessian_times(self, g: torch.Tensor, gamma: torch.Tensor) -> torch.Tensor:
        """(B, n) each row's H g, H built from its pairs on the initial matrix gamma I (gamma (B,))."""
        m = self.size
        gamma = gamma[:, None, None]
        projected = torch.bmm(self.pairs, g[:, :, None])  # (B, 2m, 1): S'g, Y'g
        sy = self.gram[:, :m, m:]
        diagonal = sy.diagonal(dim1=1, dim2=2)
        r = sy.triu() + torch.diag_embed((diagonal == 0).to(sy.dtype))
        u = torch.linalg.solve_triangular(r, projected[:, :m], upper=True)
        yy_u = (self.gram[:, m:, m:] * u.mT).sum(2, keepdim=True)  # Y'Y u (bmm's sums change with B on the CPU)
        v = diagonal[:, :, None] * u + gamma * (yy_u - projected[:, m:])
        a = torch.linalg.solve_triangular(r.mT, v, upper=False)
        return gamma[:, :, 0] * g + torch.bmm(self.pairs.mT, torch.cat((a, -gamma * u), 1))[:, :, 0]


class AdamRows:
    """torch.optim.Adam's update for parameters whose rows are separate problems (P rows each): a
    row keeps its own step count and step-size scale (`scale`, 1 at first), and a step moves only
    the rows named. With one row it is Adam itself. Its state lives on the parameters' device and
    a step reads tensors only, so it can be part of a recorded CUDA graph (`recorded`)."""

    def __init__(self, params: list[torch.Tensor], lrs: list[float], rows: int,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.params, self.lrs, self.betas, self.eps = params, lrs, betas, eps
        self.moments = [(torch.zeros_like(p), torch.zeros_like(p)) for p in params]
        dev = params[0].device
        self.count = torch.zeros(rows, dtype=torch.float64, device=dev)
        self.scale = torch.ones(rows, dtype=torch.float64, device=dev)

    @torch.no_grad()
    def reset(self) -> None:
        """Every row back to its first step (moments 0, count 0, scale 1), in place."""
        for m, v in self.moments:
            m.zero_()
            v.zero_()
        self.count.zero_()
        self.scale.fill_(1.0)

    @torch.no_grad()
    def step(self, moving: torch.Tensor, grads: list[torch.Tensor]) -> None:
        """One step of the rows where `moving` (P,) bool is set, along `grads` (one per parameter)."""
        b1, b2 = self.betas
        self.count.add_(moving)
        dtype = self.params[0].dtype
        size = (self.scale / (1 - b1 ** self.count)).to(dtype)[:, None]  # bias corrections in float64, as a
        root = (1 - b2 ** self.count).sqrt().to(dtype)[:, None]  # host computes them (infinite where count is 0)
        for p, g, lr, (m, v) in zip(self.params, grads, self.lrs, self.moments):
            on = moving.view(-1, *[1] * (p.dim() - 1))
            m.copy_(torch.where(on, m.lerp(g, 1 - b1), m))
            v.copy_(torch.where(on, v * b2 + (1 - b2) * g * g, v))
            p.copy_(torch.where(on, p - (lr * size) * m / (v.sqrt() / root + self.eps), p))
