"""The assembled thermo-elastic model of a machine at a pose.

Thermal system in temperature rise x = T - T_ref [K]::

    M x' + (K + Σ_i h_i H_i) x = B q(t) + Σ_i h_i H_i 1 ΔT_air,i(t)

Inputs ``u = [q_1 .. q_m [W], ΔT_air,1 .. ΔT_air,z [K]]`` enter through
``input_matrix`` (n × (m + z)).  Outputs: sensor temperatures ``C x + T_ref``
and the TCP-minus-table drift ``G x`` [m], whose three rows come from adjoint
solves of the thermo-elastic problem ``K_u u = F_th x`` with statically
determinate supports.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from hybridcomp.fem import assembly
from hybridcomp.fem.mesh import MM, MachineMesh, mesh_machine
from hybridcomp.fem.operators import HasOperators, ThermalOperators
from hybridcomp.fem.solvers import solve_spd_few
from hybridcomp.fem.stepping import DEFAULT_SCHEME, TimeTolerance, integrate_inputs
from hybridcomp.models.geometry import table_point_weights
from hybridcomp.models.layout import (
    DRIFT_OUTPUTS,
    InputLayout,
    Loads,
    heat_input_name,
    layout_from_names,
    power_column,
    temperature_column,
)
from hybridcomp.models.machine import HeatSource, Machine, MachineFileError
from hybridcomp.models.simulation import SimulationResult

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ThermoElasticModel(HasOperators):
    """Assembled operators of one machine at one pose (SI units).

    Attributes
    ----------
    machine : the machine it was built from
    mesh : its mesh at the pose
    operators : the thermal system, read through the attributes of :class:`~hybridcomp.fem.operators.HasOperators`:
        ``M`` heat capacity [J/K], ``K`` conduction [W/K], ``H`` unit convection per zone (sparse, n × n each)
        [m^2], ``h_W_m2K`` [W/(m^2 K)], ``B`` heat distribution per input (n × m, columns sum to 1) [-], ``Hb``
        ``H_i 1`` per zone [m^2], ``C`` sensor interpolation rows (s × n, sparse) [-], ``input_names`` the loads
        columns in input order, ``output_names`` the sensors
    G : drift rows dx, dy, dz of TCP minus table point (the table reference, or the point under the tool) (3 × n) [m/K]
    reference_temperature_degC : the state x = 0 [°C]
    """

    machine: Machine
    mesh: MachineMesh
    operators: ThermalOperators
    G: np.ndarray
    reference_temperature_degC: float
    timings_s: dict = field(default_factory=dict, compare=False)
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    def __getstate__(self) -> dict:
        """The model without its cache: factorisations hold a solver's state, and a process rebuilds them."""
        return {**self.__dict__, "_cache": {}}

    @property
    def n(self) -> int:
        return self.M.shape[0]

    @property
    def sensor_names(self) -> tuple[str, ...]:
        """The sensors, one per row of ``C``."""
        return self.output_names

    @property
    def coords_m(self) -> np.ndarray:
        return self.mesh.mesh.p.T

    def A(self) -> sp.csr_matrix:
        """K + Σ h_i H_i [W/K]."""
        key = ("A",)
        if key not in self._cache:
            A = self.K.copy()
            for h, H in zip(self.h_W_m2K, self.H):
                A = A + h * H
            self._cache[key] = A.tocsr()
        return self._cache[key]

    def input_matrix(self) -> np.ndarray:
        """[B, h_i H_i 1] (n × (m + z))."""
        key = ("Bu",)
        if key not in self._cache:
            cols = [self.B] + [(h * (H @ np.ones(self.n)))[:, None] for h, H in zip(self.h_W_m2K, self.H)]
            self._cache[key] = np.hstack(cols)
        return self._cache[key]

    def disturbance_columns(self) -> tuple[np.ndarray, tuple[str, ...]]:
        """Heat the model does not know, as shapes for a state observer, and their names.

        Per body, 1 W spread uniformly over it and 1 W varying linearly along x, y and z across it
        (n × 4·bodies); names ``column``, ``column:x`` ...

        A source the machine file lacks (a pump, a cabinet, a misplaced loss) heats some body; its first moments
        over that body are these four shapes.  The uniform column sums to 1 W; a linear one to 0 W, its magnitudes
        to 1 W (heat rising linearly from −½ W over the lower half of the body along the direction to +½ W over the
        upper half).
        """
        key = ("disturbances",)
        if key not in self._cache:
            self._cache[key] = disturbance_heat_columns(self.machine, self.mesh)
        return self._cache[key]

    def layout(self) -> InputLayout:
        """The model's inputs and outputs.

        Its own heat inputs and zones: a model built from an extended or planted machine may have more than the
        machine it was given.
        """
        layout = self.machine.layout()
        if layout.columns == self.input_names and layout.sensors == self.sensor_names:
            return layout
        return layout_from_names(self.input_names, self.sensor_names + DRIFT_OUTPUTS, self.reference_temperature_degC,
                                 f"machine {self.machine.name!r}")

    def simulate(self, loads: Loads, initial: str | np.ndarray = "steady", *, scheme: str = DEFAULT_SCHEME,
                 theta: float | None = None, tolerance: TimeTolerance | None = None,
                 store_steps: tuple[int, ...] | None = None, progress: bool = False) -> SimulationResult:
        """Run the model on a loads time series: sensor temperatures [°C] and drift [µm] at the loads' times.

        Parameters
        ----------
        loads : heat powers [W] and air temperatures [°C] by loads column; a missing column is zero power or
            the reference temperature, an unknown one an error
        initial : ``"steady"`` (steady state of the first loads row), ``"reference"`` (zero rise) or a state [K]
        scheme : ``"trbdf2"`` (default): TR-BDF2 sub-steps refined until the time error meets ``tolerance``
            (default :data:`hybridcomp.fem.stepping.DEFAULT_TOLERANCE`; the estimate is ``result.time_error``);
            ``"theta"``: the θ-method on the loads' own times
        theta : θ of the θ-method in [0.5, 1] (default 1, backward Euler); ``scheme="theta"`` only
        tolerance : accepted time error of the outputs; ``scheme="trbdf2"`` only
        store_steps, progress : see :func:`hybridcomp.fem.stepping.integrate_inputs`
        """
        U = self.layout().inputs(loads.names, loads.values, "loads")
        return integrate_inputs(self, loads.time_s, U, scheme=scheme, theta=theta, tolerance=tolerance,
                                initial=initial, store_steps=store_steps, progress=progress)

    def with_heat_input(self, source: HeatSource) -> ThermoElasticModel:
        """The model with one more heat input after the others: ``source``'s patch on this mesh.

        A source the machine file lacks, planted in a test or a benchmark; 1 W of heat per W of input.
        """
        b, names = heat_input_matrix(dataclasses.replace(self.machine, heat_sources=(source,)), self.mesh,
                                     assembly.cell_basis(self.mesh.mesh))
        m = self.B.shape[1]
        return self.with_operators(B=np.hstack([self.B, b]), input_names=(
            *self.input_names[:m], *map(power_column, names), *self.input_names[m:]))


