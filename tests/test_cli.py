"""The warpsim command line and scene registry: every scene's cache validates and reads back equal
to an independent run of the scene; the seed's numbers; exit codes and messages; checkpoint and
resume bit for bit; crash (SIGKILL) then resume."""
import io
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("pxr")
from pxr import Sdf, Usd

from warpsim.usd.checkpoint import load_checkpoint
from warpsim.cli import main
from warpsim.cli_common import timing_from_flags
from warpsim.commands.run import checkpoint_path
from warpsim.scenes import SimulatorScene, format_value, get_scene, register_scene, scenes
from warpsim.usd.writer import UsdCacheWriter
from warpsim.usd.validate import validate_cache


def run(*argv):
    """main([...]) in-process: (exit status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    code = main(list(argv), out=out, err=err)
    return code, out.getvalue(), err.getvalue()


def run_ok(*argv):
    code, out, err = run(*argv, "--device", "cpu", "--no-progress")
    assert code == 0, err
    return out


def read_all(path):
    """{attribute path: [value at frame 0, 1, ...]} of every attribute, composed through the clips."""
    stage = Usd.Stage.Open(str(path))
    frames = range(int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode()) + 1)
    out = {}
    for prim in stage.Traverse():
        for attr in prim.GetAttributes():
            out[str(attr.GetPath())] = [attr.Get(f) for f in frames]
    return out


def assert_same_cache(a, b):
    ra, rb = read_all(a), read_all(b)
    assert ra.keys() == rb.keys()
    for key in ra:
        assert len(ra[key]) == len(rb[key]), key
        for f, (x, y) in enumerate(zip(ra[key], rb[key])):
            assert (x is None) == (y is None), (key, f)
            if x is not None:
                assert np.array_equal(np.asarray(x), np.asarray(y)), (key, f)


@pytest.mark.parametrize("name", sorted(scenes()))
def test_every_scene_validates_and_reads_back_its_simulation(name, tmp_path):
    frames = 3
    path = tmp_path / f"{name}.usda"
    cls = get_scene(name)
    sets = [a for k, v in cls.smoke_params.items() for a in ("--set", f"{k}={format_value(v)}")]
    out = run_ok("run", name, "--frames", str(frames), "--out", str(path), "--chunk", "2", *sets)
    assert f"open: {os.path.relpath(path)}" in out
    assert validate_cache(str(path)) == []
    # an independent run of the same scene, frame by frame
    given = cls.resolve_params(dict(cls.smoke_params))
    given = {k: given[k] for k in cls.smoke_params}
    params = cls.resolve_params(given)
    timing, params = timing_from_flags(cls, params, given, None, None)
    fps, substeps = timing.fps, timing.steps
    scene = cls(params, device="cpu")
    scene.use_timing(timing)
    ref_writer = UsdCacheWriter(tmp_path / "ref" / "unused.usda")
    scene.declare(ref_writer)  # declarations only: turns frame data into attribute samples
    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == pytest.approx(fps)
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, frames)
    for f in range(frames + 1):
        if f:
            scene.advance(timing.frame_dt, substeps)
        data = scene.frame_data()
        assert set(data) == {n for n, d in ref_writer.prims.items() if d.is_dynamic}
        for prim, values in data.items():
            for attr, expected in ref_writer.prims[prim].frame_samples(values, f).items():
                got = stage.GetPrimAtPath(f"/World/{prim}").GetAttribute(attr).Get(f)
                assert got is not None, (prim, attr, f)
                assert np.array_equal(np.asarray(got), np.asarray(expected)), (prim, attr, f)


def test_bounce_reproduces_the_seed(tmp_path):
    path = tmp_path / "b.usda"
    run_ok("run", "bounce", "--frames", "4", "--out", str(path), "--set", "collision=seed")
    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == pytest.approx(25.0)  # dt = 0.04 s, one step per frame
    ball = stage.GetPrimAtPath("/World/ball")
    p = [np.asarray(ball.GetAttribute("points").Get(f))[0] for f in range(5)]
    v = [np.asarray(ball.GetAttribute("velocities").Get(f))[0] for f in range(5)]
    np.testing.assert_allclose(p[0], [0, 0.04, 0])
    np.testing.assert_allclose(v[1][1], -0.3924, rtol=1e-6)
    np.testing.assert_allclose(p[1][1], 0.024304, rtol=1e-6)
    # step 2 would reach y = 0.024304 - 0.04 * 0.7848 < 0: the lecture's floor mirrors it (r = 0.5)
    h = 0.024304 - 0.04 * 0.7848
    assert h < 0
    np.testing.assert_allclose(p[2][1], -0.5 * h, rtol=1e-4)
    np.testing.assert_allclose(v[2][1], 0.5 * 0.7848, rtol=1e-4)
    assert all(q[1] >= 0 for q in p)


def test_pendulum_integrators_and_energy(tmp_path):
    energies = {}
    for integrator in ("rk4", "explicit_euler"):
        path = tmp_path / f"{integrator}.usda"
        run_ok("run", "pendulum", "--frames", "60", "--out", str(path), "--integrator", integrator,
               "--set", "angle=1.0")
        stage = Usd.Stage.Open(str(path))
        bob = stage.GetPrimAtPath("/World/bob")
        total = np.array([bob.GetAttribute("warpsim:totalEnergy").Get(f) for f in range(61)])
        ke = np.array([bob.GetAttribute("warpsim:kineticEnergy").Get(f) for f in range(61)])
        pe = np.array([bob.GetAttribute("warpsim:potentialEnergy").Get(f) for f in range(61)])
        np.testing.assert_allclose(total, ke + pe, rtol=1e-12)
        assert pe[0] == pytest.approx(9.81 * (1 - np.cos(1.0)), rel=1e-5)  # m g l (1 - cos q0)
        # the bob hangs on the rod: |bob - pivot| = l, and the rod's end is the bob
        for f in (0, 30, 60):
            b = np.asarray(bob.GetAttribute("points").Get(f))[0]
            rod = np.asarray(stage.GetPrimAtPath("/World/rod").GetAttribute("points").Get(f))
            assert np.linalg.norm(b - [0, 1, 0]) == pytest.approx(1.0, rel=1e-5)
            np.testing.assert_array_equal(rod[1], b)
        energies[integrator] = total
    rk4 = energies["rk4"]
    assert np.abs(rk4 / rk4[0] - 1).max() < 1e-4  # RK4 holds the energy
    assert energies["explicit_euler"][-1] > 1.05 * energies["explicit_euler"][0]  # explicit Euler gains


def test_springs_pinned_particle_stays_and_curves_follow(tmp_path):
    path = tmp_path / "s.usda"
    run_ok("run", "springs", "--frames", "10", "--out", str(path), "--set", "shape=lattice", "--set", "count=3")
    stage = Usd.Stage.Open(str(path))
    masses = stage.GetPrimAtPath("/World/masses")
    p0 = np.asarray(masses.GetAttribute("points").Get(0))
    p10 = np.asarray(masses.GetAttribute("points").Get(10))
    np.testing.assert_array_equal(p10[[0, 2]], p0[[0, 2]])  # the two pinned corners
    assert (p10[3:, 1] < p0[3:, 1]).all()  # the rest has fallen
    counts = stage.GetPrimAtPath("/World/springs").GetAttribute("curveVertexCounts").Get()
    assert len(counts) == 3 * 2 * 2 + 4 * 2  # structural + shear springs of a 3 x 3 lattice


def test_usage_errors_exit_2_with_suggestions(tmp_path):
    out = str(tmp_path / "x.usda")
    cases = [
        (["run", "bounc"], "Did you mean 'bounce'"),
        (["run", "bounce", "--set", "restitutin=0.3"], "Did you mean 'restitution'"),
        (["run", "bounce", "--set", "dt=fast"], "dt='fast' is not a valid float"),
        (["run", "bounce", "--set", "restitution"], "write --set KEY=VALUE"),
        (["run", "bounce", "--set", "restitution=2"], "restitution 2.0 must be in [0, 1]"),
        (["run", "bounce", "--set", "velocity=1,2"], "not a valid 3 floats"),
        (["run", "bounce", "--integrator", "rk5"], "Did you mean 'rk4'"),
        (["run", "springs", "--set", "shape=ring"], "not one of chain, lattice"),
        (["run", "bounce", "--frames", "x"], "invalid int value"),
        (["run", "bounce", "--fps", "10", "--set", "dt=0.01"], "give one of them"),
        (["run", "bounce", "--resume"], "no checkpoint"),
        (["run", "bounce", "--out", str(tmp_path / "x.obj")], "must end in .usd"),
        (["info", str(tmp_path / "missing.usda")], "does not exist"),
        (["frobnicate"], "invalid choice"),
        ([], "required"),
    ]
    for argv, message in cases:
        if argv and argv[0] == "run":
            argv = argv + (["--out", out] if "--out" not in argv else []) + ["--device", "cpu", "--no-progress"]
        code, _, err = run(*argv)
        assert code == 2, (argv, err)
        assert message in err, (argv, err)
        assert err.startswith("warpsim: error:")
    assert not os.path.exists(out)  # usage mistakes write nothing


def test_blow_up_exits_1_and_keeps_frames(tmp_path):
    path = tmp_path / "boom.usda"
    code, _, err = run("run", "springs", "--set", "dt=10", "--frames", "20", "--out", str(path), "--device", "cpu",
                       "--no-progress")
    assert code == 1
    assert "simulation failed at frame 1" in err and "Remedy" in err
    assert "kept frames 0..0" in err
    stage = Usd.Stage.Open(str(path))
    assert stage.GetEndTimeCode() == 0
    assert validate_cache(stage) == []
    # just past the stability limit dt ~ 2 / (2 sqrt(k / m)) = 0.0112 s the chain blows up later;
    # every frame before the failure is kept
    path = tmp_path / "late.usda"
    code, _, err = run("run", "springs", "--set", "dt=0.012", "--frames", "200", "--chunk", "3",
                       "--out", str(path), "--device", "cpu", "--no-progress")
    assert code == 1
    failed = int(err.split("simulation failed at frame ")[1].split(":")[0])
    assert failed > 1
    stage = Usd.Stage.Open(str(path))
    assert stage.GetEndTimeCode() == failed - 1
    assert validate_cache(stage) == []


def test_list_and_info(tmp_path):
    code, out, _ = run("list")
    assert code == 0
    for name in ("bounce", "pendulum", "springs"):
        assert f"\n{name}" in "\n" + out
    assert "restitution=0.5" in out and "integrator=rk4" in out
    path = tmp_path / "p.usda"
    run_ok("run", "pendulum", "--frames", "5", "--out", str(path))
    code, out, _ = run("info", str(path))
    assert code == 0
    assert "frames 0..5 (6 frames at 60 fps" in out
    assert "/World/bob" in out and "Points" in out and "count 1" in out and "bounds" in out


def test_python_dash_m_warpsim_list():
    proc = subprocess.run([sys.executable, "-m", "warpsim", "list"], check=False, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "bounce" in proc.stdout and "springs" in proc.stdout
    proc = subprocess.run([sys.executable, "-m", "warpsim", "run", "nope"], check=False, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "unknown scene 'nope'" in proc.stderr


def test_flatten_option(tmp_path):
    path = tmp_path / "flat.usda"
    out = run_ok("run", "bounce", "--frames", "5", "--chunk", "2", "--out", str(path), "--flatten")
    assert os.listdir(tmp_path) == ["flat.usdc"]
    assert "open: " in out and "flat.usdc" in out
    stage = Usd.Stage.Open(str(tmp_path / "flat.usdc"))
    assert stage.GetEndTimeCode() == 5 and validate_cache(stage) == []


@pytest.mark.parametrize("argv", [["springs"], ["springs", "--integrator", "implicit_euler", "--set", "count=4", "--substeps", "2"],
                                  ["pendulum", "--integrator", "rk2"]])
def test_resume_matches_uninterrupted_run_bit_for_bit(argv, tmp_path):
    full = tmp_path / "full" / "c.usda"
    part = tmp_path / "part" / "c.usda"
    run_ok("run", *argv, "--frames", "13", "--chunk", "5", "--out", str(full), "--checkpoint-every", "4")
    run_ok("run", *argv, "--frames", "6", "--chunk", "5", "--out", str(part), "--checkpoint-every", "4")
    _, meta = load_checkpoint(checkpoint_path(part))
    assert meta["frame"] == 6  # every 4 frames and at the end
    out = run_ok("run", *argv, "--frames", "13", "--chunk", "5", "--out", str(part), "--checkpoint-every", "4",
                 "--resume")
    assert "(7..13" in out
    assert_same_cache(full, part)
    a, _ = load_checkpoint(checkpoint_path(full))
    b, _ = load_checkpoint(checkpoint_path(part))
    assert a.keys() == b.keys()
    for key in a:
        assert np.array_equal(a[key], b[key]), key
    assert validate_cache(str(part)) == []


def test_resume_rejects_changed_parameters_and_missing_frames(tmp_path):
    path = tmp_path / "c.usda"
    run_ok("run", "springs", "--frames", "2", "--out", str(path), "--checkpoint-every", "2")
    code, _, err = run("run", "springs", "--frames", "4", "--out", str(path), "--resume", "--set", "count=5",
                       "--device", "cpu", "--no-progress")
    assert code == 2 and "differs from the checkpoint" in err
    run_ok("run", "springs", "--frames", "3", "--out", str(path))  # a fresh run drops the old checkpoint
    assert not os.path.exists(checkpoint_path(path))
    run_ok("run", "springs", "--frames", "2", "--out", str(path), "--checkpoint-every", "2")
    os.remove(path)  # the cache is gone but the checkpoint is not
    code, _, err = run("run", "springs", "--frames", "4", "--out", str(path), "--resume", "--device", "cpu",
                       "--no-progress")
    assert code == 2 and "does not exist" in err


def test_sigkill_then_resume_matches_uninterrupted(tmp_path):
    path = tmp_path / "k" / "c.usda"
    cmd = [sys.executable, "-m", "warpsim", "run", "springs", "--frames", "100000", "--chunk", "6", "--out", str(path),
           "--checkpoint-every", "5", "--device", "cpu", "--no-progress"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ckpt = checkpoint_path(path)
    deadline = time.time() + 120
    while time.time() < deadline:
        if os.path.exists(ckpt) and load_checkpoint(ckpt)[1]["frame"] >= 15:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    frame = load_checkpoint(ckpt)[1]["frame"]
    assert frame >= 15
    layer = Sdf.Layer.OpenAsAnonymous(str(path))
    assert layer.endTimeCode >= frame  # the cache reached the checkpoint before the checkpoint existed
    del layer
    target = frame + 8
    run_ok("run", "springs", "--frames", str(target), "--chunk", "6", "--out", str(path), "--checkpoint-every", "5",
           "--resume")
    full = tmp_path / "full" / "c.usda"
    run_ok("run", "springs", "--frames", str(target), "--chunk", "6", "--out", str(full))
    assert_same_cache(full, path)


@register_scene("test_probe", "a registry test: one particle drifting at constant velocity",
                params={"speed": (2.0, "drift speed [m/s]"), "dt": (0.05, "time step [s]")})
class _Probe(SimulatorScene):
    def build(self, p):
        import warpsim as ws

        b = ws.ModelBuilder()
        b.add_particle((0, 0, 0), vel=(p["speed"], 0, 0))
        self.sim = ws.Simulator(b.finalize(self.device), forces=[])

    def declare(self, writer):
        self.declare_state(writer, "probe", radius=0.1)


def test_register_scene_one_liner(tmp_path):
    assert get_scene("test_probe") is _Probe
    path = tmp_path / "probe.usda"
    run_ok("run", "test_probe", "--frames", "4", "--set", "speed=3", "--out", str(path))
    stage = Usd.Stage.Open(str(path))
    x = [np.asarray(stage.GetPrimAtPath("/World/probe").GetAttribute("points").Get(f))[0, 0] for f in range(5)]
    np.testing.assert_allclose(x, 3.0 * 0.05 * np.arange(5), rtol=1e-6)  # x = v t
    assert stage.GetTimeCodesPerSecond() == pytest.approx(20.0)
