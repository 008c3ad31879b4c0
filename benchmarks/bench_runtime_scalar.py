"""Why the edge softening eps is compiled in as a constant: the spring weight k (1 - L rsqrt(|d|² + e))
on a random 642-vertex ring, 1000 steps in one lax.scan, with e a literal, e a runtime argument
(hoisted one-element array), e a runtime (6, 642) table, and, for comparison, k a runtime argument.
On XLA:CPU a runtime value inside the rsqrt slows the loop by about a quarter; a runtime k does not.

Usage: python benchmarks/bench_runtime_scalar.py [--repeats 15]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
import jaxplush  # noqa: E402,F401  (before jax: it sets options jax reads when imported)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

E = 7.6e-16


def run(mode, repeats):
    rng = np.random.default_rng(0)
    rest = rng.random((6, 642)).astype(np.float32)
    ring = rng.integers(0, 642, (6, 642)).astype(np.int32)
    hoisted = lambda a: jnp.asarray(np.asarray(a, np.float32))                # noqa: E731

    def body(x, _):
        d = [x[c][ring] - x[c][None] for c in range(3)]
        dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        e = {"e literal": jnp.float32(E), "e argument": hoisted([E])[0],
             "e table": hoisted(np.full((6, 642), E)), "k argument": jnp.float32(E)}[mode]
        k = hoisted([500.0])[0] if mode == "k argument" else 500.0
        w = k * (1 - jnp.asarray(rest) * jax.lax.rsqrt(dd + e))
        return x + 1e-7 * jnp.stack([(w * dc).sum(0) for dc in d]), None

    fn = jax.jit(lambda x: jax.lax.scan(body, x, None, length=1000)[0])
    x = jnp.asarray(rng.random((3, 642)).astype(np.float32))
    fn(x).block_until_ready()
    best = min(_timed(fn, x) for _ in range(repeats))
    return 1000 / best


def _timed(fn, x):
    t = time.perf_counter()
    fn(x).block_until_ready()
    return time.perf_counter() - t


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args()
    print(f"hoisting constants into arguments: {jaxplush._xla._hoisting()}")
    print("| variant | steps/s (best) |\n|---|---:|")
    for mode in ("e literal", "e argument", "e table", "k argument"):
        print(f"| {mode} | {run(mode, args.repeats):,.0f} |")


if __name__ == "__main__":
    main()
