"""``warpsim export CACHE [--frame N] --out FILE.obj|.ply|.stl|.glb [--surface] [--merge] [--guides]
[--up y|z] [--prims NAME[,NAME]]``:
one frame's geometry as files other tools read (see :mod:`warpsim.render.export`)."""

from __future__ import annotations

import os


def add_parser(sub):
    p = sub.add_parser("export", help="write one frame of a USD cache as .obj, .ply, .stl or .glb geometry")
    p.add_argument("cache", help="path of a .usd/.usda/.usdc cache")
    p.add_argument("--frame", type=int, default=None, help="frame to export (default: the last)")
    p.add_argument("--out", required=True, help="file to write: .obj, .ply, .stl or .glb (one file per prim, "
                   "named OUT-STEM_PRIM.SUFFIX, unless --merge); a relative path is taken from the current folder")
    p.add_argument("--surface", action="store_true",
                   help="particles as a closed marching-cubes surface instead of a point cloud")
    p.add_argument("--spacing", type=float, default=None,
                   help="--surface grid spacing [m] (default: the particles' width or neighbour distance)")
    p.add_argument("--merge", action="store_true", help="every prim into the one file --out")
    p.add_argument("--up", choices=("y", "z"), default=None,
                   help="the file's up axis (default: the format's: z for .ply and .stl, which Blender reads as they "
                        "are; y for .obj and .glb, which Blender's importers turn Z-up themselves)")
    p.add_argument("--prims", default=None, metavar="NAME[,NAME]",
                   help="export only these prims (default: every drawn prim; a format without lines, .stl, leaves "
                        "curves out with a note)")
    p.add_argument("--guides", action="store_true", help="also export guide prims (pure helpers)")
    p.add_argument("--device", default=None, help="Warp device for --surface (default: CUDA when present)")
    p.add_argument("--allow-damaged", action="store_true",
                   help="export from a cache with damaged chunk files anyway (a frame outside them; default: the last "
                        "readable one)")


def run(args, out, err):
    from ..cli_common import UsageError
    from ..cli_common import device_arg
    from .export import FORMATS, export_frame

    suffix = os.path.splitext(args.out)[1].lower()
    if suffix not in FORMATS:
        raise UsageError(f"--out {args.out!r}: unknown suffix {suffix or '(none)'!r}; write one of "
                         f"{', '.join(FORMATS)}")
    if not os.path.exists(args.cache):
        raise UsageError(f"cache {args.cache!r} does not exist; write one with 'warpsim run SCENE'")
    from ..cli_common import check_output_path

    check_output_path(args.out, "--out")  # a folder, FIFO or device, an unwritable folder: before reading
    if args.spacing is not None and not args.spacing > 0.0:
        raise UsageError(f"--spacing {args.spacing}: it must be > 0 [m]")
    prims = None
    if args.prims is not None:
        prims = [name.strip() for name in args.prims.split(",")]
        if not all(prims):
            raise UsageError(f"--prims {args.prims!r}: an empty name; give NAME[,NAME], e.g. --prims teapot")
    device = None
    if args.surface:
        from ..verbosity import set_warp_verbosity

        set_warp_verbosity()
        device = device_arg(args.device)
    try:
        result = export_frame(args.cache, args.out, args.frame, surface=args.surface, merge=args.merge,
                              guides=args.guides, spacing=args.spacing, device=device,
                              allow_damaged=args.allow_damaged, up=args.up, prims=prims)
    except (ValueError, OSError) as exc:
        if getattr(exc, "exit_status", 2) != 2:
            raise  # damaged chunk files: exit 1 (like render), naming the first and the readable frames
        from ..usd.pxr_errors import error_line

        raise UsageError(error_line(exc)) from None
    for name, kind, verts, elems in result["parts"]:
        what = {"mesh": f"{elems} triangles", "curves": f"{elems} segments", "points": "points"}[kind]
        print(f"  {name}: {kind}, {verts} vertices" + ("" if kind == "points" else f", {what}"), file=out)
    for note in result["notes"]:
        print(note, file=err)
    paths = result["paths"]
    print(f"wrote frame {result['frame']} to {paths[0]}" if len(paths) == 1 else
          f"wrote frame {result['frame']} to {len(paths)} files: {', '.join(paths)}", file=out)
    return 0
