"""The compiled kernel: the C sources in csrc/ built as one shared library per platform, loaded with
ctypes. This module finds and loads the library and wraps each C entry in a function taking
numpy arrays (the entries `affine_deformers.accel` calls; `load()` returns them as a `Kernel`).

Why C and ctypes: one binary serves every Blender from 4.2 on (it depends on neither the Python nor
the numpy version), loads in milliseconds (nothing is compiled on the user's machine) and needs
nothing beyond the system C library. A ctypes call releases the GIL, so accel/threads.py runs an
entry on several Python threads at once, each claiming chunks from a shared counter.

Where the library is looked for, first match wins:

1. $AFFINE_DEFORMERS_KERNEL_LIB: a path to the library file itself;
2. the package `affine_deformers_kernel` (the platform wheel an extension package bundles, which
   Blender installs into the extension's site-packages): its LIBRARY_DIR;
3. the source tree's build/native/<platform>/ (`make native`).

On x86-64 there are three builds: the baseline, one for AVX2 CPUs (`affine_kernel_avx2`) and one for
AVX-512 CPUs (`affine_kernel_avx512`): wider vectors, no FMA contraction, so all three give the same
bits. The widest one numpy reports the CPU features of (AVX-512: AVX512_SKX; AVX2: AVX2 and FMA3) is
taken where its file is there; $AFFINE_DEFORMERS_KERNEL_VARIANT = 'baseline', 'avx2' or 'avx512'
picks one (the benchmarks and tests compare them).

The wrappers check what the C code relies on for memory safety — dtypes, C-contiguity, shapes that
agree — and raise TypeError/ValueError otherwise; values (indices into tables) are clamped in C.
"""

from __future__ import annotations

import ctypes
import importlib.util
import os
import platform
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

Arr = np.ndarray

__all__ = [
    "EXPORTS", "LIBRARY_NAMES", "PLATFORMS", "Call", "Kernel", "KernelUnavailableError", "host_platform",
    "load",
]

#: The C entries the library exports, exactly (tests/core/test_native_binaries.py checks every build).
EXPORTS: tuple[str, ...] = (
    "ak_abi_version", "ak_chunk", "ak_deform_points", "ak_motion_params", "ak_polar_log", "ak_node_pivot",
    "ak_psi_rows", "ak_cage_faces", "ak_cage_nodes", "ak_chain_points", "ak_chain_motion", "ak_rows_reading",
    "ak_same_words", "ak_spin_wait", "ak_spd_factor", "ak_spd_solve", "ak_spd_free", "ak_spd_bytes",
    "ak_arap_frame",
)
#: Platform name -> the library's file suffix there.
PLATFORMS: dict[str, str] = {
    "linux_x64": ".so",
    "windows_x64": ".dll",
    "macos_arm64": ".dylib",
    "macos_x64": ".dylib",
}
#: The baseline build and the x86-64 AVX2 and AVX-512 builds (tools/build_native.py's VARIANT_FLAGS).
LIBRARY_NAMES: tuple[str, ...] = ("affine_kernel", "affine_kernel_avx2", "affine_kernel_avx512")
#: Variant names, in LIBRARY_NAMES' order.
VARIANTS: tuple[str, ...] = ("baseline", "avx2", "avx512")
#: csrc/affine_kernel.h's AK_ABI_VERSION this module is written for.
ABI_VERSION = 1

LIBRARY_ENV = "AFFINE_DEFORMERS_KERNEL_LIB"
VARIANT_ENV = "AFFINE_DEFORMERS_KERNEL_VARIANT"
WHEEL_PACKAGE = "affine_deformers_kernel"

# core.cage's constants the C code repeats (tests/core/test_accel_cage.py compares them).
COLLAPSED_SIN = 1e-10
FOLD_KAPPA = 0.5
NO_LIFT_DIST_SQ = 9.0
NO_LIFT_NORM_SQ = 1e12
FACE_REACHED = 1
FACE_HAS_CORNER = 2
FACE_VALID = 4
FACE_NEEDS_LIFT = 8


class KernelUnavailableError(RuntimeError):
    """The library is missing, does not load, or is of another ABI version; the message says which."""


def host_platform() -> str | None:
    """This machine's platform name in PLATFORMS, or None for one without a build."""
    machine = platform.machine().lower()
    x64 = machine in ("x86_64", "amd64")
    arm = machine in ("arm64", "aarch64")
    if sys.platform.startswith("linux") and x64:
        return "linux_x64"
    if sys.platform == "win32" and x64:
        return "windows_x64"
    if sys.platform == "darwin" and arm:
        return "macos_arm64"
    if sys.platform == "darwin" and x64:
        return "macos_x64"
    return None


