"""Where the browser viewer's camera starts: looking at the subject (what moves, robust bounds)
from the front, above and to the side, far enough that the subject's bounding sphere fits the view.

- Cache playback knows the whole motion: :func:`playback_bounds` samples frames across the cache.
- A live scene does not know its future: :func:`live_bounds` takes the subject at its first frame
  together with the see-through containers it moves in (walls, tanks: static items drawn with an
  opacity below 1), and extends it down to the ground under it (the lowest static item below it),
  where what falls lands. Large opaque floors and terrain are not framed, only reached down to.
"""

from __future__ import annotations

import numpy as np

__all__ = ["VIEW", "aim", "camera_pose", "item_points", "item_radius", "live_bounds", "playback_bounds",
           "robust_bounds"]

VIEW = np.array([0.35, 0.45, 1.0])
"""Direction from the subject to the camera (front, above, a little to the right), +Y up."""


def item_points(item) -> np.ndarray:
    """A drawn item's points as an (N, 3) float64 array [m] (empty: (0, 3))."""
    p = np.asarray(item.points, np.float64)
    return p.reshape(-1, 3) if p.size else np.zeros((0, 3))


def robust_bounds(clouds, quantile=0.01, pad=0.0):
    """[[lo], [hi]] [m] of point arrays (n, 3): per axis the ``quantile`` and ``1 - quantile`` of all
    points (outliers do not stretch it), widened by ``pad`` [m] and 5 % of the extent; None if empty."""
    pts = [np.asarray(c, np.float64).reshape(-1, 3) for c in clouds]
    pts = [p[np.isfinite(p).all(1)] for p in pts if len(p)]
    if not pts:
        return None
    allp = np.concatenate(pts)
    if not len(allp):
        return None
    lo, hi = np.quantile(allp, quantile, axis=0), np.quantile(allp, 1.0 - quantile, axis=0)
    grow = 0.05 * (hi - lo) + pad
    return np.array([lo - grow, hi + grow])


def item_radius(item) -> float:
    """A drawn item's point radius [m] (0 when it has none)."""
    return float(getattr(item, "radius", 0.0) or 0.0)


def live_bounds(items, static_items):
    """Bounds to frame for a live scene: ``items`` ({name: DrawItem}, the first frame's moving prims)
    with the see-through containers among ``static_items`` and down to the ground below them."""
    moving = [it for it in items.values() if len(item_points(it))]
    pad = max([item_radius(it) for it in moving] or [0.0])
    b = robust_bounds([item_points(it) for it in moving], pad=pad)
    statics = [it for it in static_items.values() if len(item_points(it))]
    containers = [it for it in statics if it.opacity is not None and it.opacity < 1.0]
    if b is None:  # nothing moves: frame what is drawn
        return robust_bounds([item_points(it) for it in statics], quantile=0.0)
    if containers:
        c = robust_bounds([item_points(it) for it in containers], quantile=0.0)
        b = np.array([np.minimum(b[0], c[0]), np.maximum(b[1], c[1])])
    below = [(item_points(it)[:, 1]).min() for it in statics]
    below = [y for y in below if y <= b[0][1]]
    if below:
        b[0][1] = min(below)  # the ground everything below the subject rests on
    return b


def playback_bounds(reader, samples=7):
    """Bounds of a cache's moving prims over ``samples`` frames spread across it (a
    :class:`warpsim.viewer.playback.CacheReader`); its static items when nothing moves."""
    n = len(reader)
    clouds, pad = [], 0.0
    for index in sorted({int(round(k)) for k in np.linspace(0, max(n - 1, 0), min(samples, max(n, 1)))}):
        for item in (reader.items(index) if n else {}).values():
            clouds.append(item_points(item))
            pad = max(pad, item_radius(item))
    b = robust_bounds(clouds, pad=pad)
    if b is None:
        b = robust_bounds([item_points(it) for it in reader.static.values()], quantile=0.0)
    return b


def camera_pose(bounds, fov_degrees=50.0, margin=1.1):
    """(position, look_at) [m] of a camera along :data:`VIEW` that fits the bounds' sphere in a
    ``fov_degrees`` view; a 1 m box at the origin when ``bounds`` is None."""
    lo, hi = (np.array([[-0.5, 0.0, -0.5], [0.5, 1.0, 0.5]]) if bounds is None else np.asarray(bounds, np.float64))
    center = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 0.05) * margin
    distance = radius / np.sin(np.radians(0.5 * fov_degrees))
    return center + distance * VIEW / np.linalg.norm(VIEW), center


def aim(camera, position, look_at):
    """Put ``camera`` (a viser client's camera or the server's initial camera) at ``position``
    looking at ``look_at`` [m]. The position goes first: a client camera keeps its orientation when
    moved, carrying its look-at point along (looking at the old subject's offset, often empty
    space), so the look-at point set after it is the one that stays."""
    camera.position = tuple(float(v) for v in position)
    camera.look_at = tuple(float(v) for v in look_at)
