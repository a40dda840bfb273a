"""What keeps a VBD heap moving at rest: settle the donut heap, then step the saved state by each variant.

Builds the donuts scene (``--count`` tori of the benchmark's resolution, ``integrator=vbd``), takes ``--settle``
steps of ``--dt`` printing every 40 the fastest particle [m/s], its 99.9th percentile, the particles past 0.1 m/s
(and of those the ones whose velocity turned back in the window's last step: a jitter, where a slide keeps its
direction) and the contact searches run a step; then prints where the fast particles are (surface or interior, bounds, what
the bound cut of their guess) and, for each ``--variant`` (a JSON object of scene parameters), builds the scene
again with them, sets the saved positions and velocities and takes ``--steps`` steps, printing the same figures
over each 40 (benchmarks/RESULTS.md, "the heap's jitter"):

    python benchmarks/vbd_jitter.py --count 4 --settle 600 --steps 120 --variant '{}' \\
        --variant '{"friction": 0.0}' --variant '{"contact_stiffness": 8000}' \\
        --variant '{"contact_stiffness": 8000, "solver_iterations": 24}'

``--scene`` (JSON, as a variant) sets the settled heap's own parameters; ``--contacts`` prints, after settling, what
the jittering particles are pressed by and why each search point of a step searches (``contacts``):

    python benchmarks/vbd_jitter.py --count 4 --settle 400 --scene '{"contact_stiffness": 8000}' --contacts
    python benchmarks/vbd_jitter.py --device cuda:0 --count 100 --settle 1200 --contacts
"""

import argparse
import json
import time

import numpy as np
import warp as wp

import warpsim as ws

from warpsim.scenes import get_scene

WINDOW = 40
"""Steps over which each line's figures are taken."""


def build(args, **overrides):
    """The scene with ``overrides``: scene parameters, and ``ws.VBD`` attributes prefixed by "_" (e.g.
    ``"_adaptive_guess": false``), set before the first step."""
    cls = get_scene("donuts")
    integrator = {key[1:]: overrides.pop(key) for key in list(overrides) if key.startswith("_")}
    scene = cls(cls.resolve_params({"count": args.count, "segments": args.segments, "sides": args.sides,
                                    "lattice_cells": args.lattice_cells, "dt": args.dt, "integrator": "vbd",
                                    **overrides}), device=args.device)
    for key, value in integrator.items():
        setattr(scene.sim.integrator, key, value)
    return scene


def window(scene, h) -> str:
    """Step ``WINDOW`` steps; the fastest particle, its 99.9th percentile, particles past 0.1 m/s, searches a step."""
    contact = scene.vbd_contact
    before = contact.searches_run
    for _ in range(WINDOW - 1):
        scene.sim.step(h)
    previous = scene.sim.state.velocities.numpy().copy()
    scene.sim.step(h)
    velocity = scene.sim.state.velocities.numpy()
    v = np.linalg.norm(velocity, axis=1)
    fast = v > 0.1
    turned = fast & (np.einsum("ij,ij->i", velocity, previous) < 0.0)  # a jitter turns back, a slide does not
    return (f"{v.max():.3f} m/s, 99.9th percentile {np.percentile(v, 99.9):.3f}, {int(fast.sum())} past 0.1 m/s "
            f"({int(turned.sum())} turned back in the last step), {(contact.searches_run - before) / WINDOW:.2f} "
            "searches a step")


