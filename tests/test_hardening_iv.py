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
