"""The dam-break surge front against Martin and Moyce (1952): the published table, the front of a
particle liquid measured as the experiment measured it, and the deviation over a window of T.

Martin, J. C. and Moyce, W. J. (1952), "Part IV. An experimental study of the collapse of liquid
columns on a rigid horizontal plane", Phil. Trans. R. Soc. Lond. A 244, 312-324. A column of
width ``a`` and height ``n^2 a`` is released at t = 0; the surge front z (the leading edge of the
water on the floor) is tabulated as Z = z / a against T = n t sqrt(g / a), so for the n^2 = 2
column (height 2a) T = t sqrt(2 g / a). Shallow-water theory (Ritter) gives Z = 1 + 2T for every
n, the curves the paper's scaling collapses.

Tables (Z at fixed steps of 1/2 inch of a = 2 1/4 in, T read off the photographs):

* n^2 = 2 (height 2a): Table 2 of the paper, as quoted by Ocellaris' and Lethe's dam-break
  post-processing; PySPH's digitisation of the paper's Fig. 3 (n^2 = 2, a = 2.25 in) agrees
  within 3 % in Z.
* n^2 = 1 (square column): the square-column series as tabulated in JAX-SPH's (LagrangeBench)
  dam-break validation; it runs ahead of the n^2 = 2 series by up to 0.45 in T (at Z = 3.67:
  T = 2.40 against 2.98), so a 0.2 m x 0.4 m column compared with it would look 15-25 % slow
  at 1 < T < 2. Use the table of the column's own aspect ratio (:func:`table`).
"""

from __future__ import annotations

import math

import numpy as np

G = 9.81  # [m/s^2]

# n^2 = 2: Table 2 of Martin and Moyce (1952), a = 2.25 in
N2_2_T = np.array([0.41, 0.84, 1.19, 1.43, 1.63, 1.83, 1.98, 2.20, 2.32, 2.51, 2.65, 2.83, 2.98, 3.11, 3.33])
N2_2_Z = np.array([1.11, 1.22, 1.44, 1.67, 1.89, 2.11, 2.33, 2.56, 2.78, 3.00, 3.22, 3.44, 3.67, 3.89, 4.11])
# n^2 = 1: the square column, a = 2.25 in
N2_1_T = np.array([0.43, 0.62, 0.80, 0.97, 1.14, 1.29, 1.45, 1.62, 1.76, 1.93, 2.07, 2.24, 2.40, 2.54, 2.71,
                   2.87, 3.04, 3.21, 3.29, 3.32])
N2_1_Z = np.array([1.11, 1.22, 1.44, 1.67, 1.89, 2.11, 2.33, 2.56, 2.78, 3.00, 3.22, 3.44, 3.67, 3.89, 4.11,
                   4.33, 4.56, 4.78, 4.89, 5.00])

WINDOW = (0.8, 3.0)
"""The T range checked (issue 54): every tabulated point with 0.8 <= T <= 3."""

RELEASE_DELAY = 0.2
"""The experiment's start delay in T (n^2 = 2). Fronts released instantaneously at T = 0 lead the
table by 13-21 % at T = 1.2-1.4 with every method here (PBF, DFSPH, FLIP) at every resolution, yet
the particle methods with free-slip walls run the surge at the table's speed (dZ/dT within 5 %):
the lead is a start offset. Shifted later by their best dT (0.22-0.24 for free-slip particles, 0.19-0.29
for FLIP) the runs stay within 2-3 % of every point of the window; 0.2 is one number for all
methods (11 ms for a = 2.25 in), belonging to the release (the removal of the column's support),
which the idealised problem makes instantaneous. The release is not a pure delay either: the
table's first point (T = 0.41, outside the window) sits on the undelayed curve. A fit, not a
measurement: reported beside the raw deviation, never instead of it (benchmarks/RESULTS.md)."""


def table(width: float, height: float):
    """(T, Z) arrays of the series whose aspect ratio n^2 = height / width matches the column
    (1 or 2, within 2 %); ValueError naming the ratio otherwise."""
    if not (width > 0.0 and height > 0.0):
        raise ValueError(f"column width {width!r} and height {height!r} must be > 0 [m]")
    n2 = height / width
    if abs(n2 - 2.0) <= 0.04:
        return N2_2_T, N2_2_Z
    if abs(n2 - 1.0) <= 0.02:
        return N2_1_T, N2_1_Z
    raise ValueError(f"column {width:g} m x {height:g} m has n^2 = height/width = {n2:.3g}; Martin and Moyce's "
                     "tables here are for n^2 = 1 and n^2 = 2: use height = width or height = 2 width")


def time_scale(width: float, height: float, g: float = G) -> float:
    """n sqrt(g / a) [1/s]: T = t * time_scale (sqrt(2 g / a) for the n^2 = 2 column)."""
    return math.sqrt(height / width) * math.sqrt(g / width)