def _cpu_features() -> dict:
    """The CPU features numpy's runtime dispatch saw ({} when numpy does not say)."""
    for name in ("numpy._core._multiarray_umath", "numpy.core._multiarray_umath"):
        try:
            module = importlib.import_module(name)
        except ImportError:
            continue
        features = getattr(module, "__cpu_features__", None)
        if isinstance(features, dict):
            return features
    return {}


def _cpu_variants() -> list[str]:
    """The variants this CPU runs, widest first: AVX-512 needs x86-64-v4's AVX512F/CD/BW/DQ/VL (numpy's
    AVX512_SKX group), AVX2 x86-64-v3's AVX2 and FMA3 (and the BMI and F16C that come with them)."""
    features = _cpu_features()
    usable = []
    if features.get("AVX512_SKX") and features.get("AVX512F"):
        usable.append("avx512")
    if features.get("AVX2") and features.get("FMA3"):
        usable.append("avx2")
    return [*usable, "baseline"]


def _candidate_dirs(plat: str) -> list[Path]:
    dirs: list[Path] = []
    spec = importlib.util.find_spec(WHEEL_PACKAGE)
    if spec is not None and spec.origin:
        dirs.append(Path(spec.origin).parent)
    dirs.append(Path(__file__).resolve().parents[2] / "build" / "native" / plat)
    return dirs


def library_path() -> tuple[Path, str]:
    """(the library file to load, its variant 'baseline' or 'avx2'); KernelUnavailableError if none."""
    explicit = os.environ.get(LIBRARY_ENV, "").strip()
    if explicit:
        path = Path(explicit)
        if not path.is_file():
            raise KernelUnavailableError(f"{LIBRARY_ENV}={explicit} is not a file")
        stem = path.stem
        return path, next((v for v in VARIANTS[1:] if stem.endswith("_" + v)), "baseline")
    plat = host_platform()
    if plat is None:
        raise KernelUnavailableError(f"no compiled kernel for {sys.platform} {platform.machine()}")
    suffix = PLATFORMS[plat]
    wanted = os.environ.get(VARIANT_ENV, "").strip().lower()
    if wanted and wanted not in VARIANTS:
        raise KernelUnavailableError(f"{VARIANT_ENV} must be one of {', '.join(VARIANTS)}, got {wanted!r}")
    names = dict(zip(VARIANTS, LIBRARY_NAMES, strict=True))
    if wanted:  # that one, else the baseline
        order = [(v, names[v]) for v in dict.fromkeys((wanted, "baseline"))]
    elif plat.endswith("x64"):
        order = [(v, names[v]) for v in _cpu_variants()]
    else:
        order = [("baseline", names["baseline"])]
    searched = _candidate_dirs(plat)
    for directory in searched:
        for variant, name in order:
            path = directory / (name + suffix)
            if path.is_file():
                return path, variant
    where = ", ".join(str(d) for d in searched)
    raise KernelUnavailableError(f"the compiled kernel library ({LIBRARY_NAMES[0]}{suffix}) is not installed "
                            f"(looked in {where})")


# ----------------------------------------------------------------------------------------------
# argument checks (what the C code relies on for memory safety)

_F64, _F32, _I32, _I64, _U8, _U32 = (np.dtype(t) for t in (np.float64, np.float32, np.int32, np.int64,
                                                           np.bool_, np.uint32))


def _ptr(a: Arr, dtype: np.dtype, name: str, writable: bool = False) -> int:
    if not isinstance(a, np.ndarray) or a.dtype != dtype or not a.flags.c_contiguous:
        raise TypeError(f"{name} must be a C-contiguous {dtype} array")
    if writable and not a.flags.writeable:
        raise ValueError(f"{name} must be writable")
    return a.ctypes.data


def _shape(a: Arr, shape: tuple[int, ...], name: str) -> None:
    if a.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {a.shape}")


def _rows_ok(rows: Arr, use_rows: bool, n: int) -> int:
    """The work list's length; its values are checked against [0, n) in C before anything is written
    (`_done` turns the refusal into ValueError)."""
    if not use_rows:
        return n
    if rows.ndim != 1:
        raise ValueError("rows must be 1-D")
    return rows.shape[0]


