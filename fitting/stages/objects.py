"""A global stage for scenes of several fitted objects: each object's parameters scored by its own residuals.

With per-object parameters the box has P_n x O_f dimensions (two balls with k and nmol each: 4,
three: 6), and a Sobol design of a few dozen points over all of them rarely holds one point that
is close in every dimension at once: the full-dimensional global stage
(:class:`jaxplush.fitting.stages.GlobalStage`) then hands the local searches a start that is good
for one object and far off for the other, and Levenberg-Marquardt stalls in the valley between.

But each object's parameters mostly move its own vertices: its stiffness and gas set how it
inflates, rings and squashes, and another object feels them only through contact. So the
residual vector splits into one block per fitted object (the residuals of that object's vertices,
:func:`residual_objects`), and the same batch of Sobol points, scored block by block, is a
design for every object at once: object o's best points are those whose block loss is lowest,
whatever the other objects' parameters were there. :class:`PerObjectGlobal` composes candidates
from the best few parameter blocks of each object (every combination, one more batch), then,
optionally, zooms: a Sobol design in a smaller box around the best point so far, scored and
composed the same way. Its ``states`` start the local searches
(:class:`jaxplush.fitting.stages.LocalLM`), as a :class:`~jaxplush.fitting.stages.GlobalStage`'s do.

Point-cloud targets have no vertex correspondence: each target point is assigned, frame by
frame, to the object of its nearest vertex in the rollout at the start values (one more run);
a point near two objects in contact counts for one of them only. Tracked points belong to the
object of their vertices exactly. :func:`suits` says whether a problem is one this stage is made
for (several fitted objects, a position or tracks target).
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from jaxplush.fitting.stages import equation_error as _ee
from jaxplush.fitting.stages import search as _search
from jaxplush.fitting.objective.objects import (  # noqa: F401  (named here too)
    CLEARANCE_SAFETY, clear_by_separation, clear_of_contact, fitted_index, residual_objects)
from jaxplush.fitting import stages as _stages
from jaxplush.fitting.options import DEFAULT_SAMPLES, DEFAULT_STARTS, LocalOptions
from jaxplush.fitting.judge.outcome import Stop


def suits(prob):
    """Whether :class:`PerObjectGlobal` suits a problem (:class:`jaxplush.fitting.fitter.Problem`):
    more than one fitted object, and a target of vertex positions or tracks (whose residuals belong
    to objects exactly)."""
    return len(prob.objects) > 1 and prob.target.kind.material_points


def block_losses(residuals, owner, n_objects):
    """(N, O_f) each point's loss restricted to each fitted object's residuals (``owner`` from
    :func:`residual_objects`; NaN residuals of a failed point give an infinite block loss)."""
    r = np.asarray(residuals, np.float64)
    out = np.empty((len(r), n_objects))
    for o in range(n_objects):
        part = r[:, owner == o]
        out[:, o] = np.sum(part * part, axis=1)
    return np.where(np.isfinite(out), out, np.inf)


def compose(thetas, blocks, per_object):
    """Candidates (M, P_n, O_f) made of the best ``per_object`` parameter blocks of each object:
    object o's column of ``thetas`` (N, P_n, O_f) from one of the ``per_object`` points of lowest
    ``blocks[:, o]`` ((N, O_f), :func:`block_losses`; only points that ran), every combination
    (``per_object`` ** O_f of them, fewer where an object has fewer blocks that ran), in order of
    the sum of their ranks: the combination of each object's best first."""
    thetas = np.asarray(thetas, np.float64)
    n_obj = thetas.shape[-1]
    best = []
    for o in range(n_obj):
        order = [int(i) for i in np.argsort(blocks[:, o], kind="stable") if np.isfinite(blocks[i, o])]
        best.append(order[:per_object] or [0])
    combos = sorted(itertools.product(*(range(len(b)) for b in best)), key=lambda c: (sum(c), c))
    return np.asarray([np.stack([thetas[best[o][c]][:, o] for o, c in enumerate(combo)], axis=-1)
                       for combo in combos])


