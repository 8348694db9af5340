"""The unit frame in which jaxci measures and smooths: node coordinates centred on their bounding box and scaled by
a power of two, so that they lie within [-1, 1] whatever the file's units (numpy only).

`unit_frame` gives the frame ``(centre, scale)`` of an array of points of shape ``(n, 3)`` (`frame_of_bounds`: of
their bounding box); `to_unit` and `from_unit` map points into it and back (exactly: the scale is a power of
two).
"""

from __future__ import annotations

import numpy as np


def unit_frame(points: np.ndarray) -> tuple[np.ndarray, float]:
    """The frame in which jaxci measures and smooths: ``(centre, scale)`` with ``unit = (points - centre) / scale``.

    `centre` is the bounding-box centre, shape ``(3,)``; `scale` the power of two at or below the box's largest
    side (1.0 for a single point), so that the unit coordinates lie within [-1, 1] whatever the file's units
    (a box of side 1e300 or 1e-300 is measured like a unit box; the quality metrics are scale-invariant) and
    dividing by `scale` is exact.
    """
    p = np.asarray(points, dtype=np.float64)
    if not len(p):
        return np.zeros(3), 1.0
    return frame_of_bounds(p.min(axis=0), p.max(axis=0))


def frame_of_bounds(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, float]:
    """`unit_frame` of points whose bounding box is ``[lo, hi]`` (float64 ``(3,)`` each: the points' minima and
    maxima, e.g. reduced on a device)."""
    centre, scale = box_frame(np, np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64))
    return centre, float(scale)


def box_frame(xp, lo, hi):
    """`unit_frame` of the points whose bounding box is ``lo``, ``hi`` (each ``(3,)``), with the array module `xp`
    (numpy, or `jax.numpy` for points on a device): ``(centre (3,), scale ())``, the same numbers with either."""
    centre = 0.5 * lo + 0.5 * hi  # no overflow near the float64 limit
    extent = (0.5 * hi - 0.5 * lo).max() * 2.0
    ok = (extent > 0) & xp.isfinite(extent)
    exponent = xp.frexp(xp.where(ok, extent, 1.0))[1]
    return centre, xp.where(ok, xp.ldexp(xp.ones_like(extent), exponent - 1), 1.0)


def to_unit(points: np.ndarray, frame: tuple[np.ndarray, float]) -> np.ndarray:
    """`points` ``(n, 3)`` in the unit frame of `unit_frame` (float64)."""
    centre, scale = frame
    return (np.asarray(points, dtype=np.float64) - centre) / scale


def from_unit(points: np.ndarray, frame: tuple[np.ndarray, float], inplace: bool = False) -> np.ndarray:
    """The inverse of `to_unit`; `inplace`: `points` (float64) itself mapped, no new array (the same numbers)."""
    centre, scale = frame
    if not inplace:
        return np.asarray(points, dtype=np.float64) * scale + centre
    points *= scale
    points += centre
    return points
