"""Model (topology and parameters on a device) and State (per-step arrays)."""

from __future__ import annotations

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

    def __init__(self, device):
        self.device = wp.get_device(device)
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
