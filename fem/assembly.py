"""Assembly of thermal and thermo-elastic operators on any scikit-fem P1 mesh.

All functions take per-element material arrays, so one mesh can carry many
bodies.  SI units throughout.  The elastic operators are assembled with a
vectorised element loop (einsum over the scalar basis gradients) and summed per
node pair (:func:`_block_csr`): the generic vector form takes about 75 s for 50k
hexahedral nodes, this about 2 s at 65k. Displacement DOFs are node-interleaved:
dof ``3 * node + component``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import skfem
from skfem.helpers import dot, grad
from skfem.mapping import MappingIsoparametric


def element_for(mesh: skfem.Mesh) -> skfem.Element:
    """The P1 (trilinear for hexahedra) element of a mesh."""
    if isinstance(mesh, skfem.MeshHex):
        return skfem.ElementHex1()
    if isinstance(mesh, skfem.MeshTet):
        return skfem.ElementTetP1()
    if isinstance(mesh, skfem.MeshQuad):
        return skfem.ElementQuad1()
    if isinstance(mesh, skfem.MeshTri):
        return skfem.ElementTriP1()
    if isinstance(mesh, skfem.MeshLine):
        return skfem.ElementLineP1()
    raise TypeError(f"no P1 element for {type(mesh).__name__}")


def cell_basis(mesh: skfem.Mesh) -> skfem.CellBasis:
    """P1 basis with the quadrature that is exact for its mass and stiffness forms.

    scikit-fem's default for trilinear hexahedra is 4×4×4 points; on the
    axis-aligned boxes of the tensor mesher the integrands are at most
    quadratic per direction, so 2×2×2 Gauss points are exact and 8× cheaper.
    """
    if isinstance(mesh, skfem.MeshHex):
        return skfem.Basis(mesh, element_for(mesh), intorder=3)
    return skfem.Basis(mesh, element_for(mesh))


def _per_qp(basis: skfem.CellBasis, values_e: np.ndarray) -> np.ndarray:
    v = np.asarray(values_e, dtype=float)
    if v.ndim == 0:
        v = np.full(basis.nelems, float(v))
    if v.shape != (basis.nelems,):
        raise ValueError(f"need one value per element ({basis.nelems}), got shape {v.shape}")
    return np.repeat(v[:, None], basis.X.shape[1], axis=1)


@skfem.BilinearForm
def _diffusion(u, v, w):
    return w.k * dot(grad(u), grad(v))


@skfem.BilinearForm
def _mass(u, v, w):
    return w.rc * u * v


@skfem.BilinearForm
def _facet_mass(u, v, _):
    return u * v


@skfem.LinearForm
def _facet_area(v, _):
    return v


def conductivity_matrix(basis: skfem.CellBasis, conductivity_W_mK) -> sp.csr_matrix:
    """K = ∫ k ∇φ_i·∇φ_j dV [W/K]; ``conductivity_W_mK`` per element [W/(m K)]."""
    return _diffusion.assemble(basis, k=_per_qp(basis, conductivity_W_mK)).tocsr()


def capacity_matrix(basis: skfem.CellBasis, volumetric_heat_capacity_J_m3K) -> sp.csr_matrix:
    """M = ∫ ρc φ_i φ_j dV [J/K] (consistent); ρc per element [J/(m^3 K)]."""
    return _mass.assemble(basis, rc=_per_qp(basis, volumetric_heat_capacity_J_m3K)).tocsr()


def convection_matrix(mesh: skfem.Mesh, facets: np.ndarray) -> sp.csr_matrix:
    """H = ∫_Γ φ_i φ_j dA over ``facets`` [m^2]; multiply by h [W/(m^2 K)].

    On hexahedra the facets' bilinear quadrilaterals (scikit-fem keeps a hexahedral mesh's facet corners in cyclic
    order) are integrated here (:func:`_quad_facet_mass`, the same 4 × 4 Gauss points as scikit-fem's facet basis,
    equal to it to round-off; at 80 mm the four zones' in 0.01 s instead of 0.37 s: no inverse of the cells'
    mapping, and only the facets' own node pairs are stored); other meshes through scikit-fem's facet basis.
    """
    facets = np.asarray(facets, dtype=np.int64)
    if isinstance(mesh, skfem.MeshHex):
        quads = mesh.facets[:, facets]
        return _block_csr(_pattern(quads, mesh.p.shape[1]), [[_quad_facet_mass(mesh.p[:, quads])]])
    fb = skfem.FacetBasis(mesh, element_for(mesh), facets=facets)
    return _facet_mass.assemble(fb).tocsr()


def _quad_facet_mass(x: np.ndarray, points: int = 4) -> np.ndarray:
    """∫ φ_a φ_b dA of bilinear quadrilaterals (nf × 4 × 4) with corners ``x`` (3 × 4 × nf) in cyclic order.

    The facet x(ξ, η) = Σ_k N_k x_k with N_k = (1 + ξ_k ξ)(1 + η_k η)/4 over [−1, 1]², the area element
    |∂x/∂ξ × ∂x/∂η|, Gauss–Legendre with ``points`` per direction: exact on plane facets (the integrand is of degree
    3 per direction there), scikit-fem's own rule on warped ones.
    """
    g, w = np.polynomial.legendre.leggauss(points)
    xi, eta = np.meshgrid(g, g, indexing="ij")
    xi, eta, wq = xi.ravel(), eta.ravel(), np.outer(w, w).ravel()
    sx, sy = np.array([-1.0, 1.0, 1.0, -1.0]), np.array([-1.0, -1.0, 1.0, 1.0])  # the corners, cyclic
    N = 0.25 * (1 + sx[:, None] * xi) * (1 + sy[:, None] * eta)  # (4, q)
    dxi = 0.25 * sx[:, None] * (1 + sy[:, None] * eta)
    deta = 0.25 * sy[:, None] * (1 + sx[:, None] * xi)
    t1 = np.einsum("dkf,kq->dfq", x, dxi)
    t2 = np.einsum("dkf,kq->dfq", x, deta)
    J = np.linalg.norm(np.cross(t1, t2, axis=0), axis=0)  # (nf, q)
    return np.einsum("aq,bq,fq->fab", N, N, J * wq)


def facet_area_vector(mesh: skfem.Mesh, facets: np.ndarray) -> np.ndarray:
    """∫_Γ φ_i dA over ``facets`` [m^2] (H·1); sums to the area."""
    if isinstance(mesh, skfem.MeshHex):
        return np.asarray(convection_matrix(mesh, facets).sum(axis=1)).ravel()
    fb = skfem.FacetBasis(mesh, element_for(mesh), facets=np.asarray(facets, dtype=np.int64))
    return _facet_area.assemble(fb)


def probe_matrix(basis: skfem.CellBasis, points_m: np.ndarray, cells: np.ndarray) -> sp.csr_matrix:
    """Interpolation rows: (P @ T)[j] is the field at ``points_m[:, j]`` in element ``cells[j]``."""
    pts = np.asarray(points_m, dtype=float)
    cells = np.asarray(cells, dtype=np.int64)
    if (cells < 0).any():
        raise ValueError(f"points outside the mesh: {pts[:, cells < 0].T.tolist()}")
    # a point on its cell's face may lie outside it by round-off (1e-13 m where a body's offset at a pose was added
    # in another order): the inverse mapping's Newton steps then push it out and are clipped back for ever. Each
    # point is taken into its cell's bounding box, which holds the cell, so a point inside stays where it is.
    nodes = basis.mesh.p[:, basis.mesh.t[:, cells]]
    pts = np.clip(pts, nodes.min(axis=1), nodes.max(axis=1))
    X = _reference_points(basis.mapping, pts[:, :, None], cells)
    # the P1 elements' values at a point are their reference functions' there (gbasis would also map gradients,
    # inverting the Jacobian once per function)
    phis = np.array([basis.elem.lbasis(X, k)[0] for k in range(basis.Nbfun)])
    rows = np.tile(np.arange(pts.shape[1]), basis.Nbfun)
    cols = basis.element_dofs[:, cells].ravel()
    return sp.coo_matrix((phis.reshape(basis.Nbfun, -1).ravel(), (rows, cols)), shape=(pts.shape[1], basis.N)).tocsr()


def _reference_points(mapping, x: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """The reference coordinates of the points ``x`` (dim × n × 1) in their cells (the inverse mapping).

    One Newton step from the cell's centre, as the mapping's own ``invF`` takes it, is exact where the map is
    affine (a brick, a parallelepiped, every simplex): the points it lands on are kept, and only the others (a
    distorted hexahedron) go on to ``invF``'s iteration. Half of the Jacobian inversions of ``invF``, which takes a
    second step to see that the first converged.
    """
    if not isinstance(mapping, MappingIsoparametric):  # an affine map's invF is one solve already
        return mapping.invF(x, tind=cells)
    X = np.full(x.shape, 0.5)
    X = np.clip(X + np.einsum("ijkl,jkl->ikl", mapping.invDF(X, cells), x - mapping.F(X, cells)), 0.0, 1.0)
    size = np.abs(x).max() + 1.0
    off = np.abs(mapping.F(X, cells) - x).max(axis=(0, 2)) > 1e-13 * size
    if off.any():
        X[:, off] = mapping.invF(x[:, off], tind=cells[off])
    return X


def lame(youngs_modulus_Pa, poisson_ratio):
    """Lamé parameters (λ, μ) [Pa]."""
    E, nu = np.asarray(youngs_modulus_Pa, float), np.asarray(poisson_ratio, float)
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


def _gradients(basis: skfem.CellBasis) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scalar basis gradients G[a, i, e, q], values P[a, e, q] and weights dx[e, q]."""
    G = np.array([basis.basis[a][0].grad for a in range(basis.Nbfun)])
    P = np.array([np.asarray(basis.basis[a][0]) for a in range(basis.Nbfun)])
    return G, P, basis.dx


class _Pattern(NamedTuple):
    """The node pairs an element connectivity couples, sorted: where each (element, a, b) entry sums to."""

    n_nodes: int
    pairs: np.ndarray  # sorted keys row_node · n + col_node of the distinct pairs
    where: np.ndarray  # per (element, a, b), C order, the index of its pair


def _pattern(t: np.ndarray, n_nodes: int) -> _Pattern:
    nb = t.shape[0]
    nodes = t.T.astype(np.int64)
    key = np.repeat(nodes, nb, axis=1).ravel() * n_nodes + np.tile(nodes, (1, nb)).ravel()  # (e, a, b)
    pairs, where = np.unique(key, return_inverse=True)
    return _Pattern(n_nodes, pairs, where.ravel())


def _block_csr(pattern: _Pattern, entries) -> sp.csr_matrix:
    """Sum element blocks into a global matrix, node-interleaved.

    ``entries[i][j]`` (a ``p × q`` nesting) holds, per (element, a, b), the entry (i, j) of the block that couples
    node ``t[a, e]`` (rows ``p·node + i``) with node ``t[b, e]`` (columns ``q·node + j``). The node pairs are summed
    through their sorted pattern (one ``np.unique`` over the ``elements × nodes²`` pairs, then a ``bincount`` per
    block entry) instead of sorting every scalar entry: for the elasticity matrix nine times fewer keys than a COO
    assembly, and no ``elements × 24 × 24`` array (at 65,000 nodes about 2 s instead of 8 s).
    """
    n = pattern.n_nodes
    p, q = len(entries), len(entries[0])
    data = np.empty((pattern.pairs.size, p, q))
    for i in range(p):
        for j in range(q):
            data[:, i, j] = np.bincount(pattern.where, weights=np.ravel(entries[i][j]), minlength=pattern.pairs.size)
    indptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(pattern.pairs // n, minlength=n), out=indptr[1:])
    return sp.bsr_matrix((data, pattern.pairs % n, indptr), shape=(p * n, q * n)).tocsr()


def elasticity_matrix(basis: skfem.CellBasis, youngs_modulus_Pa, poisson_ratio) -> sp.csr_matrix:
    """Linear-elastic stiffness [N/m] on a scalar P1 basis, node-interleaved DOFs.

    K[(a,i),(b,j)] = ∫ λ ∂_i φ_a ∂_j φ_b + μ (δ_ij ∇φ_a·∇φ_b + ∂_j φ_a ∂_i φ_b) dV.
    """
    return _elasticity(basis, youngs_modulus_Pa, poisson_ratio, _pattern(basis.mesh.t, basis.mesh.p.shape[1]))


def thermal_load_matrix(basis: skfem.CellBasis, youngs_modulus_Pa, poisson_ratio, expansion_1_K) -> sp.csr_matrix:
    """F_th[(a,i), b] = ∫ (3λ + 2μ) α ∂_i φ_a φ_b dV [N/K]: nodal forces of a temperature rise.

    ``K_u u = F_th ΔT`` is linear elasticity with thermal strain α ΔT I.
    """
    return _thermal_load(basis, youngs_modulus_Pa, poisson_ratio, expansion_1_K,
                         _pattern(basis.mesh.t, basis.mesh.p.shape[1]))


def elastic_operators(basis: skfem.CellBasis, youngs_modulus_Pa, poisson_ratio, expansion_1_K
                      ) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """:func:`elasticity_matrix` and :func:`thermal_load_matrix` of one basis, their node-pair pattern built once."""
    pattern = _pattern(basis.mesh.t, basis.mesh.p.shape[1])
    return (_elasticity(basis, youngs_modulus_Pa, poisson_ratio, pattern),
            _thermal_load(basis, youngs_modulus_Pa, poisson_ratio, expansion_1_K, pattern))


def _elasticity(basis: skfem.CellBasis, youngs_modulus_Pa, poisson_ratio, pattern: _Pattern) -> sp.csr_matrix:
    G, _, dx = _gradients(basis)
    lam, mu = lame(youngs_modulus_Pa, poisson_ratio)
    lam = np.broadcast_to(lam, (basis.nelems,))[:, None, None]
    mu = np.broadcast_to(mu, (basis.nelems,))[:, None, None]

    def T(i, j):  # T[e, a, b] = ∫ ∂_i φ_a ∂_j φ_b dV; ∫ ∂_j φ_a ∂_i φ_b is its transpose in (a, b)
        return np.einsum("aeq,beq,eq->eab", G[:, i], G[:, j], dx, optimize=True)

    diag = [T(i, i) for i in range(3)]
    lap = mu * (diag[0] + diag[1] + diag[2])  # μ ∇φ_a·∇φ_b
    blocks = [[None] * 3 for _ in range(3)]
    for i in range(3):
        for j in range(i, 3):
            t = diag[i] if i == j else T(i, j)
            blocks[i][j] = lam * t + mu * t.transpose(0, 2, 1)
            if i == j:
                blocks[i][i] = blocks[i][i] + lap
            else:  # the (j, i) block is the (i, j) block transposed in (a, b): K is symmetric
                blocks[j][i] = blocks[i][j].transpose(0, 2, 1)
    return _block_csr(pattern, blocks)


def _thermal_load(basis: skfem.CellBasis, youngs_modulus_Pa, poisson_ratio, expansion_1_K, pattern: _Pattern
                  ) -> sp.csr_matrix:
    G, P, dx = _gradients(basis)
    lam, mu = lame(youngs_modulus_Pa, poisson_ratio)
    beta = np.broadcast_to((3 * lam + 2 * mu) * np.asarray(expansion_1_K, float), (basis.nelems,))
    w = dx * beta[:, None]
    entries = [[np.einsum("aeq,beq,eq->eab", G[:, i], P, w, optimize=True)] for i in range(3)]  # (e, a, b)
    return _block_csr(pattern, entries)


def rigid_body_modes(points_m: np.ndarray) -> np.ndarray:
    """The six rigid-body displacement fields (3n × 6), node-interleaved [m per unit]."""
    x, y, z = points_m
    n = x.size
    B = np.zeros((3 * n, 6))
    B[0::3, 0] = 1
    B[1::3, 1] = 1
    B[2::3, 2] = 1
    B[0::3, 3], B[1::3, 3] = -y, x
    B[1::3, 4], B[2::3, 4] = -z, y
    B[0::3, 5], B[2::3, 5] = z, -x
    return B
