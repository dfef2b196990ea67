"""renderer.core.blend: the branch-free select equals torch.where bit for bit, and falls back where it must."""
import pytest
import torch

from renderer.core.blend import select, selector

SPECIAL = [float("inf"), float("-inf"), float("nan"), -0.0, 0.0, 1e-45, -3.5]


def _bits(x):
    return x.view({torch.float32: torch.int32, torch.float64: torch.int64}.get(x.dtype, x.dtype))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.int32, torch.int64])
def test_select_equals_where_bit_for_bit(dtype):
    g = torch.Generator().manual_seed(0)
    n = 1037  # not a multiple of a vector width
    a = (torch.randn(n, generator=g, dtype=torch.float64) * 1e3).to(dtype)
    b = (torch.randn(3, n, generator=g, dtype=torch.float64) * 1e3).to(dtype)
    if dtype.is_floating_point:
        a[:len(SPECIAL)] = torch.tensor(SPECIAL, dtype=dtype)
        b[1, :len(SPECIAL)] = torch.tensor(SPECIAL[::-1], dtype=dtype)
    cond = torch.rand(n, generator=g) > 0.5
    column = b[:, :1].clone()  # (3, 1): broadcast along the rays
    strided = b.T.contiguous().T  # (3, n) with strides (1, 3)
    for x, y in [(a, b), (b, a), (b, column), (column, b), (a, 0), (-7, a), (strided, a), (b, strided)]:
        expected, got = torch.where(cond, x, y), select(cond, x, y)
        assert got.dtype == expected.dtype and got.shape == expected.shape, f"{got.dtype} {got.shape} vs {expected.shape}"
        assert torch.equal(_bits(got), _bits(expected)), f"select differs from where ({dtype})"


def test_one_selector_serves_several_picks_and_gradients_fall_back():
    cond = torch.tensor([True, False, True])
    pick = selector(cond)
    a, b = torch.tensor([1.0, 2.0, 3.0], requires_grad=True), torch.tensor([4.0, 5.0, 6.0])
    out = pick(a, b)
    assert out.requires_grad and torch.equal(out.detach(), torch.tensor([1.0, 5.0, 3.0])), "gradient fallback wrong"
    out.sum().backward()
    assert torch.equal(a.grad, torch.tensor([1.0, 0.0, 1.0])), f"gradient {a.grad}"
    assert torch.equal(pick(b, a.detach()), torch.tensor([4.0, 2.0, 6.0])), "second pick with the same mask wrong"


@pytest.mark.parametrize("dtype", [torch.float32, torch.int64])
def test_pair_is_both_selections(dtype):
    g = torch.Generator().manual_seed(1)
    a, b = (torch.randn(2, 515, generator=g, dtype=torch.float64) * 100).to(dtype)
    if dtype.is_floating_point:
        a[:4] = torch.tensor([float("nan"), -0.0, float("inf"), 0.0])
    cond = torch.rand(515, generator=g) > 0.3
    first, second = selector(cond).pair(a, b)
    assert torch.equal(_bits(first), _bits(torch.where(cond, a, b))), "pair: first is not where(cond, a, b)"
    assert torch.equal(_bits(second), _bits(torch.where(cond, b, a))), "pair: second is not where(cond, b, a)"
