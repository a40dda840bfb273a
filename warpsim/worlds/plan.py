"""How each varied parameter enters one world's arrays, found by building the scene a few times.

A batch is tiled on the device from ONE world (world 0's parameters). To give world w its own
values without running the scene's Python builder N times, :func:`make_plan` builds the scene
at world 0's value and at up to two other sampled values of each varied key (the extremes, so
the scene's own checks also validate them) and compares what changed:

- ``particle_q`` / ``particle_qd`` (vec3 per particle): a uniform shift of the changed particles,
  ``x_w = x_0 + C (p_w - p_0)`` (e.g. a drop height or an initial velocity), summed in float64 from
  the builder's values and cast to float32 once, as a scene built with p_w casts them;
- ``particle_mass`` / ``particle_radius`` / ``spring_*`` (float per element): proportional to the
  parameter, ``a_w[e] = (a_0[e] / p_0) p_w`` (stiffness, damping, mass, density);
- gravity (``ws.Gravity.g``) and plane / box walls (``ws.Planes`` restitution and friction):
  affine per world.

Anything else (a changed particle or spring count, a new force, a nonlinear change such as a
rotation, a changed collider shape) raises a ValueError naming the key: set such a parameter
with ``--set`` and run one sweep per value.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..core.forces import Gravity

VEC3_ARRAYS = ("particle_q", "particle_qd")
FLOAT_ARRAYS = ("particle_mass", "particle_radius", "spring_rest_length", "spring_stiffness", "spring_damping")
PLANE_ATTRS = ("restitution", "friction")
DERIVED_ATTRS = {"damping_ratio", "g", "restitution", "friction"}


class StructuralError(ValueError):
    """A parameter that cannot differ between the worlds of one batch."""


def _simple_attrs(obj):
    out = {}
    for k, v in vars(obj).items():
        if k.startswith("_") or k == "model":
            continue
        if isinstance(v, (bool, int, float, str)):
            out[k] = v
        elif isinstance(v, (tuple, list)) and all(isinstance(x, (int, float)) for x in v):
            out[k] = tuple(float(x) for x in v)
        elif isinstance(v, np.ndarray) and v.dtype.kind in "fiu":
            out[k] = v
    return out


def signature(scene) -> dict:
    """The arrays and coefficients of a built scene that a batch may vary, on the host."""
    sim = getattr(scene, "sim", None)
    if sim is None or not hasattr(sim, "model"):
        raise StructuralError(f"scene {scene.name!r} is not driven by a warpsim Simulator; batched worlds "
                              "tile a Simulator's model")
    m = sim.model
    sig = {"counts": (m.particle_count, m.spring_count), "spring_indices": m.spring_indices.numpy().copy(),
           "integrator": type(sim.integrator).__name__,
           "forces": [(type(f).__name__, _simple_attrs(f)) for f in sim.forces],
           "colliders": [(type(c).__name__, _simple_attrs(c)) for c in sim.colliders]}
    for name in VEC3_ARRAYS + FLOAT_ARRAYS:
        sig[name] = getattr(m, name).numpy().astype(np.float64)
    for name in VEC3_ARRAYS:
        sig[name + "_host"] = host_values(m, name)
    return sig


def host_values(model, name) -> np.ndarray:
    """``model.<name>`` (a vec3 array) as its builder was given it: float64 (P, 3), before the one
    cast to float32 (``<name>_host``), where that still casts to the array on the device bit for
    bit (not edited since); else the device array's float32 values."""
    values = getattr(model, name).numpy()
    host = getattr(model, name + "_host", None)
    if host is not None and host.shape == values.shape and host.astype(np.float32).tobytes() == values.tobytes():
        return host
    return values.astype(np.float64)


def _equal(a, b):
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        return a.shape == b.shape and np.array_equal(a, b)
    return a == b


@dataclass
class KeyEffect:
    """What one varied key changes; coefficients per unit of (p - p0) (vector keys: 3 columns)."""

    key: str
    p0: np.ndarray
    vec3: dict = field(default_factory=dict)     # array -> (mask (P,) bool, C (3, d))
    scale: dict = field(default_factory=dict)    # array -> coefficient (E,) float64, nan where unchanged
    gravity: dict = field(default_factory=dict)  # force index -> C (3, d)
    planes: dict = field(default_factory=dict)   # collider index -> {attr: c (d,)}
    origin: dict = field(default_factory=dict)   # vec3 array -> its values at p = 0 (float64), when buildable