def _weights_ok(table: Arr, idx: Arr, val: Arr, n: int | None = None) -> tuple[int, int, int]:
    """(m, N, K) of a (m ≥ 1, 12) table and (N, K) indices and values."""
    if table.ndim != 2 or table.shape[1] != 12 or table.shape[0] < 1:
        raise ValueError(f"table must have shape (m >= 1, 12), got {table.shape}")
    if idx.ndim != 2 or idx.shape != val.shape or (n is not None and idx.shape[0] != n):
        raise ValueError(f"indices and values must have one (N, K) shape, got {idx.shape}, {val.shape}")
    return table.shape[0], idx.shape[0], idx.shape[1]


# ----------------------------------------------------------------------------------------------
# the kernel


@dataclass(frozen=True)
class Call:
    """A chunked entry checked and bound to its arguments (`Kernel.<entry>_call`): `call(counter)` or
    `call.at(address)` runs it on this thread, claiming chunks from that counter, and returns how many
    it did. `arrays` keeps the arrays the addresses point into alive until the call is gone."""

    fn: ctypes._CFuncPtr
    args: tuple
    n: int
    arrays: tuple

    def __call__(self, counter: Arr) -> int:
        return _done(self.fn(*self.args, _counter(counter)), self.n)

    def at(self, address: int) -> int:
        """Run with the counter at `address` (an int64 of a live array the caller owns)."""
        return _done(self.fn(*self.args, address), self.n)




