"""A float64 NumPy reference of the differentiable physics, for checking gradients by central
finite differences (tests/test_differentiable.py) and for benchmarks.

A scene is a plain dict (``Scene``): particles, springs, forces, colliders, integrator, step and
step count; ``simulate(scene)`` returns the positions of every step, (steps + 1, n, 3) [m], with
the formulas of the Warp kernels (kernels/forces.py, kernels/integrate.py, kernels/collide.py,
kernels/autodiff.py) in double precision. ``build(scene, device, differentiable)`` makes the
matching ``ws.Simulator`` / ``ws.ClothSimulator``.

Scene keys: q (n, 3) [m], v (n, 3) [m/s], mass (n,) [kg] (0 pins), radius (n,) [m];
springs: list of (i, j, stiffness [N/m], damping [N s/m], rest length [m]);
forces: list of ("gravity", g), ("constant", force, indices or None), ("drag", linear, quadratic),
("wind", kwargs of ws.Wind), ("magnets", centers (M, 3), strengths (M,), softening, cutoff or None);
colliders: list of ("plane", normal, offset, kwargs) or ("sphere", center, radius, kwargs), kwargs
of ws.Plane / ws.Sphere (restitution, friction, mode, stiffness, inside);
integrator: "explicit_euler", "semi_implicit_euler" or "cloth" (ClothSimulator's fused
semi-implicit Euler); h [s]; steps.
"""

from __future__ import annotations

import copy

import numpy as np

from ..bodies.colliders import MODES, damping_ratio_for_restitution


def _forces(scene, q, v, t, include_gravity=True):
    m = np.asarray(scene["mass"], dtype=np.float64)
    w = np.where(m > 0.0, 1.0 / np.where(m > 0.0, m, 1.0), 0.0)
    f = np.zeros_like(q)
    for spec in scene["forces"]:
        kind = spec[0]
        if kind == "gravity":
            if include_gravity:
                f += m[:, None] * np.asarray(spec[1], dtype=np.float64)
        elif kind == "constant":
            idx = np.arange(len(q)) if spec[2] is None else np.asarray(spec[2])
            np.add.at(f, idx, np.asarray(spec[1], dtype=np.float64))
        elif kind == "drag":
            speed = np.linalg.norm(v, axis=1, keepdims=True)
            f -= (spec[1] + spec[2] * speed) * v
        elif kind == "wind":
            from ..core.forces import Wind

            air = Wind(**spec[1]).air_velocity(t)
            f += np.where(w[:, None] > 0.0, spec[1].get("coefficient", 0.1) * (air - v), 0.0)
        elif kind == "magnets":
            centers, strengths, soft, cutoff = np.asarray(spec[1], float).reshape(-1, 3), spec[2], spec[3], spec[4]
            for c, s in zip(centers, np.broadcast_to(strengths, (len(centers),))):
                d = c - q
                r2 = np.sum(d * d, axis=1, keepdims=True)
                s2 = r2 + soft * soft
                on = (w[:, None] > 0.0) & ((cutoff is None) | (r2 < (cutoff or 0.0) ** 2))
                f += np.where(on, s * d / (s2 * np.sqrt(s2)), 0.0)
    for i, j, k, kd, rest in scene["springs"]:
        u = q[i] - q[j]
        length = np.linalg.norm(u)
        if length < 1.0e-12:
            continue
        d = u / length
        fs = -(k * (length - rest) + kd * np.dot(v[i] - v[j], d)) * d
        f[i] += fs
        f[j] -= fs
    return f, w


def _respond(v, n, e, mu):
    vn = v @ n
    if vn >= 0.0:
        return v
    vt = v - vn * n
    length = np.linalg.norm(vt)
    if length > 0.0:
        vt = vt * max(0.0, 1.0 - mu * (1.0 + e) * (-vn) / length)
    return vt - e * vn * n


def _penalty(v, n, h, k, zeta, mu, w, dt):
    vn = v @ n
    dvn = dt * k * h * w - min(1.0, dt * 2.0 * zeta * np.sqrt(k * w)) * vn
    vt = v - vn * n
    length = np.linalg.norm(vt)
    if length > 0.0:
        vt = vt * max(0.0, 1.0 - mu * abs(dvn) / length)
    return vt + (vn + dvn) * n


