"""The shared optimisers: per-frame L-BFGS and Adam per row solve independent problems as if each were alone."""
import torch

from intercap.energies.optim import AdamRows, PairMemory, minimise, minimise_per_frame


def frame_problems(targets: torch.Tensor, x: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """(B,) a Rosenbrock valley and a badly scaled quadratic per frame, minimum at x = (a, a^2), z = a."""
    a = targets
    valley = (a - x[:, 0]) ** 2 + 100 * (x[:, 1] - x[:, 0] ** 2) ** 2
    bowl = ((z - a[:, None]) ** 2 * torch.tensor([1.0, 10.0, 1000.0])).sum(1)
    return valley + bowl


def starts(B: int) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.zeros(B, 2), torch.full((B, 3), 3.0)


def test_each_frame_reaches_its_own_minimum():
    a = torch.linspace(0.5, 2.0, 8)
    x, z = starts(8)
    result = minimise_per_frame([x, z], lambda: frame_problems(a, x, z), max_steps=20, inner_iterations=10, ftol=1e-12)
    assert torch.allclose(x[:, 0], a, atol=1e-4) and torch.allclose(x[:, 1], a**2, atol=1e-3)
    assert torch.allclose(z, a[:, None].expand(-1, 3), atol=1e-4)
    assert result.energy < 1e-6 and result.stopped == "ftol"


def test_a_frame_fits_the_same_alone_and_in_a_batch():
    """The reason for it: one L-BFGS over a batch's summed energy shares one step length and stops on
    the sum, so its frames end up where they would not alone (and worse, the larger the batch)."""
    a = torch.linspace(0.5, 2.0, 8)
    x, z = starts(8)
    minimise_per_frame([x, z], lambda: frame_problems(a, x, z), max_steps=5, inner_iterations=4)
    alone_x, alone_z = starts(1)
    minimise_per_frame([alone_x, alone_z], lambda: frame_problems(a[5:6], alone_x, alone_z), max_steps=5,
                       inner_iterations=4)
    assert torch.allclose(alone_x, x[5:6], atol=1e-6) and torch.allclose(alone_z, z[5:6], atol=1e-6)

    x, z = starts(8)  # the same budget over the batch's sum leaves the frames far further off
    minimise_per_frame([x, z], lambda: frame_problems(a, x, z), max_steps=20, inner_iterations=10, ftol=1e-12)
    joint_x, joint_z = starts(8)
    minimise([joint_x, joint_z], lambda: frame_problems(a, joint_x, joint_z).sum(), max_steps=20, inner_iterations=10,
             ftol=1e-12)
    assert (x[:, 0] - a).abs().max() < 1e-4 < 1e-3 < (joint_x[:, 0] - a).abs().max()


def test_armijo_lbfgs_solves_one_problem_with_variables_of_any_shape():
    """`minimise(line_search="armijo")`: the batched L-BFGS with the whole problem as one row reaches
    the minimum of a summed problem with a shared variable of another shape (as the body's phases with
    one phenotype per batch); "auto" on the CPU is torch's strong Wolfe L-BFGS, step for step."""
    a = torch.linspace(0.5, 2.0, 8)

    def problem(x, z, shared):
        return frame_problems(a, x, z).sum() + 10 * ((shared - a.mean()) ** 2).sum()

    x, z = starts(8)
    shared = torch.zeros(2, 1)
    result = minimise([x, z, shared], lambda: problem(x, z, shared), max_steps=60, inner_iterations=10,
                      ftol=1e-14, line_search="armijo")
    assert torch.allclose(x[:, 0], a, atol=1e-3) and torch.allclose(z, a[:, None].expand(-1, 3), atol=1e-4)
    assert torch.allclose(shared, a.mean().expand(2, 1), atol=1e-5) and result.energy < 1e-5

    runs = []
    for line_search in ("auto", "strong_wolfe"):
        x, z = starts(8)
        shared = torch.zeros(2, 1)
        runs.append((minimise([x, z, shared], lambda: problem(x, z, shared), max_steps=5, line_search=line_search),
                     x.detach().clone()))
    assert runs[0][0] == runs[1][0] and torch.equal(runs[0][1], runs[1][1])


def test_armijo_lbfgs_reads_the_host_twice_an_evaluation_where_strong_wolfe_reads_it_dozens_of_times():
    """Why the GPU runs the Armijo search: each value read back (`.item()`, `float()`, `bool()` of a
    tensor) waits for the GPU's queue to drain. On this problem torch's strong Wolfe L-BFGS reads
    about 35 values per evaluation."""
    from host_waits import HostWaits

    a = torch.linspace(0.5, 2.0, 8)
    reads = {}
    for line_search in ("strong_wolfe", "armijo"):
        x, z = starts(8)
        waits = HostWaits()
        with waits:
            result = minimise([x, z], lambda: frame_problems(a, x, z).sum(), max_steps=10, inner_iterations=8,
                              line_search=line_search)
        reads[line_search] = waits.seen.count("_local_scalar_dense") / result.evaluations
    assert reads["armijo"] <= 2.0 and reads["strong_wolfe"] > 10 * reads["armijo"], reads


def test_a_frame_that_cannot_improve_stays_put_and_the_others_go_on():
    """A frame whose energy is not finite at every trial step keeps its start; the rest converge."""
    a = torch.tensor([1.0, 1.5, 2.0])
    x, z = starts(3)

    def energy():
        e = frame_problems(a, x, z)
        wall = torch.where(x[1:2, 0] != 0, torch.full_like(e[1:2], float("nan")), torch.zeros_like(e[1:2]))
        return torch.cat([e[:1], e[1:2] + wall, e[2:]])

    minimise_per_frame([x, z], energy, max_steps=20, inner_iterations=10, ftol=1e-12)
    assert float(x[1, 0]) == 0.0
    assert torch.allclose(x[[0, 2], 0], a[[0, 2]], atol=1e-4)


def test_adam_rows_is_adam_per_row():
    """`AdamRows` with one row is torch's Adam; rows step on their own (a row not named does not
    move, and its step count waits), and a row's step-size scale is that row's learning rate."""
    target = torch.tensor([[1.0, -2.0, 0.5], [3.0, 0.0, -1.0]])
    reference = torch.zeros(1, 3, requires_grad=True)
    adam = torch.optim.Adam([reference], lr=0.1)
    rows = torch.zeros(2, 3, requires_grad=True)
    ours = AdamRows([rows], [0.1], 2)
    ours.scale[1] = 0.5
    for k in range(20):
        adam.zero_grad()
        ((reference - target[:1]) ** 2).sum().backward()
        adam.step()
        ((rows - target) ** 2).sum().backward()
        ours.step(torch.tensor([True, k >= 10]), [rows.grad])
        rows.grad = None
    assert torch.allclose(rows[0], reference[0], atol=1e-6)
    alone = torch.zeros(1, 3, requires_grad=True)  # row 1: 10 steps at half the rate, from 0
    half = torch.optim.Adam([alone], lr=0.05)
    for _ in range(10):
        half.zero_grad()
        ((alone - target[1:]) ** 2).sum().backward()
        half.step()
    assert torch.allclose(rows[1], alone[0], atol=1e-6)


def test_host_waits_sees_what_a_gpu_would_wait_for():
    from host_waits import HostWaits

    waits, mask, ones, x = HostWaits(), torch.tensor([True, False, True]), torch.ones(3), torch.zeros(3, 2)
    with waits:
        ones.nonzero()
        float(ones.sum())
        ones * torch.tensor([1.0, 2.0, 3.0], device=ones.device)  # from a list: a copy from the host
        ones[mask]
        x[1] = 2.0  # a fill, no copy
        x[1, 0] = 3.0  # one element: a copy from the host on a GPU
        x[torch.arange(2)] = 1.0  # a CPU index on a GPU run
        torch.zeros(2, device=x.device)
    assert waits.seen == ["nonzero", "_local_scalar_dense", "lift_fresh", "index", "copy_",
                          "torch.arange without a device"], waits.seen


def two_loop_recursion(g, gamma, pairs):
    """Nocedal and Wright's algorithm 7.4, row by row: H g for the pairs (s, y, kept) oldest first."""
    q, alphas = g.clone(), []
    for s, y, kept in reversed(pairs):
        rho = torch.where(kept, 1 / (s * y).sum(1), torch.zeros_like(gamma))
        alphas.append(rho * (s * q).sum(1))
        q = q - alphas[-1][:, None] * y
    q = q * gamma[:, None]
    for (s, y, kept), alpha in zip(pairs, reversed(alphas)):
        rho = torch.where(kept, 1 / (s * y).sum(1), torch.zeros_like(gamma))
        q = q + (alpha - rho * (y * q).sum(1))[:, None] * s
    return q


def test_compact_inverse_hessian_is_the_two_loop_recursions():
    """`PairMemory`'s compact form gives the two-loop product per row, with pairs skipped (not kept),
    slots still empty, and the oldest pairs dropped once the memory is full."""
    generator = torch.Generator().manual_seed(0)
    B, n, size = 3, 12, 5
    curvature = torch.randn(B, n, n, generator=generator, dtype=torch.float64)
    curvature = curvature @ curvature.mT + torch.eye(n, dtype=torch.float64)
    memory, pairs = PairMemory(B, n, size, curvature), []
    for count in range(1, 9):
        s = torch.randn(B, n, generator=generator, dtype=torch.float64)
        kept = torch.rand(B, generator=generator) > 0.3
        pairs = (pairs + [(s, (curvature @ s[:, :, None])[:, :, 0], kept)])[-size:]
        memory.push(*pairs[-1])
        g = torch.randn(B, n, generator=generator, dtype=torch.float64)
        gamma = torch.rand(B, generator=generator, dtype=torch.float64) + 0.5
        expected = two_loop_recursion(g, gamma, pairs)
        assert torch.allclose(memory.inverse_hessian_times(g, gamma), expected, rtol=1e-10, atol=1e-12), count
    empty = PairMemory(B, n, size, curvature)
    assert torch.equal(empty.inverse_hessian_times(g, gamma), gamma[:, None] * g)


def test_lbfgs_replayed_from_recordings_is_the_eager_fit(replay_on_cpu):
    """With `graph`, each part of an L-BFGS iteration (direction, evaluation, verdict, step) replays
    a recording, as on CUDA (here replayed on the CPU, `graph_replay`): every frame ends where the
    eager fit ends, bit for bit, per frame and as one problem with Armijo's search."""
    a = torch.linspace(0.5, 2.0, 8)
    runs = {}
    for graph in (False, True):
        x, z = starts(8)
        result = minimise_per_frame([x, z], lambda: frame_problems(a, x, z), max_steps=6, inner_iterations=5,
                                    graph=graph)
        shared = torch.zeros(2, 1)
        joint = minimise([shared], lambda: ((shared - a[:2, None]) ** 4).sum() + (shared ** 2).sum(), max_steps=6,
                         line_search="armijo", graph=graph)
        runs[graph] = (x.detach().clone(), z.detach().clone(), result, shared.detach().clone(), joint)
    replays = len(replay_on_cpu)
    assert replays > 100  # most parts of most iterations were replayed
    (x0, z0, result0, shared0, joint0), (x1, z1, result1, shared1, joint1) = runs[False], runs[True]
    assert torch.equal(x0, x1) and torch.equal(z0, z1) and torch.equal(shared0, shared1)
    assert result0 == result1 and joint0 == joint1
    assert result0.energy < 1e-3 * float(frame_problems(a, *starts(8)).sum())  # and the fit did go far
