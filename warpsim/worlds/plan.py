"""How each varied parameter enters one world's arrays, found by building the scene a few times.

A batch is tiled on the device from ONE world (world 0's parameters). To give world w its own
values without running the scene's Python builder N times, :func:`make_plan` builds the scene
at world 0's value and at up to two other sampled values of each varied key (the extremes, so
the scene's own checks also validate them) and compares what changed:

- ``particle_q`` / ``particle_qd`` (vec3 per particle): a uniform shift of the changed particles,
  ``x_w = x_0 + C (p_w - p_0)`` (e.g. a drop height or an initial velocity);
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
    return sig


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
    origin: dict = field(default_factory=dict)   # vec3 array -> its values at p = 0 (float32), when buildable

    def predict(self, base, p):
        """The signature's varied parts at parameter value p (for the linearity check)."""
        dp = np.atleast_1d(np.asarray(p, dtype=np.float64)) - self.p0
        out = {}
        for name, (mask, C) in self.vec3.items():
            a = base[name].copy()
            a[mask] += C @ dp
            out[name] = a
        for name, c in self.scale.items():
            a = base[name].copy()
            changed = ~np.isnan(c)
            a[changed] = c[changed] * float(dp[0] + self.p0[0])
            out[name] = a
        return out


def _diff_effect(key, base, probe, p0, p1, effect, column):
    """Fill ``effect`` with what changed between base (p0) and probe (p1), for component ``column``."""
    dp = float(p1 - p0)
    if base["counts"] != probe["counts"] or not _equal(base["spring_indices"], probe["spring_indices"]):
        raise StructuralError(f"{key} changes the number of particles or springs ({base['counts']} -> "
                              f"{probe['counts']}); it cannot differ between worlds of one batch: set it with --set")
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


def _check_linear(key, effect, base, probe, p):
    predicted = effect.predict(base, p)
    for name, a in predicted.items():
        if not np.allclose(a, probe[name], rtol=1e-5, atol=1e-6):
            raise StructuralError(f"{key} changes {name} nonlinearly; it cannot differ between worlds: set it "
                                  "with --set")


def make_plan(cls, base_scene, base_params, world_params, varied, build):
    """{key: KeyEffect} for every key in ``varied`` whose values differ between worlds.

    ``base_scene`` is world 0 built from ``base_params``; ``build(params) -> scene`` builds a
    probe world (on the CPU); ``world_params`` is the list of full parameter dicts."""
    base = signature(base_scene)
    plan = {}
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
            far = distinct[-1]
            _check_linear(key, effect, base, signature(build({**base_params, key: far})), far)
        else:
            p0 = float(p0v)
            effect = KeyEffect(key, np.array([p0]))
            others = sorted({float(v) for v in values} - {p0})
            probes = [others[-1]] + ([others[0]] if len(others) > 1 else [])
            first = signature(build({**base_params, key: _cast(default, probes[0])}))
            _diff_effect(key, base, first, p0, probes[0], effect, 0)
            for pv in probes[1:]:
                _check_linear(key, effect, base, signature(build({**base_params, key: _cast(default, pv)})), pv)
        _canonical(key, effect, base, base_params, default, build)
        if not (effect.vec3 or effect.scale or effect.gravity or effect.planes):
            raise StructuralError(f"{key} changes nothing a batch holds per world (it acts through the time step, "
                                  "the stepping or the display); set it with --set")
        plan[key] = effect
    return plan


def _cast(default, value):
    return round(value) if isinstance(default, int) and not isinstance(default, bool) else float(value)


def _canonical(key, effect, base, base_params, default, build):
    """Make a world's values independent of which world the batch was tiled from (so batches of
    any size give the same worlds): shifted arrays start from their values at p = 0, and scaled
    arrays use their exact values at p = 1, where the scene builds there."""
    vector = isinstance(default, (tuple, list))
    if effect.vec3:
        zero = tuple(0.0 for _ in effect.p0) if vector else _cast(default, 0.0)
        try:
            sig0 = signature(build({**base_params, key: zero}))
        except ValueError:
            sig0 = None
        if sig0 is not None:
            predicted = effect.predict(base, np.zeros(len(effect.p0)))
            if all(np.allclose(predicted[n], sig0[n], rtol=1e-5, atol=1e-6) for n in effect.vec3):
                effect.origin = {n: sig0[n].astype(np.float32) for n in effect.vec3}
    if effect.scale and not vector:
        try:
            sig1 = signature(build({**base_params, key: _cast(default, 1.0)}))
        except ValueError:
            return
        for name, c in effect.scale.items():
            changed = ~np.isnan(c)
            if np.allclose(sig1[name][changed], c[changed], rtol=1e-5, atol=0.0):
                c[changed] = sig1[name][changed]
