"""WorldBatch: N worlds of one scene as one model, stepped by one launch per stage.

The batch is tiled on the device from world 0 (built once by the scene's own Python builder):
particle and spring arrays are repeated with per-world index offsets (``kernels/worlds.py``),
and the varied parameters enter through per-world arrays found by :mod:`warpsim.worlds.plan`
(shifted initial positions / velocities, proportional masses and spring coefficients,
per-world gravity and wall coefficients). ``model.particle_world`` (shape (N P,)) maps each
particle to its world; world w owns particles ``w P .. (w + 1) P - 1``.

Worlds never interact: springs join particles of one world, every force and collider acts per
particle, and particle-particle collisions pair particles of one world only (their hash grid is
keyed by ``model.particle_world``). A
world that blows up (non-finite state or a speed above the scene's ``max_speed``) is flagged at
the end of the frame and frozen at its last good frame; the others run on.
"""
from __future__ import annotations

import copy
import dataclasses

import numpy as np
import warp as wp

from ..bodies.colliders import Planes
from ..core.integrators import ImplicitEuler
from ..core.forces import Springs
from ..core.model import Model, ensure_spring_adjacency
from ..kernels import worlds as KW
from .forces import WorldGravity, WorldPlanes
from .plan import FLOAT_ARRAYS, VEC3_ARRAYS, StructuralError, host_values, make_plan
from .shared import SPRING_PARAMS, SharedStepper, eligibility, world_walls

__all__ = ["WorldBatch", "is_agent_scene"]

ADJACENCY_ARRAYS = ("particle_spring_offsets", "particle_springs")



