"""Checks of the numbers read from a deformer's settings and stored data (issue #47), each made where
the value is read, worded for the deformer's status.

A script (`item["radius"] = value` on the ID property) or a damaged file bypasses the interface's
clamp to a property's range, and NaN passes that clamp anyway. A value is bad when it is not a finite
number, lies outside its property's hard range, or — for settings the interface leaves unbounded
above — exceeds the cap in `CAPS`, past which the numerics it feeds lose their meaning. The message
names the setting as the interface shows it (its RNA `name`), the control it belongs to where it is
per control, and the value; a finite value that is too large is called out of range, never
non-finite. The caller passes the mesh's input through (a status ending in `PASSES`).

Stored data (rest matrices, bind-data arrays, weight attributes) is checked the same way, with a
message saying what is damaged and to rebind. Nothing here imports the rest of the add-on but
caches.py.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from .. import caches

#: float32's largest value: Blender clamps an infinite location or scale to it, so a transform entry
#: of that size is an infinity the interface let through.
FLT_MAX = float(np.finfo(np.float32).max)
#: Transform entries (locations, scales, matrix entries, stored rest data) must stay below this in
#: magnitude: beyond it products of two entries overflow float32 and a mesh sent there is lost.
MAX_COORDINATE = 1e30
#: The largest rest rotation channel (radians, or quaternion / axis-angle components): ~1600 turns,
#: within what core.unwrap unwraps against a current channel near 0 (~7000 turns).
MAX_ANGLE = 1e4
#: The largest stored weight: weights are ≤ 1 except raw ones ('NONE') times a Weight Scale.
MAX_WEIGHT = 1e6

#: Upper bounds of settings whose interface range is unbounded above (float32's maximum).
CAPS: dict[str, float] = {
    # A length: weights depend on Radius through (Radius / d); past 1e6 the float32 rest positions
    # are spaced 0.06 apart, so no mesh has a feature at that scale.
    "radius": 1e6,
    # Inverse distance (Radius / max(d, 1e-6 Radius))^Exponent stays below 1e306 for Exponent ≤ 50.
    "exponent": 50.0,
    # Scales the raw weight: with an exponent ≤ 50 the product stays finite (1e300 · 1e6).
    "weight_scale": 1e6,
    # 1e4 times the default already holds the anchors exactly; the cap keeps the shape pass's
    # system (Laplacian + diag(α)) factorable in float64.
    "shape_anchor": 1e6,
}

#: What a status adds when the mesh passes its input through.
PASSES = "the mesh shows its input"


def shown(value: float) -> str:
    """A value as a status shows it: 'nan', 'inf', '-1', '1e+30', '0.01', '2147483647'."""
    if isinstance(value, int | np.integer):
        return str(int(value))
    return f"{float(value):g}"


def number_problem(label: str, value: float, low: float, high: float) -> str:
    """'' when `value` is a finite number in [low, high]; otherwise why not, naming `label` and the
    value: "Radius is nan (must be a finite number from 1e-06 to 1e+06)" or "Strength -1 is out of
    range (0 to 10)"."""
    number = float(value)
    if not math.isfinite(number):
        return f"{label} is {shown(value)} (must be a finite number from {shown(low)} to {shown(high)})"
    if not low <= number <= high:
        return f"{label} {shown(value)} is out of range ({shown(low)} to {shown(high)})"
    return ""


@dataclass(frozen=True)
class Range:
    """A setting as the interface shows it: its label and the values it may hold."""

    label: str
    low: float
    high: float


#: (RNA struct identifier, property name) -> its Range: the property's definition, the same for the
#: whole session; kept as a cache all the same (recomputed in microseconds).
_ranges: dict[tuple[str, str], Range] = {}


@caches.register
def _forget(_key: caches.Key | None) -> None:
    _ranges.clear()


def setting_range(item, name: str) -> Range:
    """The label (RNA `name`) and the hard range of property `name` of `item`, capped by `CAPS`."""
    rna = item.bl_rna
    key = (rna.identifier, name)
    found = _ranges.get(key)
    if found is None:
        prop = rna.properties[name]
        found = Range(prop.name or name, prop.hard_min, min(prop.hard_max, CAPS.get(name, math.inf)))
        _ranges[key] = found
    return found


