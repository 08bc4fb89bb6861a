"""The reduced thermal model: a small immutable object with exact time stepping.

Reduced system, in reduced coordinates ``x_r`` (the full field is ``V x_r``) [K]::

    M_r x_r' = -(K_r + Σ_i h_i H_i,r) x_r + [B_r, h_i b_i,r] u,     y = C_r x_r

``M_r`` and ``K_r + Σ h_i H_i,r`` are symmetric positive definite, so the
generalized eigen-decomposition ``(K_h,r) Φ = M_r Φ Λ`` with ``Φ^T M_r Φ = I``
decouples the modes, and the system is integrated *exactly* for inputs that
vary linearly between samples (first-order hold, the way the loads CSV is
read): per mode ``z' = -λ z + w(t)``::

    z_{k+1} = e^{-λΔt} z_k + (g0 - g1) w_k + g1 w_{k+1},
    g0 = (1 - e^{-λΔt}) / λ,   g1 = (1 - g0/Δt) / λ

Any Δt is exact; the coefficients are cached per Δt.  A uniform grid is
integrated as a per-mode linear recurrence (``scipy.signal.lfilter``), which
steps a week at 1 s in well under a second.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.linalg as la

from hybridcomp.errors import HybridcompError
from hybridcomp.fem.operators import HasOperators, ThermalOperators
from hybridcomp.models import jsonio
from hybridcomp.models.layout import (
    InputLayout,
    Loads,
    LoadsColumnError,
    OutputLayout,
    OutputLayoutError,
    layout_from_names,
    output_layout,
)
from hybridcomp.models.simulation import SimulationResult, initial_state
from hybridcomp.models.toml import open_regular_file, read_text

log = logging.getLogger(__name__)

HOLDS = ("linear", "step")
SCHEMES = ("exact",)
FORMAT = "hybridcomp-rom"
_ONE = np.ones(1)
_STEPWISE_MAX_PER_MODE = 10  # runs of at most 10 steps per mode: step by step (crossover measured at 13, order 150)
FORMAT_VERSION = 1


class RomFileError(HybridcompError, ValueError):
    """A ROM file is unreadable, of another version, or does not belong to the given machine."""


class RomInputError(HybridcompError, ValueError):
    """Inputs, states or step sizes do not fit the reduced model."""


@dataclass(frozen=True)
class Discretization:
    """Exact first-order-hold discretisation for one step size, in modal coordinates.

    Attributes
    ----------
    dt_s : step [s]
    a : e^{-λΔt} per mode (r,) [-]
    P0, P1 : weights of the inputs at the start and end of the step (r × nu)
    Ad, Bd0, Bd1 : the same step in reduced coordinates: x1 = Ad x0 + Bd0 u0 + Bd1 u1
    """

    dt_s: float
    a: np.ndarray
    P0: np.ndarray
    P1: np.ndarray
    Ad: np.ndarray
    Bd0: np.ndarray
    Bd1: np.ndarray


@dataclass(frozen=True)
class RomState:
    """A saved state of a reduced model (for the monitor's persistence).

    Attributes
    ----------
    time_s : time of the state [s]
    x : reduced coordinates (r,) [K]
    rom_id : :attr:`ReducedModel.rom_id` of the model it belongs to
    """

    time_s: float
    x: np.ndarray
    rom_id: str

    def to_json(self) -> str:
        return jsonio.dumps({"time_s": self.time_s, "x": self.x.tolist(), "rom_id": self.rom_id})

    @staticmethod
    def from_json(text: str) -> RomState:
        d = json.loads(text)
        return RomState(float(d["time_s"]), np.asarray(d["x"], float), str(d["rom_id"]))


def _g_coefficients(lam: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step coefficients a = e^{-λΔt}, g0 = ∫_0^Δt e^{-λ(Δt-τ)} dτ, g1 = ∫_0^Δt e^{-λ(Δt-τ)} τ/Δt dτ, stable for small λΔt."""
    x = lam * dt
    # e^{-x} below 1e-22 is flushed to zero: its contribution is below round-off, and products with
    # subnormal numbers (e^{-x} < 2e-308 and what it multiplies) are ~100x slower on x86
    a = np.where(x > 50.0, 0.0, np.exp(-np.minimum(x, 50.0)))
    small = x < 1e-3
    xs = np.where(small, 1.0, x)
    g0 = np.where(small, dt * (1 - x / 2 + x**2 / 6 - x**3 / 24), -np.expm1(-xs) / np.where(small, 1.0, lam))
    g1 = np.where(small, dt * (0.5 - x / 6 + x**2 / 24 - x**3 / 120), (1 - g0 / dt) / np.where(small, 1.0, lam))
    return a, g0, g1


@dataclass(frozen=True)
class ReducedModel(HasOperators):
    """A reduced thermal model with convection affine in ``h`` (SI units).

    Attributes
    ----------
    operators : the reduced system, read through the attributes of :class:`~hybridcomp.fem.operators.HasOperators`:
        ``M`` reduced capacity (r × r) [J/K], ``K`` reduced conduction (r × r) [W/K], ``H`` reduced unit
        convection per zone (z × r × r) [m^2], ``h_W_m2K`` heat-transfer coefficient per zone (z,) [W/(m^2 K)],
        ``B`` reduced heat input columns (r × m) [-], ``Hb`` reduced ``H_i 1`` per zone (r × z) [m^2], ``C``
        reduced output rows (q × r; outputs are temperature rises [K] or drifts [m]), ``input_names`` the loads
        column per input (``*_W`` powers, ``*_degC`` zone air), ``output_names`` the name per output
    V : basis (n × r) for reconstructing the full field, or None
    D : reduced disturbance heat columns (r × d): heat the model does not know, as shapes for a state observer
        (:meth:`hybridcomp.fem.model.ThermoElasticModel.disturbance_columns`), [-] per W; None: none
    disturbance_names : name per column of ``D``
    pose_transfer : a pose-aware model's state transfer between its support poses' blocks (R × R over the first R
        states, R the blocks' total order; block (k, j) maps block j's state to the field it stands for, carried
        onto support pose k's mesh and projected there; on the diagonal a block's own round trip), for the pose
        history (:func:`hybridcomp.rom.poses.blend_history`); None: none
    meta : provenance (machine, hash, pose, expansion points, achieved errors)
    """

    operators: ThermalOperators
    V: np.ndarray | None = None
    D: np.ndarray | None = None
    disturbance_names: tuple[str, ...] = ()
    pose_transfer: np.ndarray | None = None
    meta: dict = field(default_factory=dict, compare=False)
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self):
        r = self.M.shape[0]
        if np.ndim(self.H) != 3:
            raise RomInputError(f"reduced model field 'H' has shape {np.shape(self.H)}, expected (zones, {r}, {r})")
        for name, got, want in self.operators.shape_problems():
            raise RomInputError(f"reduced model field {name!r} has shape {got}, expected {want}")
        if self.V is not None and self.V.shape[1] != r:
            raise RomInputError(f"reduced model field 'V' has {self.V.shape[1]} columns, expected {r}")
        d = 0 if self.D is None else self.D.shape[1]
        if (self.D is not None and self.D.shape[0] != r) or len(self.disturbance_names) != d:
            raise RomInputError(f"reduced model field 'D' has shape {None if self.D is None else self.D.shape} for "
                                f"{len(self.disturbance_names)} disturbance names and order {r}")
        T = self.pose_transfer
        if T is not None and (np.ndim(T) != 2 or T.shape[0] != T.shape[1] or T.shape[0] > r):
            raise RomInputError(f"reduced model field 'pose_transfer' has shape {np.shape(T)}, expected (R, R) with "
                                f"R at most the order {r}")

    # -- sizes and variants ----------------------------------------------------------------------
    @property
    def order(self) -> int:
        return self.M.shape[0]

    @property
    def n_inputs(self) -> int:
        return len(self.input_names)

    @property
    def rom_id(self) -> str:
        """Hash of the reduced operators (identifies the model a saved state belongs to)."""
        if "rom_id" not in self._cache:
            hsh = hashlib.sha256()
            for a in (self.M, self.K, self.H, self.B, self.Hb, self.C):
                hsh.update(np.ascontiguousarray(a, dtype=float).tobytes())
            if self.pose_transfer is not None:  # (a model without one keeps its identity)
                hsh.update(np.ascontiguousarray(self.pose_transfer, dtype=float).tobytes())
            self._cache["rom_id"] = hsh.hexdigest()[:16]
        return self._cache["rom_id"]

    # -- operators -------------------------------------------------------------------------------
    def stiffness(self) -> np.ndarray:
        """K_r + Σ h_i H_i,r [W/K]."""
        return self.K + np.einsum("i,ijk->jk", self.h_W_m2K, self.H)

    def input_matrix(self) -> np.ndarray:
        """[B_r, h_i b_i,r] (r × nu)."""
        return np.hstack([self.B, self.Hb * self.h_W_m2K[None, :]])

    def _modes(self) -> tuple[np.ndarray, np.ndarray]:
        if "modes" not in self._cache:
            lam, Phi = la.eigh(self.stiffness(), self.M)
            if lam[0] <= 0:
                raise RomInputError(f"reduced model is not stable: smallest decay rate {lam[0]:.3g} 1/s ≤ 0")
            self._cache["modes"] = (lam, Phi)
        return self._cache["modes"]

    def poles(self) -> np.ndarray:
        """Poles of the reduced system, ascending magnitude [1/s] (all negative)."""
        return -self._modes()[0]

    def transfer(self, s: float) -> np.ndarray:
        """C_r (s M_r + K_h,r)^-1 [B_r, h_i b_i,r] at a real ``s`` [1/s]."""
        return self.C @ la.solve(s * self.M + self.stiffness(), self.input_matrix(), assume_a="pos")

    # -- states ----------------------------------------------------------------------------------
    def _check_u(self, u, name="u") -> np.ndarray:
        u = np.asarray(u, float)
        if u.shape != (self.n_inputs,):
            raise RomInputError(f"{name} must have {self.n_inputs} entries ({', '.join(self.input_names)}), got shape {u.shape}")
        return u

    def steady_state(self, u: np.ndarray) -> np.ndarray:
        """Reduced state at steady state for constant inputs ``u`` (powers [W], air rises [K])."""
        u = self._check_u(u)
        return la.solve(self.stiffness(), self.input_matrix() @ u, assume_a="pos")

    def outputs(self, x: np.ndarray) -> np.ndarray:
        """Outputs ``C_r x`` (temperature rises [K], drifts [m])."""
        return self.C @ np.asarray(x, float)

    def field(self, x: np.ndarray) -> np.ndarray:
        """Full temperature-rise field ``V x`` [K] (needs the basis)."""
        if self.V is None:
            raise RomInputError("this reduced model was saved without its basis V; reduce again with the basis kept")
        return self.V @ np.asarray(x, float)

    def state(self, x: np.ndarray, time_s: float = 0.0) -> RomState:
        """Wrap a reduced state for saving."""
        x = np.asarray(x, float)
        if x.shape != (self.order,):
            raise RomInputError(f"state must have {self.order} entries, got shape {x.shape}")
        return RomState(float(time_s), x.copy(), self.rom_id)

    def restore(self, state: RomState) -> np.ndarray:
        """The reduced coordinates of a saved state; an error if it belongs to another model."""
        if state.rom_id != self.rom_id or state.x.shape != (self.order,):
            raise RomInputError(
                f"state belongs to reduced model {state.rom_id} of order {state.x.size}, "
                f"not to {self.rom_id} of order {self.order}"
            )
        return state.x.copy()

    # -- time stepping ---------------------------------------------------------------------------
    def discretize(self, dt_s: float) -> Discretization:
        """Exact first-order-hold step of ``dt_s`` [s], cached per step size."""
        dt = float(dt_s)
        if not (np.isfinite(dt) and dt > 0):
            raise RomInputError(f"step size must be positive, got {dt_s} s")
        key = ("dt", round(dt, 12))
        if key not in self._cache:
            lam, Phi = self._modes()
            a, g0, g1 = _g_coefficients(lam, dt)
            W = Phi.T @ self.input_matrix()  # modal input matrix (r × nu)
            P0 = (g0 - g1)[:, None] * W
            P1 = g1[:, None] * W
            PhiTM = Phi.T @ self.M
            self._cache[key] = Discretization(dt, a, P0, P1, Phi @ (a[:, None] * PhiTM), Phi @ P0, Phi @ P1)
        return self._cache[key]

    def step(self, x: np.ndarray, u0: np.ndarray, u1: np.ndarray, dt_s: float) -> np.ndarray:
        """One exact step of ``dt_s`` [s] from state ``x`` with inputs ``u0`` at its start and ``u1`` at its end."""
        d = self.discretize(dt_s)
        return d.Ad @ x + d.Bd0 @ u0 + d.Bd1 @ u1

    def layout(self) -> InputLayout:
        """The input layout of a machine ROM: its input and output names and the machine's reference temperature.

        Raises
        ------
        RomInputError
            not a machine ROM (an external system's inputs and outputs are raw model quantities)
        """
        t_ref = self.meta.get("reference_temperature_degC")
        if t_ref is None:
            raise RomInputError("not a machine ROM: its metadata has no 'reference_temperature_degC' (an external "
                                "system's inputs and outputs are raw model quantities)")
        try:
            return layout_from_names(self.input_names, self.output_names, float(t_ref), "the reduced model")
        except LoadsColumnError as exc:
            raise RomInputError(f"not a machine ROM: {exc}") from None

    def output_layout(self) -> OutputLayout:
        """The outputs by typed group (:class:`~hybridcomp.models.layout.OutputLayout`).

        Sensors, drift at the model's pose and, as the model has them, drift per support pose, the drives'
        positioning errors, per-body drift; built from the output names and ``meta`` (``poses``, ``feedback``),
        as every saved model carries them.

        Raises
        ------
        RomInputError
            the names and metadata do not form the groups (an external system's outputs ``y1`` … have none)
        """
        try:
            return output_layout(self.output_names, self.meta, "the reduced model")
        except OutputLayoutError as exc:
            raise RomInputError(str(exc)) from None

    def simulate(self, loads: Loads, initial: str | np.ndarray = "steady", *, scheme: str = "exact",
                 hold: str = "linear") -> SimulationResult:
        """Run a machine ROM on a loads time series: sensor temperatures [°C] and drift [µm].

        The signature of :meth:`hybridcomp.fem.model.ThermoElasticModel.simulate`; the reduced model's one scheme
        is exact for inputs that hold as ``hold`` says, at any step size (the module docstring).

        Parameters
        ----------
        loads : heat powers [W] and air temperatures [°C] by loads column; a missing column is zero power or
            the reference temperature, an unknown one an error
        initial : ``"steady"`` (steady state of the first loads row), ``"reference"`` (zero rise) or a reduced state
        scheme : ``"exact"``, the only one (the FE model's ``"trbdf2"`` and ``"theta"`` approximate what this
            scheme integrates exactly)
        hold : how the inputs vary between samples, see :meth:`integrate`
        """
        if scheme not in SCHEMES:
            raise RomInputError(f"unknown time scheme {scheme!r} of a reduced model (schemes: {', '.join(SCHEMES)})")
        layout, outputs = self.layout(), self.output_layout()
        U = layout.inputs(loads.names, loads.values, "loads")
        Y, x = self.integrate(loads.time_s, U, initial, hold=hold)
        return SimulationResult(np.asarray(loads.time_s, float),
                                outputs.take(Y, "sensors") + layout.reference_temperature_degC,
                                outputs.take(Y, "drift") * 1e6, sensor_names=outputs.sensors, final_state=x)

    def integrate(self, time_s: np.ndarray, inputs: np.ndarray, initial: str | np.ndarray = "steady",
                  chunk: int = 65536, hold: str = "linear") -> tuple[np.ndarray, np.ndarray]:
        """Integrate over ``time_s`` with ``inputs`` (nt × nu), exactly.

        Parameters
        ----------
        time_s : strictly increasing times [s]
        inputs : heat powers [W] and air temperature rises [K] in ``input_names`` order (nt × nu)
        initial : ``"steady"`` (steady state of the first inputs), ``"reference"`` (zero) or a reduced state
        chunk : steps per vectorised block (bounds memory)
        hold : ``"linear"`` (first-order hold: inputs linear between samples) or ``"step"`` (row k held over
            the interval that ends at sample k: the reading of the histogram's loads, mean power per increment)

        Returns
        -------
        outputs (nt × q) in output units and the final reduced state
        """
        if hold not in HOLDS:
            raise RomInputError(f"hold must be one of {HOLDS}, got {hold!r}")
        t = np.asarray(time_s, float)
        U = np.asarray(inputs, float)
        if t.ndim != 1 or t.size < 1:
            raise RomInputError("time_s must be a non-empty vector")
        if U.shape != (t.size, self.n_inputs):
            raise RomInputError(f"inputs must be ({t.size}, {self.n_inputs}) for inputs {self.input_names}, got {U.shape}")
        dts = np.diff(t)
        if np.any(~(dts > 0)):
            k = int(np.flatnonzero(~(dts > 0))[0]) + 1
            raise RomInputError(f"step sizes must be positive: step {k} goes from {t[k - 1]} s to {t[k]} s")
        try:
            x = initial_state(initial, self.order, lambda: self.steady_state(U[0]))
        except ValueError as exc:
            raise RomInputError(str(exc)) from None
        # with a step hold, the input at the start of each interval is the one at its end: U0[k - 1] = U[k]
        U0 = U if hold == "linear" else np.vstack([U[1:], U[-1:]])
        Phi = self._modes()[1]
        if "Cz" not in self._cache:  # (a path with many moves integrates many short segments)
            self._cache["Cz"] = self.C @ Phi
        Cz = self._cache["Cz"]
        z = Phi.T @ (self.M @ x)
        Y = np.empty((t.size, self.C.shape[0]))
        Y[0] = Cz @ z
        if t.size == 1:
            return Y, x
        uniform = np.allclose(dts, dts[0], rtol=1e-9, atol=0.0)
        if not uniform:
            for k in range(1, t.size):
                d = self.discretize(dts[k - 1])
                z = d.a * z + d.P0 @ U0[k - 1] + d.P1 @ U[k]
                Y[k] = Cz @ z
            return Y, Phi @ z
        d = self.discretize(dts[0])
        if t.size - 1 <= _STEPWISE_MAX_PER_MODE * self.order:
            # a short run (a segment between two switches of h, a 15 min window): one vectorised step over all
            # modes per sample costs less than one filter call per mode
            F = U0[:-1] @ d.P0.T + U[1:] @ d.P1.T  # forcing per step and mode (L × r)
            a = d.a
            for k in range(F.shape[0]):
                z = a * z + F[k]
                F[k] = z
            Y[1:] = F @ Cz.T
            return Y, Phi @ z
        from scipy.signal import lfilter  # here: scipy.signal takes 0.9 s to import, a daemon's start-up

        for k0 in range(0, t.size - 1, chunk):
            k1 = min(k0 + chunk, t.size - 1)
            Z = d.P0 @ U0[k0:k1].T + d.P1 @ U[k0 + 1:k1 + 1].T  # forcing per mode and step (r × L), rows contiguous
            for j in range(self.order):
                Z[j], _ = lfilter(_ONE, [1.0, -d.a[j]], Z[j], zi=[d.a[j] * z[j]])
            z = Z[:, -1].copy()
            Y[k0 + 1:k1 + 1] = (Cz @ Z).T
        return Y, Phi @ z


