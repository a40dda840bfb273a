"""Model (topology and parameters on a device) and State (per-step arrays)."""

from __future__ import annotations

import numpy as np
import warp as wp


class State:
    """Per-step particle arrays; each is a ``wp.array(dtype=wp.vec3)`` of shape (particle_count,)."""

    def __init__(self, positions: wp.array, velocities: wp.array, forces: wp.array):
        self.positions = positions
        """Particle positions [m]."""
        self.velocities = velocities
        """Particle velocities [m/s]."""
        self.forces = forces
        """Force accumulated on each particle in the last force evaluation [N]."""

    @property
    def particle_count(self) -> int:
        return self.positions.shape[0]

    def assign(self, other: "State") -> None:
        """Copy another state's arrays into this one (no allocation)."""
        wp.copy(self.positions, other.positions)
        wp.copy(self.velocities, other.velocities)
        wp.copy(self.forces, other.forces)


class Model:
    """Static particle and spring data on one device, built by ``ModelBuilder.finalize``.

    Arrays (all on ``device``):
      particle_q, particle_qd: initial positions [m] / velocities [m/s], wp.vec3, (particle_count,)
      particle_mass, particle_inv_mass: [kg] / [1/kg], float, (particle_count,); inv_mass 0 = pinned
      particle_radius: collision radius [m], float, (particle_count,)
      spring_indices: int, (2 * spring_count,), particles i, j of spring s at 2s, 2s+1
      spring_rest_length [m], spring_stiffness [N/m], spring_damping [N s/m]: float, (spring_count,)
      spring_break_strain [1], spring_break_force [N]: float, (spring_count,); inf = never breaks
      spring_broken: int, (spring_count,), 1 once the spring has broken (warpsim.core.fracture)
      breakable_spring_count: host int, springs with a finite threshold
      particle_spring_offsets: int, (particle_count + 1,), CSR row starts into particle_springs
      particle_springs: int, (2 * spring_count,), the springs touching each particle, ascending
        (each spring appears twice, once per end): spring forces and Jacobians are gathered per
        particle in this fixed order, so every run sums them alike (bit-reproducible)
      particle_q_host, particle_qd_host: the builder's float64 values before their float32 cast,
        numpy (particle_count, 3), or None; batched worlds shift them and cast once, as the scene does
    """

    particle_q: wp.array
    particle_qd: wp.array
    particle_mass: wp.array
    particle_inv_mass: wp.array
    particle_radius: wp.array
    spring_indices: wp.array
    spring_rest_length: wp.array
    spring_stiffness: wp.array
    spring_damping: wp.array
    spring_break_strain: wp.array
    spring_break_force: wp.array
    spring_broken: wp.array
    particle_spring_offsets: wp.array  # CSR adjacency (warpsim.core.builder.ensure_spring_adjacency)
    particle_springs: wp.array
    particle_q_host: np.ndarray | None
    particle_qd_host: np.ndarray | None

    def __init__(self, device):
        self.device = wp.get_device(device)
        self.particle_q_host = self.particle_qd_host = None
        self.particle_count = 0
        self.spring_count = 0
        self.breakable_spring_count = 0

    def state(self) -> State:
        """A new State holding the model's initial positions and velocities."""
        return State(
            wp.clone(self.particle_q),
            wp.clone(self.particle_qd),
            wp.zeros(self.particle_count, dtype=wp.vec3, device=self.device),
        )


def spring_adjacency(spring_indices, particle_count: int) -> tuple:
    """CSR adjacency (offsets (particle_count + 1,), springs (2 * spring_count,)), both int32, of
    the springs touching each particle in ascending spring order; ``spring_indices`` holds the
    ends i, j of spring s at 2s, 2s + 1 (host array)."""
    pairs = np.asarray(spring_indices, dtype=np.int64).reshape(-1, 2)
    ends = pairs.reshape(-1)  # end e belongs to spring e // 2
    springs = np.arange(len(ends), dtype=np.int64) // 2
    order = np.lexsort((springs, ends))  # by particle, then spring
    counts = np.bincount(ends, minlength=particle_count) if len(ends) else np.zeros(particle_count, np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
    return offsets, springs[order].astype(np.int32)


def ensure_spring_adjacency(model) -> None:
    """Give ``model`` its ``particle_spring_offsets`` / ``particle_springs`` (built once; models
    made by ``ModelBuilder.finalize`` already have them)."""
    if getattr(model, "particle_springs", None) is not None:
        return
    offsets, springs = spring_adjacency(model.spring_indices.numpy() if model.spring_count else np.zeros(0),
                                        model.particle_count)
    model.particle_spring_offsets = wp.array(offsets, dtype=int, device=model.device)
    model.particle_springs = wp.array(springs, dtype=int, device=model.device)
