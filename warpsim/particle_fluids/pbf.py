"""Lagrangian particle liquid: position-based fluids (PBF), an incompressible SPH-family method.

Method (Macklin and Mueller 2013, "Position Based Fluids"): each step predicts positions under
gravity, finds neighbours once with ``wp.HashGrid`` (candidates filtered by true distance into a
per-particle list, fused with the first density evaluation), then runs Jacobi iterations that
project every particle's density constraint ``C_i = max(rho_i / rho0 - 1, 0)`` and finally
derives velocities from the position change, filtered by XSPH viscosity, optional vorticity
confinement and optional surface tension (Akinci et al. 2013).

Adaptive iterations: a step stops iterating once the mean compression is below
``density_tolerance`` and no particle is compressed by ``peak_tolerance`` (10x) or more;
``iterations`` is the most it runs. It skips the solve only when no particle is compressed by
``density_tolerance`` or more: the compression a step leaves turns into velocity (~ C spacing / dt)
at the next correction, so a local compression left to build up over steps kicks harder the
smaller the steps are. The decision is a one-thread kernel and the loop a ``wp.capture_while``, so
no step reads anything back (a conditional node in a CUDA graph). On the CPU each correction
reuses the kernel gradients its density pass cached in the neighbour list (GPUs re-evaluate them:
cheaper there than storing and re-reading them), and the velocity update is fused with the XSPH /
vorticity / surface-tension filters and the wall friction.

Why PBF on GPUs: every iteration is two embarrassingly parallel gather passes over a neighbour
list built once per step (no linear system, no atomics, no global reductions), it is stable at
time steps set by the CFL condition rather than by a stiff equation of state, and the Jacobi
update conserves momentum exactly (pairwise antisymmetric corrections). Its pressure is
recovered from the multipliers: ``p_i = -rho0 sum_iterations(lambda_i) / dt^2``.

Boundaries are signed-distance boundaries: the domain box walls and the colliders' planes,
spheres and triangle meshes contribute the kernel integral over the solid to the density (so
particles at a wall feel the right density and pressure), and positions are projected to at
least one particle radius in front of every boundary inside each iteration (planes) or after
the solve (spheres, meshes), so no particle ever leaves a closed container.

Time steps: :meth:`ParticleFluid.advance` splits a frame into equal sub-steps chosen from the CFL
condition ``dt <= cfl * spacing / v_max`` (a few small device read-backs per frame: the
largest speed, neighbour-list overflow, sink counts); :meth:`step` itself allocates nothing and,
reads nothing back (so it can be captured in a graph; outside a graph, ``wp.capture_while``
reads its one-int condition per iteration).

Example::

    fluid = ParticleFluid(fluid_block((0, 0, 0), (0.2, 0.4, 0.2), 0.02), spacing=0.02,
                          domain=((0, 0, 0), (1, 1, 0.2)))
    for frame in range(60):
        fluid.advance(1 / 60)
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import warp as wp

from ..core import checks
from ..core.errors import SimulationError
from ..core.reduction import FixedOrderReduction
from ..core.simulator import check_dt
from ..core.solver import SolverBase, frame_steps
from ..kernels import sph as K
from .boundaries import collider_geometry, positive_value
from .dfsph import BOUNDARIES, DfsphSolver
from .emitters import Nozzle, Sink
from .records import FluidRecords
from .smoothing import KERNELS, fluid_block, kernel_numpy, lattice_mass, wall_tables

__all__ = ["KERNELS", "Nozzle", "ParticleFluid", "Sink", "fluid_block", "kernel_numpy"]

METHODS = ("pbf", "dfsph")
"""Pressure solvers of :class:`ParticleFluid`."""
DEFAULT_DENSITY_TOLERANCE = {"pbf": 0.002, "dfsph": 0.0005}
"""Mean compression each method's density solve stops at by default (DFSPH: SPlisHSPlasH's 0.05 %)."""
DEFAULT_WALL_FRICTION = {"pbf": 5.0, "dfsph": 0.0}
"""Wall friction rate [1/s] of each method by default: DFSPH's boundary particles are free-slip walls
(a free-slip DFSPH dam break runs the surge at Martin and Moyce's speed, within 5 %; 5 /s slows it
by 8 %: benchmarks/RESULTS.md)."""


def check_method(method) -> str:
    """The method name, or a ValueError naming the value and the choices."""
    if method not in METHODS:
        raise ValueError(f"method={method!r} is not a particle-fluid method; use method='pbf' (position-based "
                         f"fluids) or method='dfsph' (divergence-free SPH)")
    return method


class ParticleFluid(FluidRecords, SolverBase):
    """Position-based fluid with signed-distance boundaries, emitters and sinks (a
    ``warpsim.core.solver.Solver``: ``advance`` is ``frame`` with CFL-limited sub-steps).

    Args:
        positions: initial particle centres, (N, 3) [m] (e.g. :func:`fluid_block`).
        velocities: initial velocities, (N, 3) [m/s]; default zero.
        spacing: rest particle spacing [m] (particle volume spacing^3; radius spacing/2).
        rest_density: rho0 [kg/m^3].
        capacity: most particles ever alive (emitters fill it); default N.
        domain: (lower, upper) box [m] whose six walls contain the fluid, or None (no walls).
        colliders: warpsim colliders used as static boundaries at their current pose: planes
            (Plane, Planes, Box), Sphere (inside=True: a spherical container), Capsule, Quad
            and TriangleMesh (solid=True: closed, fluid outside; else a thin two-sided surface),
            each thickened by its ``thickness``. Their restitution/friction/mode are not used:
            the fluid's own boundary handling (density contribution + projection) applies.
        gravity: [m/s^2].
        kernel: "cubic" (cubic B-spline) or "wendland" (Wendland C2).
        support: kernel support radius in spacings (default 2: about 33 neighbours).
        iterations: most PBF Jacobi iterations (position corrections) per step. Deep fluids need
            more: Jacobi spreads a correction about one kernel radius per iteration (a dam break
            column of 79 x 158 x 79 particles kept a 2 % mean density error at a fixed 4).
        density_tolerance: (None: 0.002 for PBF, 0.0005 for DFSPH) a step stops iterating once the mean compression
            mean(max(rho/rho0 - 1, 0)) is below this (0: always run ``iterations``), after at
            least one correction if any particle is compressed by this or more; decided on
            the device (``wp.capture_while``), so CUDA steps read nothing back and can be
            captured in a graph.
        peak_tolerance: a step also keeps iterating while any particle is compressed by this
            or more (None: 10 x ``density_tolerance``). Without it small steps let a local
            compression persist under a small mean (each step's single correction removes only
            part of it) and turn it into velocity ~ C spacing / dt: a 27k-particle dam break
            at cfl 0.1 reached 10 % peak compression and 1.5x the speeds of the cfl 0.4 run,
            and the 1M one blew up (101 m/s at t = 0.083 s); with it the cfl 0.1 run tracks
            the cfl 0.4 one (1.76 vs 1.73 m/s) at 1.9 corrections per step.
        viscosity: XSPH coefficient c in [0, 1].
        vorticity: vorticity-confinement strength epsilon [m] (0: off).
        surface_tension: Akinci cohesion/curvature coefficient gamma [1/s^2] (0: off).
        wall_friction: (None: 5 for PBF, 0 for DFSPH) damping rate k [1/s] of a particle's velocity at walls and colliders, a
            time-step independent model of a solid wall's resistance (no-slip drag and the
            contact line's friction on a dry floor): every step v_i *= exp(-k phi_i dt), phi_i
            the solid's share of particle i's kernel support (about 0.5 at a wall; 0 in the
            bulk). 0: free slip. The default 5 /s equals XSPH friction 0.01 per step (the fluid's
            viscosity against the walls' virtual particles at rest) at a dam break's ~2 ms steps;
            being a rate, the front then moves the same at any step size (the per-step form
            made it 9 % slower at cfl 0.05 than at 0.4).
        emitters: list of :class:`Nozzle`; sinks: list of :class:`Sink`.
        cfl: CFL number: sub-steps keep v_max dt <= cfl * spacing. None: 0.4 on the CPU, 0.2 on
            GPUs. Halving the step cuts the corrections a step needs 3.4-4.9x (the compression a
            step builds grows like dt^2), and on a GPU, where a correction is cheap next to the
            neighbour search, that wins: a 1M-particle dam break on an H200 simulates 1.12-1.14x
            more time per wall-clock second at 0.2 than at 0.4 (3.8 vs 12.9-18.5 corrections per
            step); on the CPU (8k particles), 0.4 is 1.2x faster than 0.2.
        max_dt: largest sub-step [s].
        max_neighbors: neighbour-list capacity per particle.
        max_speed: speed [m/s] beyond which the run counts as blown up.
        method: "pbf" (position-based fluids, the default) or "dfsph" (divergence-free SPH, Bender and
            Koschier 2015: a divergence solve and a density solve of the SPH pressure per step,
            ``warpsim.particle_fluids.dfsph``); vorticity and surface tension are PBF's only.
        boundary: DFSPH's domain walls: "particles" (a shell of boundary particles continuing the
            fluid's lattice, in the same hash grid) or "volume" (signed-distance walls, as PBF's).
        kinematic_viscosity: DFSPH: nu [m^2/s] of the SPH (Monaghan) viscosity between fluid particles.
        boundary_viscosity: DFSPH: nu [m^2/s] of the same term against the boundary particles at
            rest (a no-slip wall; boundary="particles").
        no_slip: DFSPH: the walls ``boundary_viscosity`` acts on: "all" (every boundary particle) or
            "floor" (the domain wall gravity points at, edges included; the side walls and a slab's
            front and back walls stay free slip).
        divergence_tolerance: DFSPH: the divergence solve stops when the mean relative density
            change per step is below this (SPlisHSPlasH's 0.1 %).
        moving_boundary: DFSPH with boundary particles: (points (M, 3) [m] at t = 0, velocity (3,)
            [m/s]), boundary particles moving at a constant velocity, e.g. a gate lifted off a column.
        sort_every: every this many frames of :meth:`advance`, reorder the particles into
            spatial (hash-grid cell) order for memory locality (0: never). Indices change, ids
            stay with their particles.
        mass_fraction: every particle's mass (the boundary particles' too) as a fraction of the
            lattice's (1: a block sampled at ``spacing`` starts at ``rest_density``). SPlisHSPlasH uses 0.8 ("to prevent pressure at
            the beginning"): the block starts 20 % under-dense and, its pressure clamped at >= 0,
            soft; a dam break then collapses later (Martin and Moyce's front: +17.7 % -> +6.7 %
            with DFSPH at a/20, benchmarks/RESULTS.md). For comparisons with such codes.
        device: Warp device (None: preferred).

    Arrays (``positions``, ``velocities``, ``ids``, ``density`` [kg/m^3], ``pressure`` [Pa]) are
    views of the first ``active_count`` entries of capacity-sized device buffers.
    """

    def __init__(self, positions, velocities=None, *, spacing, rest_density=1000.0, capacity=None, domain=None,
                 colliders=(), gravity=(0.0, -9.81, 0.0), kernel="cubic", support=2.0, iterations=40,
                 density_tolerance=None, peak_tolerance=None, viscosity=0.01, vorticity=0.0, surface_tension=0.0,
                 wall_friction=None, emitters=(), sinks=(), cfl=None, max_dt=1.0 / 200.0, max_neighbors=64,
                 max_speed=100.0, sort_every=0, method="pbf", boundary="particles", kinematic_viscosity=0.0,
                 boundary_viscosity=0.0, divergence_tolerance=0.001, moving_boundary=None, mass_fraction=1.0,
                 no_slip="all", device=None):
        self.method = check_method(method)
        """Pressure solver: "pbf" (position-based fluids) or "dfsph" (divergence-free SPH)."""
        if boundary not in BOUNDARIES:
            raise ValueError(f"boundary={boundary!r} is unknown; use boundary='particles' (the domain walls as "
                             "boundary particles) or boundary='volume' (signed-distance walls); method='dfsph' only")
        if density_tolerance is None:
            density_tolerance = DEFAULT_DENSITY_TOLERANCE[self.method]
        if wall_friction is None:
            wall_friction = DEFAULT_WALL_FRICTION[self.method]
        filters, cfl = self._check_options(spacing, rest_density, kernel, support, iterations, density_tolerance,
                                           peak_tolerance, viscosity, wall_friction, vorticity, surface_tension, cfl,
                                           max_dt, max_speed, sort_every, max_neighbors, gravity)
        self.mass_fraction = positive_value("mass_fraction", mass_fraction)
        if self.mass_fraction > 2.0:
            raise ValueError(f"mass_fraction = {mass_fraction}: the block would start over twice its rest density; "
                             "use a value in (0, 2] (1: at rest density)")
        pos, vel = self._check_particles(positions, velocities, capacity)
        self._check_domain(domain, pos)
        self._check_emitters(emitters, sinks)
        planes_n, planes_o, capsules, meshes = self._collect_boundaries(colliders)
        d = wp.get_device(device)
        self.device = d
        self.cfl = (0.4 if d.is_cpu else 0.2) if cfl is None else cfl
        """CFL number of :meth:`advance`'s sub-steps."""
        self._upload_boundaries(planes_n, planes_o, capsules, meshes)
        self._set_params(*filters)
        self._allocate(pos, vel, max_neighbors)
        self._reset_counters(len(pos))
        self._dfsph = None
        if self.method == "dfsph":
            self._dfsph = DfsphSolver(
                positions=self._x, velocities=self._v, density_out=self._density, pressure_out=self._pressure,
                params=self._params, boundaries=self._boundaries, domain=self.domain, spacing=self.spacing,
                support=self.h / self.spacing, boundary=boundary,
                kinematic_viscosity=positive_value("kinematic_viscosity", kinematic_viscosity, allow_zero=True),
                boundary_viscosity=positive_value("boundary_viscosity", boundary_viscosity, allow_zero=True),
                density_tolerance=self.density_tolerance,
                divergence_tolerance=positive_value("divergence_tolerance", divergence_tolerance),
                iterations=self.iterations, total_counter=self._total_iterations,
                grid_dims=self.grid_dims, max_neighbors=max_neighbors, device=d,
                moving_boundary=moving_boundary, no_slip=no_slip)
        elif moving_boundary is not None:
            raise ValueError("moving_boundary (boundary particles moving at a constant velocity) needs method='dfsph'")
        elif no_slip != "all":
            raise ValueError(f"no_slip={no_slip!r} (boundary viscosity on some walls only) needs "
                             "method='dfsph'")

    # ------------------------------------------------------------------------------ construction steps
    def _check_options(self, spacing, rest_density, kernel, support, iterations, density_tolerance, peak_tolerance,
                       viscosity, wall_friction, vorticity, surface_tension, cfl, max_dt, max_speed, sort_every,
                       max_neighbors, gravity):
        """Validate the scalar options (before anything touches the device); returns the filter
        coefficients (viscosity, wall_friction, vorticity, surface_tension) and the cfl option."""
        self.spacing = positive_value("spacing", spacing)
        self.rest_density = positive_value("rest_density", rest_density)
        if kernel not in KERNELS:
            raise ValueError(f"kernel {kernel!r} is unknown; use one of {sorted(KERNELS)}")
        self.kernel = kernel
        support = positive_value("support", support)
        if support < 1.0:
            raise ValueError(f"support = {support} spacings is too small; use >= 1 (2 is typical)")
        self.h = support * self.spacing
        """Kernel support radius [m]."""
        if int(iterations) != iterations or iterations < 1:
            raise ValueError(f"iterations = {iterations!r}; it must be an integer >= 1")
        self.iterations = int(iterations)
        self.density_tolerance = positive_value("density_tolerance", density_tolerance, allow_zero=True)
        if peak_tolerance is None:
            peak_tolerance = 10.0 * self.density_tolerance if self.density_tolerance > 0.0 else 3.0e38
        self.peak_tolerance = positive_value("peak_tolerance", peak_tolerance)
        if not (0.0 <= float(viscosity) <= 1.0):
            raise ValueError(f"viscosity = {viscosity}; it must be in [0, 1]")
        wall_friction = positive_value("wall_friction", wall_friction, allow_zero=True)
        vorticity = positive_value("vorticity", vorticity, allow_zero=True)
        surface_tension = positive_value("surface_tension", surface_tension, allow_zero=True)
        if cfl is not None:
            cfl = positive_value("cfl", cfl)
        self.max_dt = positive_value("max_dt", max_dt)
        self.max_speed = positive_value("max_speed", max_speed)
        if int(sort_every) != sort_every or sort_every < 0:
            raise ValueError(f"sort_every = {sort_every!r}; it must be an integer >= 0 (0: never sort)")
        self.sort_every = int(sort_every)
        if int(max_neighbors) != max_neighbors or max_neighbors < 1:
            raise ValueError(f"max_neighbors = {max_neighbors!r}; it must be an integer >= 1")
        self.gravity = np.array(checks.vec3(gravity, "gravity"))
        return (float(viscosity), wall_friction, vorticity, surface_tension), cfl

    def _check_particles(self, positions, velocities, capacity):
        """Validated (N, 3) float64 positions and velocities; sets ``capacity``."""
        pos = np.asarray(positions, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ValueError(f"positions must have shape (N, 3), got {pos.shape}")
        n = len(pos)
        bad = np.flatnonzero(~np.all(np.isfinite(pos), axis=1))
        if len(bad):
            raise ValueError(f"particle {int(bad[0])} has a non-finite position {pos[bad[0]]}; give finite positions")
        vel = np.zeros_like(pos) if velocities is None else np.asarray(velocities, dtype=np.float64)
        if vel.shape != pos.shape:
            raise ValueError(f"velocities must have shape {pos.shape} like positions, got {vel.shape}")
        bad = np.flatnonzero(~np.all(np.isfinite(vel), axis=1))
        if len(bad):
            raise ValueError(f"particle {int(bad[0])} has a non-finite velocity {vel[bad[0]]}; give finite velocities")
        capacity = n if capacity is None else capacity
        if int(capacity) != capacity or capacity < max(n, 1):
            raise ValueError(f"capacity = {capacity!r}; it must be an integer >= the {n} initial particles and >= 1")
        self.capacity = int(capacity)

        return pos, vel

    def _check_domain(self, domain, pos):
        """The (lower, upper) wall box, with every particle inside it."""
        self.domain = None
        if domain is not None:
            try:
                lo, hi = domain
            except (TypeError, ValueError):
                raise ValueError(f"domain must be (lower, upper) or None, got {domain!r}") from None
            lo, hi = np.array(checks.vec3(lo, "domain lower")), np.array(checks.vec3(hi, "domain upper"))
            if np.any(hi - lo < 2.0 * self.spacing):
                raise ValueError(f"domain upper {tuple(hi)} must exceed lower {tuple(lo)} by >= 2 spacings on every axis")
            self.domain = (lo, hi)
            outside = np.flatnonzero(np.any((pos < lo - 1e-6) | (pos > hi + 1e-6), axis=1))
            if len(outside):
                k = int(outside[0])
                raise ValueError(f"particle {k} at {pos[k]} is outside the domain {tuple(lo)}..{tuple(hi)}; "
                                 "place the fluid inside the domain box")


    def _check_emitters(self, emitters, sinks):
        self.emitters = list(emitters)
        for k, e in enumerate(self.emitters):
            if not isinstance(e, Nozzle):
                raise ValueError(f"emitters[{k}] is {type(e).__name__}, not a warpsim.Nozzle")
        self.sinks = list(sinks)
        for k, s in enumerate(self.sinks):
            if not isinstance(s, Sink):
                raise ValueError(f"sinks[{k}] is {type(s).__name__}, not a warpsim.Sink")


    def _collect_boundaries(self, colliders):
        """Host-side boundary geometry (validated before anything touches the device): plane
        normals and offsets (the domain walls first), capsules and meshes."""
        planes_n, planes_o, capsules, meshes = [], [], [], []
        if self.domain is not None:
            lo, hi = self.domain
            eye = np.eye(3)
            planes_n += list(eye) + list(-eye)
            planes_o += list(lo) + list(-hi)
        self.colliders = list(colliders)
        for k, c in enumerate(self.colliders):
            g = collider_geometry(k, c)
            if g[0] == "planes":
                lengths = np.linalg.norm(g[1], axis=1)
                if np.any(~np.isfinite(lengths)) or np.any(lengths == 0.0) or np.any(~np.isfinite(g[2])):
                    raise ValueError(f"colliders[{k}]: every plane normal must be non-zero and every offset finite")
                planes_n += list(g[1] / lengths[:, None])
                planes_o += list(g[2])
            elif g[0] == "capsule":
                capsules.append(g[1:])
            else:
                meshes.append(g[1:])

        return planes_n, planes_o, capsules, meshes

    def _upload_boundaries(self, planes_n, planes_o, capsules, meshes):
        """The ``K.Boundaries`` struct on the device, with the wall tables of the kernel."""
        d, kernel = self.device, self.kernel
        self._meshes = [wp.Mesh(points=wp.array(pts.astype(np.float32), dtype=wp.vec3, device=d),
                                indices=wp.array(faces.astype(np.int32).reshape(-1), dtype=int, device=d))
                        for pts, faces, _, _ in meshes]

        def arr(values, shape, dtype):
            return wp.array(np.array(values, dtype=np.float32 if dtype is not int else np.int32).reshape(shape),
                            dtype=dtype, device=d)

        b = K.Boundaries()
        b.plane_normals = arr(planes_n, (-1, 3), wp.vec3)
        b.plane_offsets = arr(planes_o, (-1,), float)
        b.capsule_a = arr([c[0] for c in capsules], (-1, 3), wp.vec3)
        b.capsule_b = arr([c[1] for c in capsules], (-1, 3), wp.vec3)
        b.capsule_radii = arr([c[2] for c in capsules], (-1,), float)
        b.capsule_signs = arr([c[3] for c in capsules], (-1,), float)
        b.mesh_ids = wp.array(np.array([m.id for m in self._meshes], np.uint64), dtype=wp.uint64, device=d)
        b.mesh_solid = arr([m[2] for m in meshes], (-1,), int)
        b.mesh_thickness = arr([m[3] for m in meshes], (-1,), float)
        phi, dphi = wall_tables(self.h, kernel, self.spacing)
        b.phi_table = wp.array(phi.astype(np.float32), dtype=float, device=d)
        b.dphi_table = wp.array(dphi.astype(np.float32), dtype=float, device=d)
        self._boundaries = b
        self._has_shapes = bool(capsules or meshes)


    def _set_params(self, viscosity, wall_friction, vorticity, surface_tension):
        """The ``K.FluidParams`` struct: kernel normalisation, particle mass and filter coefficients."""
        kernel = self.kernel
        self.particle_mass = self.mass_fraction * lattice_mass(self.spacing, self.h, self.rest_density, kernel)
        """Mass of every particle [kg]."""
        p = K.FluidParams()
        p.h = self.h
        p.kernel = KERNELS[kernel]
        p.rest_density = self.rest_density
        p.mass = self.particle_mass
        p.radius = 0.5 * self.spacing
        p.gravity = wp.vec3(*self.gravity)
        p.relaxation = 1.0e-6 / self.spacing**2
        p.viscosity = float(viscosity)
        p.vorticity = vorticity
        p.surface_tension = surface_tension
        p.wall_friction = wall_friction
        h = self.h
        p.inv_h = 1.0 / h
        p.h2 = h * h
        if kernel == "cubic":
            w_norm, g_norm = 8.0 / (math.pi * h**3), 48.0 / (math.pi * h**4)
        else:
            w_norm, g_norm = 21.0 / (2.0 * math.pi * h**3), 210.0 / (math.pi * h**4)
        p.w_scale = self.particle_mass * w_norm
        p.g_scale = self.particle_mass / self.rest_density * g_norm
        p.self_density = self.particle_mass * w_norm
        self._params = p
        self._use_curl = vorticity > 0.0 or surface_tension > 0.0
        self._use_filters = self._use_curl or viscosity > 0.0 or wall_friction > 0.0


    def _allocate(self, pos, vel, max_neighbors):
        """Every device buffer, sized once to ``capacity`` (a step allocates nothing)."""
        d, n = self.device, len(pos)
        cap = self.capacity
        x0 = np.zeros((cap, 3), np.float32)
        v0 = np.zeros((cap, 3), np.float32)
        x0[:n], v0[:n] = pos, vel
        ids0 = np.zeros(cap, np.int32)
        ids0[:n] = np.arange(n)
        self._x = wp.array(x0, dtype=wp.vec3, device=d)
        self._v = wp.array(v0, dtype=wp.vec3, device=d)
        self._ids = wp.array(ids0, dtype=int, device=d)
        self._xp = wp.zeros(cap, dtype=wp.vec3, device=d)
        self._xq = wp.zeros(cap, dtype=wp.vec3, device=d)
        self._vtmp = wp.zeros(cap, dtype=wp.vec3, device=d)
        self._density = wp.zeros(cap, dtype=float, device=d)
        self._pressure = wp.zeros(cap, dtype=float, device=d)
        self._lambda = wp.zeros(cap, dtype=float, device=d)
        self._lambda_sum = wp.zeros(cap, dtype=float, device=d)
        self._bgrad = wp.zeros(cap, dtype=wp.vec3, device=d)
        self._curl = wp.zeros(cap, dtype=wp.vec3, device=d)
        self._normal = wp.zeros(cap, dtype=wp.vec3, device=d)
        nb = K.NeighborList()
        nb.capacity = int(max_neighbors)
        nb.count = wp.zeros(cap, dtype=int, device=d)
        nb.index = wp.zeros(cap * nb.capacity, dtype=int, device=d)
        # cache the pair gradients on the CPU (one thread: compute is dear); re-evaluate them on GPUs,
        # where writing and re-reading them cost more (H200, 1M particles: a dam-break step at CFL
        # steps 31.2 ms cached, 11.5 ms re-evaluated; the position-correction pass 4.4x faster)
        nb.cache_gradients = int(d.is_cpu)
        nb.grad_factor = wp.zeros(cap * nb.capacity if nb.cache_gradients else 1, dtype=float, device=d)
        nb.stride_i, nb.stride_k = nb.capacity, 1  # row-major: measured faster than column-major on an H200 too
        self._neighbors = nb
        self._overflow = wp.zeros(1, dtype=int, device=d)
        self._reduce = wp.zeros(2, dtype=float, device=d)
        self._compression = wp.zeros(cap, dtype=float, device=d)  # C_i = max(rho_i / rho0 - 1, 0)
        # sum and max of C in a fixed order (no float atomics: the iteration count is the same every run)
        self._stat_reduction = FixedOrderReduction(2, first_max_column=1, device=d)
        self._stats = self._stat_reduction.result  # (sum of C, max C)
        self._counter = wp.zeros(1, dtype=int, device=d)  # corrections in the current / last step
        self._total_iterations = wp.zeros(1, dtype=int, device=d)
        self._go = wp.zeros(1, dtype=int, device=d)  # loop condition of wp.capture_while
        self._zero = wp.zeros(1, dtype=int, device=d)
        self._adaptive = self.density_tolerance > 0.0
        self._fused_density = d.is_cpu  # first density pass inside the neighbour search (see the kernel)
        self._alive = wp.zeros(cap, dtype=int, device=d)
        self._slot = wp.zeros(cap, dtype=int, device=d)
        self._ids_tmp = wp.zeros(cap, dtype=int, device=d)
        if self.sinks:
            self._sink_lower = wp.array(np.array([s.lower for s in self.sinks], np.float32), dtype=wp.vec3, device=d)
            self._sink_upper = wp.array(np.array([s.upper for s in self.sinks], np.float32), dtype=wp.vec3, device=d)
            self._sink_removed = wp.zeros(len(self.sinks), dtype=int, device=d)
        self._emit_offsets = [wp.array(e.layer_offsets(self.spacing).astype(np.float32), dtype=wp.vec3, device=d)
                              for e in self.emitters]

        if self.domain is not None:
            extent = self.domain[1] - self.domain[0]
            dims = [int(min(128, max(1, math.ceil(e / self.h)))) for e in extent]
        else:
            dims = [64, 64, 64]
        self._grid = wp.HashGrid(*dims, device=d)
        self.grid_dims = tuple(dims)


    def _reset_counters(self, n):
        self.active_count = n
        """Particles alive now (the first ``active_count`` entries of every buffer)."""
        self.next_id = n
        """Id the next emitted particle receives (ids are never reused)."""
        self.time = 0.0
        """Simulated time [s]."""
        self.step_count = 0
        self.frame_count = 0
        self.last_substeps = 0
        self.last_dt = 0.0
        """Length of the last step [s] (0 before the first)."""
        self.dropped = 0
        """Particles an emitter could not emit because the capacity was full."""

    # ------------------------------------------------------------------------------ views
    @property
    def positions(self) -> wp.array:
        """Particle positions [m], wp.vec3, shape (active_count,)."""
        return self._x[: self.active_count]

    @property
    def velocities(self) -> wp.array:
        """Particle velocities [m/s], wp.vec3, shape (active_count,)."""
        return self._v[: self.active_count]

    @property
    def ids(self) -> wp.array:
        """Persistent particle ids, int32, shape (active_count,)."""
        return self._ids[: self.active_count]

    @property
    def density(self) -> wp.array:
        """Density [kg/m^3] at the last constraint evaluation, shape (active_count,)."""
        return self._density[: self.active_count]

    @property
    def pressure(self) -> wp.array:
        """Pressure [Pa] of the last step (-rho0 sum(lambda) / dt^2), shape (active_count,)."""
        return self._pressure[: self.active_count]

    @property
    def state(self):
        """This fluid as a warpsim State-like object (positions, velocities), for USD writers."""
        return _FluidState(self)

    @property
    def last_iterations(self) -> int:
        """Position corrections (PBF) or pressure iterations of both solves (DFSPH) the last step ran
        (a device read-back)."""
        if self._dfsph is not None:
            return self._dfsph.last_iterations
        return int(self._counter.numpy()[0])

    @property
    def total_iterations(self) -> int:
        """Position corrections over all steps (with step_count: the mean per step; a read-back)."""
        return int(self._total_iterations.numpy()[0])

    @property
    def total_mass(self) -> float:
        return self.particle_mass * self.active_count

    # ------------------------------------------------------------------------------ stepping
    def _emit(self, dt: float) -> None:
        for e, offsets in zip(self.emitters, self._emit_offsets):
            for shift in e.layers_due(self.time, dt, self.spacing):
                k = min(offsets.shape[0], self.capacity - self.active_count)
                if k < offsets.shape[0]:
                    if self.dropped == 0:
                        warnings.warn(f"ParticleFluid capacity {self.capacity} is full: emitters stop emitting; "
                                      "raise capacity= or add a Sink", RuntimeWarning, stacklevel=3)
                    self.dropped += offsets.shape[0] - k
                if k <= 0:
                    continue
                origin = e.center + e.direction * shift
                wp.launch(K.emit_particles, k,
                          inputs=[offsets, wp.vec3(*origin), wp.vec3(*(e.direction * e.speed)), self.active_count,
                                  self.next_id],
                          outputs=[self._x, self._v, self._ids], device=self.device)
                self.active_count += k
                self.next_id += k
                e.emitted += k

    def step(self, dt: float) -> None:
        """One PBF step of ``dt`` [s] (emitters included). Allocates nothing; in a CUDA graph reads
        nothing back (outside one, the iteration loop reads its condition, one int, per iteration).

        Keep consecutive steps of similar size: like every position-based method, PBF turns the
        compression a step leaves into velocity over the next one, so a much shorter step right
        after a long one kicks the particles (``advance`` uses equal sub-steps per frame)."""
        dt = check_dt(dt)
        if self.step_count == 0 and self._dfsph is not None:
            self._check_first_step(dt)
        self._emit(dt)
        n = self.active_count
        if n > 0:
            self._solve(n, dt)
        self.time += dt
        self.step_count += 1

    def _check_first_step(self, dt: float) -> None:
        """Before the first step (one read-back): a RuntimeWarning when ``dt`` exceeds the CFL-limited
        step for the speed reachable within it (:meth:`cfl_dt`), the step :meth:`advance` keeps to."""
        limit = self.cfl_dt(horizon=dt)
        if dt > limit * (1.0 + 1e-6):
            warnings.warn(f"ParticleFluid(method={self.method!r}): step dt = {dt:.4g} s exceeds the CFL-limited step "
                          f"{limit:.4g} s (cfl {self.cfl:g} x spacing / the speed reachable within the step, at most "
                          "max_dt): the run may be unstable; use advance(frame_dt), which sub-steps within the limit, "
                          "or a smaller dt", RuntimeWarning, stacklevel=3)

    def _solve(self, n: int, dt: float) -> None:
        if self._dfsph is not None:
            self._dfsph.solve(n, dt, self.time)
            self.last_dt = dt
            return
        d, p, b = self.device, self._params, self._boundaries
        x, v = self._x[:n], self._v[:n]
        xp, xq = self._xp[:n], self._xq[:n]
        wp.launch(K.predict_positions, n, inputs=[p, b, x, v, dt, xp], device=d)
        self._lambda_sum.zero_()
        self._counter.zero_()
        self._build_neighbors(xp, n, with_stats=1)
        self._stat_reduction.sum_max(self._compression, n)
        # Jacobi corrections while the mean compression is above density_tolerance, at most
        # `iterations`: the decision is taken on the device (iteration_control), so the loop reads
        # nothing back inside a CUDA graph (wp.capture_while makes it a conditional node there)
        control = [self._stats, n, self.density_tolerance, self.peak_tolerance, 0, self.iterations]
        outputs = [self._counter, self._total_iterations, self._go]
        wp.launch(K.iteration_control, 1, inputs=[*control, 0], outputs=outputs, device=d)
        nb = self._neighbors

        def body():
            wp.launch(K.solve_density_correct, n, inputs=[p, b, xp, nb, self._lambda, self._bgrad],
                      outputs=[self._lambda_sum, xq], device=d)
            wp.copy(xp, xq, count=n)
            # skipped on the device after the last allowed correction (counter + 1 >= iterations; the
            # stale sums then read are not used: iteration_control stops at the iteration cap)
            wp.launch(K.solve_density_lambda, n, inputs=[p, b, xp, nb, 1, self._counter, self.iterations - 1],
                      outputs=[self._density, self._lambda, self._bgrad, self._compression], device=d)
            self._stat_reduction.sum_max(self._compression, n)
            wp.launch(K.iteration_control, 1, inputs=[*control, 1], outputs=outputs, device=d)

        wp.capture_while(self._go, body)
        if self._has_shapes:
            wp.launch(K.project_boundaries, n, inputs=[p, b, xp], device=d)
        if self._use_filters:
            if self._use_curl:
                wp.launch(K.compute_curl_normals, n, inputs=[p, x, xp, dt, self._density, nb],
                          outputs=[self._curl, self._normal], device=d)
            wp.launch(K.apply_velocity_filters, n,
                      inputs=[p, b, x, xp, self._density, nb, self._curl, self._normal, int(self._use_curl),
                              self._lambda_sum, dt],
                      outputs=[v, self._pressure], device=d)
            wp.copy(x, xp, count=n)
        else:
            wp.launch(K.update_velocities, n, inputs=[p, x, xp, self._lambda_sum, dt], outputs=[v, self._pressure],
                      device=d)
        self.last_dt = dt

    def _build_neighbors(self, x, n: int, with_stats: int = 0) -> None:
        """Neighbour lists at positions ``x`` and the densities, multipliers and pair gradients
        there (in the same pass on the CPU, in a second one on GPUs)."""
        d, p, b, nb = self.device, self._params, self._boundaries, self._neighbors
        self._grid.build(x, self.h)
        wp.launch(K.find_neighbors_density, n, inputs=[self._grid.id, p, b, x, int(self._fused_density), with_stats],
                  outputs=[nb, self._overflow, self._density, self._lambda, self._bgrad, self._compression],
                  device=d)
        if not self._fused_density:
            wp.launch(K.solve_density_lambda, n, inputs=[p, b, x, nb, with_stats, self._zero, 1],
                      outputs=[self._density, self._lambda, self._bgrad, self._compression], device=d)

    def cfl_dt(self, horizon: float = 0.0) -> float:
        """Largest step [s] allowed by the CFL condition for the speed the fluid may reach within
        ``horizon`` [s] under gravity, capped by ``max_dt``. Reads one value back; raises
        SimulationError if the state is not finite or exceeds ``max_speed``."""
        vmax = self.max_speed_now()
        vbound = vmax + float(np.linalg.norm(self.gravity)) * horizon
        if vbound <= 0.0:
            return self.max_dt
        return min(self.max_dt, self.cfl * self.spacing / vbound)

    def advance(self, frame_dt: float, max_substeps: int = 1000) -> int:
        """Advance one frame of ``frame_dt`` [s] in equal CFL-limited sub-steps (emitters run per
        sub-step, sinks once at the end). Returns the number of sub-steps."""
        frame_dt = check_dt(frame_dt)
        dt = self.cfl_dt(horizon=frame_dt)
        substeps = max(1, math.ceil(frame_dt / dt - 1e-9))
        if substeps > max_substeps:
            raise SimulationError(
                f"frame {self.frame_count + 1}: the CFL condition asks for {substeps} sub-steps (> {max_substeps}); "
                "the fluid is far too fast: lower gravity/emitter speed or check the setup",
                step=self.step_count, time=self.time, particle=-1, frame=self.frame_count + 1)
        self.frame(frame_dt, substeps)
        return substeps

    def frame(self, frame_dt: float, steps: int = 1) -> None:
        """Advance one frame of ``frame_dt`` [s] in ``steps`` equal sub-steps (emitters run per
        sub-step, sinks once at the end; particles sorted every ``sort_every`` frames)."""
        frame_dt, steps = frame_steps(frame_dt, steps, "ParticleFluid")
        h = frame_dt / steps
        if self.sort_every and self.frame_count % self.sort_every == 0:
            self.sort_particles()
        for _ in range(steps):
            self.step(h)
        self.apply_sinks()
        self.frame_count += 1
        self.last_substeps = steps
        self._check_overflow()

    def sort_particles(self) -> None:
        """Reorder the active particles into hash-grid cell order (ids move with them)."""
        n = self.active_count
        if n == 0:
            return
        self._grid.build(self._x[:n], self.h)
        wp.launch(K.gather_sorted, n, inputs=[self._grid.id, self._x, self._v, self._ids],
                  outputs=[self._xp, self._vtmp, self._ids_tmp], device=self.device)
        self._take_moved(n)

    def _take_moved(self, m: int) -> None:
        """Copy the first m reordered particles back from the temporaries that gather_sorted /
        compact_particles wrote."""
        for dst, src in ((self._x, self._xp), (self._v, self._vtmp), (self._ids, self._ids_tmp)):
            wp.copy(dst, src, count=m)

    def _check_overflow(self) -> None:
        over = int(self._overflow.numpy()[0])
        if self._dfsph is not None:
            over = max(over, self._dfsph.overflow())
        if over > 0:
            self._overflow.zero_()
            warnings.warn(f"a particle had {over} neighbours but max_neighbors = {self._neighbors.capacity}; the extra ones "
                          "were ignored: raise max_neighbors", RuntimeWarning, stacklevel=3)

    def apply_sinks(self) -> int:
        """Remove particles inside any sink (stable compaction; one read-back of the per-sink
        counts). Returns the number removed."""
        n = self.active_count
        if not self.sinks or n == 0:
            return 0
        d = self.device
        self._sink_removed.zero_()
        wp.launch(K.mark_alive, n, inputs=[self._x[:n], self._sink_lower, self._sink_upper],
                  outputs=[self._alive, self._sink_removed], device=d)
        removed = self._sink_removed.numpy()
        total = int(removed.sum())
        if total == 0:
            return 0
        wp.utils.array_scan(self._alive[:n], self._slot[:n], inclusive=False)
        wp.launch(K.compact_particles, n, inputs=[self._alive, self._slot, self._x, self._v, self._ids],
                  outputs=[self._xp, self._vtmp, self._ids_tmp], device=d)
        m = n - total
        self._take_moved(m)
        self.active_count = m
        for sink, count in zip(self.sinks, removed):
            sink.removed += int(count)
        return total


class _FluidState:
    """positions/velocities view of a ParticleFluid for code that expects a warpsim State."""

    def __init__(self, fluid):
        self.positions = fluid.positions
        self.velocities = fluid.velocities
        self.ids = fluid.ids

    @property
    def particle_count(self):
        return self.positions.shape[0]
