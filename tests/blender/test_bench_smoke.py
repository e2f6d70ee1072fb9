"""`make bench` must keep working: its quick mode runs every case on small meshes and validates them.

The benchmark exits 1 when a timed update did not really change the mesh, when a result was still
moving after the timed passes, or when our operators fail — so this catches a benchmark that would
silently time nothing.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_quick_benchmark_runs_and_validates(extension_zip: Path, tmp_path: Path) -> None:
    markdown = tmp_path / "bench.md"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "run.py"), "--quick", "--zip", str(extension_zip),
         "--markdown", str(markdown)],
        capture_output=True, text=True, timeout=600, cwd=ROOT, env=dict(os.environ),
    )
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    table = markdown.read_text()
    for case in ("Hook", "Armature", "Mesh Deform", "Affine probes (ours)", "Affine cage (ours)",
                 "(d) 8 bones", "Armature, Preserve Volume", "Armature, linear", "(m) playback",
                 "Hook ×4 per object", "(e) cages made for the mesh", "Mesh Deform, made cage"):
        assert case in table, case
    bones = table[table.index("### (d)"):].split("###")[1]
    rows = [line for line in bones.splitlines()[3:] if line.startswith("| ")]  # below header and rule
    assert len(rows) == 2 and all("—" not in row for row in rows), bones  # ours and both natives timed