def _impact(v, n, h, d0, a_n, e, mu, dt):
    vn = v @ n
    b = (-h - d0) / dt - 0.5 * a_n * dt
    tc = 0.0
    if d0 > 0.0:
        root = np.sqrt(max(b * b - 2.0 * a_n * d0, 0.0))
        tc = min(max(2.0 * d0 / max(root - b, 1.0e-30), 0.0), dt)
    u = -e * (b + a_n * tc)
    r = dt - tc
    s_end, vn_new = u * r + 0.5 * a_n * r * r, u + a_n * r - 0.5 * a_n * dt
    if s_end < 0.0:
        s_end, vn_new = 0.0, 0.0
    vt = v - vn * n
    length = np.linalg.norm(vt)
    if length > 0.0:
        vt = vt * max(0.0, 1.0 - mu * max(vn_new - vn, 0.0) / length)
    return (s_end + h) * n, vt + vn_new * n


def _contact(x, v, n, h, opts, w, dt, x0, a):
    e, mu = opts.get("restitution", 0.5), opts.get("friction", 0.0)
    mode = MODES[opts.get("mode", "reflect")]
    if mode == MODES["penalty"]:
        return x, _penalty(v, n, h, opts.get("stiffness", 1.0e4), damping_ratio_for_restitution(e), mu, w, dt)
    if mode == MODES["reflect"]:
        dx, v = _impact(v, n, h, n @ (x0 - x) - h, a @ n, e, mu, dt)
        return x + dx, v
    x = x + ((1.0 + e) * h if mode == MODES["seed"] else h) * n
    return x, _respond(v, n, e, mu)


def _collide(scene, q, v, w, dt, q_start, accel):
    radius = np.asarray(scene["radius"], dtype=np.float64)
    for spec in scene["colliders"]:
        for i in range(len(q)):
            if w[i] == 0.0:
                continue
            if spec[0] == "plane":
                opts = spec[3]
                n = np.asarray(spec[1], float) / np.linalg.norm(spec[1])
                h = radius[i] + opts.get("thickness", 0.0) - (n @ q[i] - spec[2])
            else:
                opts = spec[3]
                c, inside = np.asarray(spec[1], float), opts.get("inside", False)
                d = radius[i] + opts.get("thickness", 0.0)
                r = spec[2] - d if inside else spec[2] + d
                delta = q[i] - c
                dist = np.linalg.norm(delta)
                n = -delta / dist if inside else delta / dist
                h = dist - r if inside else r - dist
            if h > 0.0:
                q[i], v[i] = _contact(q[i], v[i], n, h, opts, w[i], dt, q_start[i], accel[i])
    return q, v


def simulate(scene) -> np.ndarray:
    """Positions after every step, (steps + 1, n, 3) [m], in float64."""
    q = np.array(scene["q"], dtype=np.float64)
    v = np.array(scene["v"], dtype=np.float64)
    h, cloth = scene["h"], scene["integrator"] == "cloth"
    g = sum((np.asarray(s[1], float) for s in scene["forces"] if s[0] == "gravity"), np.zeros(3))
    out = [q.copy()]
    for k in range(scene["steps"]):
        f, w = _forces(scene, q, v, k * h, include_gravity=not cloth)
        q_start = q.copy()
        accel = np.zeros_like(q) if cloth else w[:, None] * f  # the cloth step leaves its force unset
        if cloth:
            v = v + np.where(w[:, None] > 0.0, h * (w[:, None] * f + g), 0.0)
            q = q + h * v
        elif scene["integrator"] == "semi_implicit_euler":
            v = v + h * w[:, None] * f
            q = q + h * v
        else:
            q, v = q + h * v, v + h * w[:, None] * f
        q, v = _collide(scene, q, v, w, h, q_start, accel)
        out.append(q.copy())
    return np.array(out)


