"""Explaining away among the frame-space causes: forward stepwise selection (issue 14).

Each frame-space cause of :mod:`.frames` is fitted *alone* on the linear sensor. A single
sensor effect then makes several of them significant, each absorbing part of it (a black
offset of 14 DN also gives shutter_error and led_drift held-out gains far above the
threshold: both bend the short exposures of dark pixels), and as sensor causes are read
first (:func:`glossrig.core.diagnose.report.verdict`) they push a second, real effect
seen in BRDF space out of the first two places.

Rule (forward stepwise selection, Hastie, Tibshirani & Friedman, *The Elements of
Statistical Learning*, 2nd ed., sec. 3.3.2; the causes' terms refitted together by
backfitting, Hastie & Tibshirani, *Generalized Additive Models*, 1990, sec. 4.3):

1. The selected model S starts with the frame-space cause of the largest held-out gain
   among the eligible ones (the one the verdict names when the frames decide, unless hot
   pixels outrank it).
2. Every other eligible frame-space cause X is fitted *on top of* S: the terms compose in
   the linear per-pixel model of :func:`.frames._linear_pred` (offsets add, gains
   multiply, compressions add), and all terms of S + X are re-fitted per fold on the
   training exposures - X from its null value with the cause's own grid search, the terms
   of S from their estimates of the previous step with a local search, alternately,
   :data:`ROUNDS` sweeps (block coordinate descent; every sweep lowers the training cost,
   so the joint fit is at least as good as keeping S fixed). S is re-fitted and not
   frozen at its own fold estimate because a winner fitted alone has absorbed part of a
   real second effect; frozen, it would leave X less to gain than X really explains and
   the test would lean towards explaining a real effect away.
3. X is scored on the same held-out folds (even / odd exposure index) against S alone
   (S's own fit on the same training exposures), and stays eligible only if it still gains significantly by
   the rule of :attr:`.catalogue.CauseResult.significant`: positive in every fold and a
   pooled relative gain above its space's threshold plus the penalty per extra parameter
   of X. Otherwise it gets ``blocked_by`` = the causes of S (joined by " + ") and a note.
4. The surviving X with the largest conditional gain joins S, and the remaining
   survivors are tested again on top of the larger S (greedy), until none survives.

Every tested cause records the test in ``params["conditional"]`` (the causes it was
conditioned on, held-out errors, pooled and per-fold conditional gains, threshold, its
estimate on top of them) so report.json shows it.

Hot pixels (pixel space) are not conditioned, nor used to condition: a dark current adds
D t to a pixel's signal, linear in t, so the per-pixel rate of the frame-space base model
absorbs it exactly and hot pixels leave no frame-space residual; conversely every
frame-space cause acts alike on all pixels of a colour (or of an LED's frame) and cannot
put an isolated spike at the same place under every LED. The two spaces' evidence is
disjoint: neither can explain the other away.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from glossrig.core.diagnose.catalogue import CauseResult
from glossrig.core.diagnose.frames import (BOUNDS, CHANNEL_NAMES, FrameSet, _line, _linear_pred, _scalar_fit,
                                           _score, shutter_bounds)

#: backfitting sweeps over the terms of S + X. Measured on the black offset + non-linearity stacks of
#: tests/test_diagnose_conditional.py (seeds 2, 3): a third sweep moved the conditional gains by < 7e-6 and
#: the non-linearity's c by < 0.1 %, one sweep left c 2 % short; the decisions were the same for 1, 2, 3
ROUNDS = 2
LOCAL_STEPS = 2     # a re-fitted term searches this many of its grid steps either side of its last value


@dataclass
class Term:
    """A frame-space cause as a composable term of the linear per-pixel model: one scalar per
    block, each block touching the pixels of its scope - (LED index, pixel columns or None for
    all) pairs: per-pixel rates are independent, so the training cost of the other pixels does
    not depend on the block; ``kw(i, theta)`` the term's part of :func:`.frames._linear_pred`'s
    offset / gain / c for LED ``i``; ``param`` the key of the cause's ``params`` that holds its
    estimate (:func:`theta` turns it into the term's parameters)."""

    name: str
    param: str
    bounds: list[tuple[float, float]]
    scopes: list[list[tuple[int, np.ndarray | None]]]
    kw: Callable[[int, np.ndarray], dict]
    grid_n: int = 13


def term(fs: FrameSet, name: str) -> Term | None:
    """The term of frame-space cause ``name`` (None for a cause that is not one: hot pixels)."""
    n = len(fs.Z)
    every: list[list[tuple[int, np.ndarray | None]]] = [[(i, None) for i in range(n)]]
    if name == "black_level_offset":
        return Term(name, "b_dn", [BOUNDS[name]], every, lambda i, th: {"offset": th[0]})
    if name == "sensor_nonlinearity":
        return Term(name, "c", [BOUNDS[name]], every, lambda i, th: {"c": th[0]})
    if name == "shutter_error":
        return Term(name, "delta_s", [shutter_bounds(fs)], every,
                    lambda i, th: {"gain": (fs.T[i] + th[0]) / fs.T[i]})
    if name == "channel_response":
        per_colour: list[list[tuple[int, np.ndarray | None]]] = [
            [(i, np.flatnonzero(fs.colour[i] == k)) for i in range(n)] for k in range(3)]
        return Term(name, "c", [BOUNDS[name]] * 3, per_colour, lambda i, th: {"c": th[fs.colour[i]]})
    if name == "led_drift":
        return Term(name, "gain_slope_per_min", [BOUNDS[name]] * n, [[(i, None)] for i in range(n)],
                    lambda i, th: {"gain": 1 + th[i] * fs.tau[i]}, grid_n=11)
    return None


def theta(e) -> np.ndarray:
    """A cause's estimate as its term's parameters: a value, a list (one per block) or a dict over the
    colour channels (channel_response)."""
    if isinstance(e, dict):
        return np.array([e[k] for k in CHANNEL_NAMES], float)
    return np.atleast_1d(np.asarray(e, float))


def fold_start(c: CauseResult, fold: int) -> np.ndarray:
    """The cause's own estimate on training fold ``fold`` (its ``params["fold_estimates"]``)."""
    return theta(c.params["fold_estimates"][fold])


def _compose(parts):
    off, gain, c = 0.0, None, 0.0
    for p in parts:
        off = off + p.get("offset", 0.0)
        if "gain" in p:
            gain = p["gain"] if gain is None else gain * p["gain"]
        c = c + p.get("c", 0.0)
    return off, gain, c


def _model(fs, terms, thetas):
    def pred(i, M):
        off, gain, c = _compose([t.kw(i, th) for t, th in zip(terms, thetas)])
        return _linear_pred(fs, i, M, offset=off, gain=gain, c=c)
    return pred


def _ss(fs, terms, thetas, i, cols, M) -> float:
    """Weighted training sum of squares of LED ``i``'s pixels ``cols`` (None: all) over mask M."""
    if cols is None:
        return float(np.sum(np.where(M, (fs.Z[i] - _model(fs, terms, thetas)(i, M)) ** 2 / fs.V[i], 0.0)))
    off, gain, c = _compose([t.kw(i, th) for t, th in zip(terms, thetas)])
    Z, V, m = fs.Z[i][:, cols], fs.V[i][:, cols], M[:, cols]
    pred = _line(Z, fs.T[i][:, cols], 1.0 / V, m, fs.range, off, None if gain is None else gain[:, cols],
                 c[cols] if np.ndim(c) else c)
    return float(np.sum(np.where(m, (Z - pred) ** 2 / V, 0.0)))


def _held_out(fs, terms, thetas, fold) -> float:
    """Held-out chi^2 of the joint model, pooled over LEDs (:func:`.frames._score`)."""
    return _score(fs, _model(fs, terms, thetas), fold)


def joint_fit(fs, terms: list[Term], start: list[np.ndarray], fold, fresh: int | None = None) -> list[np.ndarray]:
    """Backfitting of ``terms`` on the training exposures of ``fold``: each block's scalar in
    turn minimises the weighted training chi^2 of its scope with every other block fixed.
    Term ``fresh`` (the candidate, started at its null value) gets the cause's grid search
    over its whole bounds on its first visit; every other visit is a bounded search of
    :data:`LOCAL_STEPS` grid steps either side of the current value."""
    tr, _ = fold
    th = [np.array(s, float) for s in start]
    order = ([fresh] if fresh is not None else []) + [k for k in range(len(terms)) if k != fresh]
    for rnd in range(ROUNDS):
        for k in order:
            t = terms[k]
            for b, (lo, hi) in enumerate(t.bounds):
                scope = t.scopes[b]

                def cost(v, k=k, b=b, scope=scope):
                    trial = [x.copy() if j == k else x for j, x in enumerate(th)]
                    trial[k][b] = v
                    return sum(_ss(fs, terms, trial, i, cols, tr[i] & fs.ok[i]) for i, cols in scope)
                if rnd == 0 and k == fresh:
                    v = _scalar_fit(cost, (lo, hi), t.grid_n)[0]
                else:
                    # the tolerance scales with the grid step: scipy's default (1e-5 absolute) is a
                    # fifth of a shutter error's grid step (delta ~ 1e-5 s)
                    step = (hi - lo) / (t.grid_n - 1)
                    a, z = max(lo, th[k][b] - LOCAL_STEPS * step), min(hi, th[k][b] + LOCAL_STEPS * step)
                    v = float(minimize_scalar(cost, bounds=(a, z), method="bounded",
                                              options={"xatol": 1e-3 * step}).x)
                # kept only where it lowers the training cost: neither the grid (which need not hold the
                # null value) nor bounded Brent (which never evaluates the current value) guarantees it,
                # and every sweep must leave the joint fit at least as good as the start
                if cost(v) <= cost(th[k][b]):
                    th[k][b] = v
    return th


def _conditional(fs, sel_terms, sel_thetas, base_err, cand: CauseResult, folds) -> tuple[CauseResult, list]:
    """``cand`` re-fitted on top of the selected terms (all re-fitted per fold) and scored on
    the held-out folds against the selected model alone (``base_err`` per fold)."""
    t = term(fs, cand.name)
    assert t is not None
    errs, fits = [], []
    for f, fold in enumerate(folds):
        th = joint_fit(fs, sel_terms + [t], sel_thetas[f] + [np.zeros(len(t.bounds))], fold, fresh=len(sel_terms))
        errs.append(_held_out(fs, sel_terms + [t], th, fold))
        fits.append(th)
    gains = [(e0 - e1) / e0 if e0 > 0 else 0.0 for e0, e1 in zip(base_err, errs)]
    from glossrig.core.diagnose.frame_gains import TESTS, camera_check, gain_series, sensor_check

    # the terms at their estimates on top of each other (the mean of the folds' joint fits)
    est = [np.mean([fit[k] for fit in fits], axis=0) for k in range(len(sel_terms) + 1)]

    def undone(terms, thetas):
        return lambda i: dict(zip(("offset", "gain", "c"), _compose([t.kw(i, th) for t, th in zip(terms, thetas)])))
    test = check = None
    if cand.test is not None:
        # a cause with its own test takes it again on the frames with the selected terms undone
        test = TESTS[cand.name](gain_series(fs, undone(sel_terms, est[:-1])))
        if test is None:
            test = {"passed": False, "rule": "no frame-gain series to test"}
    if cand.check is not None and cand.test is not None:
        # a frame-gain cause's check: the camera structure of the series its test was taken on again
        check = camera_check(test)
    elif cand.check is not None:
        # a cause with a check on the frame gains takes it on top of the selected causes: the frames with
        # their terms undone are the base, the frames with the candidate's undone as well the extension
        check = sensor_check(gain_series(fs, undone(sel_terms, est[:-1]), camera=False),
                             gain_series(fs, undone(sel_terms + [t], est), camera=False), len(t.bounds))
        if check is not None:
            check["on"] = [s.name for s in sel_terms]
    r = CauseResult(cand.name, cand.space, "", {}, {}, float(np.mean(errs)), float(np.mean(base_err)), gains,
                    cand.n_extra_params, test=test, check=check)
    return r, fits


def explain_away(fs: FrameSet, causes: list[CauseResult]) -> None:
    """Forward stepwise selection among the eligible frame-space causes (module docstring):
    blocks (``blocked_by``, a note) every cause the selected ones explain, and records each
    conditional test in the cause's ``params["conditional"]``. Changes ``causes`` in place."""
    # the candidates: every eligible frame-space cause, and those only their check on the frame gains stops
    # (a sensor effect the check was taken beside - a black offset under a compression - can fail it alone:
    # on top of the selected causes it is taken again); the first pick must be eligible
    cands = [c for c in causes if c.space == "frames" and term(fs, c.name) is not None and c.blocked_by is None
             and c.significant_without_check]
    eligible = [c for c in cands if c.eligible]
    if len(cands) < 2 or not eligible:
        return
    folds = fs.folds()
    first = max(eligible, key=lambda c: c.gain)
    sel = [first]
    sel_terms = [term(fs, first.name)]
    sel_thetas = [[fold_start(first, f)] for f in range(len(folds))]
    base_err = _errors(fs, sel_terms, sel_thetas, folds)
    first.note = (first.note + "; " if first.note else "") + "selected first among the frame-space causes (largest gain)"
    rest = [c for c in cands if c is not first]
    while rest:
        tested = [(c, *_conditional(fs, sel_terms, sel_thetas, base_err, c, folds)) for c in rest]
        on = " + ".join(c.name for c in sel)
        for c, r, fits in tested:
            est = np.mean([fit[-1] for fit in fits], axis=0)
            c.params["conditional"] = {
                "on": [s.name for s in sel], "error": r.error, "base_error": r.base_error, "gain": r.gain,
                "fold_gains": r.fold_gains, "threshold": r.threshold, "significant": r.significant, "test": r.test,
                "estimate": est.tolist(), "fold_estimates": [fit[-1].tolist() for fit in fits],
                "rule": "forward stepwise: re-fitted on top of the selected causes (all terms re-fitted per "
                        "fold), held-out gain over them"}
            if not r.significant:
                c.blocked_by = on
                why = (f"its check on the frame gains on top of it: chi^2 drop {r.check['chi2']:.1f} against "
                       f"{r.check['bound']:.1f}" if r.check is not None and not r.check["passed"] else
                       f"its test on top of it: {r.test['rule']}" if r.test is not None and "chi2" not in r.test else
                       f"its test on top of it: chi^2 {r.test['chi2']:.1f} against {r.test['bound']:.1f}"
                       if r.test is not None else
                       f"fitted on top of it the held-out gain is {r.gain:.4%} (folds "
                       f"{', '.join(f'{g:.4%}' for g in r.fold_gains)}; threshold {r.threshold:.4%})")
                c.note = (c.note + "; " if c.note else "") + f"explained by {on}: {why}, alone {c.gain:.4%}"
        alive = [(c, r, fits) for c, r, fits in tested if r.significant]
        if not alive:
            return
        best, r, fits = max(alive, key=lambda x: x[1].gain)
        if r.check is not None:
            best.check = r.check        # its check on top of the selected causes is the one that counts
        best.note = (best.note + "; " if best.note else "") + (
            f"still passes its test on top of {on} (chi^2 {r.test['chi2']:.1f} against {r.test['bound']:.1f}): kept"
            if r.test is not None else
            f"still gains {r.gain:.4%} held-out on top of {on} (threshold {r.threshold:.4%}): kept")
        sel.append(best)
        sel_terms.append(term(fs, best.name))
        sel_thetas = fits
        base_err = _errors(fs, sel_terms, sel_thetas, folds)
        rest = [c for c, _, _ in alive if c is not best]


def _errors(fs, terms, thetas, folds) -> list[float]:
    return [_held_out(fs, terms, th, fold) for th, fold in zip(thetas, folds)]
