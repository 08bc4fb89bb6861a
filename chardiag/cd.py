"""The characteristic diagram (CD): a piecewise-multilinear table from inputs to one drift direction.

A CD maps a few inputs — sensor temperatures [°C] and, optionally, axis
positions [mm] — to the TCP-minus-table drift of one pose in one direction
[µm]. It is a sum of *terms*; each term is a multilinear interpolation table
on a tensor grid over a few of the active inputs:

    d(x) = Σ_terms  Σ_corners  w_corner(x) · v_term[corner]

One term over all active inputs is the classic full CD (at most
``FitOptions.max_full_dims`` inputs, so the table stays small); with more
inputs the CD is additive (one 1-D term per input), which is how 13 inputs
(8 temperatures, 5 axes) stay at a few hundred values instead of n^13.
Each input's grid has ``n_support`` evenly spaced support points over
[min, max] of the training data. Outside that box an input is clamped to it
and the result is flagged.

Evaluation is exact multilinear interpolation, vectorised for arrays
(:meth:`CharDiagram.evaluate`) and in plain Python for one point at a time
(:meth:`CharDiagram.evaluate_point`, a few µs: the compensation loop's path).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from hybridcomp.errors import HybridcompError
from hybridcomp.histogram.trace import position_column
from hybridcomp.models.layout import DIRECTIONS, TEMPERATURE_RANGE_DEGC, control_character, temperature_column

TARGETS = {"X": "dx_um", "Y": "dy_um", "Z": "dz_um"}
UNITS = ("degC", "mm")

# plausibility bounds of a CD, checked when one is built or read (chardiag/README.md, "Plausibility")
#: the largest magnitude of a grid value [µm]: 10 mm of thermal drift is a broken file, not a machine
MAX_VALUE_UM = 1e4
#: the largest magnitude of a position: a pose or a position input's grid [mm] (100 m)
MAX_POSITION_MM = 1e5
#: the most support points of one input's grid
MAX_SUPPORT_POINTS = 1000


class CDError(HybridcompError, ValueError):
    """A characteristic diagram is inconsistent or cannot be evaluated; the message names the field and value."""


@dataclass(frozen=True)
class CDInput:
    """One input of a CD.

    Attributes
    ----------
    name : sensor (``"T3"``) or axis (``"X"``) name
    unit : ``"degC"`` (temperature) or ``"mm"`` (axis position)
    active : whether the CD uses it
    min, max : trained range [unit]; the grid spans it
    n_support : support points of its grid (0 for an inactive input)
    reason : why it is active or not (range, correlation, selection)
    """

    name: str
    unit: str
    active: bool
    min: float
    max: float
    n_support: int
    reason: str = ""

    @property
    def column(self) -> str:
        """Its column in a training table: ``T3_degC``, ``x_mm``."""
        return temperature_column(self.name) if self.unit == "degC" else position_column(self.name)

    def grid(self) -> np.ndarray:
        """Support points [unit]."""
        return np.linspace(self.min, self.max, self.n_support)


@dataclass(frozen=True)
class Term:
    """A multilinear table over some active inputs.

    Attributes
    ----------
    inputs : indices into ``CharDiagram.inputs``
    values : grid values [µm], shape ``(n_support of each input)``, C order
    """

    inputs: tuple[int, ...]
    values: np.ndarray


#: positions in a pose key are rounded to this [mm] (a machine's position resolution, 1 µm): two spellings of one
#: pose (``X = 1e-12`` and ``X = 0``) are one key, so one lease and one active set
POSE_RESOLUTION_MM = 1e-3


def pose_key(pose_mm: Mapping[str, float] | tuple) -> str:
    """Canonical text key of a pose, e.g. ``"X=0,Y=-50,Z=0"``.

    Axes sorted, positions rounded to :data:`POSE_RESOLUTION_MM` and written as their shortest repr [mm]
    (``X = 1e-12`` and ``X = -0.0`` are ``X=0``).
    """
    return ",".join(f"{k}={_num(v)}" for k, v in sorted(dict(pose_mm).items()))


def _num(v: float) -> str:
    v = float(v)
    if math.isfinite(v):
        v = round(v / POSE_RESOLUTION_MM) * POSE_RESOLUTION_MM
        v = float(f"{v:.6f}") + 0.0  # (no 0.30000000000000004, no -0)
    return str(int(v)) if v.is_integer() else repr(v)


@dataclass(frozen=True, eq=False)
class CharDiagram:
    """A characteristic diagram for one pose and one direction.

    Attributes
    ----------
    machine : machine name
    machine_sha256 : hash of the machine file it was trained for
    pose_mm : axis positions of the pose ((axis, position [mm]), ...)
    direction : ``"X"``, ``"Y"`` or ``"Z"``
    inputs : every candidate input, active or not, in evaluation order
    terms : the multilinear tables (over active inputs only)
    smoothing : second-difference smoothing weight λ of the fit [-]
    ridge : relative Tikhonov weight of the fit [-]
    load_case : name of the training load case(s)
    signature : load-case signature of the training data (``histogram.signatures`` layout)
    t_reference_degC : structure-model sensor temperatures of the training load case ((sensor, [°C]), ...)
    fit : fit statistics ((name, value), ...): samples, rms_residual_um, rms_target_um, r2, max_abs_residual_um
    created : creation time (ISO 8601, UTC)
    software_version : hybridcomp version that fitted it
    """

    machine: str
    machine_sha256: str
    pose_mm: tuple[tuple[str, float], ...]
    direction: str
    inputs: tuple[CDInput, ...]
    terms: tuple[Term, ...]
    smoothing: float
    ridge: float
    load_case: str
    signature: np.ndarray
    t_reference_degC: tuple[tuple[str, float], ...]
    fit: tuple[tuple[str, float], ...] = ()
    created: str = ""
    software_version: str = ""

    def __post_init__(self):
        if self.direction not in DIRECTIONS:
            raise CDError(f"direction: {self.direction!r} is not one of {DIRECTIONS}")
        self._check_text()
        names = [i.name for i in self.inputs]
        if len(set(names)) != len(names):
            raise CDError(f"inputs: duplicate names in {names}")
        for inp in self.inputs:
            if inp.unit not in UNITS:
                raise CDError(f"input {inp.name!r}: unit {inp.unit!r} is not one of {UNITS}")
            if inp.active:
                if not (math.isfinite(inp.min) and math.isfinite(inp.max) and inp.max > inp.min):
                    raise CDError(f"input {inp.name!r}: range [{inp.min!r}, {inp.max!r}] must be finite with max > min")
                lo, hi = TEMPERATURE_RANGE_DEGC if inp.unit == "degC" else (-MAX_POSITION_MM, MAX_POSITION_MM)
                if not (lo <= inp.min and inp.max <= hi):
                    raise CDError(f"input {inp.name!r}: range [{inp.min!r}, {inp.max!r}] {inp.unit} is outside the "
                                  f"plausible [{lo:g}, {hi:g}] {inp.unit}")
                if not 2 <= inp.n_support <= MAX_SUPPORT_POINTS:
                    raise CDError(f"input {inp.name!r}: n_support {inp.n_support!r} must be from 2 to {MAX_SUPPORT_POINTS}")
        if not self.terms:
            raise CDError("terms: a CD needs at least one term")
        for k, t in enumerate(self.terms):
            if not t.inputs:
                raise CDError(f"term {k}: has no inputs")
            for j in t.inputs:
                if not 0 <= j < len(self.inputs) or not self.inputs[j].active:
                    raise CDError(f"term {k}: input index {j} is not an active input")
            if len(set(t.inputs)) != len(t.inputs):
                dup = next(j for j in t.inputs if t.inputs.count(j) > 1)
                raise CDError(f"term {k}: input {self.inputs[dup].name!r} appears twice in its inputs "
                              f"{' '.join(self.inputs[j].name for j in t.inputs)!r}")
            shape = tuple(self.inputs[j].n_support for j in t.inputs)
            if t.values.shape != shape:
                raise CDError(f"term {k}: values have shape {t.values.shape}, the grid is {shape}")
            bad = ~(np.abs(t.values) <= MAX_VALUE_UM)  # also NaN
            if bad.any():
                v = float(t.values.flat[int(np.argmax(bad.ravel()))])
                raise CDError(f"term {k}: value {v!r} µm is not finite or beyond the plausible ±{MAX_VALUE_UM:g} µm")
        for a, x in self.pose_mm:
            if not (math.isfinite(x) and abs(x) <= MAX_POSITION_MM):
                raise CDError(f"pose: axis {a!r} position {x!r} mm is not finite or beyond ±{MAX_POSITION_MM:g} mm")
        lo, hi = TEMPERATURE_RANGE_DEGC
        for sensor, T in self.t_reference_degC:
            if not lo <= T <= hi:
                raise CDError(f"referenceTemperatures: sensor {sensor!r} T_degC {T!r} is not finite or outside the "
                              f"plausible [{lo:g}, {hi:g}] °C")
        for what, v in (("smoothing", self.smoothing), ("ridge", self.ridge)):
            if not (math.isfinite(v) and v >= 0):
                raise CDError(f"regularisation: {what} {v!r} must be finite and not negative")
        sig = np.asarray(self.signature, float)
        if not np.all(np.isfinite(sig)):
            raise CDError(f"loadCase: signature value {float(sig[~np.isfinite(sig)][0])!r} is not finite")

    def _check_text(self) -> None:
        """No control character in any name or text of the CD (it would forge lines in listings and logs)."""
        texts = [("machine name", self.machine), ("machine sha256", self.machine_sha256),
                 ("loadCase name", self.load_case), ("created", self.created), ("software version", self.software_version)]
        texts += [(f"input {i.name!r} name", i.name) for i in self.inputs]
        texts += [(f"input {i.name!r} reason", i.reason) for i in self.inputs]
        texts += [("pose axis name", a) for a, _ in self.pose_mm]
        texts += [("referenceTemperatures sensor name", n) for n, _ in self.t_reference_degC]
        texts += [("fit statistic name", n) for n, _ in self.fit]
        for what, text in texts:
            if not isinstance(text, str):
                raise CDError(f"{what}: must be text, got {text!r}")
            c = control_character(text)
            if c is not None:
                raise CDError(f"{what}: {text!r} has a control character {c!r}")

    # ------------------------------------------------------------------ description

    @property
    def target(self) -> str:
        """The drift column it predicts: ``dx_um``, ``dy_um`` or ``dz_um``."""
        return TARGETS[self.direction]

    @property
    def input_names(self) -> tuple[str, ...]:
        return tuple(i.name for i in self.inputs)

    @property
    def active_inputs(self) -> tuple[CDInput, ...]:
        return tuple(i for i in self.inputs if i.active)

    @property
    def n_values(self) -> int:
        return int(sum(t.values.size for t in self.terms))

    @property
    def memory_bytes(self) -> int:
        """Memory of its tables [bytes] (float64 values)."""
        return 8 * self.n_values

    @property
    def pose_key(self) -> str:
        return pose_key(self.pose_mm)

    def t_reference(self) -> dict[str, float]:
        """Reference sensor temperatures [°C]."""
        return dict(self.t_reference_degC)

    def fit_stats(self) -> dict[str, float]:
        return dict(self.fit)

    def __eq__(self, other) -> bool:  # bit-exact, including the arrays
        if not isinstance(other, CharDiagram):
            return NotImplemented
        plain = ("machine", "machine_sha256", "pose_mm", "direction", "inputs", "smoothing", "ridge", "load_case",
                 "t_reference_degC", "fit", "created", "software_version")
        if any(getattr(self, a) != getattr(other, a) for a in plain):
            return False
        if len(self.terms) != len(other.terms) or self.signature.shape != other.signature.shape:
            return False
        if self.signature.tobytes() != other.signature.tobytes():
            return False
        return all(a.inputs == b.inputs and a.values.shape == b.values.shape and a.values.tobytes() == b.values.tobytes()
                   for a, b in zip(self.terms, other.terms))

    __hash__ = None

    # ------------------------------------------------------------------ evaluation

    def evaluate(self, X) -> tuple[np.ndarray, np.ndarray]:
        """Drift [µm] at many points.

        Parameters
        ----------
        X : (n, len(input_names)) inputs in ``input_names`` order [°C, mm]; inactive columns are ignored

        Returns
        -------
        drift_um (n,), outside (n,) bool: True where an active input was outside its trained range (clamped)
        """
        X = np.asarray(X, float)
        if X.ndim == 1:
            X = X[None, :]
        if X.ndim != 2 or X.shape[1] != len(self.inputs):
            raise CDError(f"evaluate: X must have {len(self.inputs)} columns {self.input_names}, got shape {X.shape}")
        n = X.shape[0]
        out = np.zeros(n)
        outside = np.zeros(n, bool)
        for term in self.terms:
            v, off = _term_values(self.inputs, term, X)
            outside |= off
            out += v
        return out, outside

    def evaluate_table(self, columns: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`evaluate` on named columns (``T3_degC``, ``x_mm``); only the active inputs are needed."""
        n = None
        cols = []
        for inp in self.inputs:
            if inp.active:
                if inp.column not in columns:
                    raise CDError(f"column {inp.column!r} of active input {inp.name!r} is missing "
                                  f"(have: {', '.join(sorted(columns))})")
                c = np.asarray(columns[inp.column], float)
                n = len(c)
                cols.append(c)
            else:
                cols.append(None)
        X = np.column_stack([c if c is not None else np.zeros(n) for c in cols])
        return self.evaluate(X)

    @cached_property
    def _fast(self) -> tuple[list, list]:
        """Plans for evaluate_point.

        1-D terms as (name, low, inverse spacing, last cell, values); other terms as (names, lows, inverse spacings,
        last cells, strides, flat values).
        """
        one, plan = [], []
        for term in self.terms:
            inps = [self.inputs[j] for j in term.inputs]
            if len(inps) == 1:
                i = inps[0]
                one.append((i.name, i.min, (i.n_support - 1) / (i.max - i.min), i.n_support - 1,
                            term.values.tolist()))
                continue
            shape = term.values.shape
            plan.append((
                tuple(i.name for i in inps),
                tuple(i.min for i in inps),
                tuple((i.n_support - 1) / (i.max - i.min) for i in inps),
                tuple(i.n_support - 1 for i in inps),
                tuple(int(np.prod(shape[k + 1:])) for k in range(len(shape))),
                term.values.ravel().tolist(),
            ))
        return one, plan

    def evaluate_point(self, values: Mapping[str, float]) -> tuple[float, bool]:
        """Drift [µm] at one point and whether it was outside the trained box (clamped).

        ``values`` maps input names (``"T1"`` [°C], ``"X"`` [mm]) to values; every active input must be there.
        """
        total = 0.0
        outside = False
        one, plan = self._fast
        for name, lo, a, m, vals in one:
            u = (values[name] - lo) * a
            if not u >= 0.0:
                u = 0.0
                outside = True
            elif u > m:
                u = float(m)
                outside = True
            i = int(u)
            if i == m:
                i -= 1
            v0 = vals[i]
            total += v0 + (u - i) * (vals[i + 1] - v0)
        for names, lows, inv, last, strides, flat in plan:
            base = 0
            w = [1.0]
            offs = [0]
            for name, lo, a, m, s in zip(names, lows, inv, last, strides):
                u = (values[name] - lo) * a
                if not u >= 0.0:  # also NaN: clamped to the low end and flagged
                    u = 0.0
                    outside = True
                elif u > m:
                    u = float(m)
                    outside = True
                i = int(u)
                if i == m:
                    i -= 1
                f = u - i
                base += i * s
                g = 1.0 - f
                w = [x * g for x in w] + [x * f for x in w]
                offs = offs + [o + s for o in offs]
            for x, o in zip(w, offs):
                total += x * flat[base + o]
        return total, outside