def setting_problem(item, name: str, owner: str = "") -> str:
    """`number_problem` of the numeric property `name` of `item` (a deformer or a control item) with
    its interface label, prefixed by `owner` (e.g. "Probe 'Alpha': ") for a per-control setting."""
    limits = setting_range(item, name)
    return number_problem(owner + limits.label, getattr(item, name), limits.low, limits.high)


def settings_problem(item, names: Sequence[str]) -> str:
    """The first of `names` whose value `setting_problem` refuses, with what the update does ('' when
    all are fine)."""
    for name in names:
        problem = setting_problem(item, name)
        if problem:
            return f"{problem}: {PASSES}"
    return ""


def items_problem(items, name: str, label: Callable[[int], str]) -> str:
    """The first control item whose float property `name` is refused, named by `label(i)` (e.g.
    "Probe 'Alpha'"), with what the update does; '' when all are fine. One foreach_get for all."""
    if not len(items):
        return ""
    values = np.empty(len(items), dtype=np.float32)
    items.foreach_get(name, values)
    limits = setting_range(items[0], name)
    with np.errstate(invalid="ignore"):
        bad = ~((values >= limits.low) & (values <= limits.high))  # NaN is bad too
    if not bad.any():
        return ""
    i = int(np.flatnonzero(bad)[0])
    problem = number_problem(f"{label(i)}: {limits.label}", values[i], limits.low, limits.high)
    return f"{problem}: {PASSES}"


# ------------------------------------------------------------------------------------ transforms


def transform_problem(matrix: np.ndarray, what: str = "transform") -> str:
    """Why a control's or target's transform (4, 4) cannot be used, as the end of a sentence about
    it (`what`: 'transform', 'pose'): 'has a non-finite transform (NaN or infinity)' (an entry at
    float32's maximum is an infinity Blender clamped), 'has a transform out of range (an entry of
    1e+30; …)', or '' when every entry is below MAX_COORDINATE in magnitude. Over Python floats: a
    few microseconds for a 4×4."""
    values = np.asarray(matrix, dtype=np.float64).ravel().tolist()
    if all(abs(value) < MAX_COORDINATE for value in values):
        return ""
    if not all(abs(value) < FLT_MAX for value in values):  # NaN compares False too
        return f"has a non-finite {what} (NaN or infinity)"
    worst = max(values, key=abs)
    return (f"has a {what} out of range (an entry of {shown(worst)}; entries must stay below "
            f"{shown(MAX_COORDINATE)} in magnitude)")


def rest_matrix_problem(label: str, matrix: np.ndarray, mirrored: bool = False) -> str:
    """Why a stored rest matrix (4, 4) is damaged — a non-finite entry, an entry out of range, a
    bottom row other than (0, 0, 0, 1), or a 3×3 part that is singular or (unless `mirrored`)
    mirrored, det ≤ 0 — naming `label`; '' when it is usable. A cage's rest is in Aff+(3) (bind
    refuses a mirrored cage); a probe's may be mirrored (an Empty scaled by −1 at bind: its motion
    C · C_rest⁻¹ is not). The caller adds what the update does and asks to rebind."""
    rest = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
    values = rest.ravel().tolist()
    bad = [value for value in values if not math.isfinite(value)]
    if bad:
        return f"{label} has a non-finite entry ({shown(bad[0])})"
    large = [value for value in values if abs(value) >= MAX_COORDINATE]
    if large:
        return (f"{label} has an entry of {shown(large[0])}, out of range (entries must stay below "
                f"{shown(MAX_COORDINATE)} in magnitude)")
    if values[12:] != [0.0, 0.0, 0.0, 1.0]:
        row = ", ".join(shown(value) for value in values[12:])
        return f"{label} has the bottom row ({row}), not (0, 0, 0, 1)"
    det = float(np.linalg.det(rest[:3, :3]))
    if not (det != 0.0 if mirrored else det > 0.0):
        return f"{label} is {'singular' if mirrored else 'singular or mirrored'} (determinant {shown(det)})"
    return ""


