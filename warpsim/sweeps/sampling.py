"""Parameter sampling for many worlds: ``--vary`` specs and the grid / random / Latin-hypercube plans.

A spec is ``KEY=LO:HI`` (a range; ``KEY=LO:HI:log`` samples it log-uniformly, both bounds > 0)
or ``KEY=A,B,C`` (a list of values). Vector parameters (e.g. ``velocity``, written ``x,y,z``) take
``KEY=X,Y,Z:X,Y,Z`` ranges (component-wise, no ``log``) and ``KEY=X,Y,Z;X,Y,Z`` lists. Integer
parameters are rounded after sampling.

Plans (``sample``):
  grid    the Cartesian product: each list contributes its values, each range ``m`` evenly spaced
          values (ends included; geometric for ``log``); ``m`` is chosen so the product is exactly
          ``n`` (a ValueError names the nearest world counts that work);
  random  ``n`` independent draws, uniform (log-uniform) in ranges, uniform over list values;
  lhs     Latin hypercube: every range and list is cut into ``n`` equal strata, each used once.
Draws come from ``numpy.random.default_rng(seed)``: the same seed gives the same worlds.
"""
from __future__ import annotations

from typing import Optional
import math
from dataclasses import dataclass

import numpy as np

SAMPLES = ("grid", "random", "lhs")

__all__ = ["SAMPLES", "VarySpec", "parse_vary", "sample_params"]


@dataclass(frozen=True)
class VarySpec:
    """One varied parameter: ``values`` (a list) or ``lo``/``hi`` (a range, ``log`` spacing)."""

    key: str
    values: Optional[tuple] = None
    lo: object = None
    hi: object = None
    log: bool = False

    @property
    def is_range(self) -> bool:
        return self.values is None


def parse_vary(text, params) -> VarySpec:
    """Parse one ``--vary`` item against a scene's ``{key: Param}``; ValueError (one line) names
    the key, the value and the fix."""
    from ..core.names import close_matches
    from ..scenes import parse_value

    text = str(text)
    if "=" not in text:
        raise ValueError(f"--vary {text!r} is malformed; write KEY=LO:HI[:log] or KEY=A,B,C")
    key, spec = (s.strip() for s in text.split("=", 1))
    if key not in params:
        raise ValueError(f"--vary {key}: the scene has no parameter {key!r}.{close_matches(key, params)} "
                         f"Its parameters: {', '.join(params) or 'none'}")
    param = params[key]
    default = param.default
    if isinstance(default, (bool, str)) and ":" in spec:
        raise ValueError(f"--vary {key}={spec}: {key} is a {param.type_name}, not a number; give a list A,B")
    vector = isinstance(default, (tuple, list))
    if ":" in spec:
        parts = spec.split(":")
        log = False
        if len(parts) == 3 and parts[2].strip().lower() == "log":
            log = True
            parts = parts[:2]
        if len(parts) != 2:
            raise ValueError(f"--vary {key}={spec} is malformed; write {key}=LO:HI or {key}=LO:HI:log")
        if not isinstance(default, (int, float)) and not vector:
            raise ValueError(f"--vary {key}={spec}: {key} is a {param.type_name}; ranges need numbers, give a list")
        try:
            lo, hi = (parse_value(param, key, p) for p in parts)
        except ValueError as exc:
            raise ValueError(f"--vary {key}={spec}: {exc}") from None
        if vector:
            if log:
                raise ValueError(f"--vary {key}={spec}: log ranges need scalar parameters; {key} is a vector")
            if any(a > b for a, b in zip(lo, hi)):
                raise ValueError(f"--vary {key}={spec}: lo > hi in a component; write the smaller bound first")
        else:
            if lo > hi:
                raise ValueError(f"--vary {key}={spec}: lo {lo:g} > hi {hi:g}; write {key}={hi:g}:{lo:g}")
            if log and not (lo > 0 and hi > 0):
                raise ValueError(f"--vary {key}={spec}: a log range needs bounds > 0 (got {lo:g}:{hi:g}); "
                                 "drop ':log' or use positive bounds")
            if isinstance(lo, float):  # the worlds hold float32: bounds that round away are not what was asked
                tiny, huge = float(np.finfo(np.float32).tiny), float(np.finfo(np.float32).max)
                for name, bound in (("lo", lo), ("hi", hi)):
                    if bound != 0.0 and not tiny <= abs(bound) <= huge:
                        raise ValueError(f"--vary {key}={spec}: {name} {bound:g} is outside the float32 range the "
                                         f"simulation holds ({tiny:.3g} .. {huge:.3g} in magnitude, or 0); give "
                                         "bounds inside it")
        return VarySpec(key, lo=lo, hi=hi, log=log)
    items = spec.split(";") if vector else spec.split(",")
    items = [s for s in (i.strip() for i in items) if s]
    if not items:
        raise ValueError(f"--vary {key}={spec!r} has no values; write {key}=A,B,C or {key}=LO:HI")
    try:
        values = tuple(parse_value(param, key, s) for s in items)
    except ValueError as exc:
        raise ValueError(f"--vary {key}={spec}: {exc}") from None
    return VarySpec(key, values=values)


