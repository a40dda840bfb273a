"""``warpsim view SCENE|CACHE.usd [--set k=v ...] [--device D] [--port P] [--host H]``.

A scene name starts the live viewer on that scene; a path ending in .usd/.usda/.usdc plays the
cache back. Usage mistakes (unknown scene or parameter, bad value, port in use, missing cache)
exit 2 with one line, as ``warpsim run`` does. Imports nothing heavy until it runs.
"""
from __future__ import annotations

import os
import sys

from ..cli_common import (
    UsageError, device_arg, parse_sets, stability_check, substeps_arg, timing_from_flags, timing_note,
)

__all__ = ["add_parser", "run"]


def add_parser(sub):

    v = sub.add_parser("view", help="watch a scene live in the browser (or play a USD cache)")
    v.add_argument("scene", help="scene name (see 'warpsim list') or a warpsim cache .usd/.usda/.usdc to play")
    v.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="set a scene parameter (repeatable)")
    v.add_argument("--integrator", default=None, help="time integrator (scenes with an 'integrator' parameter)")
    v.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0 (default: CUDA when present)")
    v.add_argument("--fps", type=float, default=None, help="frames per second (default: the scene's)")
    v.add_argument("--substeps", type=substeps_arg, default=None,
                   help="simulation steps per frame at the scene's frame rate, or 'auto' (default: the scene's; "
                        "as 'warpsim run --help' says)")
    v.add_argument("--strict", action="store_true",
                   help="exit 2 before serving when the time step is above the stability limit or --substeps "
                        "overrides the scene's dt (default: warn)")
    v.add_argument("--port", type=int, default=8080, help="port to serve on (default 8080)")
    v.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    v.add_argument("--max-points", type=int, default=200_000,
                   help="points drawn per particle prim; larger sets are shown as an even subset")
    v.add_argument("--allow-damaged", action="store_true",
                         help="play a cache with damaged chunk files anyway, leaving their frames out")
    v.add_argument("--paused", action="store_true", help="start paused")
    v.add_argument("--environment", action="store_true",
                   help="image-based lighting (prettier; slow where the browser has no GPU)")
    v.add_argument("--world", type=int, default=0, metavar="N",
                   help="a sweep run with --store none keeps no frames: world N (default 0) is re-run exactly, on "
                        "demand, and played")
    v.add_argument("--record-dir", default="usd_out", help="folder for recordings; a relative path is taken from the "
                   "current folder (default usd_out)")
    return v


def _viser_or_usage():
    from ..extras import require_extra

    require_extra("viewer", "warpsim view")


def _check_address(args):
    """UsageError for a port, --max-points or host the viewer cannot serve with."""
    from .server import PortInUseError, check_port

    if not 0 < args.port < 65536:
        raise UsageError(f"--port {args.port}: it must be in 1..65535")
    if args.max_points < 1:
        raise UsageError(f"--max-points {args.max_points}: it must be >= 1")
    try:
        check_port(args.host, args.port)
    except PortInUseError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"--host {args.host!r}: {exc}") from None


def _is_cache(args):
    return os.path.splitext(args.scene)[1] in (".usd", ".usda", ".usdc")


def _live_scene(args):
    """(scene class, resolved parameters, device) of a live scene's arguments; UsageError (one
    line, exit 2) for an unknown scene, parameter or device, or flags that disagree: all said before
    anything is built or served."""
    from ..scenes import get_scene

    try:
        cls = get_scene(args.scene)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    given = parse_sets(cls, args.sets, args.integrator)
    params = cls.resolve_params(given)
    timing_from_flags(cls, params, given, args.fps, args.substeps)  # flags that disagree: one line, exit 2, before serving
    return cls, params, device_arg(args.device)


