"""`torch.where` without per-element branches, for the eager CPU tracer's hot paths.

torch's CPU `where` (and `masked_fill`) picks each element with a branch: on a mask without spatial order
(which octant of the lens square a sample falls in) the branch is mispredicted half the time, which makes it
several times slower than on an ordered mask. `selector` blends the bits instead, `b ^ ((a ^ b) & m)` with m
all ones where the condition holds: integer operations that vectorise, exact for every value (infinities,
NaN and signed zeros included), at the same speed whatever the mask (measurements in docs/speed.md).
"""
from __future__ import annotations

import torch

# Integer dtype of the same width as each floating dtype the bit blend handles.
_BITS = {torch.float32: torch.int32, torch.float64: torch.int64, torch.int32: torch.int32,
         torch.int64: torch.int64}


def selector(cond: torch.Tensor):
    """`pick(a, b)` = torch.where(cond, a, b), several picks sharing the mask's preparation.

    Args:
        cond: (...,) bool condition.
    Returns:
        pick(a, b): a, b tensors of one dtype (or a Python number for one of them) broadcasting with cond.
        Bit blending where it is exact and faster (CPU tensors of float32/float64/int32/int64 that carry no
        derivative, `carries_derivative`, outside torch.compile); `torch.where` otherwise. `pick.pair(a, b)` returns (pick(a, b),
        pick(b, a)), the second from the first with one more operation (a ^ b ^ first).
    """
    masks: dict = {}
    eager_cpu = cond.device.type == "cpu" and not torch.compiler.is_compiling()

    def blend(a, b):
        """(x = (a ^ b) & m, b's bits, dtype) for the bit blend, or None where torch.where must answer."""
        like = a if isinstance(a, torch.Tensor) else b
        bits = _BITS.get(like.dtype)
        if not eager_cpu or bits is None or carries_derivative(a) or carries_derivative(b) or _wrapped(cond):
            return None
        a = a if isinstance(a, torch.Tensor) else torch.tensor(a, dtype=like.dtype)
        b = b if isinstance(b, torch.Tensor) else torch.tensor(b, dtype=like.dtype)
        if a.dtype != b.dtype:
            return None
        if bits not in masks:
            masks[bits] = cond.to(bits).neg_()  # all ones (−1) where cond holds, else 0
        a_bits, b_bits, m = a.view(bits), b.view(bits), masks[bits]
        x = a_bits ^ b_bits
        x = x.bitwise_and_(m) if x.shape == torch.broadcast_shapes(x.shape, m.shape) else x & m
        return x, a_bits, b_bits, like.dtype

    def pick(a, b):
        parts = blend(a, b)
        if parts is None:
            return torch.where(cond, a, b)
        x, _, b_bits, dtype = parts
        return x.bitwise_xor_(b_bits).view(dtype) if x.shape == torch.broadcast_shapes(x.shape, b_bits.shape) \
            else (x ^ b_bits).view(dtype)

    def pair(a, b):
        parts = blend(a, b)
        if parts is None:
            return torch.where(cond, a, b), torch.where(cond, b, a)
        x, a_bits, b_bits, dtype = parts
        first = x ^ b_bits  # a where cond, else b
        return first.view(dtype), (first ^ a_bits ^ b_bits).view(dtype)

    pick.pair = pair
    return pick


def select(cond: torch.Tensor, a, b) -> torch.Tensor:
    """torch.where(cond, a, b) with one condition used once (see `selector`)."""
    return selector(cond)(a, b)


def carries_derivative(x) -> bool:
    """Whether x is a tensor some derivative flows through: one that requires grad (with grad enabled), a
    forward-mode dual number, or one wrapped by a torch.func transform (jacfwd, vmap, grad). Bit tricks and
    `out=` steps would drop its derivative or fail; only plain tensors may take them."""
    if not isinstance(x, torch.Tensor):
        return False
    return (torch.is_grad_enabled() and x.requires_grad) or _wrapped(x) \
        or torch.autograd.forward_ad.unpack_dual(x).tangent is not None


def _wrapped(x: torch.Tensor) -> bool:
    """Whether x is a torch.func transform's wrapper (batched or dual levels)."""
    return bool(torch._C._functorch.is_functorch_wrapped_tensor(x))
