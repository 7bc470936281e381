"""tools.count_ops: the operation counter behind the GPU-time estimate (BENCHMARKS.md, 2026-11-27)."""
import torch

from tools.count_ops import OperationCount


def test_counts_kernels_apart_from_views_and_backward_apart_from_forward():
    x = torch.randn(4, 3, requires_grad=True)
    with OperationCount() as count:
        y = (x * 2).view(-1)[:5].unsqueeze(0)  # one kernel (mul), three views
        total = (y.exp() + 1).sum()  # three kernels
    assert (count.kernels, count.backward, count.waits) == (4, 0, 0)
    assert count.all >= 7  # the views, and any detach autograd adds to save a result
    assert sum(count.sites.values()) == 4 and set(count.sites) == {"-"}  # issued by this test, not by intercap
    with OperationCount() as count:
        total.backward()
    assert count.backward == count.kernels - 1 >= 3  # all but the seed gradient (ones_like), issued before any node
    expected = torch.zeros(12)
    expected[:5] = 2 * torch.exp(2 * x.detach().flatten()[:5])
    assert torch.allclose(x.grad.flatten(), expected)  # counting leaves the results alone


def test_kernels_count_at_the_intercap_function_issuing_them():
    from intercap.geometry.cameras import distort

    xy, coefficients = torch.rand(2, 5, 2), torch.rand(2, 8) * 0.1
    with OperationCount() as count:
        distort(xy, coefficients)
    assert set(count.sites) == {"geometry.cameras:distort", "geometry.cameras:_radial_factor"}
    assert count.sites["geometry.cameras:_radial_factor"] >= 10  # its rational polynomial, op by op


def test_lines_name_the_line_in_the_body_model_or_library_issuing():
    """`--lines`: a kernel issued inside roma (or anny, or our body models) counts at that line,
    not at its intercap caller; intercap's own sites get their line too."""
    import roma

    from intercap.geometry.cameras import distort

    with OperationCount(lines=True) as count:
        roma.rotvec_to_unitquat(torch.randn(4, 3))
        distort(torch.rand(2, 5, 2), torch.rand(2, 8) * 0.1)
    sites = set(count.sites)
    assert any(s.startswith("roma:mappings:rotvec_to_unitquat:") for s in sites), sites
    assert any(s.startswith("intercap:geometry.cameras:_radial_factor:") for s in sites), sites
    assert all(s.rsplit(":", 1)[1].isdigit() for s in sites - {"-"}), sites  # "-": issued by this test


def test_replayed_evaluations_count_apart():
    """Kernels run while `replaying` (a GPU's CUDA-graph replay) count in `in_graphs`, not as
    launched kernels, so `--graphs` predicts the launches a GPU makes."""
    x = torch.randn(3)
    with OperationCount() as count:
        x.exp()
        count.replaying = True
        (x * 2).sin()
        count.replaying = False
    assert (count.kernels, count.in_graphs) == (1, 2)


def test_counts_what_the_host_waits_for():
    x = torch.randn(5)
    with OperationCount() as count:
        float(x.sum())  # a value read back
        x.nonzero()  # a shape that depends on the data
        x * 2
    assert (count.waits, count.kernels) == (2, 4)  # sum, the read (a copy), nonzero, mul
    assert count.wait_sites == {"-": 2}  # issued by this test, not by intercap