def build(args, address_checked=False):
    """The Viewer (or PlaybackViewer) the arguments describe; UsageError for mistakes
    (``address_checked``: the port was checked, and is held by the starting page)."""
    if not address_checked:
        _check_address(args)
    if _is_cache(args):
        if args.sets or args.integrator:
            raise UsageError("--set and --integrator apply to scenes, not to a cache being played")
        from ..usd.validate import DamagedCacheError, check_damage
        from ..browse.gallery import GalleryViewer, is_sweep_root
        from .playback import PlaybackViewer

        rerun = on_demand_world(args.scene, getattr(args, "world", 0))
        if rerun is not None:  # a sweep that stored no frames: its world re-run now, then played
            print(f"{args.scene} stored no frames (--store none): world {rerun.world} re-ran exactly in "
                  f"{rerun.seconds:.2f} s; playing it", file=sys.stderr)
            from ..browse.roots import unstored_sweep
            from ..sweeps.rerun import pick_or_rerun
            from .unstored import UnstoredSweepViewer

            return UnstoredSweepViewer(args.scene, rerun.world, rerun.path, rerun.folder,  # any world, on demand
                                       int(unstored_sweep(args.scene)["worldCount"]), pick_or_rerun,
                                       host=args.host, port=args.port, max_points=args.max_points)

        player = GalleryViewer if is_sweep_root(args.scene) else PlaybackViewer  # a sweep: its worlds side by side
        try:
            bad = check_damage(args.scene, getattr(args, "allow_damaged", False), what="play")
            viewer = player(args.scene, host=args.host, port=args.port, max_points=args.max_points)
        except DamagedCacheError:
            raise  # exit 1: the cache, not the command line, is at fault
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        reader = getattr(viewer, "reader", None)
        if bad and reader is not None and hasattr(reader, "frames"):
            reader.frames = [f for f in reader.frames if f not in bad]
            print(f"warpsim: leaving out {len(bad)} frame(s) of damaged chunk files", file=sys.stderr)
        return viewer
    from .server import Viewer

    cls, params, device = _live_scene(args)
    print(f"warpsim view: building scene {cls.name!r} on {device or 'the default device'} (then the first frame "
          "compiles Warp's kernels; the page says so) ...", file=sys.stderr, flush=True)
    try:
        return Viewer(cls, params, device, host=args.host, port=args.port, fps=args.fps, substeps=args.substeps,
                      max_points=args.max_points, record_dir=args.record_dir, paused=args.paused,
                      environment=args.environment)
    except ValueError as exc:
        raise UsageError(f"scene {cls.name!r}: {exc}") from None


def on_demand_world(root, world=0):
    """For the root of a sweep run with ``--store none``: world ``world`` re-run exactly from the
    sweep's manifest into a scratch folder (``.path`` the cache, ``.folder`` its
    ``TemporaryDirectory``, ``.world``, ``.seconds``); None for any other file. UsageError (one
    line) for a world out of range or a root without its manifest."""
    import tempfile
    import time
    import types

    from ..browse.roots import unstored_sweep

    if not os.path.isfile(root) or unstored_sweep(root) is None:
        return None
    from ..sweeps.rerun import pick_or_rerun

    folder = tempfile.TemporaryDirectory(prefix="warpsim_view_world_")
    t0 = time.perf_counter()
    try:
        path = pick_or_rerun(root, int(world), os.path.join(folder.name, f"world_{int(world):06d}.usda"))
    except (OSError, ValueError) as exc:
        folder.cleanup()
        raise UsageError(str(exc).splitlines()[0]) from None
    return types.SimpleNamespace(path=path, folder=folder, world=int(world), seconds=time.perf_counter() - t0)


def threading_is_main():
    import threading

    return threading.current_thread() is threading.main_thread()


def _build_and_start(args, page, err):
    """The viewer built (what the build says on standard error also shown on the starting
    ``page``, when there is one), its notes said, then started on the port the page held (closed
    just before: an open tab reconnects to the viewer by itself)."""
    import contextlib

    from .server import PortInUseError

    with page.reporting() if page is not None else contextlib.nullcontext():
        viewer = build(args, address_checked=page is not None)
        session = getattr(viewer, "session", None)
        if session is not None and hasattr(session.scene, "stability_warning"):
            import warnings

            from ..core.stability import StabilityWarning

            warnings.simplefilter("ignore", StabilityWarning)  # said once here; the page shows the limit
            timing_note(session.timing, getattr(args, "strict", False), err)
            stability_check(session.scene, session.frame_dt, session.substeps, getattr(args, "strict", False), err)
    if page is not None:
        page.close()
    try:
        viewer.start()
    except PortInUseError as exc:  # taken between the check and the start
        raise UsageError(str(exc)) from None
    return viewer


def run(args, out, err):
    from ..verbosity import set_warp_verbosity

    _viser_or_usage()  # before any work
    set_warp_verbosity()  # Warp's module-load lines only with --verbose
    from ..usd.validate import DamagedCacheError

    page = None
    if not _is_cache(args):  # a live scene: a page says how its build goes, at the viewer's address
        from .starting import StartingPage

        _check_address(args)
        _live_scene(args)  # its mistakes said before anything is served
        page = StartingPage(args.host, args.port, f"warpsim view {args.scene}: starting")
        print(f"warpsim view: http://{args.host}:{args.port}   (the page says how the start goes)", file=out,
              flush=True)
    try:
        viewer = _build_and_start(args, page, err)
    except DamagedCacheError as exc:
        print(f"warpsim: error: {exc}", file=err)
        return 1
    finally:
        if page is not None:
            page.close()
    import signal

    if threading_is_main():
        signal.signal(signal.SIGTERM, lambda *_: viewer.request_stop())  # kill: stop cleanly, completing a recording
    live = hasattr(viewer, "session")
    print(f"warpsim view: {viewer.url}   (Ctrl-C stops" + (f"; recordings go to {args.record_dir}/)" if live else ")"),
          file=out, flush=True)
    viewer.run()
    return 0
