"""``warpsim plot CACHE [--out FILE.png]``: plots of the per-frame scalar data a cache carries.

What is plotted (:func:`cache_series` reads it; matplotlib draws it):
- every time-sampled scalar attribute (``warpsim:totalEnergy``, ``warpsim:densityError``,
  ``warpsim:iterations``, ``warpsim:volume``, ``warpsim:overWallFraction``, ...); attributes of
  one prim whose names end in ``Energy`` share one panel;
- the element count of every prim whose count changes (particles, smoke samples, agents);
- agents per state: the per-frame histogram of an instancer's ``primvars:state``.

The x axis is time [s] (frame / fps); a y axis carries the unit its attribute was declared with
(``customData["unit"]``, e.g. the pendulum's ``angle [rad]``).
"""
from __future__ import annotations

import os

import numpy as np

from ..usd.validate import frame_codes, open_stage

_COUNT_ATTR = {"Points": "points", "Mesh": "points", "BasisCurves": "points", "PointInstancer": "positions"}
_SCALARS = ("double", "float", "int", "int64", "half", "uint", "bool")


def _state_names():
    try:
        from ..agents.params import AgentState

        return {int(s): s.name.lower() for s in AgentState}
    except ImportError:  # pragma: no cover
        return {}


def cache_series(path, allow_damaged=False, on_skip=None):
    """Panels of a cache's per-frame data: a list of ``{"title", "ylabel", "lines": {label: values}}``
    plus the time axis: returns ``(times [s] (frames,), panels)``. ValueError when the cache does
    not open; :class:`warpsim.usd.validate.DamagedCacheError` when chunk files are damaged
    (``allow_damaged``: their frames are left out and ``on_skip(line)`` says which)."""
    from pxr import UsdGeom

    from ..usd.validate import check_damage

    bad = check_damage(path, allow_damaged, what="plot")
    stage = open_stage(path)
    frames = frame_codes(stage)
    if bad:
        frames = [f for f in frames if f not in bad]
        if on_skip is not None:
            on_skip(f"skipping {len(bad)} frame(s) of damaged chunk files (readable: {len(frames)} frames)")
    fps = stage.GetTimeCodesPerSecond()
    times = np.asarray(frames, np.float64) / fps
    panels = []
    counts = {}
    for prim in stage.Traverse():
        name = prim.GetName()
        energy = {}
        for attr in prim.GetAttributes():
            if str(attr.GetTypeName()) not in _SCALARS or attr.GetNumTimeSamples() == 0 and not \
                    attr.ValueMightBeTimeVarying():
                continue
            label = attr.GetName().split(":")[-1]
            values = np.array([attr.Get(f) for f in frames], np.float64)
            unit = attr.GetCustomDataByKey("unit")  # declared with the attribute (add_attribute(..., unit=))
            if label.endswith("Energy"):
                energy[label] = values
            else:
                panels.append({"title": f"{name}: {label}", "ylabel": f"{label} [{unit}]" if unit else label,
                               "lines": {label: values}})
        if energy:
            panels.append({"title": f"{name}: energy", "ylabel": "energy [J]", "lines": energy})
        count_attr = prim.GetAttribute(_COUNT_ATTR[prim.GetTypeName()]) if prim.GetTypeName() in _COUNT_ATTR else None
        if count_attr and count_attr.ValueMightBeTimeVarying():
            n = np.array([len(count_attr.Get(f) or []) for f in frames], np.float64)
            if len(n) and n.min() != n.max():
                counts[name] = n
        if prim.IsA(UsdGeom.PointInstancer):
            state = UsdGeom.PrimvarsAPI(prim).GetPrimvar("state")
            if state and state.HasValue() and len(frames):
                per = [np.asarray(state.Get(f) if state.Get(f) is not None else [], np.int64) for f in frames]
                top = max((int(s.max()) for s in per if len(s)), default=-1)
                if top >= 0:
                    names = _state_names()
                    hist = np.array([np.bincount(s, minlength=top + 1) for s in per], np.float64)
                    lines = {names.get(k, f"state {k}"): hist[:, k] for k in range(top + 1) if hist[:, k].any()}
                    panels.append({"title": f"{name}: agents per state", "ylabel": "agents", "lines": lines})
    if counts:
        panels.append({"title": "element counts", "ylabel": "count", "lines": counts})
    return times, panels