class WorldBatch:
    """N worlds of scene class ``cls`` with parameters ``world_params`` (one dict each).

    ``fused=True`` steps a scene that uses ``ws.Simulator`` with semi-implicit Euler through the
    cloth solver's fused step instead (``ClothSemiImplicitEuler``: one particle-centric kernel per
    step without atomics on GPUs, frames as captured graphs): the same physics, summed in another
    order (agrees to float32 rounding, not bit for bit).

    Attributes: ``scene`` (world 0 as built by the scene, used for declarations and frame
    data), ``sim`` (the batched simulator), ``model`` (the tiled model: ``world_count``,
    ``world_particle_count``, ``world_spring_count``, ``particle_world``), ``params`` (typed
    parameters per world), ``varied`` (keys that differ), ``world_bad`` (1 = blown up, frozen)
    and ``world_blown_frame`` (first bad frame, -1 none), both of shape (world_count,).

    ``shared`` (None: wherever eligible, the default; see :mod:`warpsim.worlds.shared`): the
    springs, their adjacency and base parameters are stored once for all worlds and one fused
    kernel per sub-step sums each particle's springs, integrates and resolves the walls,
    bit-identical to the tiled path (``shared=False``: every array tiled per world, one launch
    per stage) and to the scene's own Simulator, with a quarter of the memory per world.
    ``block_per_world`` (shared path): a frame's sub-steps in one launch, one thread block per
    world (``kernels/world_step.py: frame_shared_worlds``), the same bits.

    Step counts (:meth:`world_steps`): each world takes the steps a frame its scene takes run
    alone with its parameters (with automatic timing, from its own stability limit, estimated as
    its own run estimates it), so world N of a sweep equals ``warpsim run SCENE --set ...`` with
    its parameters, bit for bit on the same device, whichever worlds share its batch (on CUDA too:
    the mass-spring step's kernel modules build without FMA contraction, so the shared path's fused
    kernel and a lone run's Simulator kernels round alike; ``kernels/world_step.py``). The shared
    path masks per world (worlds past their count idle); the other paths run one pass per distinct
    count (:mod:`warpsim.worlds.passes`). Scenes whose stepping the passes cannot repeat (breaking
    springs, colliders following a host ``motion``, a scene's own sub-stepping) take the largest
    count for every world (``own_counts`` False; a re-run is then told the sweep's count).

    ``reference_params``: the parameter list of the sweep these worlds belong to (None: the
    worlds themselves). Its first world is the tiling base and its values shape the plan, so a
    world gets the same arrays, and with the fixed-order gathers the same bits every step,
    whichever batch it runs in: a world of a sweep re-runs alone exactly
    (:func:`warpsim.sweeps.rerun.rerun_world`)."""

    def __init__(self, cls, world_params, device=None, *, fused=False, reference_params=None, shared=None,
                 block_per_world=False):
        if len(world_params) < 1:
            raise ValueError("a batch needs at least one world")
        self.cls = cls
        self.device = wp.get_device(device)
        self.params = [cls.resolve_params(p) for p in world_params]
        reference = self.params if reference_params is None else [cls.resolve_params(p) for p in reference_params]
        if not reference:
            raise ValueError("reference_params is empty; give the sweep's parameter list (or None)")
        base = reference[0]
        self.varied = [k for k in cls.params if any(p[k] != base[k] for p in reference + self.params)]
        self.scene = cls(base, device=self.device)
        sim0 = getattr(self.scene, "sim", None)
        if sim0 is None or not hasattr(sim0, "model"):
            raise StructuralError(f"scene {cls.name!r} is not driven by a warpsim Simulator; batched worlds tile "
                                  "a Simulator's model (supported: bounce, springs, teapot, cloth, drape, ...)")
        if isinstance(sim0.integrator, _implicit_integrators()):
            raise StructuralError(f"scene {cls.name!r} uses implicit Euler, whose conjugate-gradient solve would "
                                  "couple the worlds of a batch; use --set integrator=semi_implicit_euler")
        if getattr(sim0, "adaptive", False):
            raise StructuralError("adaptive sub-stepping picks one step count for all worlds; turn it off")
        def probe(p):
            try:
                return cls(p, device="cpu")
            except StructuralError:
                raise
            except ValueError as exc:
                bad = {k: p[k] for k in self.varied if p[k] != base[k]}
                raise ValueError(f"a world with {', '.join(f'{k}={v}' for k, v in bad.items())}: {exc}") from None

        self.plan = make_plan(cls, self.scene, base, reference if reference_params is None else
                              reference + self.params, self.varied, probe)
        self.fused = bool(fused)
        why = eligibility(sim0)
        if shared and (why or self.fused):
            raise StructuralError(f"shared=True needs a mass-spring scene the fused world step serves; scene "
                                  f"{cls.name!r} has {'fused=True' if self.fused else why}")
        self.shared = why is None and not self.fused if shared is None else bool(shared)
        self._scales = {}
        self.model = self._tile(sim0.model)
        self.sim = self._simulator(sim0)
        self.stepper = None
        self._steps = None  # (key, counts) of world_steps
        self._passes = None
        if self.shared:  # the simulator was built without springs; the model counts every world's
            self.model.spring_count = self.world_count * self.model.world_spring_count
            gravity = next((f.g for f in self.sim.forces if isinstance(f, WorldGravity)), None)
            if gravity is None:
                gravity = np.tile(np.asarray(sim0.forces[0].g, dtype=np.float64), (self.world_count, 1))
            self.stepper = SharedStepper(self, sim0.model, self._scales, self._world_values,
                                         self._key_count, gravity, world_walls(self.sim.colliders,
                                                                               self.world_count, self.device),
                                         block_per_world=block_per_world)
            self.sim.stability_model = self._springs_model
        self.batch_scene = copy.copy(self.scene)
        self.batch_scene.sim = self.sim
        self.batch_scene.use_timing(self.scene.timing, limit=self)  # automatic steps: each world's own limit
        if hasattr(self.batch_scene, "model"):
            self.batch_scene.model = self.model
        n, d = self.world_count, self.device
        self.world_bad = wp.zeros(n, dtype=int, device=d)
        self.world_blown_frame = wp.full(n, -1, dtype=int, device=d)
        self.frame_counter = wp.zeros(1, dtype=int, device=d)
        self.q_good = wp.clone(self.sim.state.positions)
        self.max_speed = float(getattr(sim0, "max_speed", 1.0e4))

    # ------------------------------------------------------------------ building
    @property
    def world_count(self) -> int:
        return len(self.params)

    def _deltas(self, effect):
        p = np.array([np.atleast_1d(np.asarray(q[effect.key], dtype=np.float64)) for q in self.params])
        return p - effect.p0  # (N, d)

    def _tile(self, m0):
        n, P, S, d = self.world_count, m0.particle_count, m0.spring_count, self.device
        mb = Model(d)
        mb.particle_count, mb.spring_count = n * P, n * S
        mb.world_count, mb.world_particle_count, mb.world_spring_count = n, P, S
        mb.particle_world = wp.empty(n * P, dtype=int, device=d)
        wp.launch(KW.tile_world_index, n * P, inputs=[max(P, 1), mb.particle_world], device=d)
        for name in VEC3_ARRAYS:
            mask = np.zeros(P, dtype=bool)
            shift = np.zeros((n, 3))
            origin = None
            movers = [e for e in self.plan.values() if name in e.vec3]
            if len(movers) == 1 and name in movers[0].origin:  # canonical: origin + C p_w
                effect = movers[0]
                changed, C = effect.vec3[name]
                mask[changed] = True
                origin = effect.origin[name]
                shift = (self._deltas(effect) + effect.p0) @ C.T
                movers = []
            for effect in movers:
                if name in effect.vec3:
                    changed, C = effect.vec3[name]
                    if mask.any() and not np.array_equal(mask, changed):
                        raise StructuralError(f"{effect.key} and another varied key shift different particles' "
                                              f"{name}; vary one of them")
                    mask[changed] = True
                    shift += self._deltas(effect) @ C.T
            setattr(mb, name, self._shifted(m0, name, origin, mask, shift))
        keys = [k for k, e in self.plan.items() if e.scale]
        values = np.array([[p[k] for k in keys] for p in self.params], dtype=np.float32).reshape(-1)
        world_values = wp.array(values if len(values) else np.zeros(1, np.float32), dtype=float, device=d)
        self._world_values, self._key_count = world_values, max(len(keys), 1)
        for name in FLOAT_ARRAYS:
            base = getattr(m0, name)
            count = base.shape[0]
            key = np.full(count, -1, dtype=np.int32)
            coefficient = np.zeros(count, dtype=np.float32)
            for k, kname in enumerate(keys):
                c = self.plan[kname].scale.get(name)
                if c is None:
                    continue
                changed = ~np.isnan(c)
                if (key[changed] >= 0).any():
                    raise StructuralError(f"{kname} and another varied key both scale {name}; vary one of them")
                key[changed] = k
                coefficient[changed] = c[changed]
            if self.shared and name in SPRING_PARAMS:  # stored once; the fused step scales per world
                self._scales[name] = (base.numpy(), wp.array(key, dtype=int, device=d),
                                      wp.array(coefficient, dtype=float, device=d))
                continue
            out = wp.empty(n * count, dtype=float, device=d)
            if count:
                wp.launch(KW.tile_float, n * count, inputs=[base, wp.array(key, dtype=int, device=d),
                                                            wp.array(coefficient, dtype=float, device=d),
                                                            world_values, max(len(keys), 1), out], device=d)
            setattr(mb, name, out)
        for name, base in vars(m0).items():  # further per-element arrays (e.g. breakable springs)
            if not isinstance(base, wp.array) or hasattr(mb, name) or name in ("particle_inv_mass", "spring_indices",
                                                                              *ADJACENCY_ARRAYS):
                continue
            if self.shared and name.startswith("spring_"):
                continue
            count = P if name.startswith("particle_") else S if name.startswith("spring_") else None
            if count is None or base.shape[0] != count:
                raise StructuralError(f"model array {name} is neither per particle nor per spring; batched worlds "
                                      "cannot tile it")
            out = wp.empty(n * count, dtype=base.dtype, device=d)
            if count and base.dtype == wp.int32:
                wp.launch(KW.tile_int, n * count, inputs=[base, out], device=d)
            elif count and base.dtype == wp.float32:
                wp.launch(KW.tile_float, n * count, inputs=[base, wp.full(count, -1, dtype=int, device=d),
                                                            wp.zeros(count, dtype=float, device=d), world_values, 1,
                                                            out], device=d)
            elif count:
                raise StructuralError(f"model array {name} has dtype {base.dtype}; batched worlds tile int and float")
            setattr(mb, name, out)
        for name, value in vars(m0).items():  # further per-world counts (e.g. breakable_spring_count)
            if name.endswith("_count") and isinstance(value, int) and not name.startswith(("world_", "particle_",
                                                                                            "spring_")):
                setattr(mb, name, n * value)
        mass = mb.particle_mass.numpy() if "particle_mass" in self._scaled() else None
        if mass is not None and (mass < 0).any():
            bad = int(np.flatnonzero(mass < 0)[0])
            raise ValueError(f"world {bad // P} has particle {bad % P} with negative mass {mass[bad]}; give masses >= 0")
        mb.particle_inv_mass = wp.empty(n * P, dtype=float, device=d)
        wp.launch(KW.inverse_masses, n * P, inputs=[mb.particle_mass, mb.particle_inv_mass], device=d)
        if self.shared:  # the springs stay world 0's (SharedStepper); the batch's own simulator has none
            mb.spring_count = 0  # (set to n S once the simulator exists)
            return mb
        mb.spring_indices = wp.empty(2 * n * S, dtype=int, device=d)
        if S:
            wp.launch(KW.tile_spring_indices, 2 * n * S, inputs=[m0.spring_indices, P, mb.spring_indices], device=d)
        self._tile_adjacency(m0, mb)
        return mb

    def _shifted(self, m0, name, origin, mask, shift):
        """World w's ``name`` (vec3, (n P,) on the device): ``origin[e] + shift[w]`` for the particles
        in ``mask`` (P,), ``origin[e]`` for the others; summed in float64 from the values the builder
        was given and cast to float32 once, as a scene built with world w's values casts them (origin
        None: ``m0``'s, :func:`host_values`; ``shift`` (n, 3) float64). Nothing shifted: tiled on
        the device."""
        n, P, d = len(shift), len(mask), self.device
        out = wp.empty(n * P, dtype=wp.vec3, device=d)
        if not mask.any():
            wp.launch(KW.tile_vec3, n * P, inputs=[getattr(m0, name), wp.zeros(P, dtype=float, device=d),
                                                    wp.zeros(n, dtype=wp.vec3, device=d), out], device=d)
            return out
        base = host_values(m0, name) if origin is None else origin
        chunk = max(1, (1 << 20) // P)  # worlds per host block (~24 MB of float64)
        for w0 in range(0, n, chunk):
            w1 = min(n, w0 + chunk)
            block = np.where(mask[None, :, None], base[None] + shift[w0:w1, None, :], base[None]).astype(np.float32)
            wp.copy(out, wp.array(block.reshape(-1, 3), dtype=wp.vec3, device="cpu"), dest_offset=w0 * P,
                    count=(w1 - w0) * P)
        return out

    def _tile_adjacency(self, m0, mb):
        """World w's CSR spring adjacency = world 0's with springs + w S and offsets + 2 w S: each
        particle sums its springs in the same order as in a run of its world alone."""
        n, P, S, d = self.world_count, m0.particle_count, m0.spring_count, self.device
        ensure_spring_adjacency(m0)
        mb.particle_spring_offsets = wp.full(n * P + 1, 2 * n * S, dtype=int, device=d)
        mb.particle_springs = wp.empty(2 * n * S, dtype=int, device=d)
        if P:
            wp.launch(KW.tile_spring_indices, n * P, inputs=[m0.particle_spring_offsets[:P], 2 * S,
                                                            mb.particle_spring_offsets[: n * P]], device=d)
        if S:
            wp.launch(KW.tile_spring_indices, 2 * n * S, inputs=[m0.particle_springs, S, mb.particle_springs], device=d)

    def _scaled(self):
        return {name for e in self.plan.values() for name in e.scale}

    def _affine(self, base_value, coefficients, key_effects):
        """(N, ...) per-world values base + sum_k C_k (p_w,k - p0,k)."""
        out = np.tile(np.asarray(base_value, dtype=np.float64), (self.world_count, 1))
        for effect, C in key_effects:
            out += self._deltas(effect) @ np.atleast_2d(C).T
        return out

    def _simulator(self, sim0):
        integrator = copy.copy(sim0.integrator)
        integrator.reset()  # a copy: prepare() allocates for the batched system
        forces = []
        for j, f in enumerate(sim0.forces):
            effects = [(e, e.gravity[j]) for e in self.plan.values() if j in e.gravity]
            if effects:
                forces.append(WorldGravity(self._affine(f.g, None, effects)))
            elif self.shared and isinstance(f, Springs):
                continue  # the fused world step sums the shared springs
            elif getattr(f, "particles", None) is not None or hasattr(f, "particle"):
                raise StructuralError(f"force {type(f).__name__} acts on chosen particles of one world; batched "
                                      "worlds do not tile it (remove it, e.g. --set drag=)")
            else:
                forces.append(copy.copy(f))
        colliders, tiled = [], {}
        for j, c in enumerate(sim0.colliders):
            if isinstance(c, Planes):
                coeff = {a: [(e, e.planes[j][a]) for e in self.plan.values() if j in e.planes and a in e.planes[j]]
                         for a in ("restitution", "friction")}
                r = self._affine([c.restitution], None, coeff["restitution"])[:, 0]
                mu = self._affine([c.friction], None, coeff["friction"])[:, 0]
                colliders.append(WorldPlanes(c, r, mu))
            elif hasattr(c, "tile"):  # per-world contact between bodies (ws.SoftContact): each world's own
                tiled[id(c)] = c.tile(self.world_count, self.model.world_particle_count)
                colliders.append(tiled[id(c)])
            else:  # shared shapes (each world meets its own copy); particle pairs keyed by world
                colliders.append(copy.copy(c))
        if getattr(integrator, "contacts", None):
            # an integrator that pushes contacts inside its iterations (ws.FastMassSpring) pushes the
            # batch's tiled contacts, not the single world's
            missing = [type(c).__name__ for c in integrator.contacts if id(c) not in tiled]
            if missing:
                raise StructuralError(f"the integrator's contacts ({', '.join(missing)}) are not among the scene's "
                                      "colliders; batched worlds tile only those")
            integrator.contacts = [tiled[id(c)] for c in integrator.contacts]
        if hasattr(integrator, "tile_worlds"):  # ws.VBD: its contact keeps each world's bodies apart
            integrator.tile_worlds(self.world_count, self.model.world_particle_count)
        if getattr(integrator, "body_size", None) is not None and not getattr(integrator, "springs_per_copy", False):
            # ws.FastMassSpring: one matrix for every copy of every world
            varied = sorted({e.key for e in self.plan.values() for name in e.scale if name != "particle_radius"})
            if varied:
                raise StructuralError(f"{varied[0]} changes the springs or masses between worlds, but integrator "
                                      f"{integrator.name} shares one matrix among the bodies of all worlds; set it "
                                      "with --set (one sweep per value) or vary it with --set integrator=implicit_euler")
        kwargs = {"forces": forces, "colliders": colliders, "max_speed": sim0.max_speed, "check_every": 0}
        if self.fused and not hasattr(sim0, "use_graph"):
            from ..cloth.solver import ClothSemiImplicitEuler, ClothSimulator
            from ..core.integrators import SemiImplicitEuler

            if not isinstance(sim0.integrator, SemiImplicitEuler):
                raise StructuralError("fused=True steps with semi-implicit Euler; the scene uses "
                                      f"{sim0.integrator.name}")
            # the cloth's fused step: springs, gravity and the update in one particle-centric
            # kernel (gather mode on GPUs), frames captured as graphs by the ClothSimulator
            return ClothSimulator(self.model, ClothSemiImplicitEuler(), **kwargs)
        if hasattr(sim0, "use_graph"):
            kwargs["use_graph"] = sim0.use_graph
        return type(sim0)(self.model, integrator, **kwargs)

    # ------------------------------------------------------------------ stepping
    def can_capture(self) -> bool:
        """Whether a frame may be captured as one CUDA graph: not when the simulator captures its
        own frames (cloth, ``fused``) or a collider follows a host ``motion`` callback."""
        if hasattr(self.sim, "use_graph"):
            return False
        return not any(getattr(c, "motion", None) is not None for c in self.sim.colliders)

    def end_frame(self) -> None:
        """Flag worlds that blew up during the frame, freeze them, advance the frame counter."""
        end_frame(self)

    def advance(self, frame_dt, substeps) -> None:
        """One frame for every world (the scene's own stepping on the batched simulator; with
        ``fused`` the ClothSimulator's captured frame)."""
        counts = self.world_steps(frame_dt, substeps)
        if self.stepper is not None:
            self.stepper.frame(frame_dt, counts)  # each world its own count, one kernel per sub-step
        elif counts.min() == counts.max():
            self._advance_all(frame_dt, substeps, int(counts[0]))
        else:
            if self._passes is None or not np.array_equal(self._passes.host_counts, counts):  # no read-back
                from .passes import CountPasses

                self._passes = CountPasses(self, counts)
            self._passes.frame(lambda c: self._advance_all(frame_dt, substeps, c))
        self.end_frame()

    def _advance_all(self, frame_dt, substeps, count) -> None:
        """Every world a frame of ``count`` steps by the scene's own stepping."""
        timing = self.batch_scene.timing
        if timing.auto:  # the scene steps by its timing: the count given
            self.batch_scene.use_timing(timing.with_steps(int(count)))
        try:
            if self.fused and not hasattr(self.scene.sim, "use_graph"):
                self.sim.frame(frame_dt, int(count))
            else:
                self.batch_scene.advance(frame_dt, substeps)
        finally:
            if timing.auto:
                self.batch_scene.use_timing(timing, limit=self)

    @property
    def own_counts(self) -> bool:
        """Whether each world takes its own count (False: the largest for all; see the class doc)."""
        if self.stepper is not None:
            return True
        sim = self.sim
        if getattr(sim, "fracture", None) is not None or any(getattr(c, "motion", None) is not None
                                                              for c in sim.colliders):
            return False
        from ..cloth.solver import ClothSimulator
        from ..scenes import SimulatorScene
        from ..scenes.cloth import ClothScene

        advance = type(self.batch_scene).advance
        return advance in (SimulatorScene.advance, ClothScene.advance) or (self.fused and isinstance(sim,
                                                                                                     ClothSimulator))

    def world_steps(self, frame_dt, substeps) -> np.ndarray:
        """Steps each world takes in a frame of ``frame_dt`` [s] (``substeps``: as the scene's
        ``frame_steps`` takes it), shape (world_count,): the count its scene takes run alone with
        its parameters (its own rule, e.g. cloth's steps per sub-step; automatic timing: from that
        world's own limit, whatever count the batch's timing was fixed to); the batch's count for
        every world when not :attr:`own_counts`."""
        scene, timing = self.batch_scene, self.batch_scene.timing
        key = (float(frame_dt), str(substeps), timing)
        if self._steps is not None and self._steps[0] == key:
            return self._steps[1]
        n = self.world_count
        if not timing.auto or not self.own_counts:
            counts = np.full(n, int(scene.frame_steps(frame_dt, substeps)), dtype=np.int64)
        else:  # a count fixed for the whole batch (e.g. a sweep's largest) does not bind a world: its own does
            own = dataclasses.replace(timing, fixed=False)
            counts = np.empty(n, dtype=np.int64)
            try:
                for w, limit in enumerate(self.world_limits()):
                    scene.use_timing(own, limit=limit)
                    counts[w] = scene.frame_steps(frame_dt, substeps)
            finally:
                scene.use_timing(timing, limit=self)
        self._steps = (key, counts)
        return counts

    def stable_dt(self) -> np.ndarray:
        """Largest stable step [s] of each world, shape (world_count,) (``Simulator.stability``
        per world: power iteration normalised per world)."""
        return np.array([limit.dt for limit in self.stability()])

    def stability(self, iterations=None) -> list:
        """One ``ws.StabilityLimit`` per world, linearised about the initial positions
        (``iterations``: power iterations, None: ``warpsim.core.stability.POWER_ITERATIONS``)."""
        from ..core.stability import POWER_ITERATIONS, particle_limits

        sim = self.sim
        return particle_limits(self._springs_model(), self.model.particle_q, sim.integrator, sim.forces, sim.colliders,
                               particle_world=self.model.particle_world.numpy(), world_count=self.world_count,
                               iterations=POWER_ITERATIONS if iterations is None else int(iterations),
                               tiled=(self.model.world_particle_count, self.model.world_spring_count))

    def _springs_model(self):
        """The model whose springs the stability estimate reads: the batch's own, or on the shared
        path (springs stored once) a stand-in with every world's springs tiled, built for the
        estimate and dropped after it (the tiled path's arrays, the same values)."""
        if not self.shared:
            return self.model
        import types

        m0, n, d = self.scene.sim.model, self.world_count, self.device
        P, S = m0.particle_count, m0.spring_count
        stand_in = types.SimpleNamespace(**{k: v for k, v in vars(self.model).items()})
        stand_in.spring_count = n * S
        stand_in.spring_indices = wp.empty(2 * n * S, dtype=int, device=d)
        if S:
            wp.launch(KW.tile_spring_indices, 2 * n * S, inputs=[m0.spring_indices, P, stand_in.spring_indices],
                      device=d)
        for name in SPRING_PARAMS:
            base, key, coefficient = self._scales[name]
            out = wp.empty(n * S, dtype=float, device=d)
            if S:
                wp.launch(KW.tile_float, n * S, inputs=[wp.array(base, dtype=float, device=d), key, coefficient,
                                                        self._world_values, self._key_count, out], device=d)
            setattr(stand_in, name, out)
        for name in ("spring_broken", "_stability_adjacency"):
            vars(stand_in).pop(name, None)
        self._tile_adjacency(m0, stand_in)  # world 0's CSR tiled on the device (not sorted again on the host)
        return stand_in

    def world_limits(self) -> list:
        """:meth:`stability` computed once (the worlds' limits about their initial positions): each
        world's estimate starts where its own run's starts and takes as many power iterations
        (``warpsim.core.stability.POWER_ITERATIONS``), so it is its own run's limit, bit for bit."""
        if getattr(self, "_world_limits", None) is None:
            self._world_limits = self.stability()
        return self._world_limits

    def auto_steps(self, frame_dt, minimum=1) -> int:
        """The most steps a frame of ``frame_dt`` [s] takes with automatic timing (the batch's
        launches per frame on the shared path): the max over the worlds of each world's own count
        (at least ``minimum``, within ``AUTO_SAFETY`` x its own limit from its own stiffness,
        masses and damping); each world takes its own (:meth:`world_steps`)."""
        return max(limit.substeps_for(frame_dt, minimum=int(minimum)) for limit in self.world_limits())

    def substeps_for(self, frame_dt, minimum=1) -> int:
        """:meth:`auto_steps`: the batch is the limit its scene's automatic steps keep inside."""
        return self.auto_steps(frame_dt, minimum)

    def use_timing(self, timing):
        """Step the frames to come by ``timing`` (a :class:`~warpsim.scenes.timing.FrameTiming`):
        with automatic timing not yet fixed, each world takes its own count (:meth:`world_steps`).
        Returns the timing with the most steps a frame takes (:meth:`auto_steps`; the scene's own
        rule on top, e.g. cloth's steps per sub-step)."""
        self.batch_scene.use_timing(timing, limit=self)
        return self.batch_scene.current_timing()

    def stability_warning(self, frame_dt, substeps):
        """One line naming the worlds whose step is above their limit, else the first world's scene's own line
        (``Scene.scene_warning``: e.g. the donuts' fall faster than its contact follows; said of world 0, the scene
        the batch builds, when values vary); None when neither."""
        from ..core.stability import worlds_warning

        labels = [", ".join(f"{k}={p[k]}" for k in self.varied) for p in self.params]
        steps = frame_dt / self.world_steps(frame_dt, substeps)  # each world's own step [s]
        line = worlds_warning(self.world_limits(), steps, labels)
        if line is None and hasattr(self.scene, "scene_warning"):
            line = self.scene.scene_warning(frame_dt, substeps)  # built with the first world's values
            if line is not None and labels[0]:
                line = f"world 0 ({labels[0]}; the others not checked): {line}"
        return line

    def world_slices(self, ticket=None):
        """Host copies (N, P, 3) of the positions and velocities: now, or those a
        :meth:`start_host_copy` ``ticket`` began (then views of pinned buffers, valid until the
        ticket after next starts)."""
        n, P = self.world_count, self.model.world_particle_count
        if ticket is not None:
            x, v = self._host_copies.wait(ticket)
            return x.reshape(n, P, 3), v.reshape(n, P, 3)
        st = self.sim.state
        broken = getattr(self.model, "spring_broken", None)  # breakable springs: each world's own mask
        self._frame_broken = None if broken is None else broken.numpy().reshape(n, -1)
        return st.positions.numpy().reshape(n, P, 3), st.velocities.numpy().reshape(n, P, 3)

    def can_copy_ahead(self) -> bool:
        """Whether a frame's host copy may be taken while the next frame steps
        (:meth:`start_host_copy`): on CUDA devices, for scenes with no per-world spring mask."""
        return self.device.is_cuda and getattr(self.model, "spring_broken", None) is None

    def start_host_copy(self) -> int:
        """Begin copying the positions and velocities to pinned host buffers on a copy stream
        (:class:`warpsim.worlds.host_copies.HostCopies`, double-buffered); returns the ticket
        :meth:`world_slices` takes. CUDA only (:meth:`can_copy_ahead`)."""
        from .host_copies import HostCopies

        st = self.sim.state
        if getattr(self, "_host_copies", None) is None:
            self._host_copies = HostCopies([st.positions, st.velocities], self.device)
        return self._host_copies.start([st.positions, st.velocities])

    def batch_frame_data(self, x, v):
        """Every world's frame data at once from the host copies ``x``, ``v`` (N, P, 3) of
        :meth:`world_slices`: ``{prim: {key: (N, ...) array or list}}`` from the scene's
        :meth:`~warpsim.scenes.Scene.frame_arrays` (the description its own ``frame_data()`` is
        made from), or None when the scene gives none (:meth:`world_frame_data` per world then)."""
        from ..usd.frame_arrays import batch_frame_data, described

        description = described(self.scene)
        return None if description is None else batch_frame_data(description, x, v)

    def world_frame_data(self, x, v, world=None):
        """The scene's frame data for one world whose positions / velocities are ``x``, ``v`` (P, 3)
        (``world``: its index in the batch, needed when springs can break: the frame data then
        draws that world's own broken springs, read by the last :meth:`world_slices`)."""
        sim0 = self.scene.sim
        saved, saved_model = sim0.state, sim0.model
        view = copy.copy(saved)
        view.positions = wp.array(np.ascontiguousarray(x), dtype=wp.vec3, device="cpu")
        view.velocities = wp.array(np.ascontiguousarray(v), dtype=wp.vec3, device="cpu")
        sim0.state = view
        broken = getattr(self, "_frame_broken", None)
        had_report = "last_report" in vars(self.scene)
        saved_report = getattr(self.scene, "last_report", None)
        if broken is not None and world is not None:
            from types import SimpleNamespace

            mask = broken[int(world)]
            model = copy.copy(saved_model)
            model.spring_broken = wp.array(mask, dtype=saved_model.spring_broken.dtype, device="cpu")
            sim0.model = model
            seen = self.__dict__.setdefault("_broken_seen", {})
            before = seen.get(int(world), np.zeros_like(mask))
            self.scene.last_report = SimpleNamespace(springs=np.flatnonzero((mask != 0) & (before == 0)))
            seen[int(world)] = mask.copy()
        try:
            return self.scene.frame_data()
        finally:
            sim0.state, sim0.model = saved, saved_model
            if had_report:
                self.scene.last_report = saved_report
            elif "last_report" in vars(self.scene):
                del self.scene.last_report


def _implicit_integrators() -> tuple:
    """The implicit Euler classes a batch refuses: the particles' and, when its module is loaded (a cloth
    scene's simulator has imported it), the cloth's (this module does not import the cloth solver)."""
    import sys

    cloth = sys.modules.get("warpsim.cloth.solver")
    return (ImplicitEuler,) if cloth is None else (ImplicitEuler, cloth.ClothImplicitEuler)


def is_agent_scene(scene_cls) -> bool:
    """Whether ``scene_cls`` is an agent scene (:class:`warpsim.scenes.agents.AgentScene`: its module is
    loaded wherever one exists; a sweep of springs imports no agent code), batched by
    :class:`warpsim.worlds.agents.AgentWorldBatch`."""
    import sys

    agents = sys.modules.get("warpsim.scenes.agents")
    return agents is not None and issubclass(scene_cls, agents.AgentScene)


def end_frame(batch) -> None:
    """The end of a frame for any batch (``sim.state``, ``model.particle_world``, ``world_bad``,
    ``world_blown_frame``, ``frame_counter``, ``q_good``, ``max_speed``, ``device``): count the
    frame, flag the worlds that blew up, record when, and freeze them at their last good positions."""
    st, m, d = batch.sim.state, batch.model, batch.device
    wp.launch(KW.count_frame, 1, inputs=[batch.frame_counter], device=d)
    wp.launch(KW.flag_blown_worlds, m.particle_count,
              inputs=[st.positions, st.velocities, m.particle_world, batch.max_speed, batch.world_bad], device=d)
    wp.launch(KW.record_blow_ups, batch.world_count, inputs=[batch.world_bad, batch.frame_counter,
                                                             batch.world_blown_frame], device=d)
    wp.launch(KW.freeze_blown_worlds, m.particle_count,
              inputs=[m.particle_world, batch.world_bad, batch.q_good, st.positions, st.velocities,
                      m.particle_inv_mass], device=d)