def floor_front(x, spacing: float, floor: float = 0.0, origin: float = 0.0, band: float = 2.0,
                layers: int = 1, edge: float | None = None) -> float:
    """Leading edge [m] of the water on the floor, as the experiment saw it: particles whose centres
    lie within ``band`` spacings of the floor are binned along +x in bins one spacing wide, a bin
    is wet with at least ``max(1, layers // 2 + 1)`` particles (``layers``: particle layers across
    the slab's depth, so a lone particle of a thick slab is spray, not water); the front is the
    furthest such particle of the wet bins joined to ``origin`` (the column's wall; one dry bin
    between wet ones is a particle-sized hole in the film, two end it) plus ``edge`` (default half a
    spacing: the particle's edge). x: (N, 3) [m]."""
    x = np.asarray(x, np.float64)
    near = x[(x[:, 1] - floor) < band * spacing, 0] - origin
    if near.size == 0:
        return origin
    bins = np.floor(near / spacing).astype(np.int64)
    keep = bins >= 0
    near, bins = near[keep], bins[keep]
    if bins.size == 0:
        return origin
    wet = np.bincount(bins) >= max(1, layers // 2 + 1)
    return _joined_front(near, bins, wet, spacing, origin, edge)


def _joined_front(near, bins, wet, spacing: float, origin: float, edge: float | None) -> float:
    """origin + the furthest of ``near`` (x - origin [m], in bins ``bins``) among the wet bins
    joined to the wall (one dry bin between wet ones is a hole, two end the water) + edge."""
    dry = ~wet
    gap = np.flatnonzero(dry[:-1] & dry[1:]) if wet.size > 1 else np.flatnonzero(dry)
    last = gap[0] if gap.size else wet.size  # bins 0 .. last-1 hold the film joined to the wall
    if last > 0 and dry[last - 1]:
        last -= 1
    if last == 0:
        return origin
    return origin + float(near[bins < last].max()) + (0.5 * spacing if edge is None else edge)


FILM_DEPTH = 0.1
"""Water depth, over the column width a, that :func:`depth_front` takes for the front in
``run_dam_break`` (``Z_depth``): 2 spacings at a / spacing = 20, 5.7 mm in the experiment."""


def depth_front(x, spacing: float, depth: float, layers: int = 1, origin: float = 0.0,
                edge: float | None = None) -> float:
    """Leading edge [m] of the water at least ``depth`` [m] deep, a front that a film thinner than
    that does not move, the same in metres at every resolution (:func:`floor_front` counts a film
    within two spacings of the floor, thinner as the spacing shrinks): the particles binned along +x
    in bins one spacing wide, a bin's depth count * spacing / layers (each particle a spacing^3 of
    water in a slab ``layers`` particles deep), wet at >= depth; the front is the furthest particle
    of the wet bins joined to ``origin`` (one dry bin a hole, two the end, as :func:`floor_front`)
    plus ``edge`` (default half a spacing). x: (N, 3) [m]."""
    near = np.asarray(x, np.float64)[:, 0] - origin
    bins = np.floor(near / spacing).astype(np.int64)
    keep = bins >= 0
    near, bins = near[keep], bins[keep]
    if bins.size == 0:
        return origin
    wet = np.bincount(bins) * (spacing / layers) >= depth * (1.0 - 1e-9)
    return _joined_front(near, bins, wet, spacing, origin, edge)


def tip_front(x, spacing: float) -> float:
    """The furthest particle's centre plus half a spacing [m] (the particle's edge)."""
    return float(np.asarray(x)[:, 0].max()) + 0.5 * spacing


def deviation(T, Z, width: float = 1.0, height: float = 2.0, window=WINDOW):
    """Z_sim / Z_exp - 1 at every tabulated T inside ``window`` (the run's Z(T) interpolated);
    returns (T_table, deviations). The run must cover the window."""
    T, Z = np.asarray(T, np.float64), np.asarray(Z, np.float64)
    tt, zz = table(width, height)
    m = (tt >= window[0]) & (tt <= window[1])
    if T.max() < tt[m].max() - 1e-9:
        raise ValueError(f"the run ends at T = {T.max():.3f}, before the last tabulated T = {tt[m].max():.2f} "
                         "of the window: run longer")
    return tt[m], np.interp(tt[m], T, Z) / zz[m] - 1.0


def best_shift(T, Z, width: float = 1.0, height: float = 2.0, window=WINDOW, shifts=None):
    """(dT, worst |deviation|) of the time shift T -> T + dT (default candidates 0 .. 0.4 in steps of
    0.01) that minimises the largest |Z_sim / Z_exp - 1| over the window."""
    shifts = np.round(np.arange(0.0, 0.4001, 0.01), 2) if shifts is None else np.asarray(shifts, np.float64)
    errs = [np.abs(deviation(np.asarray(T) + dt, Z, width, height, window)[1]).max() for dt in shifts]
    k = int(np.argmin(errs))
    return float(shifts[k]), float(errs[k])


SPEED_WINDOW = (1.4, 3.0)
"""Where the surge runs at a steady speed in the table (a straight line through its points)."""


def surge_speed(T, Z, width: float = 1.0, height: float = 2.0, window=SPEED_WINDOW):
    """(dZ/dT of the run, dZ/dT of the table): least-squares slopes over ``window`` (the run's frames
    inside it, the table's points inside it). Unlike the deviation, a start delay does not change it."""
    T, Z = np.asarray(T, np.float64), np.asarray(Z, np.float64)
    tt, zz = table(width, height)
    m = (T >= window[0]) & (T <= window[1])
    k = (tt >= window[0]) & (tt <= window[1])
    if m.sum() < 2:
        raise ValueError(f"the run has {int(m.sum())} frames with {window[0]} <= T <= {window[1]}; it needs 2 or more")
    return float(np.polyfit(T[m], Z[m], 1)[0]), float(np.polyfit(tt[k], zz[k], 1)[0])


def worst(T, Z, width: float = 1.0, height: float = 2.0, window=WINDOW):
    """(T, deviation) of the largest |Z_sim / Z_exp - 1| over the window's tabulated points."""
    tt, dev = deviation(T, Z, width, height, window)
    k = int(np.argmax(np.abs(dev)))
    return float(tt[k]), float(dev[k])


def gate(a: float, depth: float, spacing: float, top: float, layers: int = 2) -> np.ndarray:
    """Boundary particles of a gate holding the column at x = a: ``layers`` lattice layers at
    x = a + (k + 1/2) spacing, from half a spacing above the floor to ``top`` [m], across the slab's
    depth on the fluid's lattice (the z nodes of ``dfsph.boundary_lattice``), (M, 3) [m]."""
    cells = max(1, int(round(depth / spacing)))
    z = (np.arange(cells) + 0.5) * (depth / cells)
    y = (np.arange(int(math.ceil(top / spacing))) + 0.5) * spacing
    x = a + (np.arange(layers) + 0.5) * spacing
    return np.stack(np.meshgrid(x, y, z, indexing="ij"), axis=-1).reshape(-1, 3)


def run_dam_break(method: str = "dfsph", res: int = 10, layers: int = 3, a: float = 0.2, t_end: float = 3.1,
                  frames_per_T: int = 20, gate_speed: float = 0.0, inset: bool = False, device=None,
                  **settings) -> dict:
    """Martin and Moyce's n^2 = 2 dam break with a ParticleFluid: the column a x 2a (``layers``
    particles thick, a / spacing = ``res``) in the -x corner of the box 5a x 2.5a, released at
    rest at T = 0 and advanced in frames of dT = 1 / frames_per_T (CFL sub-steps) to ``t_end``.
    Returns T, the floor front Z (:func:`floor_front`), the tip front Z_tip (:func:`tip_front`) and
    the front of the water FILM_DEPTH a deep Z_depth (:func:`depth_front`) per frame (over a), the
    mean compression per frame, steps, pressure iterations per step, particles, wall-clock seconds
    and the fluid. ``gate_speed`` > 0 [m/s] (DFSPH): the column is released by lifting a gate
    (:func:`gate`) at that speed instead of all at once. ``inset``: the
    block as SPlisHSPlasH's ``createFluidBlocks`` samples it, its first particle one spacing inside
    the column's faces and round(L / spacing) - 1 particles along x and y (a column one layer
    narrower and lower, a spacing off the wall); by default the lattice fills a x 2a exactly, its
    particles half a spacing inside the faces. ``settings`` go to ParticleFluid (e.g. DFSPH's
    ``boundary_viscosity`` with ``no_slip="floor"``: a no-slip floor, free-slip side and slab walls)."""
    import time

    from .pbf import ParticleFluid, fluid_block

    if int(res) != res or res < 2:
        raise ValueError(f"res={res!r}: the column needs at least 2 particles across (an integer >= 2)")
    s = a / res
    depth = layers * s
    if gate_speed:
        settings["moving_boundary"] = (gate(a, depth, s, 2.5 * a + 2.0 * s), (0.0, float(gate_speed), 0.0))
    if inset:
        axes = [(np.arange(int(round(length / s)) - 1) + 1.0) * s for length in (a, 2 * a)]
        axes.append((np.arange(layers) + 0.5) * s)
        block = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    else:
        block = fluid_block((0, 0, 0), (a, 2 * a, depth), s)
    f = ParticleFluid(block, spacing=s,
                      domain=((0, 0, 0), (5 * a, 2.5 * a, depth)), method=method, device=device, **settings)
    scale = time_scale(a, 2 * a)
    T, Z, tip, deep, compression = [0.0], [1.0], [1.0], [1.0], [0.0]
    start = time.perf_counter()
    for _ in range(int(round(t_end * frames_per_T))):
        f.advance(1.0 / frames_per_T / scale)
        x = f.positions.numpy()
        T.append(f.time * scale)
        Z.append(floor_front(x, s, layers=layers) / a)
        tip.append(tip_front(x, s) / a)
        deep.append(depth_front(x, s, FILM_DEPTH * a, layers=layers) / a)
        compression.append(f.density_error()[0])
    return {"T": np.array(T), "Z": np.array(Z), "Z_tip": np.array(tip), "Z_depth": np.array(deep),
            "compression": np.array(compression),
            "steps": f.step_count, "iterations": f.total_iterations / max(f.step_count, 1),
            "particles": f.active_count, "seconds": time.perf_counter() - start, "fluid": f, "res": res}
