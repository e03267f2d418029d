"""Argument checks the PyTorch and JAX wrappers share: made before the forward pass, so that a
mistake in an argument only the backward pass uses costs no render."""

from __future__ import annotations

import numbers
from typing import Optional


def samples(spp: Optional[int], grad_spp: Optional[int]) -> Optional[int]:
    """``grad_spp`` as the backward pass uses it (``spp`` when not given), each checked by name."""
    for name, value in (("spp", spp), ("grad_spp", grad_spp)):
        whole = isinstance(value, numbers.Integral) and not isinstance(value, bool)
        if value is not None and not (whole and value >= 1):
            raise ValueError(f"{name} must be a whole number ≥ 1 (got {value!r})")
    return spp if grad_spp is None else grad_spp


def seed(value: Optional[int]) -> Optional[int]:
    """A seed as volgrad takes it: None, or a whole number in [0, 2**64)."""
    whole = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if value is not None and not (whole and 0 <= value < 2**64):
        raise ValueError(f"seed must be a whole number in [0, 2**64) (got {value!r})")
    return value
