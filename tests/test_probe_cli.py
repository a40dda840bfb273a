"""A hostile but fair user's probe of the command line: every bad input below exits 2 before the
simulation starts, with ONE line on stderr (``warpsim: error: ...``) naming the offending item,
no traceback and nothing on stdout. Damaged caches: ``warpsim info`` lists the damaged chunk
files and the readable frames and exits 1; ``--resume`` never continues over a missing or
damaged chunk. Most cases call ``warpsim.cli.main`` in-process; a few run the console entry in
a subprocess to prove the same from the outside (and that ``warpsim list | head -1`` ends
without a BrokenPipeError)."""

import io
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from warpsim.cli import main
from warpsim.usd.checkpoint import save_checkpoint

RUN = ["--device", "cpu", "--no-progress"]


def run(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = main(list(argv), out, err)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def ctx(tmp_path_factory):
    """A bounce cache of frames 0..30 in chunks of 8 with a checkpoint at frame 30, files for the
    bad checkpoints, and ``fresh()``: a private copy of the cache folder for runs that change it."""
    d = tmp_path_factory.mktemp("probe_cli")
    base = d / "base"
    code, _, err = run("run", "bounce", "--frames", "30", "--chunk", "8", "--checkpoint-every", "15",
                       "--out", str(base / "b.usda"), *RUN)
    assert code == 0, err
    (d / "afile").write_text("not a folder")
    (d / "folder.usda").mkdir()
    (d / "text.usda").write_text("this is not USD\n")
    counter = [0]

    def fresh(mutate=None):
        counter[0] += 1
        dest = d / f"copy{counter[0]}"
        shutil.copytree(base, dest)
        if mutate is not None:
            mutate(dest)
        return str(dest / "b.usda")

    return {"dir": d, "base": str(base / "b.usda"), "fresh": fresh}


def ckpt(mutate):
    """A cache copy whose checkpoint ``mutate(path)`` rewrites."""
    return lambda c: c["fresh"](lambda dest: mutate(str(dest / "b.checkpoint.npz")))


def write(data):
    def mutate(path):
        with open(path, "wb") as f:
            f.write(data)
    return mutate


def truncate(path):
    data = open(path, "rb").read()
    with open(path, "wb") as f:
        f.write(data[: len(data) // 2])


def meta_only(meta):
    return lambda path: save_checkpoint(path, {"positions": np.zeros((1, 3))}, meta)


GOOD_META = {"scene": "bounce", "frame": 30, "fps": 25.0, "substeps": 1}


def chunk(name, action):
    """A cache copy with chunk file ``name`` deleted, truncated or overwritten (same size)."""
    def mutate(dest):
        path = dest / name
        if action == "delete":
            path.unlink()
        elif action == "truncate":
            path.write_bytes(path.read_bytes()[:100])
        else:
            data = bytearray(path.read_bytes())
            data[len(data) // 2] ^= 0xFF
            path.write_bytes(bytes(data))
    return lambda c: c["fresh"](mutate)


def resume(path_fn, *extra):
    return lambda c: ["run", "bounce", "--frames", "40", "--chunk", "8", "--resume", "--out", path_fn(c),
                      *extra, *RUN]


def scene(name, *sets):
    return lambda c: ["run", name, "--frames", "1", "--out", str(c["dir"] / "scenes" / f"{name}.usda"),
                      *[a for s in sets for a in ("--set", s)], *RUN]


def cmd(*argv):
    return lambda c: [a.format(**{k: str(v) for k, v in c.items() if not callable(v)}) for a in argv]


CASES = [
    # ---- argument parsing and run options
    ("no-command", cmd(), ["required"]),
    ("unknown-command", cmd("frobnicate"), ["invalid choice", "frobnicate"]),
    ("run-no-scene", cmd("run"), ["scene"]),
    ("unknown-scene", cmd("run", "bounc"), ["unknown scene 'bounc'", "Did you mean 'bounce'"]),
    ("list-extra", cmd("list", "extra"), ["unrecognized arguments", "extra"]),
    ("frames-neg", cmd("run", "bounce", "--frames", "-1", *RUN), ["--frames -1"]),
    ("frames-text", cmd("run", "bounce", "--frames", "x", *RUN), ["--frames", "'x'"]),
    ("chunk-zero", cmd("run", "bounce", "--chunk", "0", *RUN), ["--chunk 0"]),
    ("checkpoint-every-neg", cmd("run", "bounce", "--checkpoint-every", "-1", *RUN),
     ["--checkpoint-every -1"]),
    ("fps-zero", cmd("run", "bounce", "--fps", "0", *RUN), ["--fps 0"]),
    ("fps-neg", cmd("run", "bounce", "--fps", "-5", *RUN), ["--fps -5"]),
    ("fps-nan", cmd("run", "bounce", "--fps", "nan", *RUN), ["--fps nan"]),
    ("fps-text", cmd("run", "bounce", "--fps", "fast", *RUN), ["--fps", "'fast'"]),
    ("substeps-zero", cmd("run", "bounce", "--substeps", "0", *RUN), ["--substeps 0"]),
    ("fps-and-dt", cmd("run", "bounce", "--fps", "10", "--set", "dt=0.01", *RUN), ["dt", "give one of them"]),
    ("integrator-unknown", cmd("run", "bounce", "--integrator", "rk5", *RUN), ["rk5", "Did you mean 'rk4'"]),
    ("integrator-none", cmd("run", "metaballs", "--integrator", "rk4", *RUN), ["no integrator choice"]),
    ("integrator-disagree", cmd("run", "bounce", "--integrator", "rk4", "--set", "integrator=rk2", *RUN),
     ["--integrator", "disagree"]),
    ("device-unknown", cmd("run", "bounce", "--device", "tpu", "--no-progress"),
     ["--device 'tpu'", "available"]),
    ("set-malformed", cmd("run", "bounce", "--set", "restitution", *RUN), ["restitution", "KEY=VALUE"]),
    ("set-unknown-key", cmd("run", "bounce", "--set", "restitutin=0.3", *RUN),
     ["no parameter 'restitutin'", "Did you mean 'restitution'"]),
    ("set-float-text", cmd("run", "bounce", "--set", "dt=fast", *RUN), ["dt='fast'", "float"]),
    ("set-float-nan", cmd("run", "bounce", "--set", "height=nan", *RUN), ["height='nan'"]),
    ("set-int-text", cmd("run", "springs", "--set", "count=ten", *RUN), ["count='ten'", "int"]),
    ("set-int-float", cmd("run", "springs", "--set", "count=2.5", *RUN), ["count='2.5'"]),
    ("set-vector-short", cmd("run", "bounce", "--set", "velocity=1,2", *RUN), ["velocity='1,2'", "3 floats"]),
    ("set-vector-text", cmd("run", "bounce", "--set", "velocity=a,b,c", *RUN), ["velocity='a,b,c'"]),
    ("set-choice", cmd("run", "springs", "--set", "shape=ring", *RUN), ["shape='ring'", "chain, lattice"]),
    ("set-bool", cmd("run", "dam_break", "--set", "surface=maybe", *RUN), ["surface='maybe'", "bool"]),
    # ---- --out
    ("out-extension", cmd("run", "bounce", "--out", "{dir}/x.obj", *RUN), ["--out", "x.obj", ".usda"]),
    ("out-parent-is-file", cmd("run", "bounce", "--out", "{dir}/afile/x.usda", *RUN), ["afile", "is a file"]),
    ("out-deep-parent-is-file", cmd("run", "bounce", "--out", "{dir}/afile/a/b/x.usda", *RUN),
     ["afile", "is a file"]),
    ("out-is-folder", cmd("run", "bounce", "--out", "{dir}/folder.usda", *RUN),
     ["folder.usda", "is a folder"]),
    ("out-unwritable", cmd("run", "bounce", "--out", "/proc/warpsim_probe.usda", *RUN),
     ["/proc", "cannot write"]),
    # ---- scene-level validation (before any step)
    ("bounce-height", scene("bounce", "height=-1"), ["height=-1", "below the floor"]),
    ("bounce-mass", scene("bounce", "mass=0"), ["mass=0", "> 0"]),
    ("bounce-restitution", scene("bounce", "restitution=2"), ["restitution 2.0", "[0, 1]"]),
    ("bounce-friction", scene("bounce", "friction=-1"), ["friction -1.0"]),
    ("bounce-dt", scene("bounce", "dt=-1"), ["dt=-1"]),
    ("bounce-display-radius", scene("bounce", "display_radius=-1"), ["radius", "-1"]),
    ("pendulum-length", scene("pendulum", "length=0"), ["length"]),
    ("pendulum-mass", scene("pendulum", "mass=-1"), ["mass"]),
    ("pendulum-gravity", scene("pendulum", "gravity=0"), ["gravity"]),
    ("springs-count", scene("springs", "count=1"), ["count=1"]),
    ("springs-spacing", scene("springs", "spacing=0"), ["spacing"]),
    ("springs-stiffness", scene("springs", "stiffness=-1"), ["stiffness -1.0"]),
    ("metaballs-resolution", scene("metaballs", "resolution=2"), ["resolution 2"]),
    ("metaballs-blobs", scene("metaballs", "blobs=0"), ["blob_count 0"]),
    ("metaballs-seed", scene("metaballs", "seed=-1"), ["seed=-1"]),
    ("crowd-people", scene("crowd", "people=0"), ["people=0"]),
    ("crowd-plaza", scene("crowd", "plaza=0"), ["plaza=0"]),
    ("zombies-count", scene("zombies", "zombies=0"), ["zombies=0"]),
    ("zombies-wall", scene("zombies", "wall_height=-1"), ["wall_height=-1"]),
    ("flock-size", scene("flock", "size=0"), ["size=0"]),
    ("flock-seed", scene("flock", "seed=-3"), ["seed=-3"]),
    ("school-size", scene("school", "size=0,0,0"), ["size="]),
    ("teapot-size", scene("teapot", "size=0"), ["size=0"]),
    ("teapot-lattice", scene("teapot", "lattice_cells=0"), ["lattice_cells"]),
    ("teapot-height", scene("teapot", "height=-1"), ["height=-1"]),
    ("cloth-resolution", scene("cloth", "resolution=0"), ["resolution=0"]),
    ("drape-density", scene("drape", "density=0"), ["density=0"]),
    ("donuts-count", scene("donuts", "count=0"), ["count=0"]),
    ("donuts-radii", scene("donuts", "minor_radius=0.5"), ["minor=0.5"]),
    ("wall-spacing", scene("wall", "spacing=0"), ["spacing=0"]),
    ("wall-bricks", scene("wall", "bricks=0,0"), ["bricks=0,0"]),
    ("smoke-tol", scene("smoke", "tol=0"), ["tol=0"]),
    ("liquid-depth", scene("liquid", "depth=0"), ["depth=0"]),
    ("flip-ratio", scene("flip_splash", "flip_ratio=2"), ["flip_ratio", "2.0"]),
    ("dam-break-iterations", scene("dam_break", "iterations=0"), ["iterations = 0"]),
    ("pour-spacing", scene("pour", "spacing=-1"), ["spacing=-1"]),
    # ---- --resume: checkpoints
    ("resume-no-checkpoint",
     lambda c: ["run", "bounce", "--resume", "--out", str(c["dir"] / "none.usda"), *RUN],
     ["no checkpoint"]),
    ("resume-empty-checkpoint", resume(ckpt(write(b""))), ["checkpoint", "b.checkpoint.npz", "is empty"]),
    ("resume-truncated-checkpoint", resume(ckpt(truncate)), ["checkpoint", "b.checkpoint.npz", "damaged"]),
    ("resume-garbage-checkpoint", resume(ckpt(write(b"garbage" * 100))), ["b.checkpoint.npz", "damaged"]),
    ("resume-checkpoint-no-meta", resume(ckpt(lambda p: np.savez(open(p, "wb"), x=np.zeros(3)))),
     ["b.checkpoint.npz", "damaged or not a warpsim checkpoint"]),
    ("resume-checkpoint-meta-keys", resume(ckpt(meta_only({"scene": "bounce"}))),
     ["b.checkpoint.npz", "lacks"]),
    ("resume-other-scene", resume(ckpt(meta_only({**GOOD_META, "scene": "pendulum", "params": {}}))),
     ["scene 'pendulum'", "not 'bounce'"]),
    ("resume-checkpoint-arrays", resume(ckpt(meta_only({**GOOD_META, "params": {}}))),
     ["does not fit scene 'bounce'", "without --resume"]),
    ("resume-param-differs", resume(lambda c: c["fresh"](), "--set", "mass=2"), ["mass=2.0 differs"]),
    ("resume-fps-differs", resume(lambda c: c["fresh"](), "--fps", "50"), ["--resume", "25 fps"]),
    ("resume-beyond-frames",
     lambda c: ["run", "bounce", "--frames", "10", "--resume", "--out", c["fresh"](), *RUN],
     ["checkpoint is at frame 30", "--frames 10"]),
    # ---- --resume: damaged cache before the checkpoint is never resumed over
    ("resume-chunk-deleted", resume(chunk("b.chunk000008.usdc", "delete")),
     ["b.chunk000008.usdc", "frames 8..15", "missing"]),
    ("resume-chunk-truncated", resume(chunk("b.chunk000000.usdc", "truncate")),
     ["b.chunk000000.usdc", "damaged"]),
    ("resume-chunk-corrupted", resume(chunk("b.chunk000024.usdc", "flip")), ["b.chunk000024.usdc", "CRC-32"]),
    ("resume-root-missing", resume(lambda c: c["fresh"](lambda d: (d / "b.usda").unlink())),
     ["does not exist"]),
    # ---- info
    ("info-missing", cmd("info", "{dir}/missing.usda"), ["missing.usda", "does not exist"]),
    ("info-folder", cmd("info", "{dir}/folder.usda"), ["folder.usda", "is a folder"]),
    ("info-no-arg", cmd("info"), ["cache"]),
]


@pytest.mark.parametrize("case_id, argv, words", CASES, ids=[c[0] for c in CASES])
def test_bad_command_line_is_one_line_exit_2(ctx, case_id, argv, words):
    args = argv(ctx)
    code, out, err = run(*args)
    assert code == 2, (args, code, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("warpsim: error: "), err
    assert "Traceback" not in err and out == ""
    for word in words:
        assert word in err, f"{case_id}: {word!r} not in {err!r}"


def test_probe_size():
    assert len(CASES) >= 70 and len({c[0] for c in CASES}) == len(CASES)


def test_resume_over_damage_leaves_the_cache_alone(ctx):
    """The refused resume changes nothing: the damaged cache still reports the same damage."""
    path = chunk("b.chunk000008.usdc", "delete")(ctx)
    before = sorted(os.listdir(os.path.dirname(path)))
    code, _, err = run("run", "bounce", "--frames", "40", "--resume", "--out", path, *RUN)
    assert code == 2 and "missing" in err
    assert sorted(os.listdir(os.path.dirname(path))) == before


def test_info_reports_damaged_chunks_and_readable_frames(ctx):
    path = ctx["fresh"](lambda d: ((d / "b.chunk000008.usdc").unlink(),
                                   (d / "b.chunk000024.usdc").write_bytes(b"\0" * 10)))
    code, out, err = run("info", path)
    assert code == 1, err
    assert "frames 0..30 (31 frames" in out
    assert "b.chunk000008.usdc  frames 8..15: missing" in out
    assert "b.chunk000024.usdc  frames 24..30: damaged" in out
    assert "readable frames: 0..7, 16..23" in out
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("warpsim: error: ")
    assert "2 damaged chunk file(s)" in lines[0]
    assert "readable frames 0..7, 16..23" in lines[0] and "Traceback" not in err
    # same-size corruption is found by the CRC-32 (checked by default below 256 MiB, or --verify)
    path = chunk("b.chunk000016.usdc", "flip")(ctx)
    code, out, err = run("info", "--verify", path)
    assert code == 1 and "b.chunk000016.usdc  frames 16..23: damaged (its contents changed" in out
    assert "readable frames: 0..15, 24..30" in out


def test_info_on_an_intact_cache_matches_reading_every_frame(ctx):
    from pxr import Usd

    from warpsim.usd.validate import cache_info

    code, out, err = run("info", ctx["base"])
    assert code == 0 and err == "" and "frames 0..30 (31 frames at 25 fps" in out
    fast = cache_info(ctx["base"])
    slow = cache_info(Usd.Stage.Open(ctx["base"]))  # every frame through the value clips
    assert fast["damaged"] == [] and fast["readable"] == [(0, 30)] and fast["checked"] == "size and CRC-32"
    assert (fast["start"], fast["end"], fast["frames"]) == (slow["start"], slow["end"], slow["frames"])
    for p, q in zip(fast["prims"], slow["prims"]):
        assert (p["path"], p["type"], p["animated"], p.get("count")) == \
            (q["path"], q["type"], q["animated"], q.get("count"))
        np.testing.assert_allclose(p["bounds"], q["bounds"], rtol=1e-6, atol=1e-9)
    index = [json.loads(line) for line in open(ctx["base"].replace(".usda", ".chunks.jsonl"))]
    assert [(r["start"], r["end"]) for r in index] == [(0, 7), (8, 15), (16, 23), (24, 30)]


def test_info_without_chunk_index_still_finds_damage(ctx):
    """Caches written before the chunk index existed: each chunk is opened in USD instead."""
    path = ctx["fresh"](lambda d: ((d / "b.chunks.jsonl").unlink(),
                                   (d / "b.chunk000016.usdc").write_bytes(b"x")))
    code, out, err = run("info", path)
    assert code == 1 and "b.chunk000016.usdc  frames 16..23: damaged (does not open in USD" in out, out + err
    assert "(checked: opened in USD)" in out and "readable frames: 0..15, 24..30" in out


def test_info_on_a_file_that_is_not_usd_exits_1(ctx):
    code, out, err = run("info", str(ctx["dir"] / "text.usda"))
    assert code == 1 and out == ""
    assert err.count("\n") == 1 and err.startswith("warpsim: error: ") and "text.usda" in err


def test_resume_after_a_good_checkpoint_still_works(ctx):
    """Next to the refusals: an intact cache resumes and ends whole (info exit 0)."""
    path = ctx["fresh"]()
    code, out, err = run("run", "bounce", "--frames", "40", "--chunk", "8", "--resume", "--out", path, *RUN)
    assert code == 0, err
    code, out, _ = run("info", path)
    assert code == 0 and "frames 0..40 (41 frames" in out


def subprocess_run(*argv, shell=None):
    if shell:
        return subprocess.run(["bash", "-c", shell], capture_output=True, text=True, timeout=300)
    return subprocess.run([sys.executable, "-m", "warpsim", *argv], capture_output=True, text=True,
                          timeout=300)


def error_lines(stderr):
    """stderr without Warp's own start-up notice (no CUDA driver on a CPU machine)."""
    return [line for line in stderr.splitlines() if line.strip() and not line.startswith("Warp CUDA warning")]


@pytest.mark.parametrize("argv, word", [
    (["run", "bounce", "--set", "height=-1", "--device", "cpu", "--no-progress", "--out", "{dir}/sub/h.usda"],
     "height=-1"),
    (["run", "bounce", "--out", "{dir}/afile/x.usda", "--device", "cpu"], "is a file"),
    (["run", "bounce", "--out", "/proc/warpsim_probe.usda", "--device", "cpu"], "cannot write"),
    (["info", "{dir}/missing.usda"], "does not exist"),
    (["run", "bounce", "--set", "mass=heavy"], "mass='heavy'"),
])
def test_console_entry_one_line_exit_2(ctx, argv, word):
    proc = subprocess_run(*[a.format(dir=ctx["dir"]) for a in argv])
    lines = error_lines(proc.stderr)
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("warpsim: error: ") and word in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr and proc.stdout == ""


def test_console_entry_damaged_checkpoint_and_closed_pipe(ctx):
    path = ckpt(truncate)(ctx)
    proc = subprocess_run("run", "bounce", "--frames", "40", "--resume", "--out", path, "--device", "cpu")
    lines = error_lines(proc.stderr)
    assert proc.returncode == 2 and len(lines) == 1 and "b.checkpoint.npz" in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr
    pipe = f"{sys.executable} -m warpsim list | head -1; echo \"status=${{PIPESTATUS[0]}}\""
    proc = subprocess_run(shell=pipe)
    assert proc.stdout.splitlines()[0].startswith("bounce ") and "status=0" in proc.stdout
    assert "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr, proc.stderr