@dataclasses.dataclass
class PerObjectState:
    """A :class:`PerObjectGlobal`'s state.

    Attributes:
      theta: the start; owner: :func:`residual_objects` (None until the first step);
      result: :class:`jaxplush.fitting.stages.search.GlobalResult` of every point evaluated so far
        (designs and composed candidates); rounds: designs run; composed: the composed candidates'
        rows in ``result``; states: the local searches it starts (after the last round); linear:
        the design point of :func:`jaxplush.fitting.stages.equation_error.design_point` (NaN: none).
    """

    theta: np.ndarray
    owner: np.ndarray | None = None
    result: object = None
    rounds: int = 0
    composed: list = dataclasses.field(default_factory=list)
    states: list = dataclasses.field(default_factory=list)
    done: bool = False
    linear: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class PerObjectGlobal:
    """A global stage that scores each fitted object's parameters by that object's own residuals.

    One step is one round: a Sobol design (the first round: the start and ``samples`` points of the
    whole box, as :class:`jaxplush.fitting.stages.GlobalStage`; a later round: ``samples`` points
    in a box ``zoom`` times as wide per round, centred on the best point so far and kept inside
    the search box), one batch; then each object's parameter blocks are ranked by the loss of its
    own residuals (:func:`block_losses`), and the combinations of the best ``per_object`` blocks
    of every object (:func:`compose`) run as a second batch. After ``rounds`` rounds its
    ``states`` are :class:`jaxplush.fitting.stages.search.LMState` s at the best ``starts`` of all the
    points evaluated, each ``local.start_distance`` of the box's width from those before (as a
    :class:`~jaxplush.fitting.stages.GlobalStage`'s).

    Attributes: samples, per_object, rounds, zoom, starts, seed, retries, linear (as
    :class:`~jaxplush.fitting.stages.GlobalStage`'s; the first round's design also holds the
    linear start); local
    (:class:`jaxplush.fitting.options.LocalOptions`: the spacing, and the searches' radius and mu);
    progress: ``progress(n)`` after each batch of n points (or None).
    """

    samples: int = DEFAULT_SAMPLES
    per_object: int = 3
    rounds: int = 3
    zoom: float = 0.5
    starts: int = DEFAULT_STARTS
    seed: int = 0
    local: LocalOptions = LocalOptions()
    progress: object = None
    retries: int | None = None
    linear: bool = False

    def evaluations(self, n_objects):
        """Points this stage evaluates at most for ``n_objects`` fitted objects (the first round's
        start and linear start included; not the linear start's own rollouts)."""
        if self.samples <= 0:
            return 1
        return 1 + int(self.linear) + self.rounds * (self.samples + self.per_object ** n_objects)

    def init(self, objective, theta, state=None):
        return PerObjectState(theta=np.asarray(theta, np.float64))

    def _owner(self, objective, s):
        prob = objective.prob
        if prob.target.kind.material_points:
            return residual_objects(prob)
        e = objective.evaluator(s.theta[None], keep_frames=True)
        if not e.ok[0]:       # no rollout to assign the points by: every block scored by the whole loss
            return np.full(objective.evaluator.residual.n, -1, np.int64)
        return residual_objects(prob, e.frames[0])

    def _run(self, objective, thetas):
        ev = objective.evaluator(thetas) if self.retries is None else objective.evaluator(thetas, retries=self.retries)
        if self.progress is not None:
            self.progress(len(thetas))
        return ev

    def step(self, objective, s):
        s = _stages.own(s)
        box = objective.box
        if self.samples <= 0:
            # no design (a fit that continues from a point, e.g. replanned over a longer horizon):
            # the start alone, as GlobalStage's, without blocks to compose or a box to zoom into
            s.result = _search.global_stage(objective.evaluator, box, s.theta, 0, self.seed,
                                            progress=self.progress, retries=self.retries)
            s.rounds = self.rounds
            return self._finish(objective, s)
        if s.owner is None:
            s.owner = self._owner(objective, s)
        n_obj = s.theta.shape[-1]
        if s.rounds == 0:
            extra = []
            if self.linear:
                if s.linear is None:
                    s.linear = _ee.design_point(objective)
                if np.all(np.isfinite(s.linear)):
                    extra = [box.clip(s.linear)[None]]
            design = np.concatenate([s.theta[None]] + extra + [_search.sobol_design(box, self.samples, self.seed)])
        else:
            best = s.result.thetas[s.result.best(1, 0.0)[0]]
            half = 0.5 * (box.hi - box.lo) * self.zoom ** s.rounds
            lo, hi = np.maximum(best - half, box.lo), np.minimum(best + half, box.hi)
            design = _search.sobol_design(_search.Box(lo, hi), self.samples, self.seed + s.rounds)
        ev = self._run(objective, design)
        blocks = block_losses(ev.residuals, s.owner, n_obj)
        if (s.owner < 0).all():     # no residual belongs to a fitted object: each block by the whole loss
            blocks = np.repeat(ev.loss[:, None], n_obj, axis=1)
        cand = compose(design, blocks, self.per_object)
        ec = self._run(objective, cand)
        new = _search.GlobalResult(np.concatenate([design, cand]), np.concatenate([ev.loss, ec.loss]),
                                   np.concatenate([ev.ok, ec.ok]), np.concatenate([ev.substeps, ec.substeps]))
        start = 0 if s.result is None else len(s.result.thetas)
        s.composed += list(range(start + len(design), start + len(design) + len(cand)))
        s.result = new if s.result is None else _search.GlobalResult(
            *(np.concatenate([getattr(s.result, f), getattr(new, f)]) for f in ("thetas", "loss", "ok", "substeps")))
        s.rounds += 1
        return self._finish(objective, s) if s.rounds >= self.rounds else s

    def _finish(self, objective, s):
        """The searches' starts: the best ``starts`` points, spaced (as GlobalStage's)."""
        s.states = _stages.design_starts(s.result, self.starts, objective.box, self.local)
        s.done = True
        return s

    def terminate(self, objective, s):
        return s.done, Stop.NONE

    def postprocess(self, objective, s):
        return _stages.searches_candidate(s.states, objective.prob.theta0, "the per-object design's best point")
