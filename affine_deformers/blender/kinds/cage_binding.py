"""What binding a cage deformer checks and adjusts beyond the cage itself (kinds/cage.py is the kind):
the target's vertices the rest cage does not hold (counted for the status, faded out of the cage's
edits), and cage faces turned the other way since binding (named as such, not as a topology change).
"""

from __future__ import annotations

import numpy as np

from ...core.cage import CageTopology
from ...core.cage.distances import nearest_faces

#: Vertices outside the rest cage fade out of its edits over this share of the cage's diagonal (Mesh
#: Deform leaves them where they are; the faces' affine motions would move them ever further away).
OUTSIDE_FADE = 0.1


def outside_warning(deformer, outside: np.ndarray) -> str:
    """The bind warning for target vertices the rest cage does not enclose ('' when it holds them all)."""
    count = int(np.count_nonzero(outside))
    if not count:
        return ""
    name = deformer.cage.name if deformer.cage is not None else "?"
    return (f"{count} of {len(outside)} vertices ({count / len(outside):.0%}) lie outside cage '{name}': "
            f"they follow its edits less the further out they are (none beyond {OUTSIDE_FADE:.0%} of its "
            "size); make the cage enclose the mesh (or add the deformer with no cage selected: a cage "
            "is made around it)")


def faded_outside(values: np.ndarray, rest_points: np.ndarray, outside: np.ndarray,
                   cage_points: np.ndarray, topology: CageTopology) -> np.ndarray:
    """The weights of vertices outside the cage scaled by a smooth fade from 1 at its surface to 0 at
    OUTSIDE_FADE of its diagonal (the missing weight is the identity's: they stay, as with Mesh Deform;
    the cage object's own motion still carries them, it is applied after the blend)."""
    if not outside.any():
        return values
    reach = OUTSIDE_FADE * float(np.linalg.norm(np.ptp(cage_points, axis=0)))
    rows = np.flatnonzero(outside)
    point, _face, distance = nearest_faces(rest_points[rows], cage_points, topology, 0.0)
    nearest = np.full(len(rows), np.inf)
    np.minimum.at(nearest, point, distance)
    x = np.clip(1.0 - nearest / reach, 0.0, 1.0)
    faded = values.copy()
    faded[rows] *= (x * x * (3.0 - 2.0 * x))[:, None]
    return faded


def flipped_faces(loops: np.ndarray, start: np.ndarray, total: np.ndarray, now_loops: np.ndarray,
                   now_start: np.ndarray, now_total: np.ndarray) -> int:
    """How many faces hold the same vertices as at bind but in another order (flipped normals), when
    that is the only change (else 0: a topology change)."""
    if not (np.array_equal(start, now_start) and np.array_equal(total, now_total)
            and len(loops) == len(now_loops)) or len(total) == 0:
        return 0
    face = np.repeat(np.arange(len(total)), total)
    then = loops[np.lexsort((loops, face))]
    now = now_loops[np.lexsort((now_loops, face))]
    if not np.array_equal(then, now):
        return 0
    return int(np.count_nonzero(np.add.reduceat((loops != now_loops).astype(np.int64), start)))