def _diff_effect(key, base, probe, p0, p1, effect, column):
    """Fill ``effect`` with what changed between base (p0) and probe (p1), for component ``column``."""
    dp = float(p1 - p0)
    if base["counts"] != probe["counts"]:
        raise StructuralError(f"{key} changes the number of particles or springs ({base['counts']} -> "
                              f"{probe['counts']}); it cannot differ between worlds of one batch: set it with --set")
    if not _equal(base["spring_indices"], probe["spring_indices"]):
        s = int(np.flatnonzero(base["spring_indices"] != probe["spring_indices"])[0]) // 2
        raise StructuralError(f"{key} changes which particles the springs join (spring {s} at {key}={p0:g} and "
                              f"{key}={p1:g}); it cannot differ between worlds of one batch: set it with --set")
    for part in ("integrator",):
        if base[part] != probe[part]:
            raise StructuralError(f"{key} changes the {part}; set it with --set")
    for part in ("forces", "colliders"):
        if [t for t, _ in base[part]] != [t for t, _ in probe[part]]:
            raise StructuralError(f"{key} changes which {part} act; set it with --set")
    for name in VEC3_ARRAYS:
        d = probe[name] - base[name]
        changed = np.any(d != 0.0, axis=1)
        if not changed.any():
            continue
        rows = d[changed] / dp
        mean = rows.mean(axis=0)
        # float32 rounding of the positions bounds how exactly a small probe step is seen
        noise = 4.0 * float(np.finfo(np.float32).eps) * max(1.0, np.abs(probe[name]).max()) / abs(dp)
        if not np.allclose(rows, mean, rtol=1e-5, atol=noise):
            raise StructuralError(f"{key} moves the particles' {name[9:] or 'positions'} non-uniformly (not a "
                                  "shift, e.g. a rotation); it cannot differ between worlds: set it with --set")
        mask, C = effect.vec3.get(name, (changed, np.zeros((3, len(effect.p0)))))
        if column and not np.array_equal(mask, changed):
            raise StructuralError(f"{key}: its components change different particles; set it with --set")
        snapped = np.round(mean * 64.0) / 64.0  # coefficients are simple numbers (0, 1, -1, ...)
        mean = np.where(np.abs(mean - snapped) <= noise + 1e-6 * np.abs(mean), snapped, mean)
        C[:, column] = mean
        effect.vec3[name] = (changed, C)
    for name in FLOAT_ARRAYS:
        b, p = base[name], probe[name]
        changed = b != p
        if not changed.any():
            continue
        if len(effect.p0) != 1:
            raise StructuralError(f"{key} is a vector but changes {name}; set it with --set")
        c = np.full(len(b), np.nan)
        c[changed] = p[changed] / p1
        if p0 != 0.0 and not np.allclose(b[changed] / p0, c[changed], rtol=1e-5, atol=0.0):
            raise StructuralError(f"{key} changes {name} but not in proportion; it cannot differ between worlds: "
                                  "set it with --set")
        if p0 != 0.0:
            c[changed] = b[changed] / p0
        effect.scale[name] = c
    for j, ((t, fa), (_, fb)) in enumerate(zip(base["forces"], probe["forces"])):
        for attr in set(fa) | set(fb):
            if _equal(fa.get(attr), fb.get(attr)):
                continue
            if t == Gravity.__name__ and attr == "g":
                C = effect.gravity.setdefault(j, np.zeros((3, len(effect.p0))))
                C[:, column] = (np.asarray(fb["g"]) - np.asarray(fa["g"])) / dp
            else:
                raise StructuralError(f"{key} changes {attr} of force {t}, which batched worlds share; set it "
                                      "with --set")
    for j, ((t, ca), (_, cb)) in enumerate(zip(base["colliders"], probe["colliders"])):
        for attr in set(ca) | set(cb):
            if _equal(ca.get(attr), cb.get(attr)) or attr == "damping_ratio":
                continue
            if attr in PLANE_ATTRS and "normals" in ca:
                d = effect.planes.setdefault(j, {}).setdefault(attr, np.zeros(len(effect.p0)))
                d[column] = (cb[attr] - ca[attr]) / dp
            else:
                raise StructuralError(f"{key} changes {attr} of collider {t}, which batched worlds share; set it "
                                      "with --set")


def make_plan(cls, base_scene, base_params, world_params, varied, build):
    """{key: KeyEffect} for every key in ``varied`` whose values differ between worlds.

    ``base_scene`` is world 0 built from ``base_params``; ``build(params) -> scene`` builds a
    probe world (on the CPU); ``world_params`` is the list of full parameter dicts. Builds: one
    per scalar key (at its value farthest from world 0's; three for a vector key), then one with
    every key moved at once (shifted keys to 0, scaled keys to 1, the rest to their other
    extreme) that checks the whole plan for linearity and makes it canonical (see
    :func:`_canonical`); if the scene refuses those values, one with every key at its other
    extreme instead."""
    base = signature(base_scene)
    plan, others = {}, {}
    for key in varied:
        values = [wp_[key] for wp_ in world_params]
        p0v = base_params[key]
        default = cls.params[key].default
        if all(v == p0v for v in values):
            continue
        if isinstance(default, (bool, str)):
            raise StructuralError(f"{key} is a {cls.params[key].type_name} choice; batched worlds share it: run "
                                  "one sweep per value (--set)")
        distinct = sorted(set(values), key=lambda v: np.linalg.norm(np.subtract(v, p0v)))
        if isinstance(default, (tuple, list)):
            p0 = np.asarray(p0v, dtype=np.float64)
            effect = KeyEffect(key, p0)
            for c in range(len(p0)):
                probe_value = tuple(p0 + np.eye(len(p0))[c])
                probe = signature(build({**base_params, key: probe_value}))
                _diff_effect(key, base, probe, 0.0, 1.0, effect, c)
            others[key] = distinct[-1]
        else:
            p0 = float(p0v)
            effect = KeyEffect(key, np.array([p0]))
            ordered = sorted({float(v) for v in values} - {p0})
            first = signature(build({**base_params, key: _cast(default, ordered[-1])}))
            _diff_effect(key, base, first, p0, ordered[-1], effect, 0)
            others[key] = _cast(default, ordered[0] if len(ordered) > 1 else 0.5 * (p0 + ordered[-1]))
        if not (effect.vec3 or effect.scale or effect.gravity or effect.planes):
            raise StructuralError(f"{key} changes nothing a batch holds per world (it acts through the time step, "
                                  "the stepping or the display); set it with --set")
        plan[key] = effect
    if plan:
        _combined_check(cls, base, base_params, plan, others, build)
    return plan


