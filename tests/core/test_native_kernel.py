"""The compiled kernel's builds on this machine: every x86-64 build (baseline, AVX2, AVX-512) gives
the same bits (no FMA contraction, IEEE operations only), and a fresh process loads and checks it in
well under a second (nothing is compiled at run time)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from affine_deformers.accel import native

ROOT = Path(__file__).resolve().parents[2]

# Every entry with numerics, on inputs that reach each form of the map: stretched and rigid (small Y)
# controls, a lifted rotation (θ > 1.8π, the libm fix-up), ψ of random motions, a hierarchy chain, and
# the shape-preserving pass (its factor, and a frame with an extra iteration).
PROBE = r"""
import hashlib, json, sys, time
t0 = time.perf_counter()
import numpy as np
from affine_deformers import accel
from affine_deformers.core import aff3
from affine_deformers.core.weights import top_k_dense
from tests.core.conftest import random_affine
backend = accel.warm_up()
loaded = time.perf_counter() - t0
rng = np.random.default_rng(5)
n, m = 9000, 8
pts = rng.normal(scale=3.0, size=(n, 3))
params = aff3.params_from_matrices(random_affine(rng, m, log_scale=1.0, t_scale=5.0))
params[:2, 6:] = rng.normal(scale=1e-6, size=(2, 6))
params[2, :3] *= 15.0 / np.linalg.norm(params[2, :3])
idx, val = top_k_dense(rng.random((n, m)) ** 3, 4)
prefixes = np.zeros((2, 12))
prefixes[:, [0, 4, 8]] = 1.0
prefixes[1, 9:] = (0.5, -1.0, 2.0)
h = hashlib.sha256()
h.update(accel.deform_points_params(pts, params, idx, val).tobytes())
h.update(accel.vertex_motions(params, idx, val).tobytes())
h.update(accel.vertex_motions(params, idx, val, np.empty((4, n, 3), np.float32)).tobytes())
h.update(accel.params_from_matrices(random_affine(rng, 64, log_scale=1.0, t_scale=5.0)).tobytes())
prefix = (np.arange(n) % 2).astype(np.int32)
h.update(accel.chain_points(pts, params, np.stack([idx, idx[::-1]]), np.stack([val, val[::-1]]), prefix,
                            prefixes).tobytes())
from affine_deformers.core import arap
from tests.core.arap_rigs import bend_rig, box_bar, rig_weights
bar, tris = box_bar(6)
elements = arap.triangle_elements(bar, tris)
rig = bend_rig(4.0, 2.0)
bar_idx, bar_val = rig_weights(bar, rig)
el_idx, el_val = rig_weights(elements.centroids, rig)
solver = accel.arap_bind(arap.bind_system(elements, arap.anchor_weights(elements, bar_idx, bar_val)))
h.update(solver.frame(accel.vertex_motions(rig.params, el_idx, el_val),
                      accel.deform_points_params(bar, rig.params, bar_idx, bar_val), 2).tobytes())
