"""The compiled face path of a cage (accel.cage_faces, the C kernel's ak_cage_faces and ak_cage_nodes)
against core.cage's numpy functions: the same motions to ~1e-15, the same validity and messages,
per-face results independent of which other faces moved, the constants the C code repeats, the
wrappers' argument checks and the numpy fallback."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from affine_deformers import accel
from affine_deformers.accel import native
from affine_deformers.core import aff3, unwrap
from affine_deformers.core import cage as cage_module
from affine_deformers.core.cage import affected_faces, face_motions, signed_volume
from tests.core.test_cage import box_cage, mixed_prism, similarity

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def kernel(monkeypatch: pytest.MonkeyPatch) -> native.Kernel:
    """The C kernel, enabled and loaded (skips when the library is not built here)."""
    monkeypatch.delenv(accel.ACCEL_ENV, raising=False)
    try:
        native.library_path()
    except native.KernelUnavailableError as exc:
        pytest.skip(f"the compiled kernel is not available: {exc}")
    module = accel._load()
    assert module is not None, accel.backend()
    return module


def numpy_faces(rest: np.ndarray, current: np.ndarray, topology: cage_module.CageTopology
                ) -> tuple[cage_module.FaceMotions, np.ndarray, float]:
    """What accel.cage_faces stands for, from the numpy functions (with the compiled polar split)."""
    reached = affected_faces(rest, current, topology)
    return (face_motions(rest, current, topology, faces=reached, polar=accel.polar_log), reached,
            signed_volume(current, topology))


def assert_agree(got: tuple, want: tuple, tol: float = 1e-13) -> None:
    (fg, rg, vg), (fw, rw, vw) = got, want
    assert np.array_equal(rg, rw)
    assert np.array_equal(fg.valid, fw.valid)
    assert fg.messages == fw.messages
    scale = np.maximum(1.0, np.abs(fw.params).max(axis=1, keepdims=True))
    assert np.abs(fg.params - fw.params).max(initial=0.0) <= tol * scale.max()
    assert np.array_equal(fg.params[~rg], np.zeros((int((~rg).sum()), 12)))
    assert abs(vg - vw) <= 1e-13 * max(1.0, abs(vw))


def edits(points: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    """Local edits (one to a few vertices), a common affine map, a turn with noise."""
    out = []
    for k in (1, 2, 5):
        cur = points.copy()
        pick = rng.choice(len(points), k, replace=False)
        cur[pick] += 0.15 * rng.normal(size=(k, 3))
        out.append(cur)
    G = np.array([[1.1, 0.3, 0.0], [0.0, 0.9, 0.2], [0.1, 0.0, 1.2]])
    out.append(points @ G.T + 0.5)
    turned = points @ aff3.so3_exp(np.array([0.3, -1.2, 2.0])).T
    out.append(turned + 0.02 * rng.normal(size=points.shape))
    return out


@pytest.mark.parametrize("case", ["box", "prism"])
def test_compiled_faces_match_numpy(kernel: native.Kernel, case: str) -> None:
    rng = np.random.default_rng(151)
    points, topology = box_cage((4, 3, 5), (2.0, 1.5, 3.0)) if case == "box" else mixed_prism()
    for cur in edits(points, rng):
        assert_agree(accel.cage_faces(points, cur, topology), numpy_faces(points, cur, topology))
    at_rest = accel.cage_faces(points, points.copy(), topology)
    assert not at_rest[1].any() and np.array_equal(at_rest[0].params, np.zeros((topology.n_faces, 12)))


def test_common_affine_motion_is_exact(kernel: native.Kernel) -> None:
    points, topology = box_cage((3, 3, 3), (2.0, 2.0, 2.0))
    G = similarity(0.7, [0.2, 1.0, -0.4], 1.3, [0.5, -1.0, 2.0])
    G[:3, :3] = G[:3, :3] @ np.array([[1.0, 0.4, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.7]])  # shear, stretch
    faces, reached, _ = accel.cage_faces(points, points @ G[:3, :3].T + G[:3, 3], topology)
    assert reached.all() and faces.valid.all()
    A = aff3.matrices_from_params(faces.params)
    np.testing.assert_allclose(A, np.broadcast_to(G, A.shape), atol=1e-12)


def test_faces_near_a_half_turn_are_lifted_like_numpy(kernel: native.Kernel,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """Corners of one face on both sides of a half turn: their principal logs differ by ~2π, so the
    face is lifted onto its first corner's branch (here with unwrap.lift_params, as face_motions)."""
    calls = []
    real = unwrap.lift_params

    def counting(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(accel._unwrap, "lift_params", counting)
    rng = np.random.default_rng(153)
    points, topology = box_cage((3, 3, 3), (2.0, 2.0, 2.0))
    cur = points @ aff3.so3_exp(np.array([0.0, 0.0, np.pi - 0.004])).T + 0.01 * rng.normal(size=points.shape)
    got = accel.cage_faces(points, cur, topology)
    assert calls  # some face took the lift
    assert_agree(got, numpy_faces(points, cur, topology), tol=1e-11)


def test_collapsed_and_broken_faces_match_numpy(kernel: native.Kernel) -> None:
    points = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=float)
    faces = [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
    topology = cage_module.CageTopology.from_polygons(faces)
    current = points.copy()
    current[4] = [0.5, 0.5, 0.0]  # face 0 collinear
    got = accel.cage_faces(points, current, topology)
    assert got[0].valid.tolist() == [False] + [True] * 7 and "collapsed" in got[0].messages[0]
    assert_agree(got, numpy_faces(points, current, topology))
    current[4] = [np.nan, 0.0, 1.0]
    got = accel.cage_faces(points, current, topology)
    assert np.all(np.isfinite(got[0].params)) and not np.isfinite(got[2])
    want = numpy_faces(points, current, topology)
    assert np.array_equal(got[0].valid, want[0].valid) and np.array_equal(got[1], want[1])
    rest = points.copy()
    rest[4] = [0.5, 0.5, 0.0]  # degenerate at rest: reported whether it moves or not
    assert_agree(accel.cage_faces(rest, points, topology), numpy_faces(rest, points, topology))


def test_a_face_does_not_depend_on_which_other_faces_moved(kernel: native.Kernel) -> None:
    """Two edits far apart, alone and together: every face reached by one of them only gets the
    same bits either way (the results of a face depend on its own inputs only)."""
    points, topology = box_cage((8, 2, 2), (8.0, 1.0, 1.0))
    left, right = np.argmin(points[:, 0]), np.argmax(points[:, 0])
    a, b = points.copy(), points.copy()
    a[left] += (0.1, 0.05, -0.08)
    b[right] += (-0.07, 0.1, 0.04)
    both = a.copy()
    both[right] = b[right]
    fa, ra, _ = accel.cage_faces(points, a, topology)
    fb, rb, _ = accel.cage_faces(points, b, topology)
    fab, rab, _ = accel.cage_faces(points, both, topology)
    assert ra.any() and rb.any() and not (ra & rb).any() and np.array_equal(rab, ra | rb)
    assert np.array_equal(fab.params[ra], fa.params[ra]) and np.array_equal(fab.params[rb], fb.params[rb])


def test_face_tables_are_kept_per_rest_cage(kernel: native.Kernel) -> None:
    points, topology = box_cage((2, 2, 2), (1.0, 1.0, 1.0))
    first = cage_module.face_tables(points, topology)
    assert cage_module.face_tables(points.copy(), topology) is first  # same content: kept
    other = points * 1.5
    assert cage_module.face_tables(other, topology) is not first
    assert np.array_equal(cage_module.face_tables(other, topology).rest, other)


CORE_CONSTANTS = {
    "COLLAPSED_SIN": cage_module.COLLAPSED_SIN,
    "FOLD_KAPPA": cage_module.FOLD_KAPPA,
    "NO_LIFT_DIST_SQ": unwrap._NO_LIFT_DIST_SQ,
    "NO_LIFT_NORM_SQ": unwrap._NO_LIFT_NORM_SQ,
}
FACE_FLAGS = ("FACE_REACHED", "FACE_HAS_CORNER", "FACE_VALID", "FACE_NEEDS_LIFT")


def test_constants_repeat_the_core_ones() -> None:
    """core.cage's and core.unwrap's thresholds as native.py and the Kernel class state them (no
    library needed), and the face flags: one bit each."""
    for name, value in CORE_CONSTANTS.items():
        assert getattr(native, name) == value, name
        assert getattr(native.Kernel, name) == value, name
    flags = [getattr(native, name) for name in FACE_FLAGS]
    assert flags == [getattr(native.Kernel, name) for name in FACE_FLAGS]
    assert sorted(flags) == [1, 2, 4, 8]


def test_the_c_source_states_the_same_constants() -> None:
    """csrc/kernel_cage.c's #defines of the same thresholds and flags (the library's values)."""
    source = ROOT / "csrc" / "kernel_cage.c"
    if not source.is_file():
        pytest.skip("no C source in this tree")
    defines = dict(re.findall(r"^#define\s+(\w+)\s+([-+0-9.eE]+)\s*(?:/\*.*)?$", source.read_text(), re.M))
    for name, value in CORE_CONSTANTS.items():
        assert float(defines[name]) == value, name
    for name in FACE_FLAGS:
        assert int(defines[name]) == getattr(native, name), name


def test_the_loaded_kernel_has_the_core_constants(kernel: native.Kernel) -> None:
    for name, value in CORE_CONSTANTS.items():
        assert getattr(kernel, name) == value, name


def test_inactive_kernel_returns_none(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(accel.ACCEL_ENV, "0")
    points, topology = box_cage((2, 2, 2), (1.0, 1.0, 1.0))
    assert accel.cage_faces(points, points * 1.1, topology) is None


# --------------------------------------------------------------------------------------------------
# the harmonic weights' nodes


def node_case(rng: np.random.Generator, G: int = 60, F: int = 40) -> tuple[np.ndarray, ...]:
    """Node points, column-major weights (rows summing to 1, some zeros, two nodes without weight
    on any moved face) and face parameters with moderate rotations and stretches."""
    x = rng.normal(scale=2.0, size=(G, 3))
    W = rng.random((G, F)) ** 2 * (rng.random((G, F)) < 0.7)
    W[:2, :] = 0.0
    W[:2, -1] = 1.0  # face F − 1 never moves
    W /= W.sum(axis=1, keepdims=True)
    P = np.concatenate([rng.normal(scale=0.5, size=(F, 6)), rng.normal(scale=0.2, size=(F, 6))], axis=1)
    P[-1] = 0.0
    return x, np.asfortranarray(W), P


@pytest.mark.parametrize("broken", [False, True])
def test_compiled_nodes_match_numpy(kernel: native.Kernel, broken: bool) -> None:
    from affine_deformers.core.cage.harmonic import node_params

    rng = np.random.default_rng(157)
    x, W, P = node_case(rng)
    reached = np.flatnonzero(np.arange(W.shape[1]) % 3 != 2)[:-1]
    valid = None
    if broken:
        valid = np.ones(W.shape[1], dtype=bool)
        valid[reached[:4]] = False
        P[reached[:4]] = 0.0
    params, touched, totals = accel.cage_nodes(x, W, P, reached, valid)
    want = node_params(x, W, P, faces=reached, valid=valid)
    assert np.array_equal(touched, (W[:, reached] > 0.0).any(axis=1)) and not touched[:2].any()
    assert np.array_equal(params[~touched], np.zeros((int((~touched).sum()), 12)))
    assert np.abs(params[touched] - want[touched]).max() <= 1e-14 * max(1.0, np.abs(want).max())
    keep = np.ones(W.shape[1]) if valid is None else valid.astype(float)
    np.testing.assert_allclose(totals, W @ keep, rtol=1e-14)


def test_compiled_nodes_with_kept_totals_are_bit_identical(kernel: native.Kernel) -> None:
    """The totals one call returns, passed to later calls with the same weights and valid faces
    (what the cage deformer does on every update), change no bit of any later result; totals of the
    wrong shape are refused."""
    rng = np.random.default_rng(173)
    x, W, P = node_case(rng)
    valid = np.ones(W.shape[1], dtype=bool)
    valid[[3, 7]] = False
    _, _, totals = accel.cage_nodes(x, W, P, np.arange(W.shape[1]), valid)
    for _ in range(4):
        reached = np.sort(rng.choice(W.shape[1] - 1, size=int(rng.integers(1, 12)), replace=False))
        fresh = accel.cage_nodes(x, W, P, reached, valid)
        kept = accel.cage_nodes(x, W, P, reached, valid, totals=totals)
        for a, b in zip(fresh, kept, strict=True):
            assert np.array_equal(a, b)
    with pytest.raises(ValueError, match="totals"):
        accel.cage_nodes(x, W, P, np.arange(3), valid, totals=totals[:-1])


def test_compiled_nodes_of_a_common_motion_are_exact(kernel: native.Kernel) -> None:
    """Every face with the same motion: each node gets exactly ψ of it (to rounding), whatever its
    position (the blend is pivoted at the node)."""
    rng = np.random.default_rng(163)
    x, W, _ = node_case(rng)
    G = similarity(0.8, [0.3, -1.0, 0.5], 1.2, [1.0, 2.0, -0.5])
    P = np.broadcast_to(aff3.params_from_matrices(G), (W.shape[1], 12)).copy()
    params, touched, _ = accel.cage_nodes(x, W, P, np.arange(W.shape[1]))
    assert touched.all()
    np.testing.assert_allclose(params, np.broadcast_to(P[0], params.shape), atol=1e-12)


def test_compiled_nodes_inactive_kernel_returns_none(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(accel.ACCEL_ENV, "0")
    x, W, P = node_case(np.random.default_rng(1))
    assert accel.cage_nodes(x, W, P, np.arange(3)) is None


# --------------------------------------------------------------------------------------------------
# the wrappers of the cage entries: indices the C code follows are bounded before it runs


def _faces_arguments() -> dict[str, np.ndarray]:
    """Valid keyword arguments of Kernel.cage_faces for a 2 × 2 × 2 box (26 vertices, 24 quads, 96
    corners) moved at one corner (the layout of accel.cage_faces); outputs filled with 7."""
    points, topology = box_cage((2, 2, 2), (1.0, 1.0, 1.0))
    t = cage_module.face_tables(points, topology)
    cur = points.copy()
    cur[0] += (0.1, -0.05, 0.2)
    F, T = topology.n_faces, t.triples.shape[0]
    return {"cur": cur, "rest": t.rest.copy(), "triples": t.triples.copy(), "first": t.first.copy(),
            "usable": t.usable.copy(), "weight": t.weight.copy(), "rest_ok": t.rest_ok.copy(),
            "centres": t.centres.copy(), "inverses": t.inverses.copy(), "sv": t.stencil_vertices.copy(),
            "sg": t.stencil_gamma.copy(), "smom": t.stencil_moments.copy(),
            "sspread": t.stencil_spread.copy(), "sactive": t.stencil_active.copy(), "fan": t.fan.copy(),
            "moved": np.ones(len(cur), bool),
            "params": np.full((F, 12), 7.0), "corner_params": np.full((T, 12), 7.0),
            "flags": np.full(F, 7, np.int64)}


def _nodes_arguments() -> dict[str, object]:
    """Valid keyword arguments of Kernel.cage_nodes (the layout of accel.cage_nodes)."""
    x, W, P = node_case(np.random.default_rng(3), G=12, F=9)
    reached = np.array([0, 2, 5], np.int64)
    G, F = W.shape
    return {"Wt": np.ascontiguousarray(W.T), "reached": reached, "faces": reached.copy(),
            "face_params": np.ascontiguousarray(P[reached]), "keep": np.ones(F), "totals": np.full(G, 7.0),
            "fill_totals": True, "x": x, "terms": np.full((3, 21), 7.0), "blend": np.full((21, G), 7.0),
            "out": np.full((G, 12), 7.0), "touched": np.zeros(G, bool)}


def _set(index: tuple, value: int) -> Callable[[np.ndarray], np.ndarray]:
    def change(a: np.ndarray) -> np.ndarray:
        a = a.copy()
        a[index] = value
        return a

    return change


CAGE_WRAPPER_BAD = [
    ("cage_faces", "triples", _set((0, 1), 26), ValueError, r"triples must index \[0, 26\)"),
    ("cage_faces", "triples", _set((3, 0), -1), ValueError, r"triples must index \[0, 26\)"),
    ("cage_faces", "sv", _set((0, 0), 99), ValueError, r"sv must index \[0, 26\)"),
    ("cage_faces", "fan", _set((1, 2), 26), ValueError, r"fan must index \[0, 26\)"),
    ("cage_faces", "first", _set((-1,), 10**6), ValueError, "first must rise from 0 to at most"),
    ("cage_faces", "first", _set((2,), 0), ValueError, "first must rise from 0 to at most"),
    ("cage_faces", "first", _set((0,), -1), ValueError, "first must rise from 0 to at most"),
    ("cage_faces", "triples", lambda a: a.astype(np.int32), TypeError, "triples must be a C-contiguous int6"),
    ("cage_faces", "usable", lambda a: a.astype(np.uint8), TypeError, "usable must be a C-contiguous bool"),
    ("cage_faces", "cur", lambda a: a[:-1].copy(), ValueError, r"rest must have shape \(25, 3\)"),
    ("cage_faces", "inverses", lambda a: a[:, :2].copy(), ValueError, "inverses must have shape"),
    ("cage_faces", "fan", lambda a: a[:, :2].copy(), ValueError, r"fan must have shape \(n, 3\)"),
    ("cage_faces", "params", lambda a: a[:-1].copy(), ValueError, "params must have shape"),
    ("cage_faces", "flags", lambda a: a.astype(np.int32), TypeError, "flags must be a C-contiguous int64"),
    ("cage_nodes", "reached", _set((1,), 9), ValueError, r"reached must index \[0, 9\)"),
    ("cage_nodes", "faces", _set((0,), -1), ValueError, r"faces must index \[0, 9\)"),
    ("cage_nodes", "reached", lambda a: a[:, None].copy(), ValueError, r"reached must index"),
    ("cage_nodes", "Wt", lambda a: a.ravel().copy(), ValueError, "Wt must be 2-D"),
    ("cage_nodes", "Wt", np.asfortranarray, TypeError, "Wt must be a C-contiguous float64"),
    ("cage_nodes", "x", lambda a: a[:-1].copy(), ValueError, r"x must have shape \(12, 3\)"),
    ("cage_nodes", "keep", lambda a: a[:-1].copy(), ValueError, r"keep must have shape \(9,\)"),
    ("cage_nodes", "face_params", lambda a: a[:-1].copy(), ValueError, r"face_params must have shape \(3,"),
    ("cage_nodes", "touched", lambda a: a.astype(np.uint8), TypeError, "touched must be a C-contiguous bool"),
]


@pytest.mark.parametrize(("entry", "name", "bad", "error", "message"), CAGE_WRAPPER_BAD,
                         ids=[f"{e}-{a}-{i}" for i, (e, a, *_) in enumerate(CAGE_WRAPPER_BAD)])
def test_cage_wrappers_refuse_arguments_the_c_code_cannot_follow_safely(
    kernel: native.Kernel, entry: str, name: str, bad: Callable, error: type, message: str
) -> None:
    """Vertex and face indices out of range, face spans that do not rise within the corners, wrong
    dtypes and shapes that disagree are refused before the C code runs (nothing is written); the
    same call with the valid argument runs."""
    make = _faces_arguments if entry == "cage_faces" else _nodes_arguments
    fn = getattr(kernel, entry)
    fn(**make())  # valid
    args = make()
    args[name] = bad(args[name])
    before = {k: v.copy() for k, v in args.items() if isinstance(v, np.ndarray)}
    with pytest.raises(error, match=message):
        fn(**args)
    for k, v in before.items():
        assert np.array_equal(args[k], v, equal_nan=True), k  # nothing written


def test_the_cage_entries_called_directly_give_accel_s_results(kernel: native.Kernel) -> None:
    """The wrappers with the layouts above return what accel.cage_faces and accel.cage_nodes return."""
    points, topology = box_cage((2, 2, 2), (1.0, 1.0, 1.0))
    a = _faces_arguments()
    volume = kernel.cage_faces(**a)
    faces, reached, want_volume = accel.cage_faces(points, a["cur"], topology)
    assert volume == want_volume
    assert np.array_equal((a["flags"] & kernel.FACE_REACHED) != 0, reached)
    assert reached.any() and not reached.all()
    assert np.array_equal(a["params"][reached], faces.params[reached])
    b = _nodes_arguments()
    count = kernel.cage_nodes(**b)
    x, W, P = node_case(np.random.default_rng(3), G=12, F=9)
    params, touched, totals = accel.cage_nodes(x, W, P, b["reached"])
    assert count == touched.sum() and np.array_equal(b["touched"], touched)
    assert np.array_equal(b["out"], params) and np.array_equal(b["totals"], totals)