def contacts(scene, h, steps: int = 8) -> None:
    """Step ``steps`` steps and print what the particles that jitter (past 0.1 m/s, their velocity turned back in at
    least 3 of the steps) are pressed by at the last search (``VBDContact.active_pairs``), against the calm ones
    (under 0.01 m/s); then over 20 more steps, at each search point of a step (its opening and every
    ``detect_every`` sweeps), the particles past half their bound, at their bound (within 0.1 % of it: clipped
    there) and with their guess cut, and the searches run."""
    sim, contact, integrator = scene.sim, scene.vbd_contact, scene.sim.integrator
    velocities = []
    for _ in range(steps):
        sim.step(h)
        velocities.append(sim.state.velocities.numpy().copy())
    v = np.array(velocities)
    turns = (np.einsum("tij,tij->ti", v[1:], v[:-1]) < 0.0).sum(axis=0)
    speed = np.linalg.norm(v, axis=2).max(axis=0)
    active = contact.active_pairs()
    surface = np.zeros(len(speed), dtype=bool)
    surface[contact.surface_particles] = True
    for name, chosen in (("jittering", np.flatnonzero((turns >= 3) & (speed > 0.1))),
                         ("calm", np.flatnonzero(speed < 0.01))):
        if not len(chosen):
            print(f"{name} particles: none", flush=True)
            continue
        a = active[chosen]
        kinds = ", ".join(f"{kind} {np.mean(a[:, k] > 0):.0%} ({a[:, k].mean():.1f} a particle)" for k, kind in
                          enumerate(("as a vertex of a vertex-triangle pair", "as a triangle's corner",
                                     "as an edge's end")))
        tori = len(np.unique(chosen // contact.body_size)) if contact.body_size else "-"
        print(f"{name} particles: {len(chosen)} in {tori} tori, {np.mean(surface[chosen]):.0%} on the surface; with "
              f"a pair within the thickness {kinds}", flush=True)
    calls = []
    search = contact.search

    def counting(q, deficit=None, fraction=0.5):
        moved = np.linalg.norm(q.numpy() - contact.reference.numpy(), axis=1) / np.maximum(contact.bound.numpy(),
                                                                                          1.0e-12)
        cut = np.linalg.norm(integrator.deficit.numpy(), axis=1) > 0.0
        before = contact.searches_run
        search(q, deficit, fraction)
        calls.append((int((moved > 0.5).sum()), int((moved > 0.999).sum()), int(cut.sum()),
                       contact.searches_run - before))

    contact.search = counting
    try:
        for _ in range(20):
            sim.step(h)
    finally:
        del contact.search  # the class's method again
    rows = np.array(calls).reshape(20, -1, 4)
    for point in range(rows.shape[1]):
        r = rows[:, point].mean(axis=0)
        print(f"search point {point} of a step: {r[0]:.1f} particles past half their bound, {r[1]:.1f} at it, "
              f"{r[2]:.1f} with their guess cut; searches run {r[3]:.2f}", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--count", type=int, default=4, help="number of tori")
    parser.add_argument("--segments", type=int, default=50, help="torus segments around its axis")
    parser.add_argument("--sides", type=int, default=40, help="torus segments around its tube")
    parser.add_argument("--lattice-cells", type=int, default=10, help="interior lattice cells across a torus")
    parser.add_argument("--dt", type=float, default=1.0 / 240.0, help="step [s]")
    parser.add_argument("--settle", type=int, default=600, help="steps before the variants (a multiple of 40)")
    parser.add_argument("--steps", type=int, default=120, help="steps of each variant (a multiple of 40)")
    parser.add_argument("--scene", default="{}", help="the settled heap's scene parameters as JSON (as --variant; "
                        "the variants do not inherit them)")
    parser.add_argument("--contacts", action="store_true", help="after settling: what the jittering particles are "
                        "pressed by, and why each search point of a step searches (``contacts``)")
    parser.add_argument("--variant", action="append", default=[], help="scene parameters as JSON, e.g. "
                        "'{\"friction\": 0.0}', and ws.VBD's attributes prefixed by _, e.g. "
                        "'{\"_adaptive_guess\": false}' (repeatable; none: the scene's own, '{}')")
    args = parser.parse_args()
    variants = [json.loads(v) for v in args.variant] or [{}]
    own = json.loads(args.scene)
    vbd = ws.VBD()
    for overrides in variants + [own]:  # before any time is spent
        for key in overrides:
            if key.startswith("_") and not hasattr(vbd, key[1:]):
                parser.error(f"--variant: ws.VBD has no attribute {key[1:]!r}; give a scene parameter, or _ and one "
                             "of VBD's (e.g. _adaptive_guess)")
    scene = build(args, **own)
    h = scene.params["dt"] / scene.inner_steps
    t0 = time.perf_counter()
    for k in range(args.settle // WINDOW):
        print(f"settle, steps {k * WINDOW}-{(k + 1) * WINDOW}: {window(scene, h)} ({time.perf_counter() - t0:.0f} s)",
              flush=True)
    q, qd = scene.sim.state.positions.numpy().copy(), scene.sim.state.velocities.numpy().copy()
    contact = scene.vbd_contact
    fast = np.flatnonzero(np.linalg.norm(qd, axis=1) > 0.1)
    surface = np.isin(fast, contact.surface_particles)
    bodies = np.unique(fast // contact.body_size) if len(fast) else []
    deficit = np.linalg.norm(scene.sim.integrator.deficit.numpy()[fast], axis=1) * 1e3
    bounds = contact.bound.numpy()[fast] * 1e3
    print(f"after settling: {len(fast)} particles past 0.1 m/s ({int(surface.sum())} on the surface) in tori "
          f"{list(map(int, bodies))}; their bounds {bounds.min() if len(fast) else 0:.2f}-"
          f"{bounds.max() if len(fast) else 0:.2f} mm, their guess cut by at most "
          f"{deficit.max() if len(fast) else 0:.3f} mm", flush=True)
    if args.contacts:
        contacts(scene, h)
    for overrides in variants:
        run = build(args, **dict(overrides))
        run.sim.state.positions.assign(q)
        run.sim.state.velocities.assign(qd)
        lines = [window(run, h) for _ in range(args.steps // WINDOW)]
        print(f"variant {json.dumps(overrides)}:", *(f"\n  steps {k * WINDOW}-{(k + 1) * WINDOW}: {line}"
                                                  for k, line in enumerate(lines)), flush=True)
    wp.synchronize()


if __name__ == "__main__":
    main()