print(json.dumps({"backend": backend, "hash": h.hexdigest(), "loaded": loaded}))
"""


def _run(variant: str) -> dict:
    env = dict(os.environ, AFFINE_DEFORMERS_KERNEL_VARIANT=variant, PYTHONPATH=str(ROOT))
    env.pop("AFFINE_DEFORMERS_ACCEL", None)
    done = subprocess.run([sys.executable, "-c", PROBE], cwd=ROOT, env=env, capture_output=True, text=True,
                          check=True, timeout=120)
    return json.loads(done.stdout.strip().splitlines()[-1])


def _built(name: str) -> bool:
    plat = native.host_platform()
    return plat is not None and (ROOT / "build" / "native" / plat / (name + native.PLATFORMS[plat])).is_file()


@pytest.mark.skipif(not _built("affine_kernel"), reason="the compiled kernel is not built (make native)")
def test_a_fresh_process_loads_the_kernel_in_well_under_a_second() -> None:
    result = _run("baseline")
    assert result["backend"].startswith("C kernel (affine_kernel"), result["backend"]
    # import of the package, numpy included, plus loading and checking every entry
    assert result["loaded"] < 1.0, result


@pytest.mark.parametrize("variant", ["avx2", "avx512"])
def test_every_x86_build_gives_the_baseline_bits(variant: str) -> None:
    name = dict(zip(native.VARIANTS, native.LIBRARY_NAMES, strict=True))[variant]
    if not (_built("affine_kernel") and _built(name)):
        pytest.skip(f"needs the baseline and the {variant} build (make native)")
    if variant not in native._cpu_variants():
        pytest.skip(f"this CPU cannot run the {variant} build")
    baseline, other = _run("baseline"), _run(variant)
    assert "affine_kernel." in baseline["backend"]
    assert f"_{variant}." in other["backend"]
    assert baseline["hash"] == other["hash"]


def test_the_variant_follows_the_cpu_and_the_override(monkeypatch: pytest.MonkeyPatch,
                                                      tmp_path: Path) -> None:
    """The widest build the CPU runs is picked (or the one asked for), falling back to the baseline
    when that file is absent."""
    plat = native.host_platform()
    if plat is None or not plat.endswith("x64"):
        pytest.skip("x86-64 only")
    suffix = native.PLATFORMS[plat]
    for name in native.LIBRARY_NAMES:
        (tmp_path / (name + suffix)).write_bytes(b"")
    monkeypatch.setattr(native, "_candidate_dirs", lambda _plat: [tmp_path])
    monkeypatch.delenv(native.LIBRARY_ENV, raising=False)
    monkeypatch.delenv(native.VARIANT_ENV, raising=False)
    skx = {"AVX512F": True, "AVX512_SKX": True, "AVX2": True, "FMA3": True}
    monkeypatch.setattr(native, "_cpu_features", lambda: skx)
    assert native.library_path() == (tmp_path / ("affine_kernel_avx512" + suffix), "avx512")
    (tmp_path / ("affine_kernel_avx512" + suffix)).unlink()
    assert native.library_path() == (tmp_path / ("affine_kernel_avx2" + suffix), "avx2")
    monkeypatch.setattr(native, "_cpu_features", lambda: {"AVX2": True, "FMA3": False})
    assert native.library_path() == (tmp_path / ("affine_kernel" + suffix), "baseline")
    monkeypatch.setenv(native.VARIANT_ENV, "avx2")
    assert native.library_path()[1] == "avx2"
    (tmp_path / ("affine_kernel_avx2" + suffix)).unlink()
    assert native.library_path()[1] == "baseline"
    monkeypatch.setenv(native.VARIANT_ENV, "sse9")
    with pytest.raises(native.KernelUnavailableError, match="must be one of baseline, avx2, avx512"):
        native.library_path()


def test_a_missing_library_says_where_it_looked(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv(native.LIBRARY_ENV, raising=False)
    monkeypatch.delenv(native.VARIANT_ENV, raising=False)
    monkeypatch.setattr(native, "_candidate_dirs", lambda _plat: [tmp_path])
    if native.host_platform() is None:
        pytest.skip("no build for this platform")
    with pytest.raises(native.KernelUnavailableError, match=r"is not installed \(looked in"):
        native.library_path()
    monkeypatch.setenv(native.LIBRARY_ENV, str(tmp_path / "nothing.so"))
    with pytest.raises(native.KernelUnavailableError, match="is not a file"):
        native.library_path()


def test_a_file_that_is_no_library_is_refused(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    bogus = tmp_path / "affine_kernel.so"
    bogus.write_bytes(b"not a shared library")
    monkeypatch.setenv(native.LIBRARY_ENV, str(bogus))
    with pytest.raises(native.KernelUnavailableError, match="does not load"):
        native.load()


def test_the_wrappers_refuse_what_would_be_unsafe_in_c() -> None:
    """Wrong dtypes, non-contiguous arrays, shapes that disagree and rows out of range are refused
    before any C code runs."""
    try:
        kernel = native.load()
    except native.KernelUnavailableError as exc:
        pytest.skip(str(exc))
    n = 5
    pts, table = np.zeros((n, 3)), np.zeros((2, 12))
    idx, val = np.zeros((n, 2), np.int32), np.ones((n, 2))
    out, no32, counter = np.empty((n, 3)), np.empty((0, 3), np.float32), np.zeros(1, np.int64)
    rows = np.empty(0, np.int64)

    def call(**changes: object) -> int:
        args = dict(points=pts, table=table, idx=idx, val=val, rows=rows, use_rows=False, offsets=False,
                    out=out, out32=no32, use32=False, counter=np.zeros(1, np.int64))
        args.update(changes)
        return kernel.deform_points_entry(**args)

    assert call() == 1
    with pytest.raises(TypeError, match="points must be a C-contiguous float64"):
        call(points=pts.astype(np.float32))
    with pytest.raises(TypeError, match="idx must be"):
        call(idx=idx.astype(np.int64))
    with pytest.raises(TypeError, match="out must be"):
        call(out=np.empty((3, n)).T)
    with pytest.raises(ValueError, match="out must have shape"):
        call(out=np.empty((n + 1, 3)))
    with pytest.raises(ValueError, match="indices and values"):
        call(val=np.ones((n, 3)))
    with pytest.raises(ValueError, match="rows must be in"):
        call(rows=np.array([0, n], np.int64), use_rows=True)
    with pytest.raises(ValueError, match="out32 must have shape"):
        call(use32=True)
    with pytest.raises(ValueError, match="table must have shape"):
        call(table=np.zeros((0, 12)))
    assert counter[0] == 0
