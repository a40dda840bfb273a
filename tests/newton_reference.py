"""Newton's ``SolverVBD`` on warpsim's donut heap: another vertex block descent on the same heap, in the same process.

``NewtonHeap(scene)`` builds a Newton model from a ``donuts`` scene built with ``integrator=vbd``: the same
particles (masses; the tori as built as Newton's rest shape, then the scene's state: positions and velocities),
springs (rest lengths, stiffness, damping: Newton's damping force is kd / h x the length change over the step, ours
kd x the relative velocity along the spring, the same to first order), the tori's surface triangles and edges as
collision primitives only (no membrane or bending stiffness), the same colouring (``ws.VBD``'s over the springs;
Newton's ``ModelBuilder.color`` colours by triangles, tetrahedra and bending edges and would leave spring ends in
one colour), the floor and the four walls as static planes, gravity, and the contact's coefficients: interaction
distance r_c = ``VBDContact.thickness`` for vertex-triangle and edge-edge pairs (``particle_self_contact_margin``)
and for particle-plane contact (every particle's radius), stiffness k_c (``soft_contact_ke`` and the planes'
``ke``), friction mu and its smoothing (Newton's ``friction_epsilon`` is a speed: ours [m] / h), no contact damping,
the same iterations a step and a contact detection every ``detect_every`` iterations. Where the two differ by
design: Newton's contact energy is quadratic k_c / 2 (r_c - d)^2 only down to d = r_c / 2 and a log barrier below
(ours quadratic all the way); Newton checks pairs within one torus too (self contact of every body, with its
topological filter of 2 rings; ours skips pairs of one body unless the scene's ``self_contact``: Newton is given the
tori as built, apart, as its rest shape, with ``particle_rest_shape_contact_exclusion_radius`` 3 r_c, so that it
leaves out the pairs of one torus closer than that at rest: else its vertex queries, which run over every particle,
push the interior lattice's particles near the surface away from their own torus's triangles, and a torus resting on
the floor came to rest 0.6 mm higher than the springs, gravity and floor balance, residual forces up to 1.6 N);
Newton bounds each vertex's motion by its DAT truncation (relaxation 0.85), ours by the step bound of
``warpsim.bodies.vbd``.

Newton is not a warpsim dependency: ``pip install newton`` (pure Python, needs warp-lang >= 1.17; 1.8.0 was the one
measured; the test extra installs it). On a machine with no package index copy its wheel over as Warp's.
"""

from __future__ import annotations

import numpy as np
import warp as wp


def newton_version() -> str | None:
    """Newton's version, or None when it is not installed."""
    try:
        import newton
    except ImportError:
        return None
    return str(newton.__version__)


def surface_edges(faces: np.ndarray) -> np.ndarray:
    """The edges of a closed triangle mesh ``faces`` (F, 3) with their two opposite vertices, as Newton's
    ``add_edges`` takes them: rows (o0, o1, v0, v1), triangles (o0, v0, v1) and (o1, v1, v0); an edge with one
    triangle gets o1 = -1. The edges and their faces are ``meshtools.edge_topology``'s."""
    from warpsim.bodies import meshtools

    directed = meshtools.directed_edges(faces)  # face f's edges (a, b) at rows f, F + f, 2F + f
    opposite = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])  # the corner facing each
    edges, counts, edge_of = meshtools.edge_topology(faces)
    order = np.argsort(edge_of, kind="stable")  # each edge's directed edges together, in row order
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    first = order[starts]
    rows = np.full((len(edges), 4), -1, dtype=np.int64)
    rows[:, 0], rows[:, 2], rows[:, 3] = opposite[first], directed[first, 0], directed[first, 1]
    paired = counts > 1
    rows[paired, 1] = opposite[order[starts[paired] + 1]]
    return rows


