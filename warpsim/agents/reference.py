"""NumPy reference of the boid rules and of a plain boids step (float64), the oracle for the
agent tests and the baseline of ``benchmarks/bench_boids.py``.

The rules follow ``kernels.agents.eval_neighbour_rules`` to the letter but are written over
candidate pairs (i, j): all pairs (:func:`all_pairs`, O(n^2)) or those of a uniform cell grid
(:func:`grid_pairs`, the NumPy counterpart of ``wp.HashGrid``). Candidates are filtered by
true (minimum-image) distance, so both give the same result.
"""

from __future__ import annotations

import numpy as np

MOBILE = (0, 2, 3, 5)  # FLYING, WALKING, CLIMBING, LANDING


def all_pairs(n):
    """Every ordered pair i != j: (i, j) int arrays of length n (n - 1)."""
    i, j = np.nonzero(~np.eye(n, dtype=bool))
    return i, j


def grid_pairs(x, cell, box=None):
    """Ordered candidate pairs i != j from the 27 cells around each agent's cell of width
    ``cell`` [m]; periodic cells on wrapped axes of ``box`` = (lower, upper, wrap flags)."""
    x = np.asarray(x, dtype=np.float64)
    n = len(x)
    if box is not None:
        lo, hi, wrap = (np.asarray(b) for b in box)
        dims = np.maximum(np.floor((hi - lo) / cell).astype(np.int64), 1)
        c = np.floor((x - lo) / ((hi - lo) / dims)).astype(np.int64)
        c = np.clip(c, 0, dims - 1)
    else:
        wrap = np.zeros(3, dtype=bool)
        c = np.floor(x / cell).astype(np.int64)
        c -= c.min(axis=0)
        dims = c.max(axis=0) + 1
    dims = dims.astype(np.int64)
    key = (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]
    order = np.argsort(key, kind="stable")
    sorted_keys = key[order]
    ncell = int(dims.prod())
    starts = np.searchsorted(sorted_keys, np.arange(ncell), side="left")
    ends = np.searchsorted(sorted_keys, np.arange(ncell), side="right")
    ii, jj = [], []
    offsets = np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij")).reshape(3, -1).T
    seen = set()
    for off in offsets:
        cn = c + off
        valid = np.ones(n, dtype=bool)
        for ax in range(3):
            if wrap[ax]:
                cn[:, ax] %= dims[ax]
            else:
                valid &= (cn[:, ax] >= 0) & (cn[:, ax] < dims[ax])
        # with fewer than 3 cells on a wrapped axis, two offsets can name the same cell: visit it once
        effective = tuple(int(o % dm) if w else int(o) for o, dm, w in zip(off, dims, wrap))
        if effective in seen:
            continue
        seen.add(effective)
        agents = np.flatnonzero(valid)
        kn = (cn[agents, 0] * dims[1] + cn[agents, 1]) * dims[2] + cn[agents, 2]
        s, e = starts[kn], ends[kn]
        counts = e - s
        rep_i = np.repeat(agents, counts)
        first = np.repeat(s - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
        rep_j = order[first + np.arange(counts.sum())]
        keep = rep_i != rep_j
        ii.append(rep_i[keep])
        jj.append(rep_j[keep])
    return np.concatenate(ii), np.concatenate(jj)


def _steer(direction, v, max_speed, max_force):
    l = np.linalg.norm(direction, axis=1, keepdims=True)
    desired = np.where(l > 0, direction * (max_speed[:, None] / np.where(l > 0, l, 1.0)), 0.0)
    s = desired - v
    return np.where(l > 0, _limit(s, max_force), 0.0)


def _limit(v, m):
    l = np.linalg.norm(v, axis=1, keepdims=True)
    m = np.asarray(m, dtype=np.float64).reshape(-1, 1)
    return np.where(l > m, v * (m / np.where(l > 0, l, 1.0)), v)


def neighbour_rules(x, v, kind, group, state, rules, box=None, pairs=None, lookahead=0.0):
    """Reference of ``eval_neighbour_rules``. ``rules``: list of dicts (``BoidParams.rule_values()``)
    indexed by ``kind``; ``box`` = (lower, upper, wrap flags) or None; ``pairs`` = (i, j)
    candidates (default all pairs); ``lookahead`` [s] for the push. Returns a dict of separation, alignment, cohesion, draft,
    push (n, 3), benefit (n,) and neighbours (n,)."""
    x = np.asarray(x, np.float64)
    v = np.asarray(v, np.float64)
    kind = np.asarray(kind)
    group = np.asarray(group)
    state = np.asarray(state)
    n = len(x)
    R = {key: np.array([r[key] for r in rules], dtype=np.float64)[kind] for key in rules[0]}
    i, j = all_pairs(n) if pairs is None else pairs
    d = x[j] - x[i]
    if box is not None:
        lo, hi, wrap = box
        L = np.asarray(hi, np.float64) - np.asarray(lo, np.float64)
        for ax in range(3):
            if wrap[ax]:
                d[:, ax] -= L[ax] * np.round(d[:, ax] / L[ax])
    dist = np.linalg.norm(d, axis=1)
    mobile = np.isin(state, MOBILE)
    m = mobile[i] & (dist < R["query_radius"][i]) & (dist > 0)
    i, j, d, dist = i[m], j[m], d[m], dist[m]
    same = group[i] == group[j]

    out = {key: np.zeros((n, 3)) for key in ("separation", "alignment", "cohesion", "draft", "push")}
    out["benefit"] = np.zeros(n)
    out["neighbours"] = np.zeros(n, dtype=np.int64)

    dmin = np.where(same, R["min_distance"][i], R["min_distance_other"][i])
    dp = d + (v[j] - v[i]) * lookahead
    dpl = np.linalg.norm(dp, axis=1)
    mp = (dmin > 0) & (dpl < dmin) & (dpl > 0)
    np.add.at(out["push"], i[mp], -dp[mp] * (0.5 * (dmin[mp] - dpl[mp]) / dpl[mp])[:, None])

    speed = np.linalg.norm(v, axis=1)
    use_fov = (speed > 1e-6) & (R["fov_cos"] > -1.0)
    heading = np.where(speed[:, None] > 1e-6, v / np.where(speed > 1e-6, speed, 1.0)[:, None], 0.0)
    vis = ~use_fov[i] | ((heading[i] * d).sum(axis=1) >= R["fov_cos"][i] * dist)
    i, j, d, dist, same = i[vis], j[vis], d[vis], dist[vis], same[vis]

    rsep = np.where(same, R["separation_radius"][i], R["separation_radius_other"][i])
    ms = dist < rsep
    sep = np.zeros((n, 3))
    np.add.at(sep, i[ms], -d[ms] * ((1.0 - dist[ms] / rsep[ms]) / dist[ms])[:, None])

    mn = same & (dist < R["perception_radius"][i]) & mobile[j]
    i, j, d = i[mn], j[mn], d[mn]
    ali = np.zeros((n, 3))
    coh = np.zeros((n, 3))
    np.add.at(ali, i, v[j])
    np.add.at(coh, i, d)
    cnt = np.bincount(i, minlength=n)
    out["neighbours"] = cnt
    has = cnt > 0
    safe = np.maximum(cnt, 1)[:, None]
    out["separation"] = _limit(sep * R["max_force"][:, None], R["max_force"])
    out["alignment"] = np.where(has[:, None], _steer(ali / safe, v, R["max_speed"], R["max_force"]), 0.0)
    out["cohesion"] = np.where(has[:, None], _steer(coh / safe, v, R["max_speed"], R["max_force"]), 0.0)

    # drafting
    sj = np.linalg.norm(v[j], axis=1)
    md = (R["draft"][i] != 0) & (sj > 1e-6)
    i, j, d, sj = i[md], j[md], d[md], sj[md]
    hj = v[j] / sj[:, None]
    back = (d * hj).sum(axis=1)
    mb = back > 0
    i, j, d, hj, back = i[mb], j[mb], d[mb], hj[mb], back[mb]
    lat_v = -d + back[:, None] * hj
    lat = np.linalg.norm(lat_v, axis=1)
    fallback = np.cross(hj, [0.0, 1.0, 0.0])
    fl = np.linalg.norm(fallback, axis=1)
    fallback = np.where(fl[:, None] < 1e-6, [[1.0, 0.0, 0.0]], fallback / np.where(fl > 0, fl, 1.0)[:, None])
    side = np.where(lat[:, None] > 1e-6, lat_v / np.where(lat > 1e-6, lat, 1.0)[:, None], fallback)
    db = back - R["draft_back"][i]
    ds = lat - R["draft_side"][i]
    w = R["draft_width"][i]
    np.maximum.at(out["benefit"], i, np.exp(-(db ** 2 + ds ** 2) / (2 * w ** 2)))
    rel = d - R["draft_back"][i][:, None] * hj + R["draft_side"][i][:, None] * side
    rl = np.linalg.norm(rel, axis=1)
    order = np.lexsort((rl, i))
    first = order[np.r_[True, i[order][1:] != i[order][:-1]]] if len(order) else order
    ai = i[first]
    out["draft"][ai] = _limit(v[j[first]] + rel[first] / R["draft_time"][ai][:, None] - v[ai],
                              R["max_force"][ai])
    return out


def boids_step(x, v, kind, rules, weights, min_speed, dt, box=None, pairs=None):
    """One plain boids step (all agents FLYING, no food, energy, obstacles or terrain), the
    NumPy counterpart of ``Flock.step``: a = limit(sum_k w_k rule_k + soft walls, max_force),
    speed kept in [min_speed, max_speed], x += v dt (+ hard-distance push), wrap/clamp.
    ``weights``: (separation, alignment, cohesion, boundary, margin). Returns new (x, v)."""
    n = len(x)
    state = np.zeros(n, dtype=np.int64)
    r = neighbour_rules(x, v, kind, kind, state, rules, box, pairs, lookahead=dt)
    ws, wa, wc, wb, margin = weights
    max_speed = np.array([q["max_speed"] for q in rules])[kind]
    max_force = np.array([q["max_force"] for q in rules])[kind]
    a = ws * r["separation"] + wa * r["alignment"] + wc * r["cohesion"]
    if box is not None:
        lo, hi, wrap = (np.asarray(b) for b in box)
        bnd = np.zeros((n, 3))
        for ax in range(3):
            if not wrap[ax]:
                low, high = lo[ax] + margin, hi[ax] - margin
                bnd[:, ax] = np.where(x[:, ax] < low, max_force * np.minimum((low - x[:, ax]) / margin, 1.0),
                                      np.where(x[:, ax] > high,
                                               -max_force * np.minimum((x[:, ax] - high) / margin, 1.0), 0.0))
        a = a + wb * bnd
    a = _limit(a, max_force)
    vn = v + a * dt
    sp = np.linalg.norm(vn, axis=1)
    vn = np.where((sp > max_speed)[:, None], vn * (max_speed / np.maximum(sp, 1e-30))[:, None], vn)
    slow = (sp < min_speed) & (sp > 1e-6)
    vn = np.where(slow[:, None], vn * (min_speed / np.maximum(sp, 1e-30))[:, None], vn)
    xn = x + vn * dt + r["push"]
    if box is not None:
        for ax in range(3):
            if wrap[ax]:
                xn[:, ax] = lo[ax] + np.mod(xn[:, ax] - lo[ax], hi[ax] - lo[ax])
            else:
                xn[:, ax] = np.clip(xn[:, ax], lo[ax], hi[ax])
                out_lo = (xn[:, ax] <= lo[ax]) & (vn[:, ax] < 0)
                out_hi = (xn[:, ax] >= hi[ax]) & (vn[:, ax] > 0)
                vn[out_lo | out_hi, ax] = 0.0
    return xn, vn