def _predict(base, plan, values):
    """Arrays and coefficients the plan predicts at ``values`` {key: value}."""
    out = {name: base[name].copy() for name in VEC3_ARRAYS + FLOAT_ARRAYS}
    forces = [dict(attrs) for _, attrs in base["forces"]]
    colliders = [dict(attrs) for _, attrs in base["colliders"]]
    for key, effect in plan.items():
        dp = np.atleast_1d(np.asarray(values[key], dtype=np.float64)) - effect.p0
        for name, (mask, C) in effect.vec3.items():
            out[name][mask] += C @ dp
        for name, c in effect.scale.items():
            changed = ~np.isnan(c)
            out[name][changed] = c[changed] * float(values[key])
        for j, C in effect.gravity.items():
            forces[j]["g"] = tuple(np.asarray(forces[j]["g"]) + C @ dp)
        for j, attrs in effect.planes.items():
            for attr, d in attrs.items():
                colliders[j][attr] = colliders[j][attr] + float(d @ dp)
    return out, forces, colliders


def _mismatch(base, plan, values, sig):
    """The first part of ``sig`` the plan does not predict at ``values`` (None: all agree)."""
    arrays, forces, colliders = _predict(base, plan, values)
    for name, a in arrays.items():
        if not np.allclose(a, sig[name], rtol=1e-5, atol=1e-6):
            return name
    for j, attrs in enumerate(forces):
        if "g" in attrs and not np.allclose(attrs["g"], sig["forces"][j][1]["g"], rtol=1e-6, atol=1e-9):
            return f"the gravity of force {j}"
    for j, attrs in enumerate(colliders):
        for attr in PLANE_ATTRS:
            if attr in attrs and not np.isclose(attrs[attr], sig["colliders"][j][1][attr], rtol=1e-6, atol=1e-9):
                return f"the {attr} of collider {j}"
    return None


def _combined_check(cls, base, base_params, plan, others, build):
    canonical = {}
    for key, effect in plan.items():
        default = cls.params[key].default
        if effect.vec3:
            canonical[key] = tuple(0.0 for _ in effect.p0) if isinstance(default, (tuple, list)) else _cast(default, 0)
        elif effect.scale:
            canonical[key] = _cast(default, 1.0)
        else:
            canonical[key] = others[key]
    for values in (canonical, others):
        try:
            sig = signature(build({**base_params, **values}))
        except ValueError:
            continue  # the scene refuses these values together (e.g. a teapot at height 0)
        if _mismatch(base, plan, values, sig) is not None:
            for key in plan:  # name the key
                single = signature(build({**base_params, key: values[key]}))
                part = _mismatch(base, {key: plan[key]}, {**{k: plan[k].p0 for k in plan}, key: values[key]},
                                 single)
                if part is not None:
                    raise StructuralError(f"{key} changes {part} nonlinearly; it cannot differ between worlds: set "
                                          "it with --set")
            raise StructuralError(f"{', '.join(plan)} act on the same values together; vary one of them")
        if values is canonical:
            _canonical(plan, sig)
        return
    raise StructuralError(f"could not check that {', '.join(plan)} act linearly: the scene refuses their other "
                          "sampled values together; vary fewer parameters at once")


def _cast(default, value):
    return round(value) if isinstance(default, int) and not isinstance(default, bool) else float(value)


def _canonical(plan, sig):
    """Make a world's values independent of which world the batch was tiled from (so batches of
    any size give the same worlds): shifted arrays start from their values at p = 0 and scaled
    arrays use their exact values at p = 1, both read from ``sig`` (the scene built there)."""
    for effect in plan.values():
        movers = [e for e in plan.values() if set(e.vec3) & set(effect.vec3)]
        if effect.vec3 and len(movers) == 1:
            effect.origin = {n: sig[n + "_host"] for n in effect.vec3}  # as the builder got them there
        for name, c in effect.scale.items() if not effect.vec3 else ():  # built at p = 1
            changed = ~np.isnan(c)
            c[changed] = sig[name][changed]
