"""Issue 51 (Hardening IV): locks and files beside an output are never written through a planted
link, FIFO or folder; a full or read-only disk ends in one line naming the file and the frames
kept, with no temporary file left; booleans are parsed strictly; the misleading messages."""

import errno
import glob
import io
import os

import numpy as np
import pytest

pytest.importorskip("pxr")
from pxr import Tf, Usd

from warpsim.cli import main
from warpsim.core.safe_files import UnsafePathError, open_for_write, open_temporary
from warpsim.usd import chunk_index
from warpsim.usd.checkpoint import save_checkpoint
from warpsim.usd.writer import UsdCacheWriter


def run(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = main(list(argv), out=out, err=err)
    return code, out.getvalue(), err.getvalue()


# ---------------------------------------------------------------- part 1: links
def test_planted_symlink_lock_leaves_its_target_untouched(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    (tmp_path / "b.lock").symlink_to(victim)
    code, _, err = run("run", "bounce", "--frames", "6", "--out", str(tmp_path / "b.usda"), "--device", "cpu",
                       "--no-progress")
    assert code == 2, err
    assert victim.read_text() == "precious\n"
    assert os.path.islink(tmp_path / "b.lock")  # named, not removed
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "b.lock" in lines[0] and "symbolic link" in lines[0] and "remove it" in lines[0]
    assert not os.path.exists(tmp_path / "b.usda")


@pytest.mark.parametrize("kind", ["folder", "fifo"])
def test_lock_that_is_a_folder_or_fifo_is_named(tmp_path, kind):
    lock = tmp_path / "b.lock"
    if kind == "folder":
        lock.mkdir()
    else:
        os.mkfifo(lock)
    code, _, err = run("run", "bounce", "--frames", "2", "--out", str(tmp_path / "b.usda"), "--device", "cpu",
                       "--no-progress")
    assert code == 2, err
    assert "b.lock" in err and ("folder" if kind == "folder" else "FIFO") in err and "remove it" in err
    assert len(err.strip().splitlines()) == 1


def test_files_beside_an_output_are_not_written_through_links(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    index = tmp_path / "c.chunks.jsonl"
    index.symlink_to(victim)
    with pytest.raises(UnsafePathError, match="c.chunks.jsonl.*symbolic link"):
        chunk_index.append_record(str(index), {"file": "x"})
    with pytest.raises(UnsafePathError):
        open_for_write(str(index), "w")
    # a temporary name planted as a link is removed (the link only) and written fresh
    tmp = tmp_path / "t.tmp-1"
    tmp.symlink_to(victim)
    with open_temporary(str(tmp)) as f:
        f.write("new")
    assert victim.read_text() == "precious\n" and not os.path.islink(tmp) and tmp.read_text() == "new"
    # the checkpoint's temporary name, planted: the checkpoint is written, the victim untouched
    ckpt = tmp_path / "s.checkpoint.npz"
    (tmp_path / f"s.checkpoint.tmp-{os.getpid()}.npz").symlink_to(victim)
    save_checkpoint(str(ckpt), {"x": [1.0]}, {"frame": 1})
    assert victim.read_text() == "precious\n" and ckpt.is_file()
    # a cache's chunk and root temporaries planted as links
    (tmp_path / f"w.chunk000000.tmp-{os.getpid()}.usdc").symlink_to(victim)
    (tmp_path / f"w.tmp-{os.getpid()}.usda").symlink_to(victim)
    with UsdCacheWriter(tmp_path / "w.usda", chunk_size=2) as w:
        w.add_points("p")
        for frame in range(3):
            w.write_frame(frame, {"p": {"points": [[0.0, frame, 0.0]], "velocities": [[0.0, 0.0, 0.0]]}})
    assert victim.read_text() == "precious\n"
    assert Usd.Stage.Open(str(tmp_path / "w.usda")).GetEndTimeCode() == 2


# ---------------------------------------------------------------- part 2: full disks
def _leftovers(folder):
    return [f for f in glob.glob(os.path.join(folder, "*")) if ".tmp" in os.path.basename(f)]


@pytest.mark.parametrize("failure", ["oserror", "pxr", "erofs"])
def test_full_disk_is_one_line_without_temporaries(tmp_path, monkeypatch, failure):
    calls = {"n": 0}
    real = UsdCacheWriter._export_atomic

    def export(self, layer, final):
        calls["n"] += 1
        if calls["n"] > 4:  # manifest, first root, then two chunks' roots: the third chunk's root fails
            tmp = f"{os.path.splitext(final)[0]}.tmp-{os.getpid()}{os.path.splitext(final)[1]}"
            open(tmp, "w").write("half")  # what a writer leaves when the disk fills mid-file
            if failure == "pxr":
                raise Tf.ErrorException("Error in 'pxrInternal_v0_24::SdfLayer::Export' at line 1 in file x : "
                                        "'Failed to write: No space left on device'")
            raise OSError(errno.EROFS if failure == "erofs" else errno.ENOSPC, os.strerror(errno.ENOSPC), tmp)
        return real(self, layer, final)

    monkeypatch.setattr(UsdCacheWriter, "_export_atomic", export)
    out = tmp_path / "small" / "s.usda"
    code, _, err = run("run", "springs", "--frames", "30", "--chunk", "4", "--out", str(out), "--device", "cpu",
                       "--no-progress")
    assert code == 1, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "s.usda" in lines[0] and "kept frames 0..7" in lines[0]
    assert ("read-only" if failure == "erofs" else "no space left on device") in lines[0]
    assert "Traceback" not in err and "pxrInternal" not in err
    assert _leftovers(out.parent) == []
    stage = Usd.Stage.Open(str(out))
    assert stage.GetEndTimeCode() == 7  # the frames kept are readable
    assert not os.path.exists(out.parent / "s.lock")


def test_full_disk_while_saving_a_chunk(tmp_path, monkeypatch):
    from pxr import Sdf

    real_save = Sdf.Layer.Save
    state = {"chunks": 0}

    def finish(self):
        state["chunks"] += 1
        if state["chunks"] == 2:
            raise OSError(errno.ENOSPC, "No space left on device", self._chunk.tmp_path)
        return UsdCacheWriter._real_finish(self)

    monkeypatch.setattr(UsdCacheWriter, "_real_finish", UsdCacheWriter._finish_chunk, raising=False)
    monkeypatch.setattr(UsdCacheWriter, "_finish_chunk", finish)
    out = tmp_path / "s.usda"
    code, _, err = run("run", "springs", "--frames", "20", "--chunk", "5", "--out", str(out), "--device", "cpu",
                       "--no-progress")
    assert real_save is Sdf.Layer.Save
    assert code == 1 and len(err.strip().splitlines()) == 1, err
    assert "kept frames 0..4" in err and "no space left" in err
    assert _leftovers(tmp_path) == []
    assert Usd.Stage.Open(str(out)).GetEndTimeCode() == 4


# ---------------------------------------------------------------- part 3: booleans, indices, backward
def _spring_model():
    import warpsim as ws

    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.0, 0.0), mass=1.0)
    b.add_particle((0.1, 0.0, 0.0), mass=1.0)
    b.add_spring(0, 1, stiffness=100.0, damping=0.0)
    return b.finalize(device="cpu")


@pytest.mark.parametrize("value", ["no", "false", "0", 2, None, 0.5])
def test_booleans_are_parsed_strictly(value):
    import warpsim as ws

    model = _spring_model()
    with pytest.raises(ValueError, match=r"FastMassSpring chebyshev must be True or False, got"):
        ws.FastMassSpring(model, chebyshev=value)
    with pytest.raises(ValueError, match=r"Simulator adaptive must be True or False"):
        ws.Simulator(model, adaptive=value)
    with pytest.raises(ValueError, match=r"UsdCacheWriter flatten must be True or False"):
        UsdCacheWriter("x.usda", flatten=value)


def test_strict_booleans_keep_true_false_and_numpy():
    import numpy as np

    from warpsim.core import checks

    assert checks.flag(True, "x") is True and checks.flag(np.bool_(False), "x") is False and checks.flag(1, "x")
    with pytest.raises(ValueError, match="'no' would count as True"):
        checks.flag("no", "Thing option")


def test_float_triangle_indices_are_refused_not_truncated():
    import warpsim as ws
    from warpsim.agents.world import _mesh_arrays
    from warpsim.core import checks

    assert checks.index_array([[0.0, 1.0, 2.0]], "faces").tolist() == [[0, 1, 2]]
    pts = [[0, 0, 0], [1, 0, 0], [0, 0, 1], [1, 0, 1]]
    with pytest.raises(ValueError, match=r"terrain faces holds the non-integer index 1.5"):
        _mesh_arrays(pts, [[0, 1.5, 2]], "terrain")
    from warpsim.bodies.soft_contact import _body_faces

    with pytest.raises(ValueError, match=r"SoftContact bodies\[0\] triangles holds the non-integer index 1.7"):
        _body_faces(np.array([[0.0, 1.7, 2.0]]), 0)
    assert ws is not None


def test_backward_of_none_is_refused():
    import warpsim as ws

    sim = ws.Simulator(_spring_model(), differentiable=True)
    with pytest.raises(TypeError, match="backward needs the loss as a Warp array"):
        sim.rollout.backward(None)


# ---------------------------------------------------------------- part 4: messages that named nothing
def test_render_max_frames_zero_is_named(tmp_path):
    from warpsim.render.cache import render_cache

    with pytest.raises(ValueError, match=r"render_cache max_frames must be an integer >= 1, got 0"):
        render_cache(str(tmp_path / "none.usda"), str(tmp_path / "p.gif"), max_frames=0)


def test_surface_too_fine_names_spacing():
    from warpsim.render.export import surface_from_points

    pts = np.array([[0.0, 0.0, 0.0], [1000.0, 1000.0, 1000.0]])
    with pytest.raises(ValueError, match=r"give a coarser --spacing \(e.g. --spacing [0-9.]+\)"):
        surface_from_points(pts, spacing=0.01)


def test_empty_pxr_error_on_the_command_line_is_one_line(monkeypatch):
    import warpsim.commands.listing as listing

    def broken(args, out, err):
        raise Tf.ErrorException("")

    monkeypatch.setattr(listing, "run", broken)
    code, _, err = run("list")
    assert code == 1 and len(err.strip().splitlines()) == 1 and "USD could not read or write a file" in err


def test_table_writer_full_disk_in_words(tmp_path, monkeypatch):
    import warpsim.sweeps.sweep as sweep

    real = sweep.csv.writer

    class Full:
        def __init__(self, f):
            pass

        def writerow(self, row):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(sweep.csv, "writer", Full)
    with pytest.raises(OSError) as info:
        sweep.write_table(str(tmp_path / "s.csv"), [{"world": 0}])
    assert "[Errno" not in str(info.value) and "s.csv" in str(info.value) and "no space left" in str(info.value)
    assert _leftovers(tmp_path) == [] and real is not Full


def test_empty_sweep_table_is_said_as_empty(tmp_path):
    from warpsim.sweeps import query_command

    table = tmp_path / "s.csv"
    table.write_text("world,blown_up\n")
    reader = next(getattr(query_command, n) for n in dir(query_command) if n in ("read_table", "_read_table",
                                                                                  "load_table"))
    with pytest.raises(ValueError, match="has its header and no rows"):
        reader(str(table))


def test_resume_on_other_blocks_says_devices(tmp_path):
    from warpsim.sweeps.staging import SweepStaging

    root = str(tmp_path / "S.usda")
    SweepStaging(root, {"scene": "bounce", "blocks": [[0, 20], [20, 20]]}, blocks=2)
    with pytest.raises(ValueError, match=r"give --devices with 2 devices again \(e.g. --devices cpu,cpu\)"):
        SweepStaging(root, {"scene": "bounce", "blocks": None}, resume=True)


def test_substeps_auto_at_its_cap_says_so():
    from warpsim.core.stability import AUTO_MAX_SUBSTEPS, StabilityLimit, SubstepCapWarning

    limit = StabilityLimit(dt=1e-9, integrator="semi_implicit_euler", reason="spring 3")
    with pytest.warns(SubstepCapWarning, match=r"stops at its cap of 100000.*implicit_euler"):
        assert limit.substeps_for(1 / 60) == AUTO_MAX_SUBSTEPS


def test_damaged_index_line_names_the_index_and_the_intact_chunk(tmp_path):
    import json

    with UsdCacheWriter(tmp_path / "c.usda", chunk_size=2) as w:
        w.add_points("p")
        for frame in range(3):
            w.write_frame(frame, {"p": {"points": [[0.0, frame, 0.0]], "velocities": [[0.0, 0.0, 0.0]]}})
    index = tmp_path / "c.chunks.jsonl"
    lines = index.read_text().splitlines()
    rec = json.loads(lines[0])
    rec["bytes"] = "abc"
    index.write_text("\n".join([json.dumps(rec), *lines[1:]]) + "\n")
    why = chunk_index.chunk_problem(str(tmp_path), rec["file"], chunk_index.read_index(str(index))[rec["file"]])
    assert "in c.chunks.jsonl" in why and "the chunk itself opens in USD" in why
