"""The thermal half of the volumetric error model: its coefficients as functions of the machine's temperatures.

:mod:`hybridcomp.chardiag.kinematic` gives the TCP error at any pose from the coefficients of each linear axis' six
error functions.  Those coefficients drift as the machine warms: a volumetric calibration at one thermal state
identifies one set of them.  From calibrations at several thermal states, each with the sensor temperatures taken
during it, :func:`fit_thermal_map` fits

    c(T) = c0 + G · (T − T_ref)

with ``T_ref`` the mean of the training states' temperatures, ``c0`` the coefficients there (axes × 6 × degree + 1
[µm, µrad]) and ``G`` the gains [µm/K, µrad/K], zero for every sensor not selected.  :meth:`ThermalErrorModel.model_at`
gives the :class:`~hybridcomp.chardiag.kinematic.ErrorModel` at any later temperatures and :func:`predict_um` the TCP
error at any poses.

How it is fitted
----------------
1. **One identification per state.** Each calibration is identified with
   :func:`~hybridcomp.chardiag.kinematic.identify`.  The coefficients are brought to common column-scaled coordinates
   (the column norms of all states' measured rows together) and projected onto the coefficient space *every* state's
   plan can see (the intersection of the plans' row spaces; its orthogonal complement, spanned by every plan's null
   space, is left at zero and counted in ``rank_deficit``).  With the same plan every state (the usual case) this is
   the plan's own observable space and the projection changes nothing but the choice among the invisible
   combinations, which :func:`~hybridcomp.chardiag.kinematic.identify` makes per state; with plans that differ (other
   poses, other directions missing) each state's coefficients are the same canonical representative of its TCP
   errors, so the states are comparable, at the price of the combinations only some plans see.
2. **Components of the drift.** The per-state coefficients are whitened with the states' mean Gram matrix, so that a
   coefficient vector's squared norm is the summed squared TCP error it makes over a calibration plan [µm²] and the
   identification noise is isotropic (exactly so for one plan).  The principal components of the centred whitened
   vectors are the independent patterns in which the TCP error field drifts between states; a component is kept
   when its singular value is above the largest a matrix of pure noise would give, ``σ (√(S − 1) + √r)`` (the
   Marchenko–Pastur edge; ``σ`` the pooled residual of the identifications [µm], ``S`` states, ``r`` the observable
   dimension).  A drift driven by ``p`` thermal causes lives in ``p`` components whatever the number of coefficients.
3. **One set of inputs.** The kept components' scores over the states are regressed on the sensors' ``ΔT``; the
   inputs are the one set of at most ``max_inputs`` sensors that minimises the criterion of the total residual
   over the ``S`` training states: the components' residual sums of squares added, which (whitened) is the TCP
   error energy over a plan the set leaves, with an intercept and one gain per input as the parameters.  The drift
   field is one response and the components its coordinates: a criterion summed per component charges a shared
   input once per component, the near-noise ones too, and on a simulated job-shop day (8 calibrations, 6 kept
   components, ``python benchmarks/verification.py``) it took no input at all where the total takes T1 and T2
   (held-out largest TCP error 29 µm against 10 µm).  The criterion:
   ``bicc``, the small-sample BIC of McQuarrie (1999, *Statistics & Probability Letters* 45, 195–199),
   ``n ln(RSS/n) + n k ln n / (n − k − 2)``, infinite for ``n − k − 2 ≤ 0``, or ``bic``, ``n ln(RSS/n) + k ln n``
   (infinite for ``k ≥ n``).
   With 6 to 16 states the correction matters: at ``n = 10`` the first, second and third input cost 4.4, 6.1 and
   9.2 in BICc against 2.3 each in BIC; BICc takes no input from fewer than 5 states and at most two from 6.  The
   subsets are searched exhaustively (92 subsets for 3 of 8 sensors); above :data:`EXHAUSTIVE_LIMIT` subsets the
   search is greedy forward, which is led astray when a distractor sensor resembles the mixture of true inputs a
   component is (it is taken first, and the true ones cannot displace it).  Within one size the best subset
   is the same for both criteria and BICc's penalty grows faster with the size, so BICc never takes more inputs
   than BIC.  Sensors whose range over the training states is below ``min_range_K`` are no candidates (their gain
   would be a guess extrapolated over every later state).
4. **Back to the coefficients.** ``c0`` is the mean of the projected state coefficients and ``G`` the components'
   gains mapped back through the whitening and the scaling.

Why these choices (``python benchmarks/thermal_map_selection.py``: the planted problem of
``tests/test_thermal_map.py``, a cubic model of the demonstrator from a 5 × 5 × 5 calibration plan with 0.5 µm
noise, 2 true inputs among 8 sensors correlated with them through two common heat sources, 10 training and 5
held-out states; 40 seeds; held-out TCP error rms over a 3 × 3 × 3 grid, median (max); in how many seeds the input
set was not the planted one):

=================================================  ===================  =================
variant                                            held-out [µm]        wrong input set
=================================================  ===================  =================
one shared set, exhaustive, BICc (this module)     0.116 (0.209)        1 / 40
one shared set, greedy forward, BICc               0.116 (0.209)        6 / 40
a set per component, exhaustive, BICc              0.117 (0.209)        13 / 40
a set per component, greedy forward, BICc          0.130 (14.0)         22 / 40
one shared set, exhaustive, BIC                    0.119 (0.212)        33 / 40
a set per coefficient (72 selections), BICc        0.343 (1.32)         40 / 40
least squares on all 8 sensors                     0.648 (4.58)         —
least squares on the 2 planted sensors (oracle)    0.116 (0.209)        —
one input (``max_inputs=1``)                       10.6 (18.9)          —
no input (``max_inputs=0``)                        17.8 (28.1)          —
=================================================  ===================  =================

With 6 training states (``--states 6``) the shared exhaustive BICc set is still right in 40 of 40 (0.181 µm), the
greedy one predicts as badly as 22.5 µm in some seed, BIC takes a distractor in 39 seeds and the per-coefficient
selection predicts to 2.7 µm; with 16 states BICc takes a distractor in 3 seeds, BIC in 20, each with a gain too
small to change the held-out error (0.087 µm, as the oracle's).  A coefficient-wise selection fits 54 to 72
coefficients, many poorly determined by one calibration, as if independent: the noise of the poorly determined
ones picks up spurious inputs.  The components filter the noise before any input is chosen, and one shared set
pools every component's evidence for a sensor, which is what keeps a distractor out.  A machine whose thermal
causes each act through their own sensor still gets them all in the shared set (at most ``max_inputs`` in total),
each component with a gain on every selected sensor.

Units: positions [mm], TCP errors [µm], temperatures [°C], gains [µm/K] for translation coefficients and [µrad/K]
for rotation coefficients.  Temperatures outside the training states' range are extrapolated linearly; nothing is
clamped (the training range is stored, :meth:`ThermalErrorModel.outside`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from hybridcomp.chardiag.kinematic import (
    COMPONENTS,
    DEFAULT_DEGREE,
    Chain,
    ErrorModel,
    design_matrix,
    identify,
    tcp_error_um,
)
from hybridcomp.errors import HybridcompError
from hybridcomp.models.jsonio import check_versioned

#: the dict form's format name and version (:func:`to_dict`)
MAP_FORMAT = "hybridcomp.thermal_error_map"
MAP_VERSION = 1
#: the information criteria :func:`fit_thermal_map` takes
CRITERIA = ("bicc", "bic")
#: above this many candidate subsets per component the input search is greedy forward instead of exhaustive
EXHAUSTIVE_LIMIT = 20000
#: singular values below this fraction of the largest are zero (as :func:`~hybridcomp.chardiag.kinematic.identify`)
_RCOND = 1e-10


class ThermalMapError(HybridcompError, ValueError):
    """A thermal error map refused: the message names the field and the value."""


def _ic(rss: float, n: int, k: int, criterion: str) -> float:
    """BIC or BICc (McQuarrie 1999) of a least-squares fit: ``n`` rows, ``k`` parameters, residual sum ``rss``.

    ``bic``: ``n ln(RSS/n) + k ln n``, ``inf`` for ``k ≥ n`` (a fit through every row scores no evidence);
    ``bicc``: ``n ln(RSS/n) + n k ln n / (n − k − 2)``, ``inf`` for ``n − k − 2 ≤ 0``.  (The project's data-only
    diagnosis has the same formula; this package may not import it.)
    """
    fit = n * math.log(max(rss, 1e-300) / n)
    if criterion == "bicc":
        return fit + (n * k * math.log(n) / (n - k - 2) if n - k - 2 > 0 else math.inf)
    return fit + k * math.log(n) if n > k else math.inf


@dataclass(frozen=True, eq=False)
class Calibration:
    """One volumetric calibration at one thermal state.

    Attributes
    ----------
    poses_mm : (m × axes) the poses measured [mm]
    error_um : (m × 3) TCP-minus-table error at each pose [µm]; NaN where a direction was not measured
    sensors_degC : (sensors,) the sensor temperatures during the calibration [°C] (one value per sensor, e.g. their
        mean over it)
    time_s : when the calibration started [s] (for the record: the fit uses the temperatures, not the time)
    label : a name for messages and reports
    """

    poses_mm: np.ndarray
    error_um: np.ndarray
    sensors_degC: np.ndarray
    time_s: float = 0.0
    label: str = ""

    def __post_init__(self):
        name = f"calibration {self.label!r}" if self.label else "calibration"
        P = np.atleast_2d(np.asarray(self.poses_mm, float))
        E = np.atleast_2d(np.asarray(self.error_um, float))
        T = np.asarray(self.sensors_degC, float)
        if P.ndim != 2 or P.shape[0] == 0:
            raise ThermalMapError(f"{name}: poses_mm must be (poses × axes), got shape {np.shape(self.poses_mm)}")
        if E.shape != (P.shape[0], 3):
            raise ThermalMapError(f"{name}: error_um must be ({P.shape[0]} poses × 3), got shape {E.shape}")
        if not np.isfinite(E).any():
            raise ThermalMapError(f"{name}: error_um has no finite value")
        if T.ndim != 1 or T.size == 0:
            raise ThermalMapError(f"{name}: sensors_degC must be one value per sensor, got shape {T.shape}")
        bad = np.flatnonzero(~np.isfinite(T))
        if bad.size:
            raise ThermalMapError(f"{name}: sensors_degC[{bad[0]}] = {float(T[bad[0]])!r} is not finite")
        if not math.isfinite(float(self.time_s)):
            raise ThermalMapError(f"{name}: time_s = {self.time_s!r} is not finite")
        object.__setattr__(self, "poses_mm", P)
        object.__setattr__(self, "error_um", E)
        object.__setattr__(self, "sensors_degC", T)
        object.__setattr__(self, "time_s", float(self.time_s))
        object.__setattr__(self, "label", str(self.label))


@dataclass(frozen=True, eq=False)
class ThermalErrorModel:
    """A volumetric error model whose coefficients follow the sensor temperatures: ``c0 + gains · (T − reference)``.

    Attributes
    ----------
    chain, degree : the kinematic model (:class:`~hybridcomp.chardiag.kinematic.ErrorModel`'s)
    sensor_names : the sensors, in the order of every temperature vector
    reference_degC : (sensors,) the mean of the training states' temperatures [°C]
    coef0 : (axes × 6 × degree + 1) the coefficients at the reference [µm, µrad]
    gains : (axes × 6 × degree + 1 × sensors) [µm/K, µrad/K]; zero for every sensor not selected
    selected : the indices of the sensors the model uses (one set shared by all drift components), sorted
    criterion : ``bicc`` or ``bic``
    n_states : how many calibrations it was fitted to
    noise_um : the pooled rms residual of the per-state identifications [µm] (NaN when no plan had a spare row)
    rank_deficit : how many coefficient combinations no training plan could see (left at zero)
    components : how many drift components were above the noise
    range_degC : (sensors × 2) each sensor's min and max over the training states [°C]
    """

    chain: Chain
    degree: int
    sensor_names: tuple[str, ...]
    reference_degC: np.ndarray
    coef0: np.ndarray
    gains: np.ndarray
    selected: tuple[int, ...]
    criterion: str
    n_states: int
    noise_um: float = math.nan
    rank_deficit: int = 0
    components: int = 0
    range_degC: np.ndarray | None = None

    def __post_init__(self):
        n = len(self.sensor_names)
        shape = (len(self.chain.axes), len(COMPONENTS), int(self.degree) + 1)
        arrays = {"reference_degC": ((n,), self.reference_degC), "coef0": (shape, self.coef0),
                  "gains": ((*shape, n), self.gains)}
        if self.range_degC is not None:
            arrays["range_degC"] = ((n, 2), self.range_degC)
        for field, (want, value) in arrays.items():
            a = np.asarray(value, float)
            if a.shape != want:
                raise ThermalMapError(f"thermal map: {field} has shape {a.shape}, expected {want}")
            if not np.all(np.isfinite(a)):
                raise ThermalMapError(f"thermal map: {field} has a value that is not finite")
            object.__setattr__(self, field, a)
        if self.criterion not in CRITERIA:
            raise ThermalMapError(f"thermal map: criterion {self.criterion!r}, expected one of {CRITERIA}")
        sel = tuple(sorted(int(i) for i in self.selected))
        if any(not 0 <= i < n for i in sel) or len(set(sel)) != len(sel):
            raise ThermalMapError(f"thermal map: selected {list(self.selected)} is not a set of sensor indices "
                                  f"below {n}")
        if np.any(np.delete(self.gains, list(sel), axis=-1)):
            raise ThermalMapError("thermal map: gains of a sensor not in selected are not zero")
        object.__setattr__(self, "selected", sel)
        object.__setattr__(self, "sensor_names", tuple(str(s) for s in self.sensor_names))

    @property
    def inputs(self) -> tuple[str, ...]:
        """The names of the sensors the model uses (any component), in sensor order."""
        return tuple(self.sensor_names[i] for i in self.selected)

    def temperatures(self, sensors_degC) -> np.ndarray:
        """A temperature vector in sensor order [°C] from a vector or a mapping name → °C.

        A mapping needs only the sensors the model uses: one it does not use and the mapping does not name is taken
        at its reference.
        """
        if isinstance(sensors_degC, Mapping):
            T = self.reference_degC.copy()
            missing = [s for s in self.inputs if s not in sensors_degC]
            if missing:
                raise ThermalMapError(f"sensors_degC: no value for sensor {missing[0]!r}, which the model uses")
            unknown = [s for s in sensors_degC if s not in self.sensor_names]
            if unknown:
                raise ThermalMapError(f"sensors_degC: sensor {unknown[0]!r} is not one of {list(self.sensor_names)}")
            for s, v in sensors_degC.items():
                T[self.sensor_names.index(s)] = float(v)
        else:
            T = np.asarray(sensors_degC, float)
            if T.shape != (len(self.sensor_names),):
                raise ThermalMapError(f"sensors_degC: {T.size} values (shape {T.shape}) for "
                                      f"{len(self.sensor_names)} sensors ({', '.join(self.sensor_names)})")
        bad = np.flatnonzero(~np.isfinite(T))
        if bad.size:
            raise ThermalMapError(f"sensors_degC: {self.sensor_names[bad[0]]} = {float(T[bad[0]])!r} is not finite")
        return T

    def coef_at(self, sensors_degC) -> np.ndarray:
        """The coefficients at the temperatures (axes × 6 × degree + 1) [µm, µrad]."""
        return self.coef0 + self.gains @ (self.temperatures(sensors_degC) - self.reference_degC)

    def model_at(self, sensors_degC) -> ErrorModel:
        """The volumetric error model at the temperatures (a vector in sensor order or a mapping name → °C)."""
        return ErrorModel(self.chain, int(self.degree), self.coef_at(sensors_degC), rank_deficit=self.rank_deficit)

    def outside(self, sensors_degC) -> tuple[str, ...]:
        """The used sensors whose temperature is outside their training range (an extrapolation)."""
        if self.range_degC is None:
            return ()
        T = self.temperatures(sensors_degC)
        return tuple(s for s in self.inputs if not (self.range_degC[i := self.sensor_names.index(s), 0] <= T[i]
                                                     <= self.range_degC[i, 1]))


def predict_um(model: ThermalErrorModel, sensors_degC, poses_mm) -> np.ndarray:
    """The TCP-minus-table error (m × 3) [µm] at ``poses_mm`` (m × axes) [mm] when the sensors read ``sensors_degC``."""
    return tcp_error_um(model.model_at(sensors_degC), poses_mm)


def _check_inputs(chain, calibrations, sensor_names, degree, criterion, max_inputs, min_range_K):
    names = tuple(sensor_names) if not isinstance(sensor_names, str) else (sensor_names,)
    if not names:
        raise ThermalMapError("sensor_names: no sensor")
    for s in names:
        if not isinstance(s, str) or not s or any(ord(ch) < 32 for ch in s):
            raise ThermalMapError(f"sensor_names: {s!r} is not a name")
    if len(set(names)) != len(names):
        dup = next(s for s in names if names.count(s) > 1)
        raise ThermalMapError(f"sensor_names: {dup!r} is given twice")
    if criterion not in CRITERIA:
        raise ThermalMapError(f"criterion: {criterion!r}, expected one of {', '.join(CRITERIA)}")
    if isinstance(max_inputs, bool) or int(max_inputs) != max_inputs or max_inputs < 0:
        raise ThermalMapError(f"max_inputs: {max_inputs!r} must be a whole number ≥ 0")
    if not (math.isfinite(min_range_K) and min_range_K >= 0):
        raise ThermalMapError(f"min_range_K: {min_range_K!r} must be finite and ≥ 0")
    if isinstance(degree, bool) or int(degree) != degree or degree < 0:
        raise ThermalMapError(f"degree: {degree!r} must be a whole number ≥ 0")
    cals = list(calibrations)
    if len(cals) < 2:
        raise ThermalMapError(f"calibrations: {len(cals)} thermal state(s), at least 2 are needed")
    for i, c in enumerate(cals):
        name = f"calibration {i}" + (f" ({c.label!r})" if getattr(c, "label", "") else "")
        if not isinstance(c, Calibration):
            raise ThermalMapError(f"{name}: a {type(c).__name__}, expected a Calibration")
        if c.sensors_degC.shape != (len(names),):
            raise ThermalMapError(f"{name}: sensors_degC has {c.sensors_degC.size} values for {len(names)} sensors "
                                  f"({', '.join(names)})")
        if c.poses_mm.shape[1] != len(chain.axes):
            raise ThermalMapError(f"{name}: poses_mm has {c.poses_mm.shape[1]} columns for the axes "
                                  f"{', '.join(chain.axes)}")
    return names, cals


def _select(X: np.ndarray, Y: np.ndarray, candidates: Sequence[int], criterion: str, max_inputs: int,
            limit: int = EXHAUSTIVE_LIMIT) -> tuple[tuple[int, ...], np.ndarray]:
    """The one set of inputs the criterion selects for responses ``Y``, and their gains.

    ``X`` (rows × columns) the candidates' values and ``Y`` (rows × K) the responses, both centred; returns the
    selected columns (sorted) and the gains (columns × K, zero for a column not selected).  A set's score is the
    criterion of the responses' residual sums of squares added, with the intercept and the set's inputs as
    parameters.  Every subset of at most
    ``max_inputs`` candidates is scored when there are at most ``limit`` of them, else the search is greedy forward;
    ties go to the smaller subset.
    """
    Y = Y.reshape(len(Y), -1)
    n = Y.shape[0]

    def fit(sub):
        if not sub:
            return Y, None
        A = X[:, list(sub)]
        B, *_ = np.linalg.lstsq(A, Y, rcond=None)
        return Y - A @ B, B

    def score(sub):
        R, _ = fit(sub)
        return _ic(float(np.sum(R * R)), n, 1 + len(sub), criterion)

    best = ((), score(()))
    top = min(max_inputs, len(candidates))
    count = sum(math.comb(len(candidates), p) for p in range(1, top + 1))
    if count <= limit:
        for p in range(1, top + 1):
            sub = min(itertools.combinations(candidates, p), key=score)
            if score(sub) < best[1]:
                best = (sub, score(sub))
    else:
        cur: tuple[int, ...] = ()
        for _ in range(top):
            nxt = min((cur + (j,) for j in candidates if j not in cur), key=score)
            if score(nxt) >= best[1]:
                break
            cur, best = nxt, (nxt, score(nxt))
    sub = tuple(sorted(best[0]))
    G = np.zeros((X.shape[1], Y.shape[1]))
    if sub:
        G[list(sub)] = fit(sub)[1]
    return sub, G


def fit_thermal_map(chain: Chain, calibrations: Sequence[Calibration], sensor_names: Sequence[str],
                    degree: int = DEFAULT_DEGREE, criterion: str = "bicc", max_inputs: int = 3,
                    min_range_K: float = 0.1) -> ThermalErrorModel:
    """Fit the coefficients' dependence on the sensor temperatures to calibrations at several thermal states.

    Parameters
    ----------
    chain : the machine's kinematic chain (:func:`~hybridcomp.chardiag.kinematic.chain_of`)
    calibrations : at least 2 :class:`Calibration`, each with one temperature per sensor
    sensor_names : the sensors, in the order of the calibrations' temperature vectors
    degree : the Legendre degree of every error function
    criterion : ``bicc`` (default) or ``bic``, over the training states (module docstring)
    max_inputs : at most this many sensors per drift component (0: a model that does not follow the temperatures)
    min_range_K : a sensor that varies less than this over the training states is no candidate [K]

    Raises
    ------
    ThermalMapError
        fewer than 2 states, a temperature vector of another length or not finite, a calibration without a finite
        error, poses outside the travel or of another width, a bad name, criterion or count
    """
    names, cals = _check_inputs(chain, calibrations, sensor_names, degree, criterion, max_inputs, min_range_K)
    d = _drift(chain, cals, int(degree))
    T = np.array([c.sensors_degC for c in cals])
    candidates = [j for j in range(len(names)) if np.ptp(T[:, j]) >= max(min_range_K, 1e-12)]
    selected, g = _select(d.dT, d.scores, candidates, criterion, int(max_inputs), limit=EXHAUSTIVE_LIMIT)
    coef0, gains = _coefficients(chain, int(degree), d, d.directions.T @ g.T)
    return ThermalErrorModel(chain, int(degree), names, d.reference_degC, coef0, gains, selected, criterion, len(cals),
                             noise_um=d.noise_um, rank_deficit=d.rank_deficit, components=d.scores.shape[1],
                             range_degC=np.column_stack([T.min(axis=0), T.max(axis=0)]))


class _Drift(NamedTuple):
    """The states' coefficients reduced to their drift components (:func:`_drift`)."""

    scale: np.ndarray  # (coefficients,) the common column scaling
    from_w: np.ndarray  # (coefficients × r) whitened coordinates → scaled coefficients
    w0: np.ndarray  # (r,) the states' mean, whitened
    scores: np.ndarray  # (states × K) the kept components' scores
    directions: np.ndarray  # (K × r) the kept components' directions, whitened
    reference_degC: np.ndarray  # (sensors,) the states' mean temperatures
    dT: np.ndarray  # (states × sensors) the temperatures less the reference
    noise_um: float
    rank_deficit: int


def _drift(chain: Chain, cals: list[Calibration], degree: int) -> _Drift:
    """Steps 1 and 2 of the module docstring: every state identified, the drift components above the noise."""
    S = len(cals)
    rows, models = [], []
    for i, c in enumerate(cals):
        try:
            D = design_matrix(chain, c.poses_mm, degree)
            models.append(identify(chain, c.poses_mm, c.error_um, degree))
        except ValueError as exc:
            raise ThermalMapError(f"calibration {i}" + (f" ({c.label!r})" if c.label else "") + f": {exc}") from None
        y = c.error_um.ravel()
        ok = np.isfinite(y)
        rows.append((D[ok], y[ok], ok))
    scale = np.sqrt(sum(np.einsum("ij,ij->j", D, D) for D, _, _ in rows))
    scale = np.where(scale > 0, scale, 1.0)
    n_coef = scale.size
    Z = np.array([m.coef.ravel() * scale for m in models])  # states × coefficients, scaled
    rss, dof = 0.0, 0
    for (D, y, _), m in zip(rows, models):
        r = y - D @ m.coef.ravel()
        rss += float(r @ r)
        dof += y.size - (n_coef - m.rank_deficit)
    noise = math.sqrt(rss / dof) if dof > 0 else math.nan
    # the space every plan sees: the complement of all plans' null spaces (one SVD per distinct plan)
    nulls, gram, seen = [], np.zeros((n_coef, n_coef)), set()
    for (D, _, ok), c in zip(rows, cals):
        A = D / scale
        gram += A.T @ A / S
        key = (c.poses_mm.tobytes(), ok.tobytes())
        if key in seen:
            continue
        seen.add(key)
        _, s, Vt = np.linalg.svd(A, full_matrices=True)
        nulls.append(Vt[int(np.sum(s > _RCOND * s[0])):])
    N = np.vstack(nulls)
    if N.shape[0]:
        _, s, Vt = np.linalg.svd(N, full_matrices=True)
        dim_null = int(np.sum(s > 1e-8 * s[0]))
    else:
        Vt, dim_null = np.eye(n_coef), 0
    Q = Vt[dim_null:].T  # coefficients × r, orthonormal
    r = Q.shape[1]
    if r == 0:
        raise ThermalMapError("calibrations: their plans have no coefficient combination in common to identify")
    lam, E = np.linalg.eigh(Q.T @ gram @ Q)
    lam = np.maximum(lam, 1e-300)
    to_w = (E * np.sqrt(lam)).T @ Q.T  # r × coefficients: scaled coefficients → whitened [µm over a plan]
    from_w = Q @ (E / np.sqrt(lam))
    W = Z @ to_w.T
    w0 = W.mean(axis=0)
    U, sv, Vt = np.linalg.svd(W - w0, full_matrices=False)
    floor = _RCOND * (sv[0] if sv.size else 0.0)
    edge = noise * (math.sqrt(S - 1) + math.sqrt(r)) if math.isfinite(noise) else floor
    keep = np.flatnonzero(sv > max(edge, floor))
    T = np.array([c.sensors_degC for c in cals])
    ref = T.mean(axis=0)
    return _Drift(scale, from_w, w0, U[:, keep] * sv[keep], Vt[keep], ref, T - ref, noise, n_coef - r)


def _coefficients(chain: Chain, degree: int, d: _Drift, gains_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Step 4: ``c0`` and the gains (whitened: r × sensors) back in the coefficients' units and shape."""
    shape = (len(chain.axes), len(COMPONENTS), degree + 1)
    coef0 = (d.from_w @ d.w0) / d.scale
    gains = (d.from_w @ gains_w) / d.scale[:, None]
    return coef0.reshape(shape), gains.reshape(*shape, gains_w.shape[1])


def _chain_to_dict(chain: Chain) -> dict:
    return {"axes": list(chain.axes), "directions": list(chain.directions), "sides": list(chain.sides),
            "travel_mm": [list(t) for t in chain.travel_mm], "tip_mm": np.asarray(chain.tip_mm).tolist(),
            "tip_moves": np.asarray(chain.tip_moves).tolist(), "ref_mm": np.asarray(chain.ref_mm).tolist(),
            "ref_moves": np.asarray(chain.ref_moves).tolist()}


def _chain_from_dict(d: Mapping) -> Chain:
    n = len(d["axes"])
    chain = Chain(axes=tuple(str(a) for a in d["axes"]), directions=tuple(int(v) for v in d["directions"]),
                  sides=tuple(float(v) for v in d["sides"]),
                  travel_mm=tuple((float(lo), float(hi)) for lo, hi in d["travel_mm"]),
                  tip_mm=np.asarray(d["tip_mm"], float), tip_moves=np.asarray(d["tip_moves"], float),
                  ref_mm=np.asarray(d["ref_mm"], float), ref_moves=np.asarray(d["ref_moves"], float))
    want = {"directions": (len(chain.directions), n), "sides": (len(chain.sides), n),
            "travel_mm": (len(chain.travel_mm), n), "tip_mm": (chain.tip_mm.shape, (3,)),
            "tip_moves": (chain.tip_moves.shape, (n,)), "ref_mm": (chain.ref_mm.shape, (n, 3)),
            "ref_moves": (chain.ref_moves.shape, (n, n))}
    for field, (got, expected) in want.items():
        if got != expected:
            raise ThermalMapError(f"thermal map: chain.{field} has shape {got}, expected {expected}")
    return chain


def to_dict(model: ThermalErrorModel) -> dict:
    """The model as plain JSON types (floats round-trip exactly through JSON), versioned (:data:`MAP_VERSION`)."""
    return {"format": MAP_FORMAT, "version": MAP_VERSION, "chain": _chain_to_dict(model.chain),
            "degree": int(model.degree), "sensor_names": list(model.sensor_names),
            "reference_degC": model.reference_degC.tolist(), "coef0": model.coef0.tolist(),
            "gains": model.gains.tolist(), "selected": list(model.selected),
            "criterion": model.criterion, "n_states": int(model.n_states),
            "noise_um": None if math.isnan(model.noise_um) else float(model.noise_um),
            "rank_deficit": int(model.rank_deficit), "components": int(model.components),
            "range_degC": None if model.range_degC is None else model.range_degC.tolist()}


def from_dict(d: Mapping) -> ThermalErrorModel:
    """The model of :func:`to_dict`'s form; a :class:`ThermalMapError` naming the field on anything else."""
    check_versioned(d, MAP_FORMAT, MAP_VERSION, "thermal error map", ThermalMapError)
    try:
        noise = d.get("noise_um")
        return ThermalErrorModel(
            chain=_chain_from_dict(d["chain"]), degree=int(d["degree"]), sensor_names=tuple(d["sensor_names"]),
            reference_degC=d["reference_degC"], coef0=d["coef0"], gains=d["gains"],
            selected=tuple(d["selected"]), criterion=d["criterion"], n_states=int(d["n_states"]),
            noise_um=math.nan if noise is None else float(noise), rank_deficit=int(d.get("rank_deficit", 0)),
            components=int(d.get("components", 0)), range_degC=d.get("range_degC"))
    except ThermalMapError:
        raise
    except KeyError as exc:
        raise ThermalMapError(f"thermal error map: field {exc} missing") from None
    except (TypeError, ValueError) as exc:
        raise ThermalMapError(f"thermal error map: malformed field ({exc})") from None


__all__ = ["CRITERIA", "Calibration", "EXHAUSTIVE_LIMIT", "MAP_FORMAT", "MAP_VERSION", "ThermalErrorModel",
           "ThermalMapError", "fit_thermal_map", "from_dict", "predict_um", "to_dict"]
