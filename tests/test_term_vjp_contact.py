"""The fused adjoint's one-step VJP against jax.vjp: the 128 term combinations with soft-soft
contact (CI tier). The check and the scenes are those of tests/test_term_vjp.py; this file only
holds the half of the enumeration that is slow to compile, so that it runs on its own worker."""

from __future__ import annotations

import pytest

from test_term_vjp import ALL, _check, _name


@pytest.mark.heavy
@pytest.mark.parametrize("on", [c for c in ALL if "contact" in c], ids=_name)
def test_step_vjp_every_term_combination_with_contact(x64, on):
    """The 128 combinations with contact (CI tier)."""
    _check(on)
