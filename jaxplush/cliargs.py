"""Argument handling shared by the command-line tools (``jaxplush``, ``jaxplush-fit``).

argparse reads a token that starts with ``-`` as an option unless it looks like a plain
negative number (``-5``, ``-0.5``); ``--dt -5e-4`` therefore fails with "expected one
argument" instead of reaching the program's own check ("--dt must be a positive number").
:func:`attach_negative_values` joins such a value to its option (``--dt=-5e-4``) first, so
every CLI gives its own clear message for a negative or exponent-form number.
"""

from __future__ import annotations

import re

_NUMBER = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|nan|infinity)$", re.IGNORECASE)


def attach_negative_values(argv):
    """``[..., "--opt", "-5e-4", ...]`` -> ``[..., "--opt=-5e-4", ...]`` for negative numbers.

    Only a long option without ``=`` followed by a token that parses as a negative number is
    joined; everything else is left for argparse.
    """
    out = []
    for tok in argv:
        prev = out[-1] if out else ""
        if _NUMBER.match(tok) and prev.startswith("--") and "=" not in prev and len(prev) > 2:
            out[-1] = f"{prev}={tok}"
        else:
            out.append(tok)
    return out