@dataclass
class Kernel:
    """The loaded library's entries as numpy functions (the names `affine_deformers.accel` calls)."""

    path: Path
    variant: str
    lib: ctypes.CDLL
    CHUNK: int = 0
    _fns: dict[str, ctypes._CFuncPtr] = field(default_factory=dict)

    # the same constants as csrc/kernel_cage.c
    COLLAPSED_SIN = COLLAPSED_SIN
    FOLD_KAPPA = FOLD_KAPPA
    NO_LIFT_DIST_SQ = NO_LIFT_DIST_SQ
    NO_LIFT_NORM_SQ = NO_LIFT_NORM_SQ
    FACE_REACHED = FACE_REACHED
    FACE_HAS_CORNER = FACE_HAS_CORNER
    FACE_VALID = FACE_VALID
    FACE_NEEDS_LIFT = FACE_NEEDS_LIFT

    def describe(self) -> str:
        return f"C kernel ({self.path.name})"

    def deform_points_entry(self, points: Arr, table: Arr, idx: Arr, val: Arr,
                            rows: Arr, use_rows: bool, offsets: bool, out: Arr, out32: Arr,
                            use32: bool, counter: Arr) -> int:
        """out[v] = φ(Σ_k val[v, k] table[idx[v, k]]) points[v] (minus points[v] when offsets; with use32
        also out32[v] = float32(out[v])) for every row v, or v in rows when use_rows; the chunks this
        thread claimed from counter (int64 (1,), 0 at the start of a call). Returns how many it did."""
        return self.deform_points_call(points, table, idx, val, rows, use_rows, offsets, out, out32,
                                       use32)(counter)

    def deform_points_call(self, points: Arr, table: Arr, idx: Arr, val: Arr, rows: Arr, use_rows: bool,
                           offsets: bool, out: Arr, out32: Arr, use32: bool) -> Call:
        """`deform_points_entry` checked and bound to its arguments, waiting for a counter (a batch
        of calls run together: accel/batch.py)."""
        n_points = points.shape[0]
        m, _, K = _weights_ok(table, idx, val, n_points)
        _shape(points, (n_points, 3), "points")
        _shape(out, (n_points, 3), "out")
        if use32:
            _shape(out32, (n_points, 3), "out32")
        n_rows = _rows_ok(rows, use_rows, n_points)
        args = (_ptr(points, _F64, "points"), n_points, _ptr(table, _F64, "table"), m, _ptr(idx, _I32, "idx"),
                _ptr(val, _F64, "val"), K, _ptr(rows, _I64, "rows"), n_rows, bool(use_rows), bool(offsets),
                _ptr(out, _F64, "out", True), _ptr(out32, _F32, "out32", True), bool(use32))
        return Call(self._fns["ak_deform_points"], args, n_points,
                    (points, table, idx, val, rows, out, out32))

    def motion_params(self, table: Arr, idx: Arr, val: Arr, rows: Arr, use_rows: bool,
                      out: Arr, out32: Arr, use32: bool, counter: Arr) -> int:
        """out[:, v] = (M e_x, M e_y, M e_z, t) of φ(Σ_k val[v, k] table[idx[v, k]]) (float64 out, or
        float32 out32 with use32), every v or v in rows; chunks claimed from counter."""
        return self.motion_params_call(table, idx, val, rows, use_rows, out, out32, use32)(counter)

    def motion_params_call(self, table: Arr, idx: Arr, val: Arr, rows: Arr, use_rows: bool, out: Arr,
                           out32: Arr, use32: bool) -> Call:
        """`motion_params` checked and bound to its arguments, waiting for a counter."""
        m, N, K = _weights_ok(table, idx, val)
        _shape(out32 if use32 else out, (4, N, 3), "out32" if use32 else "out")
        n_rows = _rows_ok(rows, use_rows, N)
        args = (_ptr(table, _F64, "table"), m, _ptr(idx, _I32, "idx"), _ptr(val, _F64, "val"), N, K,
                _ptr(rows, _I64, "rows"), n_rows, bool(use_rows), _ptr(out, _F64, "out", True),
                _ptr(out32, _F32, "out32", True), bool(use32))
        return Call(self._fns["ak_motion_params"], args, N, (table, idx, val, rows, out, out32))

    def _chain_shapes(self, table: Arr, idx: Arr, val: Arr, prefix: Arr,
                      mats: Arr) -> tuple[int, int, int, int, int]:
        if table.ndim != 2 or table.shape[1] != 12 or table.shape[0] < 1:
            raise ValueError(f"table must have shape (m >= 1, 12), got {table.shape}")
        if mats.ndim != 2 or mats.shape[1] != 12 or mats.shape[0] < 1:
            raise ValueError(f"mats must have shape (m' >= 1, 12), got {mats.shape}")
        if idx.ndim != 3 or idx.shape != val.shape:
            raise ValueError(f"indices and values must have one (P, N, K) shape, got {idx.shape} {val.shape}")
        _shape(prefix, (idx.shape[1],), "prefix")
        return table.shape[0], idx.shape[0], idx.shape[1], idx.shape[2], mats.shape[0]

    def chain_points_entry(self, points: Arr, table: Arr, idx: Arr, val: Arr,
                           prefix: Arr, mats: Arr, rows: Arr, use_rows: bool, offsets: bool,
                           out: Arr, out32: Arr, use32: bool, counter: Arr) -> int:
        """x = points[v], x ← φ(pass p's blend) x for p = 0 … P−1, then x ← M x + t with (M, t) =
        mats[prefix[v]]; stored as `deform_points_entry` stores (out must not share memory with points)."""
        return self.chain_points_call(points, table, idx, val, prefix, mats, rows, use_rows, offsets, out,
                                      out32, use32)(counter)

    def chain_points_call(self, points: Arr, table: Arr, idx: Arr, val: Arr, prefix: Arr, mats: Arr,
                          rows: Arr, use_rows: bool, offsets: bool, out: Arr, out32: Arr,
                          use32: bool) -> Call:
        """`chain_points_entry` checked and bound to its arguments, waiting for a counter."""
        m, n_pass, N, K, n_mats = self._chain_shapes(table, idx, val, prefix, mats)
        _shape(points, (N, 3), "points")
        _shape(out, (N, 3), "out")
        if use32:
            _shape(out32, (N, 3), "out32")
        n_rows = _rows_ok(rows, use_rows, N)
        args = (_ptr(points, _F64, "points"), N, _ptr(table, _F64, "table"), m, _ptr(idx, _I32, "idx"),
                _ptr(val, _F64, "val"), n_pass, K, _ptr(prefix, _I32, "prefix"), _ptr(mats, _F64, "mats"),
                n_mats, _ptr(rows, _I64, "rows"), n_rows, bool(use_rows), bool(offsets),
                _ptr(out, _F64, "out", True), _ptr(out32, _F32, "out32", True), bool(use32))
        return Call(self._fns["ak_chain_points"], args, N,
                    (points, table, idx, val, prefix, mats, rows, out, out32))

    def chain_motion_entry(self, table: Arr, idx: Arr, val: Arr, prefix: Arr,
                           mats: Arr, rows: Arr, use_rows: bool, out: Arr, out32: Arr,
                           use32: bool, counter: Arr) -> int:
        """The motion (M, t) ∘ F_(P−1) ∘ ⋯ ∘ F_0 of `chain_points_entry` per vertex, stored as
        `motion_params` stores."""
        return self.chain_motion_call(table, idx, val, prefix, mats, rows, use_rows, out, out32,
                                      use32)(counter)

    def chain_motion_call(self, table: Arr, idx: Arr, val: Arr, prefix: Arr, mats: Arr, rows: Arr,
                          use_rows: bool, out: Arr, out32: Arr, use32: bool) -> Call:
        """`chain_motion_entry` checked and bound to its arguments, waiting for a counter."""
        m, n_pass, N, K, n_mats = self._chain_shapes(table, idx, val, prefix, mats)
        _shape(out32 if use32 else out, (4, N, 3), "out32" if use32 else "out")
        n_rows = _rows_ok(rows, use_rows, N)
        args = (_ptr(table, _F64, "table"), m, _ptr(idx, _I32, "idx"), _ptr(val, _F64, "val"), n_pass, N, K,
                _ptr(prefix, _I32, "prefix"), _ptr(mats, _F64, "mats"), n_mats, _ptr(rows, _I64, "rows"),
                n_rows, bool(use_rows), _ptr(out, _F64, "out", True), _ptr(out32, _F32, "out32", True),
                bool(use32))
        return Call(self._fns["ak_chain_motion"], args, N, (table, idx, val, prefix, mats, rows, out, out32))

    def polar_log(self, M: Arr, R: Arr, Yh: Arr) -> int:
        """R[i] = U Vᵀ, Yh[i] = V diag(log σ) Vᵀ for the SVD of each M[i] (n, 3, 3); returns n."""
        n = M.shape[0]
        for a, name in ((M, "M"), (R, "R"), (Yh, "Yh")):
            _shape(a, (n, 3, 3), name)
        return int(self._fns["ak_polar_log"](_ptr(M, _F64, "M"), n, _ptr(R, _F64, "R", True),
                                              _ptr(Yh, _F64, "Yh", True)))

    def psi_rows(self, rows: Arr) -> int:
        """ψ of every row of rows (n, 12) in place, (M row-major, t) ↦ (ω, u, Y₆); the first row that
        is not finite, −1 when every row is."""
        if rows.ndim != 2 or rows.shape[1] != 12:
            raise ValueError(f"rows must have shape (n, 12), got {rows.shape}")
        return int(self._fns["ak_psi_rows"](_ptr(rows, _F64, "rows", True), rows.shape[0]))

    def node_pivot(self, finish: bool, A: Arr, x: Arr, out: Arr) -> int:
        """finish False: A (n, 12) face parameters → out (n, 9) B = V(ω)⁻¹ (M − I); finish True: A
        (G, 21) blended (ω, u, Y, B) and x (G, 3) → out (G, 12) = (ω, u + B x + V(ω)⁻¹ (x − M x), Y)."""
        n = A.shape[0]
        cols = 21 if finish else 12
        _shape(A, (n, cols), "A")
        _shape(out, (n, 12 if finish else 9), "out")
        if finish:
            _shape(x, (n, 3), "x")
        return int(self._fns["ak_node_pivot"](bool(finish), _ptr(A, _F64, "A"), n, cols, _ptr(x, _F64, "x"),
                                               _ptr(out, _F64, "out", True)))

    def cage_faces(self, cur: Arr, rest: Arr, triples: Arr, first: Arr,
                   usable: Arr, weight: Arr, rest_ok: Arr, centres: Arr,
                   inverses: Arr, sv: Arr, sg: Arr, smom: Arr, sspread: Arr,
                   sactive: Arr, fan: Arr, moved: Arr, params: Arr,
                   corner_params: Arr, flags: Arr) -> float:
        """core.cage.face_motions for the faces a shape change reaches, and the cage's signed volume
        (returned); the layout of `affine_deformers.accel.cage_faces`."""
        V, T, F = cur.shape[0], triples.shape[0], first.shape[0] - 1
        S = sv.shape[1] if sv.ndim == 2 else -1
        for a, shape, name in ((cur, (V, 3), "cur"), (rest, (V, 3), "rest"), (triples, (T, 3), "triples"),
                               (usable, (T,), "usable"), (weight, (T,), "weight"), (rest_ok, (T,), "rest_ok"),
                               (centres, (T, 3), "centres"), (inverses, (T, 3, 3), "inverses"),
                               (sv, (T, S), "sv"), (sg, (T, S), "sg"), (smom, (T, 3), "smom"),
                               (sspread, (T,), "sspread"), (sactive, (T,), "sactive"), (moved, (V,), "moved"),
                               (params, (F, 12), "params"), (corner_params, (T, 12), "corner_params"),
                               (flags, (F,), "flags")):
            _shape(a, shape, name)
        if fan.ndim != 2 or fan.shape[1] != 3:
            raise ValueError(f"fan must have shape (n, 3), got {fan.shape}")
        # Vertex indices are read as they are (they come from the cage's own topology): bound them once.
        for a, name in ((triples, "triples"), (sv, "sv"), (fan, "fan")):
            if a.size and (int(a.min()) < 0 or int(a.max()) >= V):
                raise ValueError(f"{name} must index [0, {V})")
        if F < 0 or (first.size and (int(first[0]) < 0 or int(first[-1]) > T or np.any(np.diff(first) < 0))):
            raise ValueError(f"first must rise from 0 to at most {T}")
        return float(self._fns["ak_cage_faces"](
            _ptr(cur, _F64, "cur"), _ptr(rest, _F64, "rest"), V, _ptr(triples, _I64, "triples"), T,
            _ptr(first, _I64, "first"), F, _ptr(usable, _U8, "usable"), _ptr(weight, _F64, "weight"),
            _ptr(rest_ok, _U8, "rest_ok"), _ptr(centres, _F64, "centres"), _ptr(inverses, _F64, "inverses"),
            _ptr(sv, _I64, "sv"), _ptr(sg, _F64, "sg"), S, _ptr(smom, _F64, "smom"),
            _ptr(sspread, _F64, "sspread"), _ptr(sactive, _U8, "sactive"), _ptr(fan, _I64, "fan"),
            fan.shape[0], _ptr(moved, _U8, "moved", True),
            _ptr(params, _F64, "params", True), _ptr(corner_params, _F64, "corner_params", True),
            _ptr(flags, _I64, "flags", True)))

    def cage_nodes(self, Wt: Arr, reached: Arr, faces: Arr, face_params: Arr,
                   keep: Arr, totals: Arr, fill_totals: bool, x: Arr, terms: Arr,
                   blend: Arr, out: Arr, touched: Arr) -> int:
        """core.cage.harmonic.node_params for the nodes a moved face reaches (the layout of
        `affine_deformers.accel.cage_nodes`); returns how many nodes that is."""
        if Wt.ndim != 2:
            raise ValueError(f"Wt must be 2-D, got {Wt.shape}")
        F, G = Wt.shape
        n = faces.shape[0]
        for a, shape, name in ((face_params, (n, 12), "face_params"), (keep, (F,), "keep"),
                               (totals, (G,), "totals"), (x, (G, 3), "x"), (terms, (n, 21), "terms"),
                               (blend, (21, G), "blend"), (out, (G, 12), "out"), (touched, (G,), "touched")):
            _shape(a, shape, name)
        for a, name in ((reached, "reached"), (faces, "faces")):
            if a.ndim != 1 or (a.size and (int(a.min()) < 0 or int(a.max()) >= F)):
                raise ValueError(f"{name} must index [0, {F})")
        return int(self._fns["ak_cage_nodes"](
            _ptr(Wt, _F64, "Wt"), F, G, _ptr(reached, _I64, "reached"), reached.shape[0],
            _ptr(faces, _I64, "faces"), n, _ptr(face_params, _F64, "face_params"), _ptr(keep, _F64, "keep"),
            _ptr(totals, _F64, "totals", fill_totals), bool(fill_totals), _ptr(x, _F64, "x"),
            _ptr(terms, _F64, "terms", True), _ptr(blend, _F64, "blend", True), _ptr(out, _F64, "out", True),
            _ptr(touched, _U8, "touched", True)))

    def rows_reading(self, hit: Arr, idx: Arr, val: Arr, out: Arr) -> int:
        """The vertices v with val[v, k] != 0 and hit[idx[v, k]] for some k, ascending, into out[:count]."""
        if idx.ndim != 2 or idx.shape != val.shape or hit.ndim != 1:
            raise ValueError("idx and val must be (N, K) of one shape, hit 1-D")
        _shape(out, (idx.shape[0],), "out")
        return int(self._fns["ak_rows_reading"](_ptr(hit, _U8, "hit"), hit.shape[0], _ptr(idx, _I32, "idx"),
                                                 _ptr(val, _F64, "val"), idx.shape[0], idx.shape[1],
                                                 _ptr(out, _I64, "out", True)))

    def same_words(self, a: Arr, b: Arr) -> bool:
        """Whether the uint32 arrays a and b (n,) hold the same words."""
        if a.ndim != 1 or a.shape != b.shape:
            raise ValueError("a and b must be 1-D of one length")
        return bool(self._fns["ak_same_words"](_ptr(a, _U32, "a"), _ptr(b, _U32, "b"), a.shape[0]))

    def spd_factor(self, indptr: Arr, indices: Arr, data: Arr, ordering: int, perm_in: Arr | None,
                   perm_out: Arr, info: Arr) -> int | None:
        """Factor the symmetric positive definite matrix given as a full CSR (n × n: indptr (n + 1,),
        indices and data (nnz,), int64 / int64 / float64; sorted or not, symmetric, every index in
        [0, n)): L Lᵀ = P A Pᵀ with P nested dissection (ordering 1), natural (0) or `perm_in` (2).
        perm_out (n,) int64 receives P (pivot k is vertex perm_out[k]); info (8,) int64 receives
        (status, nnz(L), supernodes, bytes, failed vertex, stored values, flops, largest front).
        Returns the handle (free it with spd_free), or None when status is not 0 (1: out of memory,
        2: not positive definite, 3: perm_in is not a permutation)."""
        n = indptr.shape[0] - 1
        if indptr.ndim != 1 or n < 1 or indices.ndim != 1 or indices.shape != data.shape:
            raise ValueError("the matrix must be CSR: indptr (n + 1,), indices and data (nnz,), n ≥ 1")
        if n >= 2**31 - 1:
            raise ValueError("the factor numbers its rows with 32-bit integers: n must be below 2³¹ − 1")
        if int(indptr[0]) != 0 or int(indptr[-1]) != indices.shape[0] or np.any(np.diff(indptr) < 0):
            raise ValueError("indptr must rise from 0 to nnz")
        if indices.size and (int(indices.min()) < 0 or int(indices.max()) >= n):
            raise ValueError(f"indices must be in [0, {n})")
        _shape(perm_out, (n,), "perm_out")
        _shape(info, (8,), "info")
        if ordering == 2:
            if perm_in is None:
                raise ValueError("ordering 2 needs perm_in")
            _shape(perm_in, (n,), "perm_in")
        given = perm_out if perm_in is None else perm_in
        handle = ctypes.c_void_p()
        self._fns["ak_spd_factor"](n, _ptr(indptr, _I64, "indptr"), _ptr(indices, _I64, "indices"),
                                   _ptr(data, _F64, "data"), int(ordering), _ptr(given, _I64, "perm_in"),
                                   _ptr(perm_out, _I64, "perm_out", True), _ptr(info, _I64, "info", True),
                                   ctypes.addressof(handle))
        return handle.value if int(info[0]) == 0 else None

    def spd_solve(self, handle: int, b: Arr) -> None:
        """b (n, k) float64 := A⁻¹ b in place, for the factor `handle` of an n × n matrix (the caller
        keeps n: the handle does not say it)."""
        if b.ndim != 2 or b.shape[1] < 1:
            raise ValueError(f"b must have shape (n, k >= 1), got {b.shape}")
        if int(self._fns["ak_spd_solve"](handle, _ptr(b, _F64, "b", True), b.shape[1])) < 0:
            raise MemoryError("the compiled solve could not allocate its scratch memory")

    def spd_free(self, handle: int) -> None:
        self._fns["ak_spd_free"](handle)

    def spd_bytes(self, handle: int) -> int:
        """The memory the factor `handle` holds now (its frame scratch included)."""
        return int(self._fns["ak_spd_bytes"](handle))

    def arap_frame(self, handle: int, n: int, corners: Arr, grads: Arr, weights: Arr, normals: Arr,
                   motions: Arr, field: Arr, iterations: int, out: Arr) -> None:
        """One frame of the pass (core.arap.solve_frame) with the factor `handle` of its n × n matrix:
        corners (E, K) int64 (K = 3 or 4; clamped to [0, n) in C), grads (E, K, 3), weights (E,),
        normals (E, 3), motions (3 or 4, E, 3) planar columns of the blended maps, field (n, 3);
        out (n, 3) receives the positions (iterations 0: the right-hand side instead)."""
        if corners.ndim != 2 or corners.shape[1] not in (3, 4):
            raise ValueError(f"corners must have shape (E, 3 or 4), got {corners.shape}")
        E, K = corners.shape
        if motions.ndim != 3 or motions.shape[0] not in (3, 4):
            raise ValueError(f"motions must have shape (3 or 4, {E}, 3), got {motions.shape}")
        for a, shape, name in ((grads, (E, K, 3), "grads"), (weights, (E,), "weights"),
                               (normals, (E, 3), "normals"), (motions, (motions.shape[0], E, 3), "motions"),
                               (field, (n, 3), "field"), (out, (n, 3), "out")):
            _shape(a, shape, name)
        if iterations < 0:
            raise ValueError("iterations must be ≥ 0")
        status = int(self._fns["ak_arap_frame"](
            handle, n, E, K, _ptr(corners, _I64, "corners"), _ptr(grads, _F64, "grads"),
            _ptr(weights, _F64, "weights"), _ptr(normals, _F64, "normals"), _ptr(motions, _F64, "motions"),
            _ptr(field, _F64, "field"), int(iterations), _ptr(out, _F64, "out", True)))
        if status == -1:
            raise MemoryError("the compiled pass could not allocate its scratch memory")
        if status < 0:
            raise ValueError("the factor does not match the pass's size")

    def spin_wait(self, flag: Arr, seen: int, n: int) -> bool:
        """Busy-wait (GIL released) until flag[0] != seen (True) or for n iterations (False)."""
        _shape(flag, (1,), "flag")
        return bool(self._fns["ak_spin_wait"](_ptr(flag, _I64, "flag"), int(seen), int(n)))


