"""Cage faces → rest/current tetrahedra → per-face motion parameters; cage weights; cage checks.

One module per part, each with the mathematics it relies on in its docstring:

- `topology` — `CageTopology` (Blender's flat polygon arrays), face centroids and Newell normals;
- `motions` — corner tetrahedra, the 'NEIGHBOURS' apex stencils and the per-face motion parameters
  (`face_motions`, `face_tables`, `affected_faces`; MATH.md §9), with the content-keyed caches of the
  rest corners and stencils;
- `distances` — exact point–polygon distances and the faces' part of the 'INVERSE_DISTANCE' cage
  weights (`face_weights`; MATH.md §10, §12);
- `checks` — `check_cage` / `validate_cage` / `signed_volume`;
- `harmonic` — the default 'HARMONIC' cage weights on a grid and the node blend, used as the module
  `core.cage.harmonic` (its names are not re-exported here);
- `pool` — the 'INVERSE_DISTANCE' cage weights (`cage_weights`) with where their truncation pools
  weight (MATH.md §12): a coarse grid's nodes, each a mix of the faces near it (the rest of its names
  used as the module `core.cage.pool`).

The names below are what the rest of the package, the tests and the benchmarks use as `core.cage.X`.
They are re-exports: a test that patches a module-level constant or function (FOLD_KAPPA, …) patches
it in the module that defines it.
"""

from .checks import CageReport, check_cage, signed_volume, validate_cage
from .distances import (
    BATCH_ELEMENTS,
    BOUND_SLACK,
    DISTANCE_FLOOR,
    HALF_SPACE_BAND,
    HALF_SPACE_TOL,
    TOTAL_FACES,
    face_weights,
    half_space_ramp,
    nearest_faces,
    point_triangle_distance_sq,
    polygon_distance_sq,
)
from .motions import (
    APEX_MODES,
    CHUNK_ELEMENTS,
    COLLAPSED_SIN,
    FOLD_KAPPA,
    STENCIL_MIN_BETA,
    STENCIL_RIDGE,
    STENCIL_SIZE,
    STRAIGHT_CORNER_RATIO,
    ApexStencil,
    FaceMotions,
    FaceTables,
    PolarSplit,
    RestCorners,
    _corner_frames,
    _usable_rest_triples,
    affected_faces,
    apex_stencils,
    corner_matrices,
    face_messages,
    face_motions,
    face_tables,
    rest_corners,
)
from .pool import cage_weights
from .topology import CageTopology, face_centroids, face_normals

__all__ = [
    "APEX_MODES",
    "BATCH_ELEMENTS",
    "BOUND_SLACK",
    "CHUNK_ELEMENTS",
    "COLLAPSED_SIN",
    "DISTANCE_FLOOR",
    "FOLD_KAPPA",
    "HALF_SPACE_BAND",
    "HALF_SPACE_TOL",
    "STENCIL_MIN_BETA",
    "STENCIL_RIDGE",
    "STENCIL_SIZE",
    "STRAIGHT_CORNER_RATIO",
    "TOTAL_FACES",
    "ApexStencil",
    "CageReport",
    "CageTopology",
    "FaceMotions",
    "FaceTables",
    "PolarSplit",
    "RestCorners",
    "_corner_frames",
    "_usable_rest_triples",
    "affected_faces",
    "apex_stencils",
    "cage_weights",
    "check_cage",
    "corner_matrices",
    "face_centroids",
    "face_messages",
    "face_motions",
    "face_normals",
    "face_tables",
    "face_weights",
    "half_space_ramp",
    "nearest_faces",
    "point_triangle_distance_sq",
    "polygon_distance_sq",
    "rest_corners",
    "signed_volume",
    "validate_cage",
]
