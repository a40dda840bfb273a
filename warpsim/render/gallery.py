"""The README's scene previews: ``python -m warpsim.render.gallery [--out docs] [--scenes A B ...]``.

Runs every registered scene (or the named ones) on the CPU for a short clip with the settings
below (unknown scenes: their ``smoke_params`` and 40 frames), renders each cache to a small GIF
(``docs/<scene>.gif``, 200x150, at most ~30 frames, 128 colours) with container walls drawn as
translucent guides, and prints the sizes. Caches go to a temporary folder. Each clip is made by
``python -m warpsim run`` in a child process.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

# scene -> (frames, --set overrides, draw guides)
CLIPS = {
    "bounce": (30, ["height=0.12", "restitution=0.8", "display_radius=0.025", "dt=0.02"], True),
    "pendulum": (90, [], True),
    "springs": (90, [], True),
    "teapot": (120, ["springs=false"], True),
    "cloth": (90, ["resolution=24"], True),
    "drape": (90, ["resolution=24"], True),
    "metaballs": (60, [], True),
    "dam_break": (60, ["spacing=0.04"], True),
    "pour": (90, ["spacing=0.04", "surface=false"], True),
    "smoke": (72, ["resolution=20"], False),
    "liquid": (60, ["resolution=20"], True),
    "flip_splash": (45, ["resolution=16"], True),
    "flock": (90, ["birds=150", "geese=20"], True),
    "school": (90, [], True),
    "zombies": (240, ["zombies=60"], True),
    "crowd": (120, ["people=60"], True),
    "wall": (24, ["ball_speed=6"], True),  # the impact and the first pieces (later they fly metres away)
    "donuts": (90, ["count=6", "segments=16", "sides=8", "lattice_cells=5"], True),
    "hair": (90, ["strands=300", "segments=10", "still=0.2"], True),  # the head turns and nods from 0.2 s
}
SIZE = (200, 150)
MAX_FRAMES = 30


def make(scene, out_dir, folder, err=sys.stderr):
    """Run ``scene`` (``warpsim run`` in a child process, as a user would: the dispatcher is the
    top floor, this module a floor below it) and write ``out_dir/<scene>.gif``; returns its path."""
    from ..scenes import get_scene
    from .cache import render_cache

    cls = get_scene(scene)
    frames, sets, guides = CLIPS.get(scene, (40, [f"{k}={_text(v)}" for k, v in cls.smoke_params.items()], True))
    cache = os.path.join(folder, f"{scene}.usda")
    argv = ["run", scene, "--frames", str(frames), "--out", cache, "--device", "cpu", "--no-progress"]
    for s in sets:
        argv += ["--set", s]
    child = subprocess.run([sys.executable, "-m", "warpsim", *argv], stdout=subprocess.DEVNULL,
                           stderr=subprocess.PIPE, text=True, check=False)
    err.write(child.stderr)
    code = child.returncode
    if code != 0:
        raise RuntimeError(f"warpsim {' '.join(argv)} failed with status {code}")
    step = max(1, -(-(frames + 1) // MAX_FRAMES))
    out = os.path.join(out_dir, f"{scene}.gif")
    render_cache(cache, out, frames=f"0:{frames}:{step}", size=SIZE, device="cpu", guides=guides,
                 fps=min(25.0, get_scene(scene).fps / step * 2), gif_colors=128)
    return out


def _text(v):
    return ",".join(map(str, v)) if isinstance(v, (tuple, list)) else str(v)


def main(argv=None):
    from ..scenes import scenes
    from ..verbosity import set_warp_verbosity

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs", help="folder of the GIFs (default docs)")
    parser.add_argument("--scenes", nargs="*", default=None, help="scenes to make (default: all registered)")
    parser.add_argument("--verbose", action="store_true", help="show Warp's banner and module-load lines")
    args = parser.parse_args(argv)
    set_warp_verbosity(args.verbose)
    names = args.scenes or list(scenes())
    os.makedirs(args.out, exist_ok=True)
    total, failed = 0, []
    with tempfile.TemporaryDirectory() as folder:
        for name in names:
            t0 = time.perf_counter()
            try:
                path = make(name, args.out, folder)
            except Exception as exc:  # noqa: BLE001  (report every scene that fails, make the others)
                failed.append(name)
                print(f"{name}: FAILED: {exc}", file=sys.stderr)
                continue
            size = os.path.getsize(path)
            total += size
            print(f"{path}: {size / 1024:.0f} KiB ({time.perf_counter() - t0:.1f} s)")
    print(f"{len(names) - len(failed)} previews, {total / 1024:.0f} KiB in all")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
