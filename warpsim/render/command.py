"""``warpsim render CACHE [--frame N | --frames A:B] --out FILE.png|.gif|.mp4 [--size WxH]
[--camera ex,ey,ez,tx,ty,tz] [--fps F] [--device D] [--guides]``: pictures of a cache."""
from __future__ import annotations

import os


def add_parser(sub):
    p = sub.add_parser("render", help="render a USD cache to a .png, .gif or .mp4")
    p.add_argument("cache", help="path of a .usd/.usda/.usdc cache")
    p.add_argument("--out", default=None, help="picture to write: .png (one frame), .gif or .mp4; a relative "
                   "path is taken from the current folder (default: beside the cache, its name with .gif)")
    p.add_argument("--frame", type=int, default=None, help="one frame (default for .png: the last)")
    p.add_argument("--frames", default=None, metavar="A:B[:STEP]", help="inclusive frame range (default: all)")
    p.add_argument("--size", default="480x360", metavar="WxH", help="image size in pixels (default 480x360)")
    p.add_argument("--camera", default=None, metavar="ex,ey,ez,tx,ty,tz",
                   help="eye and target [m] (default: frame the scene's bounds)")
    p.add_argument("--fps", type=float, default=None, help="playback rate (default: the cache's)")
    p.add_argument("--device", default=None, help="Warp device (default: CUDA when present)")
    p.add_argument("--guides", action="store_true", help="also draw guide prims (container walls), translucent")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--allow-damaged", action="store_true",
                   help="draw a cache with damaged chunk files anyway, skipping their frames (said on stderr)")


def preview_target(preview: str, cache: str) -> str:
    """Where ``run --preview [FILE]`` writes: FILE as given (a relative path from the current
    folder, as every output path); ``--preview`` alone (``""``): beside the cache, its name with .gif."""
    return preview or os.path.splitext(cache)[0] + ".gif"


def render_to(cache, out, err, *, frame=None, frames=None, size="480x360", camera=None, fps=None, device=None,
              guides=False, progress=True, max_frames=None, allow_damaged=False, flag="--out"):
    """Shared by ``render`` and ``run --preview``: render and return the result dict; usage
    mistakes raise ``cli.UsageError`` (a bad ``out`` is named as ``flag``)."""
    from ..cli_common import UsageError
    from ..cli_common import device_arg as _device
    from ..usd.validate import DamagedCacheError
    from ..extras import render_modules, require_extra

    require_extra("render", f"writing {os.path.basename(str(out))}", render_modules(out))
    from .cache import render_cache

    if not os.path.exists(cache):
        raise UsageError(f"cache {cache!r} does not exist; write one with 'warpsim run SCENE'")
    from ..usd.family import check_output
    from ..usd.lock import hold

    from .output import check_out

    try:
        check_out(out, flag)  # a folder, FIFO or device, or a folder that cannot be written: before anything is read
        check_output(out, [cache], flag)
    except (ValueError, OSError) as exc:
        raise UsageError(str(exc)) from None
    hold(out, flag)  # released when the command (or, through the API, the process) ends
    from ..verbosity import set_warp_verbosity

    set_warp_verbosity()  # Warp's module-load lines only with --verbose
    device = _device(device)
    bars = []

    def advance(done, total):  # the bar appears once the inputs are checked and frames are drawn
        if not bars:
            from tqdm import tqdm

            bars.append(tqdm(total=total, unit="frame", desc="render", file=err, dynamic_ncols=True))
        bars[0].update(1)

    try:
        return render_cache(cache, out, frame=frame, frames=frames, size=size, camera=camera, fps=fps, device=device,
                            guides=guides, progress=advance if progress else None, max_frames=max_frames,
                            allow_damaged=allow_damaged, on_skip=lambda line: print(f"warpsim: {line}", file=err))
    except DamagedCacheError:
        raise  # exit 1, not a usage mistake
    except (ValueError, OSError) as exc:  # FileNotFoundError/PermissionError are OSErrors
        from ..usd.pxr_errors import error_line

        raise UsageError(error_line(exc)) from None
    finally:
        for bar in bars:
            bar.close()

def run(args, out, err):
    from ..usd.validate import DamagedCacheError

    target = args.out or os.path.splitext(args.cache)[0] + ".gif"
    try:
        result = render_to(args.cache, target, err, frame=args.frame, frames=args.frames, size=args.size,
                           camera=args.camera, fps=args.fps, device=args.device, guides=args.guides,
                           progress=not args.no_progress, allow_damaged=args.allow_damaged)
    except DamagedCacheError as exc:
        print(f"warpsim: error: {exc}", file=err)
        return 1
    n = result["frames"]
    print(f"wrote {result['path']} ({n} frame{'s' if n != 1 else ''}, {result['seconds']:.2f} s, "
          f"{result['camera']})", file=out)
    return 0