def _cells(inp: CDInput, x: np.ndarray):
    """Cell index, fraction in the cell and the outside flag of one input's values."""
    m = inp.n_support
    u = (x - inp.min) * ((m - 1) / (inp.max - inp.min))
    bad = ~(u >= 0.0) | (u > m - 1)
    if bad.any():
        u = np.clip(np.nan_to_num(u, nan=0.0), 0.0, m - 1)
    i = np.minimum(u.astype(np.intp), m - 2)
    return i, u - i, bad


def _term_values(inputs, term: Term, X):
    """A term's interpolated values (n,) and outside flags.

    Gathers the 2^d cell corners, then interpolates linearly along one input after the other.
    """
    d = len(term.inputs)
    shape = term.values.shape
    strides = [int(np.prod(shape[k + 1:])) for k in range(d)]
    n = X.shape[0]
    base = np.zeros(n, np.intp)
    fr = []
    outside = np.zeros(n, bool)
    for j, s in zip(term.inputs, strides):
        i, f, bad = _cells(inputs[j], X[:, j])
        base += i * s
        fr.append(f)
        outside |= bad
    offs = np.zeros(1, np.intp)
    for s in strides:
        offs = np.concatenate([offs, offs + s])
    V = term.values.ravel()[base[:, None] + offs[None, :]]  # corners: the last input's bit is the highest
    for f in reversed(fr):  # halve the corners along the input of the highest remaining bit
        h = V.shape[1] // 2
        V = V[:, :h] + (V[:, h:] - V[:, :h]) * f[:, None]
    return V[:, 0], outside


