"""XLA:CPU settings that jaxplush needs for correct results, applied when jaxplush is imported.

jaxlib 0.10.2 turns on XLA:CPU's experimental YNNPACK fusions by default, and they miscompile
some fused reductions of broadcast operands: under ``jax.jit``,
``jnp.sum(b * (a + b), -1) * jnp.sum(a * a, -1)`` with ``a`` (512, 1, 3) and ``b`` (1, 1280, 3)
comes out up to 80% wrong on this project's CPU, while the same expression run eagerly is right
(tests/test_backend_neutral.py; upstream reports of the same family: jax-ml/jax#39103, #39257,
#40412). Turning those fusions off costs nothing measurable on jaxplush's hot paths.

So, before jax starts its backends, :func:`disable_ynn_fusion` adds
``--xla_cpu_experimental_ynn_fusion_type=`` (empty: none) to ``XLA_FLAGS``, unless the flag is
already there (your own choice wins), and only for jaxlib versions that know the flag. XLA reads
``XLA_FLAGS`` once, when its first backend starts: if jax ran a computation before jaxplush was
imported, the setting comes too late, and a warning says so.

Topology as data. :func:`hoist_constants` asks JAX to pass every non-scalar constant of a traced
program (a scene's ring tables, rest lengths, faces, contact tables, and the geometry's scalars,
which :func:`jaxplush.model.layout.scene_value` makes one-element arrays) to the compiled program
as an argument instead of writing it into the program. Two scenes of one size bucket
(:func:`jaxplush.stepping.compiled.bucket`) with the same terms and step options then lower to the
same program, and the second loads it from the persistent compilation cache instead of compiling it
(docs/cli.md, "Programs shared by scenes of one size"). ``JAXPLUSH_TOPOLOGY_AS_DATA=0`` turns it off.
"""

from __future__ import annotations

import os
import warnings

from jaxplush.errors import BackendWarning

FLAG = "--xla_cpu_experimental_ynn_fusion_type="
#: jaxlib releases that know the flag (older ones abort on an unknown XLA flag).
FIRST_JAXLIB = (0, 10, 1)


def _version(text):
    out = []
    for part in text.split(".")[:3]:
        digits = "".join(ch for ch in part if ch.isdigit())
        out.append(int(digits) if digits else 0)
    return tuple(out)


def disable_ynn_fusion():
    """Add :data:`FLAG` to ``XLA_FLAGS`` (module docstring). Returns True when it is in effect
    for this process's backends (set here or by the user), False when it could not be."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_experimental_ynn_fusion_type" in flags:
        return True
    try:
        import jaxlib
        if _version(jaxlib.__version__) < FIRST_JAXLIB:
            return False
    except ImportError:                                   # pragma: no cover - jax is a dependency
        return False
    try:
        from jax._src import xla_bridge
        started = xla_bridge.backends_are_initialized()
    except (ImportError, AttributeError):                 # pragma: no cover - jax internals moved
        started = False
    if started:
        warnings.warn("jax started its backends before jaxplush was imported, so XLA:CPU's experimental "
                      "YNNPACK fusions stay on; jaxlib 0.10.2 miscompiles some fused reductions with them. "
                      f"Import jaxplush first, or set XLA_FLAGS={FLAG}", BackendWarning, stacklevel=3)
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {FLAG}".strip()
    return True


def hoist_constants():
    """Ask JAX to hoist closed-over array constants into program arguments: set
    ``JAX_USE_SIMPLIFIED_JAXPR_CONSTANTS=true`` and ``JAX_EMBEDDED_CONSTANTS_MAX_BYTES=0`` (every
    non-scalar constant) in the environment. JAX reads the first when it is imported, so this must
    run before ``import jax``; afterwards it changes nothing: programs then carry their scene's
    constants, and only the same scene reuses them (the same results, more compiles). Off with
    ``JAXPLUSH_TOPOLOGY_AS_DATA=0``; a value the user set for either variable wins. Returns True
    when hoisting is in effect for this process."""
    import sys
    if os.environ.get("JAXPLUSH_TOPOLOGY_AS_DATA", "1").strip().lower() in ("0", "off", "false", "no"):
        return False
    if "jax" in sys.modules:
        return _hoisting()
    os.environ.setdefault("JAX_USE_SIMPLIFIED_JAXPR_CONSTANTS", "true")
    os.environ.setdefault("JAX_EMBEDDED_CONSTANTS_MAX_BYTES", "0")
    return os.environ["JAX_USE_SIMPLIFIED_JAXPR_CONSTANTS"].strip().lower() in ("1", "true", "yes", "on")


def _hoisting():
    """Whether the imported jax hoists array constants into program arguments."""
    try:
        from jax._src.interpreters import mlir
        return bool(mlir.LoweringParameters().hoist_constants_as_args)
    except Exception:                                     # pragma: no cover - jax internals moved
        return False