def _grid_counts(n, ranges, list_product):
    """Points per range so that list_product * m ** ranges == n; ValueError otherwise."""
    if ranges == 0:
        if n != list_product:
            raise ValueError(f"grid: the listed values give {list_product} worlds, not --worlds {n}; "
                             f"use --worlds {list_product} or --sample random/lhs")
        return 0
    m = max(1, round((n / list_product) ** (1.0 / ranges)))
    if list_product * m**ranges != n:
        options = sorted({list_product * k**ranges for k in (max(1, m - 1), m, m + 1)})
        raise ValueError(f"grid: --worlds {n} is not {list_product} x m^{ranges} for an integer m; use --worlds "
                         f"{' or '.join(map(str, options))}, or --sample random/lhs")
    return m


def _range_value(spec, u):
    """The value at fraction u in [0, 1] of a range spec."""
    if isinstance(spec.lo, tuple):
        return tuple(a + u * (b - a) for a, b in zip(spec.lo, spec.hi))
    if spec.log:
        return math.exp(math.log(spec.lo) + u * (math.log(spec.hi) - math.log(spec.lo)))
    return spec.lo + u * (spec.hi - spec.lo)


def _typed(value, default):
    if isinstance(default, bool):
        return bool(value)
    if isinstance(default, int):
        return round(value)
    if isinstance(default, float):
        return float(value)
    if isinstance(default, (tuple, list)):
        return tuple(float(v) for v in value)
    return value


def sample_params(specs, params, n, sample="grid", seed=0) -> list:
    """``n`` dicts {key: typed value} of the varied keys, one per world, in world order."""
    n = int(n)
    if n < 1:
        raise ValueError(f"--worlds {n}: it must be >= 1")
    if sample not in SAMPLES:
        raise ValueError(f"--sample {sample!r} is unknown; use one of {', '.join(SAMPLES)}")
    keys = [s.key for s in specs]
    dup = {k for k in keys if keys.count(k) > 1}
    if dup:
        raise ValueError(f"--vary {min(dup)} is given twice; give each parameter once")
    if not specs:
        return [{} for _ in range(n)]
    rng = np.random.default_rng(seed)
    columns = []
    if sample == "grid":
        lists = [s for s in specs if not s.is_range]
        m = _grid_counts(n, sum(s.is_range for s in specs), int(np.prod([len(s.values) for s in lists])))
        axes = []
        for s in specs:
            if s.is_range:
                us = [0.5] if m == 1 else [k / (m - 1) for k in range(m)]
                axes.append([_range_value(s, u) for u in us])
            else:
                axes.append(list(s.values))
        mesh = np.meshgrid(*[np.arange(len(a)) for a in axes], indexing="ij")
        for a, idx in zip(axes, mesh):
            columns.append([a[k] for k in idx.reshape(-1)])
    else:
        for s in specs:
            if sample == "random":
                u = rng.uniform(0.0, 1.0, n)
            else:
                u = (rng.permutation(n) + rng.uniform(0.0, 1.0, n)) / n
            if s.is_range:
                columns.append([_range_value(s, x) for x in u])
            else:
                idx = np.minimum((u * len(s.values)).astype(int), len(s.values) - 1)
                columns.append([s.values[k] for k in idx])
    return [{s.key: _typed(col[w], params[s.key].default) for s, col in zip(specs, columns)} for w in range(n)]