def _term_weights(inputs, term_inputs, X):
    """Flat corner indices (n × 2^d), multilinear weights (n × 2^d) and the outside flag (n,) of a term."""
    n = X.shape[0]
    shape = [inputs[j].n_support for j in term_inputs]
    strides = [int(np.prod(shape[k + 1:])) for k in range(len(shape))]
    outside = np.zeros(n, bool)
    idx = np.zeros((n, 1), np.intp)
    w = np.ones((n, 1))
    for j, s in zip(term_inputs, strides):
        i, f, bad = _cells(inputs[j], X[:, j])
        outside |= bad
        f = f[:, None]
        base = (i * s)[:, None]
        idx = np.hstack([idx + base, idx + base + s])
        w = np.hstack([w * (1.0 - f), w * f])
    return idx, w, outside


@dataclass(frozen=True, eq=False)
class CDSet:
    """The three CDs (X, Y, Z) that compensate one pose.

    Attributes
    ----------
    cds : {"X": CharDiagram, "Y": ..., "Z": ...}
    ids : their database ids (empty when not stored)
    """

    cds: Mapping[str, CharDiagram]
    ids: Mapping[str, int] = field(default_factory=dict)

    def __post_init__(self):
        if set(self.cds) != set(DIRECTIONS):
            raise CDError(f"a CD set needs one CD per direction {DIRECTIONS}, got {sorted(self.cds)}")
        for d, cd in self.cds.items():
            if cd.direction != d:
                raise CDError(f"CD set: the CD under {d!r} is for direction {cd.direction!r}")
        keys = {(cd.machine, cd.pose_key) for cd in self.cds.values()}
        if len(keys) != 1:
            raise CDError(f"CD set: the CDs are for different machines or poses: {sorted(keys)}")

    @property
    def machine(self) -> str:
        return self.cds["X"].machine

    @property
    def pose_key(self) -> str:
        return self.cds["X"].pose_key

    @property
    def t_reference_degC(self) -> dict[str, float]:
        """Reference temperatures [°C]: the X CD's (the three come from one load case)."""
        return self.cds["X"].t_reference()

    @property
    def signature(self) -> np.ndarray:
        return self.cds["X"].signature

    def evaluate_point(self, values: Mapping[str, float]) -> tuple[dict[str, float], bool]:
        """``({"dx_um": .., "dy_um": .., "dz_um": ..}, outside)`` at one point."""
        out = {}
        outside = False
        for d in DIRECTIONS:
            v, o = self.cds[d].evaluate_point(values)
            out[TARGETS[d]] = v
            outside |= o
        return out, outside