def _counter(counter: Arr) -> int:
    """The chunk counter's address: one int64 the C code increments atomically."""
    _shape(counter, (1,), "counter")
    return _ptr(counter, _I64, "counter", True)


def _done(count: int, n: int) -> int:
    """An entry's return value: the chunks done, or the refusal it reports."""
    if count == -2:
        raise ValueError(f"rows must be in [0, {n})")
    if count < 0:
        raise MemoryError("the compiled kernel could not allocate its scratch memory")
    return int(count)


_P, _I, _L, _D = ctypes.c_void_p, ctypes.c_int32, ctypes.c_int64, ctypes.c_double
#: Each entry's C signature (restype, argtypes), as csrc/affine_kernel.h declares it.
_SIGNATURES: dict[str, tuple[object, list[object]]] = {
    "ak_abi_version": (_I, []),
    "ak_chunk": (_L, []),
    "ak_deform_points": (_L, [_P, _L, _P, _L, _P, _P, _L, _P, _L, _I, _I, _P, _P, _I, _P]),
    "ak_motion_params": (_L, [_P, _L, _P, _P, _L, _L, _P, _L, _I, _P, _P, _I, _P]),
    "ak_chain_points": (_L, [_P, _L, _P, _L, _P, _P, _L, _L, _P, _P, _L, _P, _L, _I, _I, _P, _P, _I, _P]),
    "ak_chain_motion": (_L, [_P, _L, _P, _P, _L, _L, _L, _P, _P, _L, _P, _L, _I, _P, _P, _I, _P]),
    "ak_polar_log": (_L, [_P, _L, _P, _P]),
    "ak_psi_rows": (_L, [_P, _L]),
    "ak_node_pivot": (_L, [_I, _P, _L, _L, _P, _P]),
    "ak_cage_faces": (_D, [_P, _P, _L, _P, _L, _P, _L, _P, _P, _P, _P, _P, _P, _P, _L, _P, _P, _P, _P, _L,
                           _P, _P, _P, _P]),
    "ak_cage_nodes": (_L, [_P, _L, _L, _P, _L, _P, _L, _P, _P, _P, _I, _P, _P, _P, _P, _P]),
    "ak_rows_reading": (_L, [_P, _L, _P, _P, _L, _L, _P]),
    "ak_same_words": (_I, [_P, _P, _L]),
    "ak_spin_wait": (_I, [_P, _L, _L]),
    "ak_spd_factor": (_L, [_L, _P, _P, _P, _I, _P, _P, _P, _P]),
    "ak_spd_solve": (_L, [_P, _P, _L]),
    "ak_spd_free": (_L, [_P]),
    "ak_spd_bytes": (_L, [_P]),
    "ak_arap_frame": (_L, [_P, _L, _L, _L, _P, _P, _P, _P, _P, _P, _L, _P]),
}
assert set(_SIGNATURES) == set(EXPORTS)


def load() -> Kernel:
    """Find, load and check the library (`library_path`); KernelUnavailableError with the reason if
    that fails."""
    path, variant = library_path()
    try:
        lib = ctypes.CDLL(str(path))
    except OSError as exc:
        raise KernelUnavailableError(f"{path.name} does not load: {exc}") from None
    fns: dict[str, ctypes._CFuncPtr] = {}
    for name, (restype, argtypes) in _SIGNATURES.items():
        try:
            fn = getattr(lib, name)
        except AttributeError:
            raise KernelUnavailableError(f"{path.name} lacks {name}: a different build") from None
        fn.restype, fn.argtypes = restype, argtypes
        fns[name] = fn
    version = fns["ak_abi_version"]()
    if version != ABI_VERSION:
        raise KernelUnavailableError(f"{path.name} has ABI version {version}; this add-on needs "
                                     f"{ABI_VERSION}")
    return Kernel(path, variant, lib, int(fns["ak_chunk"]()), fns)