def _material_arrays(machine: Machine, mm: MachineMesh) -> dict[str, np.ndarray]:
    mats = [machine.materials[machine.body(b).material] for b in mm.body_names]
    get = lambda attr: np.array([getattr(m, attr) for m in mats])[mm.body_of_element]  # noqa: E731
    return {
        "k": get("conductivity_W_mK"),
        "rc": get("density_kg_m3") * get("specific_heat_J_kgK"),
        "E": get("youngs_modulus_Pa"),
        "nu": get("poisson_ratio"),
        "alpha": get("expansion_1_K"),
    }


def _sample_box(lo: np.ndarray, hi: np.ndarray, spacing: float) -> np.ndarray:
    """Cell-centred sample points of a box (3 × N), at most ``spacing`` apart."""
    axes = []
    for d in range(3):
        n = max(2, int(np.ceil((hi[d] - lo[d]) / spacing)))
        e = np.linspace(lo[d], hi[d], n + 1)
        axes.append(0.5 * (e[1:] + e[:-1]))
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    return np.vstack([X.ravel(), Y.ravel(), Z.ravel()])


def _source_patches_mm(machine: Machine, s: HeatSource, pose: dict[str, float]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Boxes [mm] at the pose over which a source's heat enters: one, or one per rail segment."""
    off = machine.body_offset_mm(s.body, pose)
    half = 0.5 * np.asarray(s.size_mm)
    c = np.asarray(s.position_mm) + off
    if s.kind == "fixed":
        return [(c - half, c + half)]
    a = machine.axis(s.axis)
    out = []
    for lo_k, hi_k in zip(a.segment_bounds_mm[:-1], a.segment_bounds_mm[1:]):
        lo, hi = c - half, c + half
        lo[a.direction] += lo_k
        hi[a.direction] += hi_k
        out.append((lo, hi))
    return out


def heat_input_matrix(machine: Machine, mm: MachineMesh, basis) -> tuple[np.ndarray, tuple[str, ...]]:
    """Distribution of 1 W of every heat input over the nodes (n × m); columns sum to 1.

    A source's heat enters uniformly over its patch (clipped to its body): the
    patch is sampled on a grid finer than the elements and each sample point's
    share is spread by the shape functions, which conserves power exactly.
    """
    R, names = heat_input_rows(machine, mm, basis)
    return np.asarray(R.T.todense()), names


def heat_input_rows(machine: Machine, mm: MachineMesh, basis) -> tuple[sp.csr_matrix, tuple[str, ...]]:
    """The transpose of :func:`heat_input_matrix`, sparse (m × n): for many patches (a search over the surface)."""
    h_mm = machine.mesh.element_size_mm
    pts_all, cells_all, col_of_pt, weight, names = [], [], [], [], []
    for s in machine.heat_sources:
        patches = _source_patches_mm(machine, s, mm.pose_mm)
        for k, (lo, hi) in enumerate(patches):
            if mm.grid_m is not None:
                b = machine.body(s.body)
                off = machine.body_offset_mm(s.body, mm.pose_mm)
                lo = np.maximum(lo, np.asarray(b.box_mm[0]) + off)
                hi = np.minimum(hi, np.asarray(b.box_mm[1]) + off)
            spacing = min(0.5 * h_mm, 0.5 * float(np.min(hi - lo)) if np.all(hi > lo) else h_mm)
            pts = _sample_box(lo, hi, max(spacing, 1e-3)) * MM if np.all(hi > lo) else np.zeros((3, 0))
            cells = mm.find_elements(pts, body=s.body) if pts.shape[1] else np.zeros(0, int)
            ok = cells >= 0
            name = heat_input_name(s.name, None if s.kind == "fixed" else k + 1)
            if not ok.any():
                raise MachineFileError(f"{machine.source}: heat source {name!r}: its patch lies outside its body {s.body!r}")
            pts_all.append(pts[:, ok])
            cells_all.append(cells[ok])
            col_of_pt.append(np.full(ok.sum(), len(names)))
            weight.append(np.full(ok.sum(), 1.0 / ok.sum()))
            names.append(name)
    if not names:
        return sp.csr_matrix((0, basis.N)), ()
    # one interpolation for every sample point of every patch (the mapping's inversion is the cost)
    P = assembly.probe_matrix(basis, np.hstack(pts_all), np.concatenate(cells_all))
    cols = np.concatenate(col_of_pt)
    S = sp.coo_matrix((np.concatenate(weight), (cols, np.arange(cols.size))), shape=(len(names), cols.size)).tocsr()
    return (S @ P).tocsr(), tuple(names)


def disturbance_heat_columns(machine: Machine, mm: MachineMesh) -> tuple[np.ndarray, tuple[str, ...]]:
    """Per body: 1 W uniformly over its volume and 1 W varying linearly along x, y, z.

    See :meth:`ThermoElasticModel.disturbance_columns`; sampled like a heat source's patch.
    """
    basis = assembly.cell_basis(mm.mesh)
    h_mm = machine.mesh.element_size_mm
    cols, names = [], []
    for b in machine.bodies:
        off = machine.body_offset_mm(b.name, mm.pose_mm)
        lo, hi = np.asarray(b.box_mm[0], float) + off, np.asarray(b.box_mm[1], float) + off
        pts = _sample_box(lo, hi, 0.5 * min(h_mm, float(np.min(hi - lo)))) * MM
        cells = mm.find_elements(pts, body=b.name)
        ok = cells >= 0
        P = assembly.probe_matrix(basis, pts[:, ok], cells[ok])
        centre, half = 0.5 * (lo + hi) * MM, 0.5 * (hi - lo) * MM
        cols.append(np.asarray(P.T @ np.full(ok.sum(), 1.0 / ok.sum())).ravel())
        names.append(b.name)
        for d, axis in enumerate("xyz"):
            w = (pts[d, ok] - centre[d]) / half[d]
            cols.append(np.asarray(P.T @ (w / np.abs(w).sum())).ravel())
            names.append(f"{b.name}:{axis}")
    return np.column_stack(cols), tuple(names)


def _point_rows(machine: Machine, mm: MachineMesh, basis, points) -> sp.csr_matrix:
    pts, cells = [], []
    for p in points:
        x = (np.asarray(p.position_mm) + machine.body_offset_mm(p.body, mm.pose_mm)) * MM
        c = mm.find_elements(x[:, None], body=p.body)[0]
        if c < 0:
            raise MachineFileError(f"{machine.source}: point {p.name!r} at {list(p.position_mm)} mm "
                                   f"is not in the mesh of body {p.body!r}")
        pts.append(x)
        cells.append(c)
    if not pts:
        return sp.csr_matrix((0, basis.N))
    return assembly.probe_matrix(basis, np.array(pts).T, np.array(cells))


def _support_dofs(machine: Machine, mm: MachineMesh) -> np.ndarray:
    """Node-interleaved displacement DOFs fixed by the supports (the node nearest each support point)."""
    fixed = []
    for s in machine.supports:
        x = (np.asarray(s.position_mm) + machine.body_offset_mm(s.body, mm.pose_mm)) * MM
        nodes_of_body = np.unique(mm.mesh.t[:, mm.body_of_element == mm.body_names.index(s.body)])
        node = nodes_of_body[np.argmin(np.sum((mm.mesh.p[:, nodes_of_body] - x[:, None]) ** 2, axis=0))]
        fixed.extend(3 * int(node) + d for d in s.directions)
    fixed = np.asarray(sorted(set(fixed)))
    if fixed.size != 6:
        raise MachineFileError(
            f"{machine.source}: field 'supports' lands {fixed.size} constraints on mesh nodes instead of 6; "
            "refine the mesh or move the supports apart"
        )
    return fixed


def solve_supported(Ku: sp.spmatrix, rhs: np.ndarray, fixed: np.ndarray, points_m: np.ndarray) -> tuple[np.ndarray, str]:
    """Solve ``Ku u = rhs`` (columns) with the ``fixed`` DOFs held at zero.

    Fixed rows and columns become identity rows, which keeps the node-interleaved
    numbering the nested-dissection ordering and AMG rely on.
    """
    keep = np.ones(Ku.shape[0])
    keep[fixed] = 0.0
    P = sp.diags(keep)
    Kc = (P @ Ku @ P + sp.diags(1.0 - keep)).tocsr()
    b = np.array(rhs, dtype=float, copy=True)
    b[fixed] = 0.0
    return solve_spd_few(Kc, b, points_m.T, block=3, near_null=assembly.rigid_body_modes(points_m))


def _adjoint_rows(machine: Machine, mm: MachineMesh, basis, mats: dict[str, np.ndarray], rows
                  ) -> tuple[np.ndarray, str]:
    """Thermal displacement rows (k × 3 × n) [m/K] of ``k`` point-interpolation rows (k × n): three adjoint solves each.

    Row ``i`` gives ``u_i = R[i] (T - T_ref)``, the displacement (x, y, z) where ``rows[i]`` interpolates.
    """
    Ku, Fth = assembly.elastic_operators(basis, mats["E"], mats["nu"], mats["alpha"])
    n, k = basis.N, rows.shape[0]
    E = np.zeros((3 * n, 3 * k))
    for i in range(k):
        r = rows[i].toarray().ravel()
        for d in range(3):
            E[d::3, 3 * i + d] = r
    lam, backend = solve_supported(Ku, E, _support_dofs(machine, mm), mm.mesh.p)
    return np.asarray(Fth.T @ lam).T.reshape(k, 3, n), backend


def drift_rows(machine: Machine, mm: MachineMesh, basis, mats: dict[str, np.ndarray]) -> tuple[np.ndarray, str]:
    """Rows g_x, g_y, g_z [m/K] with drift = G (T - T_ref), by three adjoint solves.

    The drift is TCP minus the table point of the mesh's pose (:func:`~hybridcomp.models.geometry.table_point`:
    the table reference, or the table point under the tool, continued past the table's edge by
    :func:`~hybridcomp.models.geometry.table_point_weights`).
    """
    table = table_point_weights(machine, mm.pose_mm)
    P = _point_rows(machine, mm, basis, [machine.tcp] + [p for p, _ in table])  # (1 + points) × n
    row = P[0] - sum(w * P[1 + i] for i, (_, w) in enumerate(table))
    G, backend = _adjoint_rows(machine, mm, basis, mats, row)
    return G[0], backend


def displacement_rows(model: ThermoElasticModel, points) -> np.ndarray:
    """Rows of the thermal displacement of points (points × 3 × n) [m/K]: ``u(point) = R[i] (T - T_ref)``.

    Each point (:class:`~hybridcomp.models.machine.Point`, at the reference pose on its body) is carried to the
    model's pose; three adjoint solves per point.  The drift rows ``G`` are the TCP's rows less the table point's
    (weighted as :func:`~hybridcomp.models.geometry.table_point_weights` weights them); this gives any point's,
    for diagnostics (which point's displacement an interpolation between poses misses).
    """
    machine, mm = model.machine, model.mesh
    basis = assembly.cell_basis(mm.mesh)
    return _adjoint_rows(machine, mm, basis, _material_arrays(machine, mm), _point_rows(machine, mm, basis, list(points)))[0]


def build_model(
    machine: Machine,
    pose_mm: dict[str, float] | None = None,
    element_size_mm: float | None = None,
) -> ThermoElasticModel:
    """Mesh and assemble the machine at a pose (default mid travel)."""
    if element_size_mm is not None:
        machine = dataclasses.replace(machine, mesh=dataclasses.replace(machine.mesh, element_size_mm=float(element_size_mm)))
    timings = {}
    t0 = time.perf_counter()
    mm = mesh_machine(machine, pose_mm)
    timings["mesh"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    basis = assembly.cell_basis(mm.mesh)
    mats = _material_arrays(machine, mm)
    K = assembly.conductivity_matrix(basis, mats["k"])
    M = assembly.capacity_matrix(basis, mats["rc"])
    H = tuple(assembly.convection_matrix(mm.mesh, mm.zone_facets[z.name]) for z in machine.zones)
    B, heat_names = heat_input_matrix(machine, mm, basis)
    if heat_names != machine.heat_inputs():
        raise AssertionError(f"heat inputs {heat_names} differ from the machine's {machine.heat_inputs()}")
    C = _point_rows(machine, mm, basis, machine.sensors)
    timings["assembly_thermal"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    G, backend = drift_rows(machine, mm, basis, mats)
    timings["elastic_adjoint"] = time.perf_counter() - t0
    timings["elastic_backend"] = backend
    log.info("assembled %s: %d nodes, %d heat inputs, %d zones, %s", machine.name, mm.n_nodes, len(heat_names), len(H), timings)
    n = M.shape[0]
    operators = ThermalOperators(
        M=M, K=K, H=H, h_W_m2K=np.array([z.h_W_m2K for z in machine.zones]), B=B,
        Hb=np.column_stack([Hi @ np.ones(n) for Hi in H]) if H else np.zeros((n, 0)), C=C,
        input_names=tuple(map(power_column, heat_names)) + tuple(temperature_column(z.name) for z in machine.zones),
        output_names=tuple(s.name for s in machine.sensors),
    )
    return ThermoElasticModel(machine=machine, mesh=mm, operators=operators, G=G,
                              reference_temperature_degC=machine.reference_temperature_degC, timings_s=timings)
