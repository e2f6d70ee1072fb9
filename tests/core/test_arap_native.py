"""The shape-preserving pass's compiled half (csrc/affine_solve.c through affine_deformers/accel/arap.py):
the sparse factorisation against scipy on meshes and on arbitrary SPD patterns, its fill against a
symbolic elimination done here, every ordering; the frame against core's numpy solver; exactness;
one factorisation per bind, results independent of the frames before; the handle's lifetime; the
numpy fallback."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from affine_deformers import accel
from affine_deformers.accel import arap as carap
from affine_deformers.accel import native
from affine_deformers.core import aff3, arap, deform
from affine_deformers.core.surface import Csr
from tests.core.arap_rigs import bend_rig, box_bar, rig_weights, twist_rig
from tests.core.conftest import random_affine


@pytest.fixture(scope="module")
def kernel() -> native.Kernel:
    try:
        return native.load()
    except native.KernelUnavailableError as exc:
        pytest.skip(f"the compiled kernel is not built (make native): {exc}")


LOCK = threading.RLock()


def _system_of(A: sp.spmatrix) -> arap.ArapSystem:
    """A stand-in ArapSystem holding an arbitrary matrix (the factor reads only `.matrix` and `.n`)."""
    A = sp.csr_matrix(A)
    A.sort_indices()
    n = A.shape[0]
    el = arap.Elements(np.zeros((0, 3), np.int64), np.zeros((0, 3, 3)), np.zeros(0), np.zeros((0, 3)),
                       np.zeros((0, 3)), n)
    csr = Csr(A.indptr.astype(np.int64), A.indices.astype(np.int64), A.data.astype(np.float64), A.shape)
    return arap.ArapSystem(el, np.zeros(n), csr, 0)


def _random_spd(rng: np.random.Generator, n: int, density: float) -> sp.csr_matrix:
    """BᵀB + I for a random sparse B: an SPD matrix with positive and negative off-diagonals."""
    B = sp.random(n, n, density=density, random_state=np.random.RandomState(int(rng.integers(1 << 31))))
    return (B.T @ B + sp.identity(n)).tocsr()


def _rig(n_side: int, rig, strength: float = arap.ANCHOR_STRENGTH) -> SimpleNamespace:
    P, T = box_bar(n_side)
    el = arap.triangle_elements(P, T)
    idx, val = rig_weights(P, rig)
    eidx, evals = rig_weights(el.centroids, rig)
    system = arap.bind_system(el, arap.anchor_weights(el, idx, val, strength=strength))
    return SimpleNamespace(P=P, T=T, el=el, system=system, idx=idx, val=val, eidx=eidx, evals=evals,
                           field=deform.deform_points_params(P, rig.params, idx, val),
                           motions=deform.vertex_motions(rig.params, eidx, evals))


def _symbolic_fill(A: sp.spmatrix, perm: np.ndarray) -> int:
    """nnz(L) (diagonal included) of the permuted pattern by explicit elimination on sets."""
    B = sp.csr_matrix(A)[perm][:, perm]
    n = B.shape[0]
    adj = [set(B.indices[B.indptr[i]:B.indptr[i + 1]].tolist()) - {i} for i in range(n)]
    total = 0
    for k in range(n):
        later = sorted(j for j in adj[k] if j > k)
        total += 1 + len(later)
        for a in later:
            adj[a].update(later)
            adj[a].discard(a)
    return total


# ------------------------------------------------------------------------------------ factorisation


@pytest.mark.parametrize("ordering", ["NESTED_DISSECTION", "NATURAL", "RANDOM"])
@pytest.mark.parametrize("case", ["mesh", "random", "disconnected"])
def test_the_factor_solves_like_scipy_and_fills_as_eliminated(kernel: native.Kernel, ordering: str,
                                                              case: str) -> None:
    rng = np.random.default_rng(11)
    if case == "mesh":
        P, T = box_bar(5)
        el = arap.triangle_elements(P + rng.normal(scale=0.03, size=P.shape), T)
        A = _as_scipy(arap.bind_system(el, rng.random(len(P)) * 1e-3).matrix)
    elif case == "random":
        A = _random_spd(rng, 300, 0.01)
    else:  # blocks with no coupling, and isolated vertices
        A = sp.block_diag([_random_spd(rng, 40, 0.05), sp.identity(3), _random_spd(rng, 70, 0.03)]).tocsr()
    n = A.shape[0]
    order = rng.permutation(n) if ordering == "RANDOM" else ordering
    solver = carap.CompiledArapSolver.bind(kernel, LOCK, _system_of(A), order)
    assert np.array_equal(np.sort(solver.perm), np.arange(n))
    assert solver.stats["nnz_factor"] == _symbolic_fill(A, solver.perm)
    assert solver.stats["stored"] >= solver.stats["nnz_factor"]
    B = rng.normal(size=(n, 3))
    want = spl.spsolve(A.tocsc(), B)
    got = solver.solve(B)
    bound = 1e-12 * max(1.0, np.linalg.cond(A.toarray()) / 1e3)  # backward stable: relative to κ
    assert np.abs(got - want).max() <= bound * np.abs(want).max()
    for k in (1, 5):  # other column counts, three at a time
        Bk = rng.normal(size=(n, k))
        assert np.abs(solver.solve(Bk) - spl.spsolve(A.tocsc(), Bk).reshape(n, k)).max() < 1e-9
    solver.close()


def _as_scipy(A: Csr) -> sp.csr_matrix:
    return sp.csr_matrix((A.data, A.indices, A.indptr), shape=A.shape)


def test_nested_dissection_fills_less_than_the_natural_order(kernel: native.Kernel) -> None:
    P, T = box_bar(16)
    system = arap.bind_system(arap.triangle_elements(P, T), np.full(len(P), 1e-3))
    nd = carap.CompiledArapSolver.bind(kernel, LOCK, system)
    natural = carap.CompiledArapSolver.bind(kernel, LOCK, system, "NATURAL")
    assert nd.stats["nnz_factor"] < 0.6 * natural.stats["nnz_factor"]
    assert nd.stats["flops"] < 0.5 * natural.stats["flops"]
    # comparable to a minimum degree ordering (SuperLU's, on the same pattern)
    lu = spl.splu(_as_scipy(system.matrix).tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                  options={"SymmetricMode": True})
    mmd = carap.CompiledArapSolver.bind(kernel, LOCK, system, np.argsort(lu.perm_c))
    assert nd.stats["nnz_factor"] < 1.3 * mmd.stats["nnz_factor"]
    for s in (nd, natural, mmd):
        s.close()


def test_a_matrix_that_is_not_positive_definite_is_refused(kernel: native.Kernel) -> None:
    A = sp.diags([1.0, 2.0, -1.0, 3.0]).tocsr()
    with pytest.raises(carap.FactorError, match=r"not positive definite .*vertex 2"):
        carap.CompiledArapSolver.bind(kernel, LOCK, _system_of(A), "NATURAL")
    with pytest.raises(ValueError, match="permutation"):
        carap.CompiledArapSolver.bind(kernel, LOCK, _system_of(A), [0, 1, 1, 2])
    with pytest.raises(ValueError, match="ordering must be one of"):
        carap.CompiledArapSolver.bind(kernel, LOCK, _system_of(A), "AMD")
    with pytest.raises(ValueError, match="needs a mesh with vertices"):
        accel.arap_bind(_system_of(sp.csr_matrix((0, 0))))
    assert accel.active()  # refusals are not kernel failures


# -------------------------------------------------------------------------------------------- frames


@pytest.mark.parametrize("rig", ["bend", "twist"])
def test_the_compiled_frame_matches_numpy(kernel: native.Kernel, rig: str) -> None:
    c = _rig(6, bend_rig(4.0, np.pi) if rig == "bend" else twist_rig(4.0, 1.5 * np.pi))
    compiled = carap.CompiledArapSolver.bind(kernel, LOCK, c.system)
    numpy_solver = arap.NumpyArapSolver(c.system)
    rhs = compiled.frame(c.motions, c.field, 0)
    want = arap.right_hand_side(c.el, arap.linear_maps(c.motions), c.field)
    assert np.abs(rhs - want).max() <= 1e-14 * np.abs(want).max()
    scale = np.abs(c.field).max()
    for iterations in (1, 2, 3):
        got = compiled.frame(c.motions, c.field, iterations)
        assert np.abs(got - numpy_solver.frame(c.motions, c.field, iterations)).max() < 1e-9 * scale
    assert compiled.stats["factorizations"] == 1
    compiled.close()


def test_a_compiled_frame_on_tetrahedra(kernel: native.Kernel) -> None:
    P = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    T = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])
    el = arap.tetrahedron_elements(P, T)
    system = arap.bind_system(el, np.r_[1.0, np.zeros(7)])
    rng = np.random.default_rng(12)
    A = random_affine(rng, len(T), log_scale=0.2)
    motions = np.ascontiguousarray(A[:, :3, :3].transpose(2, 0, 1))  # planar columns
    field = P + rng.normal(scale=0.1, size=P.shape)
    solver = carap.CompiledArapSolver.bind(kernel, LOCK, system)
    for iterations in (1, 2):
        want = arap.reference_positions(el, system.anchors, motions, field, iterations)
        assert np.abs(solver.frame(motions, field, iterations) - want).max() < 1e-10 * np.abs(want).max()


@pytest.mark.parametrize("motion", ["affine", "rigid", "rest"])
def test_a_shared_motion_is_exact_compiled(kernel: native.Kernel, motion: str) -> None:
    rng = np.random.default_rng(13)
    rig = twist_rig(4.0, 1.5 * np.pi)
    c = _rig(8, rig)
    G = np.eye(4)
    if motion == "affine":
        G = random_affine(rng, 1, log_scale=0.5, t_scale=100.0)[0]
    elif motion == "rigid":
        G[:3, :3] = aff3.so3_exp(rng.normal(size=3))
        G[:3, 3] = rng.normal(size=3) * 100.0
    params = np.repeat(aff3.params_from_matrices(G)[None], rig.params.shape[0], axis=0)
    field = deform.deform_points_params(c.P, params, c.idx, c.val)
    motions = deform.vertex_motions(params, c.eidx, c.evals)
    expect = c.P @ G[:3, :3].T + G[:3, 3]
    solver = accel.arap_bind(c.system)
    assert isinstance(solver, carap.CompiledArapSolver)
    for iterations in (1, 2, 3):
        assert np.abs(solver.frame(motions, field, iterations) - expect).max() <= 1e-12 * np.abs(expect).max()


def test_frames_do_not_depend_on_the_frames_before(kernel: native.Kernel) -> None:
    """One factor per bind; a frame's bits depend on its inputs only (a farm renders frame f alone), and
    two binds of one system give the same bits."""
    c = _rig(6, bend_rig(4.0, np.pi / 2))
    rig_params = bend_rig(4.0, np.pi / 2).params
    frames = []
    for s in (0.2, 0.7, 1.0):  # the rig at three moments
        params = rig_params * s
        frames.append((deform.vertex_motions(params, c.eidx, c.evals),
                       deform.deform_points_params(c.P, params, c.idx, c.val)))
    solver = carap.CompiledArapSolver.bind(kernel, LOCK, c.system)
    forward = [solver.frame(m, y, 2).copy() for m, y in frames]
    backward = [solver.frame(m, y, 2).copy() for m, y in frames[::-1]][::-1]
    alone = carap.CompiledArapSolver.bind(kernel, LOCK, c.system).frame(*frames[1], 2)
    for a, b in zip(forward, backward, strict=True):
        assert np.array_equal(a, b)
    assert np.array_equal(alone, forward[1])
    assert solver.stats["factorizations"] == 1


def test_the_handle_is_freed_once(kernel: native.Kernel) -> None:
    c = _rig(3, bend_rig(4.0, 0.5))
    solver = carap.CompiledArapSolver.bind(kernel, LOCK, c.system)
    before = solver.stats["bytes"]
    assert before > 8 * solver.stats["stored"]
    solver.frame(c.motions, c.field, 2)
    assert solver.stats["bytes"] == before + 18 * 8 * c.el.count  # the iterations' scratch, kept
    with solver as same:
        assert same is solver
    assert not solver._finalizer.alive
    solver.close()  # again: nothing
    with pytest.raises(ValueError, match="closed"):
        solver.frame(c.motions, c.field)
    other = carap.CompiledArapSolver.bind(kernel, LOCK, c.system)
    finalizer = other._finalizer
    del other  # dropped without close: the finaliser frees the factor
    assert not finalizer.alive


def test_arguments_are_checked(kernel: native.Kernel) -> None:
    c = _rig(2, bend_rig(4.0, 0.5))
    solver = carap.CompiledArapSolver.bind(kernel, LOCK, c.system)
    with pytest.raises(ValueError, match="motions must be planar"):
        solver.frame(c.motions[:, :-1], c.field)
    with pytest.raises(ValueError, match="field must have shape"):
        solver.frame(c.motions, c.field[:-1])
    with pytest.raises(ValueError, match="iterations"):
        solver.frame(c.motions, c.field, -1)
    with pytest.raises(ValueError, match="rhs must have shape"):
        solver.solve(np.zeros(3))


def test_without_the_kernel_the_pass_runs_on_numpy(kernel: native.Kernel, monkeypatch) -> None:
    c = _rig(4, twist_rig(4.0, np.pi))
    compiled = accel.arap_bind(c.system)
    monkeypatch.setenv(accel.ACCEL_ENV, "0")
    fallback = accel.arap_bind(c.system)
    assert isinstance(fallback, arap.NumpyArapSolver) and isinstance(compiled, carap.CompiledArapSolver)
    got, want = fallback.frame(c.motions, c.field), compiled.frame(c.motions, c.field)
    assert np.abs(got - want).max() < 1e-8 * np.abs(want).max()
    assert fallback.stats["cg_iterations"] > 0


def test_elements_turned_inside_out_take_the_svd_and_agree(kernel: native.Kernel) -> None:
    """A field that pushes a vertex through the bar turns its triangles inside out: their completed
    gradients have det < 0, the compiled iteration takes the SVD there (nearest rotation with the
    weakest direction flipped), as numpy's does."""
    P, T = box_bar(3)
    el = arap.triangle_elements(P, T)
    system = arap.bind_system(el, np.ones(len(P)))  # strong anchors: x stays near the field
    field = P.copy()
    corner = int(np.argmax(P @ np.array([0.0, 1.0, 1.0]) - P[:, 0]))  # a corner at x = 0, y = z = ½
    field[corner] -= np.array([0.0, 1.5, 1.5])  # through the bar and out of the far side
    motions = np.repeat(np.eye(3)[:, None, :], el.count, axis=1)  # planar identity maps
    x = arap.NumpyArapSolver(system).frame(motions, field, 1)
    F = arap.element_gradients(el, x) + np.einsum("ti,tj->tij", el.normals, el.normals)
    assert (np.linalg.det(F) < 0.0).sum() >= 2
    compiled = carap.CompiledArapSolver.bind(kernel, LOCK, system)
    for iterations in (2, 3):
        want = arap.NumpyArapSolver(system).frame(motions, field, iterations)
        assert np.abs(compiled.frame(motions, field, iterations) - want).max() < 1e-9