def plane_frame(normal, offset: float):
    """The frame of the plane n . x = ``offset`` [m] whose local z axis is the unit ``normal``, as Newton places a
    plane shape (given as an equation, Newton turns z onto the normal by the shortest arc, which has no unique axis
    for n = -z: the wall at +z came out facing +z)."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    axis = np.cross((0.0, 0.0, 1.0), n)
    if np.linalg.norm(axis) < 1.0e-9:
        axis, angle = np.array([1.0, 0.0, 0.0]), (0.0 if n[2] > 0.0 else np.pi)
    else:
        angle = float(np.arccos(np.clip(n[2], -1.0, 1.0)))
        axis = axis / np.linalg.norm(axis)
    rotation = wp.quat_from_axis_angle(wp.vec3(*axis), angle)
    return wp.transform(wp.vec3(*(float(offset) * n)), rotation)


def adjacency_on(device):
    """Newton's ``build_vertex_adjacency_with_warp`` (the CSR adjacency of vertices to edges, triangles and springs
    that ``ModelBuilder.finalize`` builds) with its count and fill kernels launched on ``device`` instead of the CPU:
    for a Warp without its CPU compiler (the GPU machine's), where Newton's own launches on "cpu" fail. The same
    kernels, one thread each as Newton launches them, so the same adjacency; returned as NumPy (values, offsets)."""

    def build(topology, particle_count, *, count_kernel, fill_kernel, values_per_entry):
        topology = topology.to(device)
        counts = wp.zeros(particle_count, dtype=wp.int32, device=device)
        wp.launch(count_kernel, dim=1, inputs=[topology, counts], device=device)
        offsets_np = np.zeros(particle_count + 1, dtype=np.int32)
        offsets_np[1:] = np.cumsum(values_per_entry * counts.numpy())
        offsets = wp.array(offsets_np, dtype=wp.int32, device=device)
        filled = wp.zeros(particle_count, dtype=wp.int32, device=device)
        values = wp.empty(int(offsets_np[-1]), dtype=wp.int32, device=device)
        wp.launch(fill_kernel, dim=1, inputs=[topology, offsets, filled, values], device=device)
        return values.numpy().copy(), offsets_np

    return build


def use_device_for_adjacency(device) -> None:
    """Where Warp has no CPU compiler (``wp.is_cpu_available()`` False), point Newton's adjacency builder at
    ``device`` (``adjacency_on``); elsewhere leave Newton as it is."""
    if wp.is_cpu_available():
        return
    from newton._src.solvers.vbd import solver_vbd
    from newton._src.utils import mesh

    build = adjacency_on(device)
    mesh.build_vertex_adjacency_with_warp = build
    solver_vbd.build_vertex_adjacency_with_warp = build


class NewtonHeap:
    """The heap of a ``donuts`` scene (``integrator=vbd``) as a Newton model stepped by Newton's ``SolverVBD``
    (module docstring). ``load`` copies a warpsim state in, ``step(h)`` takes one step, ``positions`` /
    ``velocities`` read it back [m], [m/s] as (N, 3) arrays."""

    def __init__(self, scene, device=None, iterations: int | None = None, detect_every: int | None = None,
                 gap: float | None = None):
        import newton
        from newton.solvers import SolverVBD

        sim, contact = scene.sim, scene.vbd_contact
        if contact is None:
            raise ValueError("NewtonHeap needs a donuts scene built with integrator=vbd (its ws.VBDContact)")
        integrator = sim.integrator
        model = sim.model
        self.device = wp.get_device(device or model.device)
        use_device_for_adjacency(self.device)
        gravity = float(scene.params["gravity"])
        builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=(0.0, -gravity, 0.0))
        thickness = float(contact.thickness)
        q = model.particle_q.numpy().astype(np.float64)  # the tori as built, apart: Newton's rest shape
        qd = np.zeros_like(q)
        mass = model.particle_mass.numpy().astype(np.float64)
        n = len(q)
        builder.add_particles(pos=[tuple(x) for x in q], vel=[tuple(v) for v in qd], mass=list(mass),
                              radius=[thickness] * n)
        springs = model.spring_indices.numpy().reshape(-1, 2)
        builder.spring_indices.extend(springs.reshape(-1).tolist())
        builder.spring_rest_length.extend(model.spring_rest_length.numpy().astype(np.float64).tolist())
        builder.spring_stiffness.extend(model.spring_stiffness.numpy().astype(np.float64).tolist())
        builder.spring_damping.extend(model.spring_damping.numpy().astype(np.float64).tolist())
        builder.spring_control.extend([0.0] * len(springs))
        faces = np.concatenate([body.faces for body in scene.bodies]).astype(np.int64)
        zeros = [0.0] * len(faces)
        builder.add_triangles(faces[:, 0].tolist(), faces[:, 1].tolist(), faces[:, 2].tolist(), tri_ke=zeros,
                              tri_ka=zeros, tri_kd=zeros, tri_drag=zeros, tri_lift=zeros)
        edges = surface_edges(faces)
        none = [0.0] * len(edges)
        builder.add_edges(edges[:, 0].tolist(), edges[:, 1].tolist(), edges[:, 2].tolist(), edges[:, 3].tolist(),
                          edge_ke=none, edge_kd=none)
        cfg = newton.ModelBuilder.ShapeConfig()
        cfg.ke, cfg.kd, cfg.mu = float(contact.stiffness), 0.0, float(contact.friction)
        cfg.margin = 0.0
        for plane in contact._planes.numpy():
            builder.add_shape_plane(xform=plane_frame(plane[:3], plane[3]), width=0.0, length=0.0, cfg=cfg)
        offsets = integrator.colour_offsets
        order = integrator.colour_particles.numpy()
        builder.set_coloring([order[a:b] for a, b in zip(offsets, offsets[1:])])
        self.model = builder.finalize(device=self.device)
        self.model.soft_contact_ke = float(contact.stiffness)
        self.model.soft_contact_kd = 0.0
        self.model.soft_contact_mu = float(contact.friction)
        self.h = None
        self.iterations = int(iterations or integrator.iterations)
        self.detect_every = int(integrator.detect_every if detect_every is None else detect_every)
        self.friction_eps = float(contact.friction_eps)
        self._solver_cls = SolverVBD
        self._newton = newton
        self.solver = None
        self.state_0 = self.model.state()
        self.state_1 = self.model.state()
        self.control = self.model.control()
        self.gap = 0.5 * thickness if gap is None else float(gap)  # Newton's detection reach past r_c [m]
        self.pipeline = newton.CollisionPipeline(self.model, broad_phase="nxn", soft_contact_gap=self.gap)
        self.contacts = self.pipeline.contacts()
        self.thickness = thickness
        self.exclusion = 3.0 * thickness
        self.load(sim.state.positions, sim.state.velocities)

    def _solver(self, h: float):
        """The solver for step ``h`` [s] (Newton's friction smoothing is a speed: ours over h)."""
        if self.solver is None or self.h != h:
            slot = self._solver_cls.CollisionSlot.SOFT_SELF_CONTACT
            kind = self._solver_cls.CollisionFrequencyType
            frequency, when = ({slot: self.detect_every}, {slot: kind.ITERATIONS}) if self.detect_every else (
                None, {slot: kind.PRE_INIT})
            self.solver = self._solver_cls(
                self.model, iterations=self.iterations, friction_epsilon=self.friction_eps / h,
                particle_enable_self_contact=True, particle_self_contact_margin=self.thickness,
                particle_self_contact_gap=self.gap,
                particle_rest_shape_contact_exclusion_radius=self.exclusion, collision_frequency=frequency,
                collision_frequency_type=when)
            self.h = h
        return self.solver

    def load(self, positions, velocities) -> None:
        """Set the state: positions [m] and velocities [m/s], (N, 3) arrays or warp arrays."""
        for target, source in ((self.state_0.particle_q, positions), (self.state_0.particle_qd, velocities)):
            target.assign(np.asarray(source.numpy() if hasattr(source, "numpy") else source, dtype=np.float32))

    def step(self, h: float) -> None:
        """One step of ``h`` [s]: particle-plane contacts found, then Newton's VBD step."""
        solver = self._solver(h)
        self.state_0.clear_forces()
        self.pipeline.collide(self.state_0, self.contacts)
        solver.step(self.state_0, self.state_1, self.control, self.contacts, h)
        self.state_0, self.state_1 = self.state_1, self.state_0

    def positions(self) -> np.ndarray:
        return self.state_0.particle_q.numpy()

    def velocities(self) -> np.ndarray:
        return self.state_0.particle_qd.numpy()

