"""The dam-break surge front by two independent methods: PBF particles (warpsim.particle_fluids.pbf) against an
Eulerian FLIP liquid on a MAC grid (warpsim.grid_fluids.flip), both against Martin and Moyce (1952).

tests/test_sph.py finds the PBF front 11-13 % ahead of the experiment for 1.0 < T < 1.9 and
attributes that to the idealised problem (instantaneous release, nearly inviscid water), not to
the particle method. Here a grid method with nothing in common with PBF but the geometry (a
pressure projection on a staggered grid, particles only as velocity carriers, free-slip walls)
runs the same dam break: if the lead were the particle method's, FLIP would not share it.

Same problem for both: column a x 2a (a = 0.1 m) against the x = 0 wall of a closed box 5a long
and 2.5a high, g = 9.81 m/s^2, released at rest at t = 0, frames of dT = 0.05 up to T = 3.1
(T = t sqrt(2 g / a), Z = front / a). FLIP runs in 2D (MacGrid supports it); PBF is a slab three
particles thick with walls on every side, as in tests/test_sph.py.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import warp as wp

# Martin and Moyce's data and the PBF dam break exactly as tests/test_sph.py runs it (a slab three
# particles thick, a / spacing = res, 62 frames of dT = 0.05, front = furthest particle + half a
# spacing; wall_friction=0.0 gives free-slip walls, as the MAC grid's)
from test_sph import MM_T, MM_Z
from test_sph import run_dam_break as run_pbf_dam_break

from warpsim.grid_fluids.flip import FlipLiquid
from warpsim.grid_fluids.mac_grid import MacGrid
from warpsim.particle_fluids import martin_moyce as MM

G = 9.81
A = 0.1  # column width a [m]; height 2a
SCALE = math.sqrt(2.0 * G / A)  # T = t * SCALE
FRAME_DT = 0.05 / SCALE  # frames of dT = 0.05, as run_dam_break in tests/test_sph.py
FRAMES = 62  # T = 0 .. 3.1
DEVICE = "cpu"

EARLY = (MM_T > 1.0) & (MM_T < 1.9)  # where the PBF front leads the experiment by 11-13 %


def particle_area(x, radius, lower, upper, h):
    """Area [m^2] of the union of discs of ``radius`` around the 2D points x inside the box
    [lower, upper], rasterised at spacing h (FlipLiquid.surface() uses such discs)."""
    lower = np.asarray(lower[:2], float)
    n = np.round((np.asarray(upper[:2]) - lower) / h).astype(int)
    covered = np.zeros(n, bool)
    base = np.floor((x[:, :2] - lower) / h).astype(int)
    m = int(np.ceil(radius / h))
    for di in range(-m, m + 1):
        for dj in range(-m, m + 1):
            idx = base + (di, dj)
            centre = lower + (idx + 0.5) * h
            hit = (np.linalg.norm(centre - x[:, :2], axis=1) <= radius) & np.all((idx >= 0) & (idx < n), axis=1)
            covered[idx[hit, 0], idx[hit, 1]] = True
    return covered.sum() * h * h


def run_flip_dam_break(res=20, cfl=1.0, frames=FRAMES, **settings):
    """The dam break with FlipLiquid on a 2D MacGrid of a / dx = ``res`` cells per a (5 res x 2.5 res
    cells, free-slip walls on all four sides, the default FLIP settings: flip ratio 0.95, 4
    jittered particles per cell, reseeding and the density correction on; ``settings`` go to
    FlipLiquid). Each frame of dT = 0.05 takes n equal sub-steps, n = ceil(max face speed x frame
    time / (cfl dx)), as the grid-fluid scenes do.

    Front, recorded every frame: ``Z`` = furthest particle + half a particle spacing (spacing
    dx / sqrt(particles per cell), i.e. + dx / 4), the same rule as the PBF front; ``Z_floor`` = the
    edge of the water on the floor (``martin_moyce.floor_front``); ``Z_cell`` = the
    +x face of the furthest cell holding liquid (a cross-check, quantised to dx). Also the area of
    the particle surface (union of discs of 0.6 dx) over its value at T = 0, the particle count,
    the steps and the wall-clock seconds."""
    dx = A / res
    grid = MacGrid((5 * res, round(2.5 * res)), dx, device=DEVICE)
    flip = FlipLiquid(grid, gravity=(0.0, -G), **settings)
    n0 = flip.add_box((0.0, 0.0), (A, 2.0 * A))
    half = 0.5 * dx / math.sqrt(flip.particles_per_cell)

    def area(x):
        return particle_area(x, 0.6 * dx, grid.lower, grid.upper, dx / 8.0)

    def floor(x):  # the water's edge on the floor (martin_moyce.floor_front, bins one cell wide: the jittered
        # particles leave no gaps there; spray detached ahead does not count)
        return MM.floor_front(np.pad(x[:, :2], ((0, 0), (0, 1))), dx, edge=half) / A

    x = flip.particles.numpy("x")
    area0 = area(x)
    out = {"T": [0.0], "Z": [(x[:, 0].max() + half) / A], "Z_cell": [(np.floor(x[:, 0].max() / dx) + 1) * dx / A],
           "Z_floor": [floor(x)]}
    steps = 0
    start = time.perf_counter()
    for _ in range(frames):
        vmax = max(float(np.abs(f.numpy()).max()) for f in grid.faces)
        n = max(1, math.ceil(vmax * FRAME_DT / (cfl * dx) - 1e-9))
        for _ in range(n):
            flip.step(FRAME_DT / n)
        steps += n
        x = flip.particles.numpy("x")
        if not np.all(np.isfinite(x)):
            raise FloatingPointError(f"FLIP dam break: non-finite particle positions at t = {flip.time:.4f} s")
        front = x[:, 0].max()
        out["T"].append(flip.time * SCALE)
        out["Z"].append((front + half) / A)
        out["Z_cell"].append((np.floor(front / dx) + 1) * dx / A)
        out["Z_floor"].append(floor(x))
    out = {k: np.array(v) for k, v in out.items()}
    out.update(seconds=time.perf_counter() - start, steps=steps, res=res, dx=dx, particles0=n0,
               particles=flip.particle_count(), area=area(x) / area0, fluid=flip)
    return out


@pytest.fixture(scope="module")
def runs():
    """FLIP at a / dx = 20; PBF exactly as tests/test_sph.py (a / spacing = 10, no-slip walls);
    PBF matched to the FLIP run (a / spacing = 20, free-slip walls)."""
    wp.init()
    out = {
        "flip": run_flip_dam_break(res=20),
        "pbf": run_pbf_dam_break(res=10),
        "pbf_matched": run_pbf_dam_break(res=20, wall_friction=0.0),
    }
    for name, r in out.items():
        print(f"\n{name}: a/spacing or a/dx = {r['res']}, {r['steps']} steps, {r['particles']} particles, "
              f"{r['seconds']:.1f} s")
    return out


def at_mm(run, key="Z"):
    return np.interp(MM_T, run["T"], run[key])


def test_flip_dam_break_is_sound(runs):
    """The FLIP run itself: it reaches T = 3.1 in frames of dT = 0.05; the particle front and the
    furthest liquid cell's face agree within one cell at every frame (measured: at most 0.75 dx at
    a / dx = 14, 20 and 40 and FLIP seeds 3..7: no stray particle runs ahead of the liquid); the
    particle surface's area (union of discs of 0.6 dx) stays within 4 % of its start (measured
    +0.9 .. +2.8 % at T = 3.1, the discs over-counting the thin surge's longer surface); reseeding
    adds under 1 % particles (measured 0 or 1 of 3200); the front never retreats by more than half
    a cell between frames (measured: it never retreats by more than 0.001 a); the surge really
    travels (Z > 3 at T = 3.1)."""
    r = runs["flip"]
    assert len(r["T"]) == FRAMES + 1 and abs(r["T"][-1] - 3.1) < 1e-3
    assert np.all(np.diff(r["T"]) > 0.049) and np.all(np.diff(r["T"]) < 0.051)
    gap = np.abs(r["Z"] - r["Z_cell"]).max() * A / r["dx"]
    print(f"FLIP: |Z_particle - Z_cell| <= {gap:.2f} dx, area {r['area']:.3f} of its start, "
          f"particles {r['particles']} / {r['particles0']}")
    assert gap < 1.0
    assert abs(r["area"] - 1.0) < 0.04, r["area"]
    assert r["particles0"] <= r["particles"] < 1.01 * r["particles0"]
    assert r["Z"][-1] > 3.0
    assert np.all(np.diff(r["Z"]) > -0.5 * r["dx"] / A), np.diff(r["Z"]).min()


def test_flip_and_pbf_fronts_agree_at_matched_resolution_and_walls(runs):
    """Two independent methods, the same problem: FLIP (a / dx = 20, free-slip MAC walls) and PBF
    at the same resolution (a / spacing = 20) with free-slip walls (wall_friction 0, all else
    as in tests/test_sph.py). Compared at every frame with 0.8 <= T <= 3.0.

    Measured Z_FLIP / Z_PBF - 1 at every frame in the window: +0.6 % .. +2.9 %; over FLIP seeds
    3..7 -0.3 % .. +2.9 %; pure PIC (flip ratio 0) -2.0 .. -0.3 %; no density correction -0.6 ..
    +2.7 %; cfl 0.5 +0.3 .. +2.2 %; FLIP at a / dx = 14 -3.2 .. +2.9 %, at a / dx = 40 +2.2 .. +3.3 %.
    Asserted: |Z_FLIP / Z_PBF - 1| < 5 % (the largest measured 3.3 % plus margin). Not matched,
    printed for the record and not asserted: PBF exactly as tests/test_sph.py (a / spacing = 10,
    no-slip walls) trails this FLIP run by 4.5 .. 5.6 % for 0.8 <= T <= 2.3 and by up to 8.8 % at
    T = 3 (half the resolution, and the no-slip floor slows the thin late surge; the free-slip PBF
    at a / spacing = 20 has none of the late gap), so that pair does not meet 5 %.)"""
    flip, pbf, ref = runs["flip"], runs["pbf_matched"], runs["pbf"]
    np.testing.assert_allclose(flip["T"], pbf["T"], atol=1e-3)  # both end every frame on the same T
    window = (flip["T"] >= 0.8) & (flip["T"] <= 3.0 + 1e-6)
    rel = flip["Z"][window] / pbf["Z"][window] - 1.0
    z_flip, z_pbf, z_ref = at_mm(flip), at_mm(pbf), at_mm(ref)
    print("\n   T    M&M   FLIP(a/20)  PBF(a/20,slip)  PBF(a/10,no-slip)  FLIP/PBF-1  FLIP/PBF(a/10)-1")
    for row in zip(MM_T, MM_Z, z_flip, z_pbf, z_ref, z_flip / z_pbf - 1.0, z_flip / z_ref - 1.0):
        print("  {:.2f}  {:.2f}  {:9.3f}  {:13.3f}  {:16.3f}  {:+10.3f}  {:+15.3f}".format(*row))
    print(f"every frame 0.8 <= T <= 3: FLIP / PBF(a/20, slip) - 1 in [{rel.min():+.3f}, {rel.max():+.3f}]")
    assert window.sum() > 40
    assert np.all(np.abs(rel) < 0.05), rel


def test_both_methods_lead_martin_moyce_for_1_to_1_9(runs):
    """The claim under test: the front's lead over Martin and Moyce for 1.0 < T < 1.9 belongs to
    the idealised problem, not to the particle method. Measured lead Z / Z_exp - 1 at T = 1.19,
    1.43, 1.63, 1.83: PBF exactly as tests/test_sph.py +11 .. +13 %; FLIP (a / dx = 20) +16 .. +19 %
    (+15 .. +20 % over seeds 3..7 and cfl 0.5; +12 .. +15 % even as pure PIC, the most dissipative
    blend; +16 .. +21 % at a / dx = 40: converged, not a coarse-grid effect); PBF at a / spacing =
    20, free-slip, +13 .. +17 %. Asserted: each leads by more than 8 % at every sample, and the grid
    method's front is at least the tests/test_sph.py PBF front at every sample in the window (it
    measured 4.7 .. 5.6 % further): an independent method does not remove the lead, it keeps or
    enlarges it."""
    leads = {name: at_mm(r)[EARLY] / MM_Z[EARLY] - 1.0 for name, r in runs.items()}
    for name, lead in leads.items():
        print(f"{name}: Z / Z_exp - 1 at T = {MM_T[EARLY]}: {np.round(lead, 3)}")
    for name, lead in leads.items():
        assert np.all(lead > 0.08), (name, lead)
    assert np.all(leads["flip"] >= leads["pbf"]), (leads["flip"], leads["pbf"])
