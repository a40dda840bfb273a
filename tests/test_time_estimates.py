"""Issue 51, time before a long run: ``warpsim run`` and ``warpsim sweep`` estimate the rest of a
run from a measured frame (the second they compute: the first compiles Warp's kernels and is
left out), say which frame and what its time covers, and assume no ratio between devices; the
hair scene's estimate before the first step says what it rests on."""

import io
import time

import pytest

from warpsim.cli import main
from warpsim.sweeps import preflight


def run(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = main([str(a) for a in argv], out=out, err=err)
    return code, out.getvalue(), err.getvalue()


def test_the_note_is_from_the_measured_frame_and_says_so():
    assert preflight.frame_time_note(2.0, 119, "cpu") is None  # 4 min in all: not said
    line = preflight.frame_time_note(232.0, 119, "cpu")
    assert "frame 2 took 232 s on cpu (stepping and writing; frame 1, which compiles Warp's kernels, left out)" in line
    assert "estimated from frame 2, the other 119 frames take about 7.67 h" in line
    line = preflight.frame_time_note(1.0, 3000, "cuda:0", frame=5)  # short frames, a long run: said too
    assert "frame 5 took 1 s on cuda:0" in line and "frame 4, which compiles" in line and "50 min" in line
    assert "cuda:0)" not in line.split(";", 2)[-1]  # no advice to use the device it runs on


def test_run_measures_frame_2_without_compilation(tmp_path, monkeypatch):
    """Frame 1 (made slow here, as compiling is) is left out; frame 2's stepping and writing are in."""
    from warpsim.scenes import get_scene

    cls = get_scene("bounce")
    advance = cls.advance
    calls = []

    def slow(self, frame_dt, substeps):
        calls.append(1)
        time.sleep(0.6 if len(calls) == 1 else 0.05)  # frame 1 "compiles"
        return advance(self, frame_dt, substeps)

    seen = []
    real = preflight.frame_time_note

    def note(seconds, frames_left, device, frame=2, **kw):
        seen.append((seconds, frames_left, frame))
        return real(seconds, frames_left, device, frame, **kw)

    monkeypatch.setattr(cls, "advance", slow)
    monkeypatch.setattr(preflight, "frame_time_note", note)
    monkeypatch.setattr(preflight, "LONG_REST_NOTE", 0.01)
    code, _, err = run("run", "bounce", "--frames", 4, "--device", "cpu", "--no-progress", "--out",
                       tmp_path / "b.usda")
    assert code == 0, err
    (seconds, left, frame), = seen
    assert frame == 2 and left == 2 and 0.05 <= seconds < 0.6  # frame 1's 0.6 s is not in it
    assert "warpsim: note: frame 2 took" in err and "estimated from frame 2, the other 2 frames" in err


def test_sweep_estimates_from_its_measured_second_frame(tmp_path, monkeypatch):
    pytest.importorskip("pxr")
    monkeypatch.setattr(preflight, "LONG_REST_NOTE", 0.0)
    code, _, err = run("sweep", "bounce", "--worlds", 2, "--vary", "restitution=0.2,0.8", "--frames", 4,
                       "--device", "cpu", "--no-progress", "--out", tmp_path / "s.usda", "--no-thumbnails")
    assert code == 0, err
    notes = [line for line in err.splitlines() if line.startswith("warpsim: note: frame ")]
    assert len(notes) == 1, err
    assert "stepping its 2 worlds and writing them" in notes[0] and "which compiles Warp's kernels, left out" in notes[0]
    assert "estimated from frame" in notes[0] and "fewer worlds or frames" in notes[0]


def test_hair_estimate_before_the_first_step_says_what_it_rests_on():
    from warpsim.strands.preflight import estimate_basis

    assert "assumed ratio, not measured" in estimate_basis("cuda:0") and "ten times" in estimate_basis("cuda:0")
    assert "not on this machine" in estimate_basis("cpu") and "ten" not in estimate_basis("cpu")


def test_hair_refusals_from_an_estimate_name_its_basis():
    from warpsim.strands.preflight import check_hair_steps

    with pytest.raises(ValueError, match=r"on cuda:0 \(estimated from strand steps timed on a 2-core CPU, taken as "
                                         r"ten times faster on CUDA: an assumed ratio, not measured here\); use"):
        check_hair_steps(10 ** 9, 2, 2, device="cuda:0", available=1 << 40)
    with pytest.raises(ValueError, match=r"on cpu \(estimated from strand steps timed on a 2-core CPU, not on this "
                                         r"machine\); use at most"):
        check_hair_steps(10 ** 8, 2, 2, device="cpu", available=1 << 40)