def rest_matrices_usable(rests: np.ndarray, mirrored: bool = False) -> np.ndarray:
    """(n,) bool: which rest matrices (n, 4, 4) `rest_matrix_problem` accepts, in a few stacked numpy
    calls (the batched path; the message comes from `rest_matrix_problem`)."""
    rests = np.asarray(rests, dtype=np.float64)
    n = len(rests)
    with np.errstate(all="ignore"):
        bounded = (np.abs(rests) < MAX_COORDINATE).reshape(n, 16).all(axis=1)  # NaN fails
        bottom = (rests[:, 3] == (0.0, 0.0, 0.0, 1.0)).all(axis=1)
        linear = np.where(bounded[:, None, None], rests[:, :3, :3], np.eye(3))
        det = np.linalg.det(linear) if n else np.zeros(0)
    return bounded & bottom & ((det != 0.0) if mirrored else (det > 0.0))


def channels_problem(label: str, channels: Sequence[float]) -> str:
    """Why stored rest rotation channels are damaged (non-finite, or beyond MAX_ANGLE), naming
    `label`; '' when they are usable. The caller adds what the update does and asks to rebind."""
    for value in channels:
        problem = number_problem(label, value, -MAX_ANGLE, MAX_ANGLE)
        if problem:
            return problem
    return ""


def channels_usable(channels: np.ndarray) -> np.ndarray:
    """(n,) bool: which rows of rest channels (n, 4) `channels_problem` accepts."""
    with np.errstate(invalid="ignore"):
        return (np.abs(np.asarray(channels, dtype=np.float64)) <= MAX_ANGLE).all(axis=1)


# ------------------------------------------------------------------------------- stored arrays


def values_problem(what: str, values: np.ndarray, low: float, high: float, where: str = "index") -> str:
    """Why stored `values` (any shape) are damaged — a non-finite value or one outside [low, high] —
    naming `what` (the data), the value and its position (`where`: 'index', 'vertex'); '' when none
    is."""
    flat = np.asarray(values).ravel()
    with np.errstate(invalid="ignore"):
        bad = ~((flat >= low) & (flat <= high))  # NaN is bad too
    return _first_bad(what, flat, bad, where, f"valid: {shown(low)} to {shown(high)}")


def coordinates_problem(what: str, values: np.ndarray) -> str:
    """Why stored coordinates are damaged — a value that is not finite or not below MAX_COORDINATE
    in magnitude — naming `what`, the value and its index; '' when none is."""
    flat = np.asarray(values, dtype=np.float64).ravel()
    with np.errstate(invalid="ignore"):
        bad = ~(np.abs(flat) < MAX_COORDINATE)  # NaN is bad too
    return _first_bad(what, flat, bad, "index", f"coordinates must stay below {shown(MAX_COORDINATE)} in "
                      "magnitude")


def _first_bad(what: str, flat: np.ndarray, bad: np.ndarray, where: str, valid: str) -> str:
    if not bad.any():
        return ""
    i = int(np.flatnonzero(bad)[0])
    value = flat[i]
    finite = flat.dtype.kind != "f" or math.isfinite(value)
    kind = "a value out of range" if finite else "a non-finite value"
    return f"{what} holds {kind}, {shown(value)} at {where} {i} ({valid})"


def stored_array(owner, key: str, integer: bool) -> tuple[np.ndarray | None, str]:
    """(the ID property array `owner[key]` as int32 or float64, '') or (None, why it is damaged):
    missing, not an array, or of the wrong element type (an integer array must hold integers: a
    float one would be truncated silently; booleans are no numbers)."""
    if key not in owner:
        return None, f"'{key}' is missing"
    stored = owner[key]
    typecode = getattr(stored, "typecode", None)
    if typecode is None:
        return None, f"'{key}' is not an array ({type(stored).__name__})"
    if integer and typecode != "i":
        return None, f"'{key}' holds {'floats' if typecode in ('f', 'd') else 'booleans'}, not integers"
    if typecode not in ("f", "d", "i"):
        return None, f"'{key}' holds booleans, not numbers"
    return np.asarray(stored, dtype=np.int32 if integer else np.float64), ""
