"""Check a gradient against central finite differences, and tell a rough function from a wrong
gradient.

A gradient check compares the whole gradient vector ``g`` with central differences

    d_i(h) = (f(x + h e_i) - f(x - h e_i)) / (2 h)

in the norm of the vector, never component by component (a component near zero has no relative
accuracy to speak of). Before comparing, it checks that the differences have converged: the
vectors at two step sizes ``h`` and ``h / ratio`` must agree to ``fd_rtol`` of their norm.
If they do not, the function is rough at that scale (round-off, or kinks such as hard floor
contact) and the check reports *rough*, not *wrong*; comparing ``g`` with either vector would
say nothing about ``g``.

Used by the test suite (every finite-difference test goes through :func:`check_gradient`) and
by anyone who wants to know whether a loss can be trusted at a given scale: see
:func:`roughness_scan`.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class GradCheck:
    """Outcome of :func:`check_gradient`.

    Attributes:
      grad: (n,) the gradient checked.
      fd: (n,) central differences at the smaller step (the reference when converged).
      fd_coarse: (n,) central differences at the larger step.
      steps: (h, h / ratio) the two step sizes used.
      fd_disagreement: ||fd - fd_coarse|| / max(||fd||, ||fd_coarse||).
      error: ||grad - fd|| / ||fd|| (inf when ||fd|| = 0 and grad != 0, 0 when both vanish).
      converged: the differences agree to ``fd_rtol`` (the function is smooth at this scale).
      ok: converged and ``error <= rtol``.
    """

    grad: np.ndarray
    fd: np.ndarray
    fd_coarse: np.ndarray
    steps: tuple
    fd_disagreement: float
    error: float
    converged: bool
    ok: bool
    rtol: float
    fd_rtol: float

    def message(self):
        """One line saying what was found."""
        if not self.converged:
            return (f"finite differences did not converge: steps {self.steps[0]:.3g} and {self.steps[1]:.3g} "
                    f"disagree by {self.fd_disagreement:.3g} of their norm (> {self.fd_rtol:g}); the function "
                    f"is rough at this scale, so this says nothing about the gradient "
                    f"(fd {_fmt(self.fd_coarse)} vs {_fmt(self.fd)})")
        verdict = "matches" if self.ok else "does NOT match"
        return (f"gradient {verdict} central differences: relative error {self.error:.3g} of the norm "
                f"(tolerance {self.rtol:g}); grad {_fmt(self.grad)}, fd {_fmt(self.fd)} "
                f"(steps agree to {self.fd_disagreement:.2g})")


def _fmt(v):
    return "[" + ", ".join(f"{x:.6g}" for x in np.ravel(v)) + "]"


def _norm(v):
    return float(np.linalg.norm(np.ravel(v)))


def central_differences(f, x, h, directions=None):
    """Central differences of a scalar function ``f`` at ``x`` (float64 numpy).

    Args:
      f: callable taking an array shaped like ``x`` and returning a scalar.
      x: the point (any shape).
      h: step size (scalar, or an array broadcast against ``x``: per-component steps).
      directions: optional (m,) + x.shape array of directions (default: the unit vectors).

    Returns:
      (m,) or x.shape array of (f(x + h d) - f(x - h d)) / (2 h) per direction d.
    """
    x = np.asarray(x, np.float64)
    if directions is None:
        out = np.zeros(x.size)
        hh = np.broadcast_to(np.asarray(h, np.float64), x.shape).ravel()
        for i in range(x.size):
            e = np.zeros(x.size)
            e[i] = hh[i]
            e = e.reshape(x.shape)
            out[i] = (float(f(x + e)) - float(f(x - e))) / (2.0 * hh[i])
        return out.reshape(x.shape)
    dirs = np.asarray(directions, np.float64)
    return np.array([(float(f(x + h * d)) - float(f(x - h * d))) / (2.0 * h) for d in dirs])


def check_gradient(f, x, grad, h=1e-5, ratio=10.0, rtol=1e-4, fd_rtol=None, directions=None):
    """Compare ``grad`` with central differences of ``f`` at ``x`` (whole-vector norms).

    Args:
      f: scalar function of an array shaped like ``x`` (evaluated in float64 where it can be).
      x: the point.
      grad: the gradient to check, shaped like ``x`` (or (m,) directional derivatives when
        ``directions`` is given).
      h: the larger step; the second step is ``h / ratio``.
      rtol: tolerance on ||grad - fd|| / ||fd||.
      fd_rtol: tolerance on the agreement of the two difference vectors (default ``rtol``):
        a larger disagreement means the function is rough at this scale.
      directions: optional directions (m,) + x.shape to differentiate along instead of the axes.

    Returns:
      :class:`GradCheck`.
    """
    fd_rtol = rtol if fd_rtol is None else fd_rtol
    g = np.asarray(grad, np.float64).ravel()
    coarse = np.ravel(central_differences(f, x, h, directions))
    fine = np.ravel(central_differences(f, x, np.asarray(h, np.float64) / ratio, directions))
    scale = max(_norm(coarse), _norm(fine))
    disagreement = _norm(fine - coarse) / scale if scale > 0 else 0.0
    converged = disagreement <= fd_rtol
    n = _norm(fine)
    error = _norm(g - fine) / n if n > 0 else (0.0 if _norm(g) == 0 else float("inf"))
    return GradCheck(grad=g, fd=fine, fd_coarse=coarse, steps=(float(np.max(h)), float(np.max(h)) / ratio),
                     fd_disagreement=float(disagreement), error=float(error), converged=bool(converged),
                     ok=bool(converged and error <= rtol), rtol=float(rtol), fd_rtol=float(fd_rtol))


def roughness_scan(f, x, direction, rel_steps=(1e-5, 1e-4, 1e-3, 1e-2), grad=None):
    """Directional central differences of ``f`` at ``x`` along ``direction`` for several steps.

    A smooth function gives the same slope at every small step (and equal to ``grad . d``); a
    function with kinks or jumps at some scale (hard contact events, say) gives slopes that
    scatter once the step reaches that scale.

    Args:
      f: scalar function; x: the point; direction: unit direction (shaped like x).
      rel_steps: steps (relative: x is usually a log-parameter vector, so a step of 1e-3 is a
        0.1% change of the parameter).
      grad: optional gradient; its directional derivative is returned alongside.

    Returns:
      dict with ``steps`` (k,), ``slopes`` (k,), ``exact`` (float or None) and ``spread``:
      (max - min) of the slopes over |mean|.
    """
    d = np.asarray(direction, np.float64)
    slopes = np.array([central_differences(f, x, h, d[None])[0] for h in rel_steps])
    exact = None if grad is None else float(np.vdot(np.asarray(grad, np.float64), d))
    mean = float(np.mean(slopes))
    spread = float((slopes.max() - slopes.min()) / abs(mean)) if mean != 0 else float("inf")
    return dict(steps=np.asarray(rel_steps, np.float64), slopes=slopes, exact=exact, spread=spread)
