"""Where the 'INVERSE_DISTANCE' cage weights put the weight their truncation pools (MATH.md §12).

Near ties of more faces than Max Influences the kept faces' lowered weights sum to less than 1
(core.weights.truncate); the rest λ goes to pooled nodes: the nodes of a coarse regular grid over the
cage (`pool_grid`, about POOL_NODES nodes), a vertex's λ shared among its cell's 8 corners by its
trilinear weights (continuous in the vertex's position). Node c is a fixed mix of faces (`pool_mixes`):
the untruncated weights at the node, w_f(x_c) / Σ_g w_g(x_c), kept only for faces about as near as
the node's nearest one — multiplied by 1 − smoothstep((r_f − R₁)/(R₂ − R₁)), r_f = (w_max / w_f)^(1/p)
(the distance ratio d_f / d_min for faces not faded by the half-space rule), (R₁, R₂) = POOL_REACH —
and renormalised. Each frame a node's parameters are its mix of the faces' parameters, what a vertex
with those weights blends; so a motion shared by all faces stays exact, and the pooled share of a
vertex is, to the grid's resolution, the untruncated field's blend around it, without the far faces:
a rigidly moved part of a long cage stays within ~1e-3 of its width of rigid.
"""

from __future__ import annotations

import numpy as np

from .distances import face_weights
from .harmonic import CageGrid, cage_grid, trilinear
from .topology import CageTopology

#: Nodes of the pooled nodes' grid over the cage's bounding box (`pool_grid`): 6 along a cube's side.
POOL_NODES = 216
#: (R₁, R₂): a node's mix keeps faces up to R₁ times as far as its nearest fully, fades them out by R₂.
#: Nearer (1.2, 1.8) steps 2.8× the untruncated field's through a cube cage's centre at 8 influences;
#: farther (3, 4) leaves a rigidly turned half of a long box cage 0.02 of its width off rigid
#: (docs/field_ties.md; tests/core/test_cage.py).
POOL_REACH = (1.5, 2.5)


def pool_grid(cage_points: np.ndarray) -> CageGrid:
    """The pooled nodes' grid: the cage's bounding box, nodes on its faces, about POOL_NODES nodes."""
    return cage_grid(cage_points, nodes=POOL_NODES, pad=0)


def pool_columns(points: np.ndarray, cage_points: np.ndarray, n_faces: int,
                 pooled: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(indices (N, 8) int32, values (N, 8)): each point's pooled weight `pooled` (N,) shared among its
    cell's corners by trilinear weights; node g is index n_faces + g (flat C-order grid index)."""
    nodes, weights = trilinear(pool_grid(cage_points), points)
    return (n_faces + nodes).astype(np.int32), np.asarray(pooled, dtype=np.float64)[:, None] * weights


def cage_weights(points: np.ndarray, cage_points: np.ndarray, topology: CageTopology, *, k: int = 8,
                 **options: float | bool | int) -> tuple[np.ndarray, np.ndarray]:
    """Sparse 'INVERSE_DISTANCE' cage weights: (indices (N, K or K + 8) int32, values float64),
    K = min(k, F), rows summing to 1: the faces' continuous top-K (core.cage.distances.face_weights,
    whose keyword `options` — exponent, half_space, chunk_size — it takes: inverse distance to each
    face polygon with the half-space ramp, the K largest lowered by the (K+1)-th and divided by
    D = max(S, c·T), MATH.md §10, §12), and where weight is pooled the 8 nodes F + g of the point's
    cell sharing it (`pool_columns`; their parameters: `with_pool_nodes`), so any motion shared by
    all faces stays exact."""
    indices, values = face_weights(points, cage_points, topology, k=k, **options)
    F = topology.n_faces
    K = min(int(k), F)
    if indices.shape[1] == K:  # nothing pooled
        return indices, values
    nodes, shares = pool_columns(np.asarray(points, dtype=np.float64), cage_points, F, values[:, K])
    return np.concatenate([indices[:, :K], nodes], axis=1), np.concatenate([values[:, :K], shares], axis=1)


def pool_mixes(cage_points: np.ndarray, topology: CageTopology, *, exponent: float = 2.0,
               half_space: bool = True) -> np.ndarray:
    """(G, F): the pooled nodes as mixes of the faces (module docstring); rows sum to 1."""
    grid = pool_grid(cage_points)
    F = topology.n_faces
    indices, values = face_weights(grid.points(np.arange(grid.size)), cage_points, topology,
                                   exponent=exponent, half_space=half_space, k=F)
    W = np.zeros((grid.size, F))
    np.put_along_axis(W, indices.astype(np.intp), values, axis=1)
    top = W.max(axis=1, keepdims=True)
    ratio = (top / np.maximum(W, np.finfo(np.float64).tiny)) ** (1.0 / exponent)
    near, far = POOL_REACH
    t = np.clip((ratio - near) / (far - near), 0.0, 1.0)
    W *= 1.0 - t * t * (3.0 - 2.0 * t)
    return W / W.sum(axis=1, keepdims=True)


def with_pool_nodes(table: np.ndarray, cage_points: np.ndarray, topology: CageTopology, *,
                    exponent: float = 2.0, half_space: bool = True) -> np.ndarray:
    """`table` (F, ...) — face parameters, or matrices for a linear blend — with the pooled nodes'
    rows Σ_f mix_gf table[f] appended -> (F + G, ...): what indices F + g of `cage_weights` read."""
    table = np.asarray(table, dtype=np.float64)
    mixes = pool_mixes(cage_points, topology, exponent=exponent, half_space=half_space)
    return np.concatenate([table, np.tensordot(mixes, table, axes=(1, 0))])