def plot_cache(path, out=None, size=(8.0, 2.6), allow_damaged=False, on_skip=None):
    """Draw :func:`cache_series` into ``out`` (default ``<cache stem>.plot.png``); returns
    ``(out, panel count)``. ValueError when there is nothing per-frame to plot."""
    from ..usd.family import check_output
    from ..usd.lock import OutputLock

    target = out or os.path.splitext(str(path))[0] + ".plot.png"
    check_output(target, [path], "--out")
    with OutputLock(target, "--out"):
        return _plot_cache(path, out, size, allow_damaged, on_skip)


def _plot_cache(path, out, size, allow_damaged, on_skip):
    times, panels = cache_series(path, allow_damaged, on_skip)
    if not panels or len(times) < 2:
        raise ValueError(f"cache {path!r} carries no per-frame scalar data to plot (no time-sampled scalar "
                         "attributes, changing counts or agent states over at least two frames)")
    out = out or os.path.splitext(str(path))[0] + ".plot.png"
    ext = os.path.splitext(out)[1].lower()
    if ext not in (".png", ".pdf", ".svg"):
        raise ValueError(f"--out {out!r}: write a .png, .pdf or .svg file")
    try:
        import matplotlib
    except ImportError:
        raise ImportError("warpsim plot needs matplotlib: pip install 'warpsim[plot]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(panels), 1, figsize=(size[0], size[1] * len(panels)), sharex=True, squeeze=False)
    for ax, panel in zip(axes[:, 0], panels):
        for label, values in panel["lines"].items():
            ax.plot(times, values, label=label)
        ax.set_title(panel["title"], fontsize=10)
        ax.set_ylabel(panel["ylabel"])
    axes[-1, 0].set_xlabel("time [s]")
    save_figure(fig, out)
    return out, len(panels)


def save_figure(fig, path, dpi=90, legend=True):
    """Grid and legend on every axes of a matplotlib ``fig``, tight layout, write ``path``
    (creating its folder) and close the figure (shared with the examples' figures)."""
    import matplotlib.pyplot as plt

    for ax in fig.axes:
        ax.grid(alpha=0.3)
        if legend and len(ax.get_lines()) > 1:
            ax.legend(fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    from ..core.safe_files import write_replacing

    ext = os.path.splitext(os.fspath(path))[1].lower().lstrip(".")
    try:  # under a temporary name, renamed onto path: a link planted at either is never written through
        write_replacing(path, lambda f: fig.savefig(f, dpi=dpi, format=ext or None), what=repr(os.fspath(path)))
    finally:
        plt.close(fig)


def add_parser(sub):
    p = sub.add_parser("plot", help="plot the per-frame data of a USD cache (energies, errors, counts, states)")
    p.add_argument("cache", help="path of a .usd/.usda/.usdc cache")
    p.add_argument("--out", default=None, help="figure to write (.png/.pdf/.svg); a relative path is taken "
                   "from the current folder (default: beside the cache, CACHE.plot.png)")
    p.add_argument("--allow-damaged", action="store_true",
                   help="plot a cache with damaged chunk files anyway, leaving their frames out (said on stderr)")


def run(args, out, err):
    from ..cli_common import UsageError
    from ..extras import require_extra

    require_extra("plot", "warpsim plot")

    if not os.path.exists(args.cache):
        raise UsageError(f"cache {args.cache!r} does not exist; write one with 'warpsim run SCENE'")
    from ..cli_common import check_output_path
    from ..usd.validate import DamagedCacheError

    # a folder, FIFO or device at --out, or a folder that cannot be written: before the cache is read
    check_output_path(args.out or os.path.splitext(args.cache)[0] + ".plot.png", "--out")

    try:
        path, n = plot_cache(args.cache, args.out, allow_damaged=args.allow_damaged,
                             on_skip=lambda line: print(f"warpsim: {line}", file=err))
    except DamagedCacheError as exc:
        print(f"warpsim: error: {exc}", file=err)
        return 1
    except (ValueError, OSError) as exc:
        from ..usd.pxr_errors import error_line

        raise UsageError(error_line(exc)) from None
    print(f"wrote {path} ({n} panel{'s' if n != 1 else ''})", file=out)
    return 0
