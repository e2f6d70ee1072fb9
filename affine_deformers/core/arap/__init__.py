"""The shape-preserving pass (ARAP / Poisson, MATH.md §15), numpy only: elements with their gradient
operator (`elements.py`), anchors, the system and its right-hand side (`system.py`), and a dense
least-squares reference (`reference.py`). The compiled factor and per-frame solve are
`affine_deformers.accel.arap`; `NumpyArapSolver` is the path without it.

Bind (once per bind and topology), in one call or its steps:

    bound = bind_triangles(rest_points, triangles, indices, values, strength=..., controls=m)
    #   = triangle_elements + element_weights (or the weight mode at the centroids)
    #     + anchor_weights (or painted per-vertex anchors) + bind_system
    solver = accel.arap_bind(bound.system)  # the compiled factor, or NumpyArapSolver(system)

Every frame: motions = vertex_motions(params, bound.indices, bound.values) (the blended maps at the
elements, (4, E, 3); chain_motions for bones), field = the per-vertex field's positions (N, 3),
x = solver.frame(motions, field, iterations). solver.close() when the bind or topology changes.
"""

from .elements import (
    DEGENERATE_RATIO,
    DegenerateElementsError,
    Elements,
    element_gradients,
    element_weights,
    mesh_components,
    tetrahedron_elements,
    triangle_elements,
    vertex_areas,
)
from .reference import reference_positions
from .system import (
    ANCHOR_LEVEL,
    ANCHOR_STRENGTH,
    ArapBind,
    ArapSystem,
    NumpyArapSolver,
    anchor_weights,
    bind_system,
    bind_triangles,
    closest_rotations,
    linear_maps,
    right_hand_side,
    solve_frame,
    stretch_parts,
    swapped_targets,
)

__all__ = [
    "ANCHOR_LEVEL",
    "ANCHOR_STRENGTH",
    "DEGENERATE_RATIO",
    "ArapBind",
    "ArapSystem",
    "DegenerateElementsError",
    "Elements",
    "NumpyArapSolver",
    "anchor_weights",
    "bind_system",
    "bind_triangles",
    "closest_rotations",
    "element_gradients",
    "element_weights",
    "linear_maps",
    "mesh_components",
    "reference_positions",
    "right_hand_side",
    "solve_frame",
    "stretch_parts",
    "swapped_targets",
    "tetrahedron_elements",
    "triangle_elements",
    "vertex_areas",
]
