"""Fracture kernels: springs that break for good once stretched past a threshold.

A spring s joining particles i, j (rest length L, stiffness k, damping kd) breaks when, after a
step, its tensile strain (l - L) / L exceeds ``break_strain[s]`` or its tension
k (l - L) + kd dl/dt [N] exceeds ``break_force[s]`` (``inf`` = no threshold). Breaking sets
``spring_broken[s] = 1``; the force kernels (kernels/forces.py, kernels/cloth.py) then skip the
spring and give it zero Jacobian blocks. The mask is a fixed-size device array, so a step
allocates nothing and stays capturable.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def break_springs(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    spring_indices: wp.array(dtype=int),
    spring_rest_length: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_damping: wp.array(dtype=float),
    spring_break_strain: wp.array(dtype=float),
    spring_break_force: wp.array(dtype=float),
    spring_broken_io: wp.array(dtype=int),
    broken_count_io: wp.array(dtype=int),
):
    """Mark intact springs past their strain or tension threshold as broken (module docstring);
    broken_count_io[0] counts every spring broken so far."""
    s = wp.tid()
    if spring_broken_io[s] != 0:
        return
    i = spring_indices[2 * s]
    j = spring_indices[2 * s + 1]
    u = q[i] - q[j]
    l = wp.length(u)
    rest = spring_rest_length[s]
    stretch = l - rest
    tension = spring_stiffness[s] * stretch
    if l > 1.0e-12:
        tension = tension + spring_damping[s] * wp.dot(qd[i] - qd[j], u / l)
    strain = float(0.0)
    if rest > 0.0:
        strain = stretch / rest
    if strain > spring_break_strain[s] or tension > spring_break_force[s]:
        spring_broken_io[s] = 1
        wp.atomic_add(broken_count_io, 0, 1)