def loss(scene, targets, steps=None) -> float:
    """sum over ``steps`` (default: the last) of sum_i |q_k,i - target|^2 [m^2]."""
    traj = simulate(scene)
    steps = [scene["steps"]] if steps is None else steps
    return float(sum(np.sum((traj[k] - t) ** 2) for k, t in zip(steps, targets)))


def perturbed(scene, name: str, index, delta: float):
    """A copy of ``scene`` with parameter ``name`` (see ``finite_difference``) moved by delta."""
    s = copy.deepcopy(scene)
    if name in ("q", "v", "mass"):
        arr = np.array(s[name], dtype=np.float64)
        arr[index] += delta
        s[name] = arr
    elif name in ("stiffness", "damping", "rest_length"):
        col = {"stiffness": 2, "damping": 3, "rest_length": 4}[name]
        spring = list(s["springs"][index])
        spring[col] += delta
        s["springs"][index] = tuple(spring)
    else:  # "<force kind>.<coefficient>" e.g. "gravity.g", "drag.linear", "magnets.centers"
        kind, coef = name.split(".")
        k = next(n for n, spec in enumerate(s["forces"]) if spec[0] == kind)
        spec = list(s["forces"][k])
        if kind == "wind":
            spec[1] = dict(spec[1], **{coef: spec[1].get(coef, 0.1) + delta})
        else:
            slot = {"g": 1, "force": 1, "linear": 1, "quadratic": 2, "centers": 1, "strengths": 2}[coef]
            arr = np.array(spec[slot], dtype=np.float64)
            if arr.ndim == 0:
                arr = arr + delta
            else:
                arr[index] += delta
            spec[slot] = arr
        s["forces"][k] = tuple(spec)
    return s


def finite_difference(scene, targets, name: str, indices, eps: float = 1.0e-6, steps=None) -> np.ndarray:
    """Central differences (L(p + eps) - L(p - eps)) / (2 eps) of ``loss`` for each index of
    parameter ``name``: q, v, mass, stiffness, damping, rest_length, or a force coefficient."""
    return np.array([(loss(perturbed(scene, name, i, eps), targets, steps)
                      - loss(perturbed(scene, name, i, -eps), targets, steps)) / (2.0 * eps) for i in indices])


def build(scene, device="cpu", differentiable=True):
    """The Simulator (ClothSimulator for integrator "cloth") of ``scene``."""
    from ..bodies import Plane, Sphere
    from ..cloth import ClothSimulator
    from ..core import ConstantForce, Drag, Gravity, Magnets, ModelBuilder, Simulator, Wind

    b = ModelBuilder()
    for x, v, m, r in zip(scene["q"], scene["v"], scene["mass"], scene["radius"]):
        b.add_particle(tuple(map(float, x)), tuple(map(float, v)), mass=float(m), radius=float(r))
    for i, j, k, kd, rest in scene["springs"]:
        b.add_spring(int(i), int(j), float(k), float(kd), rest_length=float(rest))
    forces = []
    for spec in scene["forces"]:
        kind = spec[0]
        if kind == "gravity":
            forces.append(Gravity(tuple(map(float, spec[1]))))
        elif kind == "constant":
            forces.append(ConstantForce(tuple(map(float, spec[1])), spec[2]))
        elif kind == "drag":
            forces.append(Drag(spec[1], spec[2]))
        elif kind == "wind":
            forces.append(Wind(**spec[1]))
        elif kind == "magnets":
            forces.append(Magnets(spec[1], spec[2], softening=spec[3], cutoff=spec[4]))
    colliders = []
    for spec in scene["colliders"]:
        if spec[0] == "plane":
            colliders.append(Plane(tuple(map(float, spec[1])), float(spec[2]), **spec[3]))
        else:
            colliders.append(Sphere(tuple(map(float, spec[1])), float(spec[2]), continuous=False, **spec[3]))
    model = b.finalize(device)
    if scene["integrator"] == "cloth":
        return ClothSimulator(model, "semi_implicit_euler", forces, colliders, differentiable=differentiable)
    return Simulator(model, scene["integrator"], forces, colliders, differentiable=differentiable)