# -- save / load ---------------------------------------------------------------------------------
def save_rom(path: str | Path, rom: ReducedModel) -> Path:
    """Write a reduced model as ``.npz`` (arrays) with its JSON metadata inside (no pickles)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {**rom.meta, "format": FORMAT, "format_version": FORMAT_VERSION, "input_names": list(rom.input_names),
            "output_names": list(rom.output_names), "order": rom.order, "rom_id": rom.rom_id}
    if rom.D is not None:
        meta["disturbance_names"] = list(rom.disturbance_names)
    arrays = {"M": rom.M, "K": rom.K, "H": rom.H, "h_W_m2K": rom.h_W_m2K, "B": rom.B, "Hb": rom.Hb, "C": rom.C,
              "meta_json": np.array(jsonio.dumps(meta))}
    if rom.V is not None:
        arrays["V"] = rom.V
    if rom.D is not None:
        arrays["D"] = rom.D
    if rom.pose_transfer is not None:
        arrays["pose_transfer"] = rom.pose_transfer
    from hybridcomp.safeio import atomic_path

    with atomic_path(path) as tmp, tmp.open("wb") as fh:  # a temporary file renamed over path: never half a model
        np.savez_compressed(fh, **arrays)
    return path


def read_npz(path: Path, error: type[Exception], what: str = "reduced model") -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` file ``path`` (a regular file, no pickles); ``error`` names the file on failure."""
    try:
        with open_regular_file(path, error, what) as fh, np.load(fh, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except error:
        raise
    except (OSError, ValueError) as exc:
        raise error(f"{path}: cannot read {what}: {exc}") from None


def load_rom(path: str | Path, machine=None) -> ReducedModel:
    """Read a reduced model; with ``machine`` (a loaded :class:`Machine`) check it was reduced from that very file.

    Raises
    ------
    RomFileError
        unreadable file, another format version, or a machine file whose hash differs
    """
    path = Path(path)
    data = read_npz(path, RomFileError)
    if "meta_json" not in data:
        raise RomFileError(f"{path}: not a hybridcomp reduced model (no 'meta_json' entry)")
    meta = json.loads(str(data["meta_json"]))
    if meta.get("format") == "hybridcomp-external-lti":
        raise RomFileError(f"{path}: field 'format' is 'hybridcomp-external-lti': the reduced model of an exported "
                           "system (reduce --matrices), a general state-space model with no machine inputs; read it "
                           "with hybridcomp.rom.external.load_external")
    if meta.get("format") != FORMAT or meta.get("format_version") != FORMAT_VERSION:
        raise RomFileError(
            f"{path}: field 'format_version' is {meta.get('format')!r} version {meta.get('format_version')!r}; "
            f"this hybridcomp reads {FORMAT!r} version {FORMAT_VERSION}"
        )
    missing = [k for k in ("M", "K", "H", "h_W_m2K", "B", "Hb", "C") if k not in data]
    if missing:
        raise RomFileError(f"{path}: array {missing[0]!r} is missing")
    if machine is not None:
        want = (meta.get("machine") or {}).get("sha256")
        if want != machine.sha256:
            raise RomFileError(
                f"{path}: field 'machine.sha256' is {want!r} (reduced from {(meta.get('machine') or {}).get('file')!r}), "
                f"but machine file {machine.source} has sha256 {machine.sha256!r}; reduce it again"
            )
    rom = ReducedModel(
        ThermalOperators(M=data["M"], K=data["K"], H=data["H"], h_W_m2K=data["h_W_m2K"], B=data["B"], Hb=data["Hb"],
                         C=data["C"], input_names=tuple(meta["input_names"]), output_names=tuple(meta["output_names"])),
        V=data.get("V"),
        D=data.get("D"), disturbance_names=tuple(meta.get("disturbance_names", ())) if "D" in data else (),
        pose_transfer=data.get("pose_transfer"), meta=meta,
    )
    if rom.rom_id != meta.get("rom_id"):
        raise RomFileError(f"{path}: field 'rom_id' is {meta.get('rom_id')!r} but the arrays hash to {rom.rom_id!r}: "
                           "file corrupted")
    return rom


def save_state(path: str | Path, state: RomState) -> Path:
    """Write a reduced state as JSON; returns the path."""
    path = Path(path)
    path.write_text(state.to_json())
    return path


def load_state(path: str | Path) -> RomState:
    """Read a reduced state written by :func:`save_state`."""
    text = read_text(path, RomFileError, "reduced state")
    try:
        return RomState.from_json(text)
    except (ValueError, KeyError) as exc:
        raise RomFileError(f"{path}: cannot read reduced state: {exc}") from None
