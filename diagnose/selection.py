"""Fitting effects with bounded least squares and greedy model selection (BIC on training, gain on validation)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares, lsq_linear

from hybridcomp.diagnose.effects import Candidate, params_key, predicted_channels
from hybridcomp.diagnose.metrics import channel_metrics, lag1_autocorrelation, rms, strongest_correlations
from hybridcomp.diagnose.problem import Problem

log = logging.getLogger(__name__)

# a channel's validation residual within this factor of its noise level is "at the noise level"
NOISE_FACTOR = 1.5
# an effect is named only if it lowers the weighted validation residual energy by this fraction ...
MIN_VALIDATION_GAIN = 0.10
# ... and the training BIC by at least this much
MIN_BIC_DROP = 10.0
MAX_EFFECTS = 4


@dataclass(frozen=True)
class Fitted:
    """A fitted effect: parameters, 1σ uncertainty, and what it gained."""

    candidate: Candidate
    params: np.ndarray
    uncertainty: np.ndarray
    bic_drop: float
    validation_gain: float

    def as_dict(self) -> dict:
        c = self.candidate
        return {
            "name": c.kind,
            "target": c.target,
            "label": c.label,
            "parameters": {n: float(v) for n, v in zip(c.param_names, self.params)},
            "nominal": {n: float(v) for n, v in zip(c.param_names, c.nominal)},
            "uncertainty": {n: float(v) for n, v in zip(c.param_names, self.uncertainty)},
            "gain": {"bic_drop_train": float(self.bic_drop), "validation_rss_reduction": float(self.validation_gain)},
            **({"where": dict(c.info)} if c.info else {}),
        }


@dataclass(frozen=True)
class Evaluation:
    """Weighted residual energy of a model variant on the training and validation rows."""

    rss_train: float
    rss_val: float
    n_train: int
    k: int

    @property
    def bic(self) -> float:
        n = self.n_train
        return n * np.log(self.rss_train / n) + self.k * np.log(n)


def dof(candidates, params) -> int:
    """Parameters a set of effects spends: the fitted ones and those chosen outside the fit (a source's location)."""
    return sum(len(p) + c.extra_dof for c, p in zip(candidates, params))


def _weighted(problem: Problem, Yhat: np.ndarray) -> np.ndarray:
    return (problem.Y - Yhat) * problem.weights[None, :]


def evaluate(problem: Problem, effects, k: int) -> tuple[Evaluation, np.ndarray]:
    """Weighted residual energies of the model with ``effects`` (``k`` parameters), and its channels."""
    Yhat = predicted_channels(problem, effects)
    R = _weighted(problem, Yhat)
    tr, va = problem.split.train, problem.split.validation
    return Evaluation(float(np.sum(R[tr] ** 2)), float(np.sum(R[va] ** 2)), int(R[tr].size), k), Yhat


def fit(problem: Problem, fixed: list, free: list[Candidate], start: list | None = None,
        max_nfev: int = 40) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """Bounded least squares of the free effects' parameters on the training rows, ``fixed`` held.

    Returns
    -------
    parameters and 1σ uncertainties per free effect, and the model's channels (nt × nch)
    """
    tr = problem.split.train
    sizes = [len(c.nominal) for c in free]
    cuts = np.cumsum([0] + sizes)
    lo = np.concatenate([c.lower for c in free])
    hi = np.concatenate([c.upper for c in free])
    x0 = np.concatenate(start) if start is not None else np.concatenate([c.start for c in free])
    x0 = np.clip(x0, lo, hi)

    def effects_at(x):
        return list(fixed) + [(c, x[cuts[i]:cuts[i + 1]]) for i, c in enumerate(free)]

    def resid(x):
        return _weighted(problem, predicted_channels(problem, effects_at(x)))[tr].ravel()

    if len(free) == 1 and free[0].linear:
        nom = np.concatenate([c.nominal for c in free])
        r0 = resid(nom)
        J = np.empty((r0.size, nom.size))
        for j in range(nom.size):
            step = max(1.0, abs(hi[j] - lo[j]) * 1e-2)
            e = nom.copy()
            e[j] += step
            J[:, j] = -(resid(e) - r0) / step
        sol = lsq_linear(J, r0, bounds=(lo - nom, hi - nom), method="bvls" if nom.size <= 8 else "trf")
        x = nom + sol.x
        r = r0 - J @ sol.x
        Jac = -J
    else:
        if start is None:
            # scan the first parameter of a single nonlinear effect for a start
            if len(free) == 1 and free[0].grid is not None:
                best = None
                for g in free[0].grid:
                    xg = x0.copy()
                    xg[0] = np.clip(g, lo[0], hi[0])
                    val = float(np.sum(resid(xg) ** 2))
                    if best is None or val < best[0]:
                        best = (val, xg)
                x0 = best[1]
        scale = np.maximum(np.abs(hi - lo) * 0.05, 1e-6)
        res = least_squares(resid, x0, bounds=(lo, hi), x_scale=scale, diff_step=1e-4, max_nfev=max_nfev, method="trf")
        x, r, Jac = res.x, res.fun, res.jac
    n, k = r.size, x.size
    s2 = float(r @ r) / max(n - k, 1)
    # residual correlation in time inflates the variance (effective sample size)
    rho = np.clip(np.mean([lag1_autocorrelation(rc) for rc in r.reshape(-1, problem.Y.shape[1]).T]), 0.0, 0.99)
    infl = (1 + rho) / (1 - rho)
    try:
        cov = np.linalg.pinv(Jac.T @ Jac) * s2 * infl
        unc = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        unc = np.full(k, np.nan)
    Yhat = predicted_channels(problem, effects_at(x))
    return ([x[cuts[i]:cuts[i + 1]] for i in range(len(free))], [unc[cuts[i]:cuts[i + 1]] for i in range(len(free))], Yhat)


def at_bound(c: Candidate, p: np.ndarray, rel: float = 0.01) -> bool:
    """A fitted parameter pinned to an edge of its search range: the effect is the wrong shape for the data.

    A bound that is the nominal value, or a physically meaningful value (``Candidate.physical``: a time constant of
    0, a source with no heat), is a result when the fit lands on it, not a sign of the wrong shape.
    """
    lo, hi, nom = np.asarray(c.lower), np.asarray(c.upper), np.asarray(c.nominal)
    phys = np.asarray(c.physical, bool).reshape(-1, 2) if c.physical else np.zeros((lo.size, 2), bool)
    tol = rel * (hi - lo)
    pinned = (((np.abs(p - lo) <= tol) & (np.abs(lo - nom) > tol) & ~phys[:, 0])
              | ((np.abs(p - hi) <= tol) & (np.abs(hi - nom) > tol) & ~phys[:, 1]))
    return bool(pinned.any())


def at_noise_level(problem: Problem, Yhat: np.ndarray, factor: float = NOISE_FACTOR) -> np.ndarray:
    """Per channel, whether the validation residual is at the noise level.

    At the noise level: within ``factor`` × the channel's noise level, or within the model's own accuracy
    ``problem.tolerance``, whichever is larger.
    """
    va = problem.split.validation
    r = problem.Y[va] - Yhat[va]
    return np.sqrt(np.mean(r**2, axis=0)) <= np.maximum(factor * problem.sigma, problem.tolerance)


@dataclass(frozen=True)
class Round:
    """One greedy round: every candidate's score given the effects accepted before it."""

    accepted: str | None
    scores: list  # dicts: label, params, bic_drop, validation_gain


@dataclass(frozen=True)
class Diagnosis:
    """What the simulation gets wrong, the named causes, the extended model and the gain.

    Attributes
    ----------
    problem : the data and the model under test
    causes : fitted effects, in the order they were accepted
    before, after : per channel validation RMS, P2P and fit % of the model as is and extended
    verdict : ``"no significant discrepancy"``, ``"explained"`` (every channel at its noise level with the named
        causes) or ``"unexplained"`` (a structured residual remains; the best library combination is then
        reported as ``partial``, not as causes: no name without evidence)
    Y_before, Y_after : the model's channels before and after (nt × nch)
    correlations : strongest correlations of the remaining residual with the available signals
    rounds : candidate scores per greedy round
    partial : with an unexplained residual, the best combination of library effects found (not confirmed)
    """

    problem: Problem
    causes: tuple[Fitted, ...]
    before: dict
    after: dict
    verdict: str
    Y_before: np.ndarray
    Y_after: np.ndarray
    correlations: list
    rounds: tuple[Round, ...]
    message: str = ""
    timings_s: dict = field(default_factory=dict)
    partial: tuple[Fitted, ...] = ()

    def summary(self) -> dict:
        return {
            "verdict": self.verdict,
            "message": self.message,
            "causes": [c.as_dict() for c in self.causes],
            "partial_candidates": [c.as_dict() for c in self.partial],
            "before": self.before,
            "after": self.after,
            "noise_level": {c: float(s) for c, s in zip(self.problem.channels, self.problem.sigma)},
            "unexplained_correlations": [c.as_dict() for c in self.correlations],
            "split": self.problem.split.describe(self.problem.time_s),
            "timings_s": self.timings_s,
        }


def validation_metrics(problem: Problem, Yhat: np.ndarray) -> dict:
    """RMS, P2P and fit % per channel on the validation rows."""
    va = problem.split.validation
    return {c: channel_metrics(problem.Y[va, k], Yhat[va, k]) for k, c in enumerate(problem.channels)}


def _conflicts(a: Candidate, chosen: list) -> bool:
    return any(a.key == c.key or (a.kind in ("htc", "htc_motion") and c.kind in ("htc", "htc_motion") and a.target == c.target)
               or (a.kind in ("power_scale", "exponent") and c.kind in ("power_scale", "exponent") and a.target == c.target
                   and a.kind == c.kind)
               for c in chosen)


def _joint(problem: Problem, free: list[Candidate], start: list, memo: dict | None):
    """A joint refit of ``free`` from ``start`` (kept in ``memo`` for a later selection on the same problem)."""
    key = ("joint", tuple(c.key for c in free), tuple(params_key(p) for p in start))
    if memo is not None and key in memo:
        return memo[key]
    params, uncs, _ = fit(problem, [], free, start=start)
    if memo is not None:
        memo[key] = (params, uncs)
    return params, uncs


def _replace(problem: Problem, chosen: list, current: Evaluation, runners: dict, banned: set, min_bic_drop: float,
             memo: dict | None) -> tuple[list, Evaluation]:
    """Replacement step after a sensor's effect is accepted: each accepted effect against the runners-up of its round.

    An effect accepted before a sensor's lag or offset was there was ranked on the evidence that effect distorts (a
    source's drive shape or place chosen on the lagged sensor): with it now accepted, each runner-up takes the
    earlier effect's place in a joint refit of all.  A swap is made when the evidence prefers it: the training BIC
    drops by ``min_bic_drop`` and the validation residual energy drops too, no parameter pinned to an artefact bound;
    the best swap first, until none is left.
    The effect replaced is not tried again (``banned``); its other runners-up pass to the one that replaced it.
    """
    for _ in range(len(chosen)):
        best = None
        for i, f in enumerate(chosen):
            rest = chosen[:i] + chosen[i + 1:]
            for cand, p0 in runners.get(f.candidate.key, ()):
                if cand.key in banned or _conflicts(cand, [g.candidate for g in rest]):
                    continue
                free = [g.candidate for g in rest] + [cand]
                try:
                    params, uncs = _joint(problem, free, [g.params for g in rest] + [p0], memo)
                except (ValueError, np.linalg.LinAlgError) as exc:
                    log.debug("replacement by %s failed: %s", cand.label, exc)
                    continue
                ev, _ = evaluate(problem, list(zip(free, params)), dof(free, params))
                drop = current.bic - ev.bic
                if (drop >= min_bic_drop and ev.rss_val < current.rss_val
                        and not any(at_bound(c, p) for c, p in zip(free, params))
                        and (best is None or drop > best[0])):
                    best = (drop, i, free, params, uncs, ev)
        if best is None:
            break
        drop, i, free, params, uncs, ev = best
        old, new = chosen[i].candidate, free[-1]
        log.info("replaced %s by %s (BIC drop %.1f, validation gain %.3f)", old.label, new.describe(params[-1]), drop,
                 1.0 - ev.rss_val / current.rss_val)
        banned.add(old.key)
        runners[new.key] = [(c, p) for c, p in runners.pop(old.key, ()) if c.key != new.key]
        chosen, current = [Fitted(c, p, u, 0.0, 0.0) for c, p, u in zip(free, params, uncs)], ev
    return chosen, current


def _paired(problem: Problem, chosen: list, current: Evaluation, screened: list, runners: dict, banned: set,
            min_bic_drop: float, min_gain: float, memo: dict | None) -> list[dict]:
    """Sensor effects that pass both tests with one earlier effect replaced by a runner-up of its round.

    ``screened``: (candidate, screening parameters) of the round's sensor effects that passed the screening.  Each is
    refitted jointly with the accepted effects, one of them replaced by one of its runners-up (``runners``), and
    judged against the model as accepted (``current``) as :func:`select` judges a new effect.  Returns the passing
    ones as :func:`select`'s joint results, each with ``"replaced"``: (the effect replaced, its replacement).
    """
    out = []
    for cand, p_new in screened:
        for i, f in enumerate(chosen):
            rest = chosen[:i] + chosen[i + 1:]
            for alt, p_alt in runners.get(f.candidate.key, ()):
                if alt.key in banned or alt.key == cand.key or _conflicts(alt, [g.candidate for g in rest]) \
                        or _conflicts(cand, [g.candidate for g in rest] + [alt]):
                    continue
                free = [g.candidate for g in rest] + [alt, cand]
                try:
                    params, uncs = _joint(problem, free, [g.params for g in rest] + [p_alt, p_new], memo)
                except (ValueError, np.linalg.LinAlgError) as exc:
                    log.debug("%s with %s failed: %s", cand.label, alt.label, exc)
                    continue
                ev, _ = evaluate(problem, list(zip(free, params)), dof(free, params))
                gain = 1.0 - ev.rss_val / current.rss_val if current.rss_val > 0 else 0.0
                j = {"free": free, "params": params, "uncs": uncs, "eval": ev, "bic_drop": current.bic - ev.bic,
                     "gain": gain, "pinned": any(at_bound(c, p) for c, p in zip(free, params)),
                     "replaced": (f.candidate, alt)}
                if j["bic_drop"] >= min_bic_drop and gain >= min_gain and not j["pinned"]:
                    out.append(j)
    return out


def select(problem: Problem, candidates: list[Candidate], max_effects: int = MAX_EFFECTS,
           min_gain: float = MIN_VALIDATION_GAIN, min_bic_drop: float = MIN_BIC_DROP, top_joint: int = 6,
           progress: bool = False, memo: dict | None = None, seed: tuple = ()) -> Diagnosis:
    """Greedy forward selection of named effects.

    Each round fits every remaining candidate (the accepted ones held at their values), ranks them
    by the drop of the training BIC, and accepts the best one whose fit also lowers the weighted
    validation residual energy by at least ``min_gain``; then all accepted effects are refitted
    together, an earlier one the others make unnecessary is dropped, and, once a sensor's effect is accepted, an
    earlier one is replaced by a runner-up of its round when the joint refit prefers that (:func:`_replace`,
    :func:`_paired`).  Stops when every channel's
    validation residual is at its noise level, when no candidate passes both tests, or after ``max_effects``.
    ``memo`` keeps the screening fits of a candidate next to given accepted effects, and the joint refits, for a
    later selection on the same problem.  ``seed``: (candidate, parameters) of effects accepted before the first
    round (refitted with every later one, dropped like any other when the others make them unnecessary).
    """
    t0 = time.perf_counter()
    base_eval, Y0 = evaluate(problem, [], 0)
    before = validation_metrics(problem, Y0)
    if at_noise_level(problem, Y0).all():
        return Diagnosis(problem, (), before, before, "no significant discrepancy", Y0, Y0, [], (),
                         "every channel's validation residual is at its noise level (within "
                         f"{NOISE_FACTOR}× the noise estimated from the data)", {"selection": time.perf_counter() - t0})
    chosen: list[Fitted] = []
    current, Ycur = base_eval, Y0
    if seed:
        chosen = [Fitted(c, np.asarray(p, float), np.zeros(len(p)), 0.0, 0.0) for c, p in seed]
        current, Ycur = evaluate(problem, list(seed), dof([c for c, _ in seed], [p for _, p in seed]))
    rounds = []
    banned: set = set()
    runners: dict = {}  # per accepted effect, the others that passed both tests in its round
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=max_effects * len(candidates), desc="candidates", unit="fit", leave=False)
    for _ in range(2 * max_effects):
        if len(chosen) >= max_effects:
            break
        fixed = [(f.candidate, f.params) for f in chosen]
        k_now = dof([f.candidate for f in chosen], [f.params for f in chosen])
        scores = []
        for cand in candidates:
            if bar is not None:
                bar.update()
            if cand.key in banned or _conflicts(cand, [f.candidate for f in chosen]):
                continue
            memo_key = (cand.key, tuple((c.key, params_key(q)) for c, q in fixed))
            if memo is not None and memo_key in memo:
                p, u, ev = memo[memo_key]
            else:
                try:
                    (p,), (u,), _ = fit(problem, fixed, [cand])
                except (ValueError, np.linalg.LinAlgError) as exc:
                    log.debug("candidate %s failed: %s", cand.label, exc)
                    continue
                ev, _ = evaluate(problem, fixed + [(cand, p)], k_now + len(p) + cand.extra_dof)
                if memo is not None:
                    memo[memo_key] = (p, u, ev)
            bic_drop = current.bic - ev.bic
            gain = 1.0 - ev.rss_val / current.rss_val if current.rss_val > 0 else 0.0
            scores.append({"candidate": cand, "params": p, "unc": u, "bic_drop": bic_drop, "gain": gain})
        scores.sort(key=lambda s: -s["bic_drop"])
        table = [{"label": s["candidate"].describe(s["params"]), "kind": s["candidate"].kind, "target": s["candidate"].target,
                  "bic_drop": float(s["bic_drop"]), "validation_gain": float(s["gain"]),
                  "at_bound": at_bound(s["candidate"], s["params"])} for s in scores[:15]]
        # the best few by screening (training BIC, among those that also gain on validation) are refitted
        # jointly with the effects already accepted
        joint = []
        for s in [s for s in scores if s["bic_drop"] >= min_bic_drop and s["gain"] >= min_gain][:top_joint]:
            free = [f.candidate for f in chosen] + [s["candidate"]]
            if not chosen:
                params, uncs, ev = [s["params"]], [s["unc"]], None
            else:
                params, uncs = _joint(problem, free, [f.params for f in chosen] + [s["params"]], memo)
            ev, _ = evaluate(problem, list(zip(free, params)), dof(free, params))
            gain = 1.0 - ev.rss_val / current.rss_val if current.rss_val > 0 else 0.0
            pinned = any(at_bound(c, p) for c, p in zip(free, params))
            joint.append({"free": free, "params": params, "uncs": uncs, "eval": ev, "bic_drop": current.bic - ev.bic,
                          "gain": gain, "pinned": pinned})
        ok = [j for j in joint if j["bic_drop"] >= min_bic_drop and j["gain"] >= min_gain and not j["pinned"]]
        if not ok and chosen:
            # none passes next to the effects as accepted: a sensor's effect with an earlier effect replaced by a
            # runner-up of its round (an effect accepted on the evidence the sensor's effect distorted)
            screened = [(s["candidate"], s["params"]) for s in scores if s["candidate"].stage == "out"
                        and s["bic_drop"] >= min_bic_drop and s["gain"] >= min_gain][:top_joint]
            ok = _paired(problem, chosen, current, screened, runners, banned, min_bic_drop, min_gain, memo)
        if not ok:
            rounds.append(Round(None, table))
            break
        top = max(j["bic_drop"] for j in ok)
        # parsimony: a candidate with fewer parameters within the significance margin of the best wins
        # (e.g. one h for a zone against separate h for motion and standstill that fit equally well)
        close = [j for j in ok if j["bic_drop"] >= top - min_bic_drop]
        best = min(close, key=lambda j: (len(j["params"][-1]) + j["free"][-1].extra_dof, -j["bic_drop"]))
        new = best["free"][-1]
        rounds.append(Round(new.describe(best["params"][-1]), table))
        log.info("accepted %s (BIC drop %.1f, validation gain %.3f)", new.describe(best["params"][-1]), best["bic_drop"],
                 best["gain"])
        chosen = [Fitted(c, p, u, 0.0, 0.0) for c, p, u in zip(best["free"], best["params"], best["uncs"])]
        current = best["eval"]
        if best.get("replaced") is not None:
            old, by = best["replaced"]
            log.info("with it, replaced %s by %s", old.label, by.label)
            banned.add(old.key)
            runners[by.key] = [(c, p) for c, p in runners.pop(old.key, ()) if c.key != by.key]
        alts = {j["free"][-1].key: (j["free"][-1], j["params"][-1]) for j in sorted(ok, key=lambda j: j["bic_drop"])}
        runners[new.key] = [a for k, a in alts.items() if k != new.key]
        # backward step: drop an earlier effect the others now make unnecessary
        while len(chosen) > 1:
            worst = None
            for i in range(len(chosen) - 1):
                rest = chosen[:i] + chosen[i + 1:]
                params, uncs = _joint(problem, [f.candidate for f in rest], [f.params for f in rest], memo)
                cands = [f.candidate for f in rest]
                ev, _ = evaluate(problem, list(zip(cands, params)), dof(cands, params))
                need_bic = ev.bic - current.bic
                need_gain = 1.0 - current.rss_val / ev.rss_val if ev.rss_val > 0 else 0.0
                if need_bic < min_bic_drop or need_gain < min_gain:
                    if worst is None or need_bic < worst[0]:
                        worst = (need_bic, i, [Fitted(f.candidate, p, u, 0.0, 0.0) for f, p, u in zip(rest, params, uncs)], ev)
            if worst is None:
                break
            log.info("dropped %s: not needed next to the others", chosen[worst[1]].candidate.label)
            banned.add(chosen[worst[1]].candidate.key)
            chosen, current = worst[2], worst[3]
        if len(chosen) > 1 and new.stage == "out":
            # a sensor's effect (its lag, its offset) accepted: the effects accepted before were chosen on the
            # evidence it distorted
            chosen, current = _replace(problem, chosen, current, runners, banned, min_bic_drop, memo)
        Ycur = predicted_channels(problem, [(f.candidate, f.params) for f in chosen])
        if at_noise_level(problem, Ycur).all():
            break
    # what each named effect is worth next to the others (leave-one-out, the rest refitted)
    final = []
    for i, f in enumerate(chosen):
        rest = chosen[:i] + chosen[i + 1:]
        if rest:
            params, _ = _joint(problem, [g.candidate for g in rest], [g.params for g in rest], memo)
            cands = [g.candidate for g in rest]
            ev, _ = evaluate(problem, list(zip(cands, params)), dof(cands, params))
        else:
            ev = base_eval
        final.append(Fitted(f.candidate, f.params, f.uncertainty, float(ev.bic - current.bic),
                            float(1.0 - current.rss_val / ev.rss_val) if ev.rss_val > 0 else 0.0))
    chosen = final
    if bar is not None:
        bar.close()
    after = validation_metrics(problem, Ycur)
    noise = at_noise_level(problem, Ycur)
    va = problem.split.validation
    corr = []
    if not noise.all():
        res = {c: problem.Y[va, k] - Ycur[va, k] for k, c in enumerate(problem.channels) if not noise[k]}
        sig = {n: v[va] for n, v in problem.signals.items()}
        corr = strongest_correlations(problem.time_s[va], res, sig)
    partial: tuple = ()
    if noise.all():
        verdict = "explained"
        msg = "the named effects bring every channel's validation residual to its noise level"
    else:
        verdict = "unexplained"
        left = [c for c, ok in zip(problem.channels, noise) if not ok]
        # partial candidates: only those that still improve the validation fit next to the others (one that makes
        # it worse is no improvement, whatever its training BIC says)
        chosen = [f for f in chosen if f.validation_gain > 0]
        if chosen:
            partial, chosen = tuple(chosen), []
            msg = ("a structured residual remains on " + ", ".join(left) + " after the best combination of library "
                   "effects; their names are not confirmed (listed as partial candidates), see the strongest correlations")
        else:
            msg = ("the residual is structured on " + ", ".join(left) + " but no effect in the library explains it "
                   "significantly; see the strongest correlations")
    return Diagnosis(problem, tuple(chosen), before, after, verdict, Y0, Ycur, corr, tuple(rounds), msg,
                     {"selection": time.perf_counter() - t0}, partial)


def residual_rms(problem: Problem, Yhat: np.ndarray) -> dict:
    """RMS of the residual per channel on the validation rows."""
    va = problem.split.validation
    return {c: rms(problem.Y[va, k] - Yhat[va, k]) for k, c in enumerate(problem.channels)}
