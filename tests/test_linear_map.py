"""``models.base.linear_map``: the grouped block-diagonal product equals ``x @ M.mT``."""

import pytest
import torch

from torchmcmcpf.models.base import linear_map


@pytest.mark.parametrize("x_shape, m_shape", [
    ((3, 8, 2, 4), (4, 4)),   # rows per run 16: grouped by 4
    ((3, 8, 2, 4), (2, 4)),   # grouped by 8
    ((2, 5, 5), (5, 5)),      # rows per run 5: no power of two divides it, plain product
    ((6, 3, 4), (4, 4)),      # rows per run 3
    ((4,), (2, 4)),           # a single vector
    ((7, 16, 1, 20), (20, 20)),  # wide state: plain product
])
def test_equals_matmul(x_shape, m_shape):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(x_shape, generator=g, dtype=torch.float64)
    M = torch.randn(m_shape, generator=g, dtype=torch.float64)
    out = linear_map(x, M)
    assert out.shape == x_shape[:-1] + (m_shape[0],)
    torch.testing.assert_close(out, x @ M.mT, rtol=1e-12, atol=1e-12)


def test_gradient_and_noncontiguous_input():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(2, 4, 8, 4, generator=g, dtype=torch.float64).transpose(1, 2).requires_grad_()
    M = torch.randn(4, 4, generator=g, dtype=torch.float64)
    torch.testing.assert_close(linear_map(x, M), x @ M.mT, rtol=1e-12, atol=1e-12)
    assert torch.autograd.gradcheck(lambda t: linear_map(t, M), (x,))


def test_non_finite_row_stays_in_its_run():
    """A non-finite row may spoil the rows grouped with it, never those of another run."""
    x = torch.ones(3, 16, 1, 4)
    x[1, 5, 0, 2] = float("inf")
    out = linear_map(x, torch.eye(4))
    assert torch.isfinite(out[0]).all() and torch.isfinite(out[2]).all()
    assert torch.isfinite(out[1, :4]).all() and torch.isfinite(out[1, 8:]).all()  # other groups of run 1


def test_the_cached_block_follows_the_matrix():
    # the block matrix is built once per model matrix and rebuilt when the matrix changes in
    # place; a matrix that needs a gradient is never cached (the gradient must reach it)
    g = torch.Generator().manual_seed(3)
    x = torch.randn(2, 64, 1, 4, generator=g, dtype=torch.float64)
    M = torch.randn(4, 4, generator=g, dtype=torch.float64)
    first = linear_map(x, M)
    torch.testing.assert_close(linear_map(x, M), x @ M.mT, rtol=0, atol=1e-14)
    assert torch.equal(linear_map(x, M), first)
    M.mul_(2.0)  # in place: a new version
    torch.testing.assert_close(linear_map(x, M), x @ M.mT, rtol=0, atol=1e-14)
    P = M.clone().requires_grad_(True)
    linear_map(x, P).sum().backward()
    torch.testing.assert_close(P.grad, torch.ones(4, 1, dtype=x.dtype) * x.reshape(-1, 4).sum(0), rtol=1e-12,
                               atol=1e-12)


@pytest.mark.parametrize("d", [1, 2, 3, 4])
def test_squared_norm(d):
    """The same bits as ATen's reduction for up to 4 coordinates, float64 and float32, over
    values of very different sizes (where an other order of the additions would round
    differently)."""
    from torchmcmcpf.runtime import squared_norm

    g = torch.Generator().manual_seed(d)
    v = torch.randn(10, 200, 2, 10, d, generator=g, dtype=torch.float64) * torch.logspace(-3, 3, d,
                                                                                          dtype=torch.float64)
    for t in (v, v.float()):
        assert torch.equal(squared_norm(t), t.square().sum(-1))


def test_block_cached_under_inference_mode_serves_autograd_later():
    """The block matrix is cached per model matrix: first built under torch.inference_mode(),
    it is still a normal tensor, so a later call on a tensor that requires grad differentiates
    (an inference tensor cannot be saved for backward)."""
    g = torch.Generator().manual_seed(2)
    M = torch.randn(4, 4, generator=g, dtype=torch.float64)
    x = torch.randn(3, 16, 1, 4, generator=g, dtype=torch.float64)
    with torch.inference_mode():
        linear_map(x, M)
    y = x.clone().requires_grad_()
    (grad,) = torch.autograd.grad(linear_map(y, M).sum(), y)
    torch.testing.assert_close(grad, M.sum(0).expand_as(x), rtol=1e-12, atol=1e-12)
