"""The shape-preserving pass (ARAP / Poisson, MATH.md §15), numpy only: elements with their gradient
operator (`elements.py`), anchors, the system and its right-hand side (`system.py`), and a dense
least-squares reference (`reference.py`). The compiled factor and per-frame solve are
`affine_deformers.accel.arap`; `NumpyArapSolver` is the path without it.

Bind (once per bind and topology):

    elements = triangle_elements(rest_points, triangles)
    elem_idx, elem_val = element_weights(elements, indices, values)   # or the weight mode at centroids
    system = bind_system(elements, anchor_weights(elements, indices, values, strength=...))
    solver = accel.arap.bind(system)  # or NumpyArapSolver(system)

Every frame: motions = vertex_motions(params, elem_idx, elem_val) (the blended maps at the elements),
field = the per-vertex field's positions, x = solver.frame(motions, field, iterations).
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
    ArapSystem,
    NumpyArapSolver,
    anchor_weights,
    bind_system,
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
    "ArapSystem",
    "DegenerateElementsError",
    "Elements",
    "NumpyArapSolver",
    "anchor_weights",
    "bind_system",
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
