"""Hardening II, the probe of the newer surfaces (issue 28): ``warpsim sweep`` refuses what it can
know up front (seed, world count against memory, output paths, ranks on parameters that are not
numbers, a --ray address) with one line and exit 2 before any world is simulated, and the
Python APIs of the worlds, soft contact, torus meshes, rendering, the viewer and differentiable
rollouts raise ValueError / TypeError naming the argument instead of crashing later."""

import io
import json
import os
import time

import numpy as np
import pytest
import warp as wp

pytest.importorskip("pxr")

import warpsim as ws
from warpsim import worlds
from warpsim.cli import main

SWEEP = ["sweep", "bounce", "--frames", "2", "--no-progress", "--device", "cpu"]
TWO = ["--worlds", "2", "--vary", "height=0.02:0.05"]


def run(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = main(list(argv), out, err)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def where(tmp_path_factory):
    d = tmp_path_factory.mktemp("probe_sweep")
    (d / "afile").write_text("not a folder")
    (d / "folder.usda").mkdir()
    (d / "folder.csv").mkdir()
    return d


CASES = [
    # resources: refused with the memory figure before sampling a billion dicts
    ("worlds-billion", ["--worlds", "1000000000", "--vary", "height=0.02:0.05", "--sample", "random"],
     ["--worlds 1000000000", "need about", "TiB", "free"]),
    ("worlds-2**63", ["--worlds", str(2**63), "--vary", "height=0.02:0.05", "--sample", "random"],
     [f"--worlds {2**63}", "need about"]),
    ("log-bounds-underflow", ["--worlds", "2", "--vary", "mass=1e-320:1e-310:log"],
     ["--vary mass=1e-320:1e-310:log", "float32 range"]),
    ("range-overflow", ["--worlds", "2", "--vary", "mass=1:1e39"], ["hi 1e+39", "float32 range"]),
    ("seed-negative", [*TWO, "--seed", "-1"], ["--seed -1", "[0, 2^63)"]),
    ("seed-huge", [*TWO, "--seed", str(2**70)], [f"--seed {2**70}"]),
    # non-numeric parameters cannot be ranked or compared: refused before the run
    ("rank-vector", [*TWO, "--set", "velocity=0,0,0", "--rank", "velocity"],
     ["--rank velocity", "vector", "compares numbers"]),
    ("where-vector", [*TWO, "--vary", "velocity=0,0,0;1,0,0", "--where", "velocity>0"],
     ["--where velocity", "vector"]),
    # output paths, in warpsim's words (no pxr or Errno text), before any step
    ("out-proc", [*TWO, "--out", "/proc/x.usda"], ["--out '/proc/x.usda'", "cannot write in folder"]),
    ("out-under-file", [*TWO, "--out", "{d}/afile/x.usda"], ["--out", "afile", "is a file, not a folder"]),
    ("out-folder", [*TWO, "--out", "{d}/folder.usda"], ["--out", "folder.usda", "is a folder"]),
    ("table-under-file", [*TWO, "--out", "{d}/ok/s.usda", "--table", "{d}/afile/t.csv"],
     ["--table", "afile", "is a file, not a folder"]),
    ("table-folder", [*TWO, "--out", "{d}/ok/s.usda", "--table", "{d}/folder.csv"], ["--table", "is a folder"]),
    ("table-extension", [*TWO, "--out", "{d}/ok/s.usda", "--table", "{d}/t.txt"], ["--table", ".csv"]),
    # --ray address syntax (no Ray text), checked before Ray is imported
    ("ray-not-a-host", [*TWO, "--ray", "not a host"], ["--ray 'not a host'", "HOST:PORT"]),
    ("ray-bad-port", [*TWO, "--ray", "10.0.0.1:99999"], ["port 99999", "1..65535"]),
    ("ray-no-port", [*TWO, "--ray", "headnode"], ["--ray 'headnode'", "HOST:PORT"]),
]


@pytest.mark.parametrize("case_id, argv, words", CASES, ids=[c[0] for c in CASES])
def test_bad_sweep_is_one_line_exit_2_before_any_world_runs(where, case_id, argv, words):
    argv = [a.format(d=where) for a in argv]
    if "--out" not in argv:
        argv += ["--out", str(where / case_id / "s.usda")]
    t0 = time.perf_counter()
    code, out, err = run(*SWEEP, *argv)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("warpsim: error:"), (code, out, err)
    for word in words:
        assert word in lines[0], (word, lines[0])
    for noise in ("pxrInternal", "Errno", "Traceback", "Maximum allowed dimension", "expected non-negative"):
        assert noise not in err
    assert out == ""
    leftovers = [p for p in where.rglob("*") if ".tmp" in p.name]
    assert not leftovers, leftovers
    assert time.perf_counter() - t0 < 60


def test_ray_address_that_does_not_answer_gives_up_within_30_s(where, monkeypatch):
    pytest.importorskip("ray")
    from warpsim.distributed import ray_sweep

    assert ray_sweep.CONNECT_TIMEOUT_S <= 30
    monkeypatch.setattr(ray_sweep, "CONNECT_TIMEOUT_S", 2.0)  # the same loop, shorter (test time)
    t0 = time.perf_counter()
    code, out, err = run(*SWEEP, *TWO, "--out", str(where / "ray1" / "s.usda"), "--ray", "127.0.0.1:1")
    assert time.perf_counter() - t0 < 30
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "--ray 127.0.0.1:1: nothing answers" in lines[0], err
    assert "gave up after 2 s" in lines[0]


@pytest.mark.parametrize("mutate, words", [
    (lambda m: m.pop("batches"), ['no "batches" table']),
    (lambda m: m.update(batches=[1, 2]), ['no "batches" table', "list"]),
    (lambda m: m.update(batches={"0": "x"}), ["batch entry '0'", "not a batch record"]),
    (lambda m: m.pop("sweep"), ['lacks its "sweep" settings']),
])
def test_resume_with_a_damaged_manifest_is_one_line(tmp_path, mutate, words):
    from warpsim.distributed.manifest import SweepManifest, manifest_path

    out = str(tmp_path / "s.usda")
    m = SweepManifest.new(manifest_path(out), {"scene": "bounce", "world_count": 2})
    m.record(0, {"dir": "s.batches/batch_0000", "sha256": "0" * 64, "error": None})
    data = json.load(open(m.path))
    mutate(data)
    json.dump(data, open(m.path, "w"))
    with pytest.raises(ValueError) as info:
        SweepManifest.load(m.path)
    for word in words:
        assert word in str(info.value)
    assert "--resume" in str(info.value) and "\n" not in str(info.value)


def test_resume_after_changing_vary_says_which_options(tmp_path):
    from warpsim.distributed.manifest import SweepManifest

    m = SweepManifest.new(str(tmp_path / "m.json"), {"scene": "bounce", "worlds_sha256": "a"})
    why = m.mismatch({"scene": "bounce", "worlds_sha256": "b"})
    assert "--vary" in why and "sha256" not in why


@wp.func
def _height(x: wp.vec3, v: wp.vec3, m: float) -> float:
    return x[1]


def _simulator(diff=False):
    b = ws.ModelBuilder()
    b.add_particle((0.0, 1.0, 0.0))
    b.add_particle((0.0, 2.0, 0.0))
    return ws.Simulator(b.finalize(device="cpu"), differentiable=diff)


def _cache(tmp_path):
    from warpsim.usd.writer import UsdCacheWriter

    path = str(tmp_path / "c.usda")
    with UsdCacheWriter(path, fps=10, chunk_size=2) as w:
        w.add_points("ball", radius=0.1, velocities=False)
        for f in range(4):
            w.write_frame(f, {"ball": {"points": np.array([[0.0, 1.0 - 0.1 * f, 0.0]])}})
    return path


API = [
    # worlds
    ("usermetric-builtin", lambda t: worlds.UserMetric("peak_speed", _height), ValueError, ["peak_speed", "built-in"]),
    ("usermetric-builtin-peak", lambda t: worlds.UserMetric("blown_up", _height), ValueError,
     ["blown_up", "built-in"]),
    ("sweep-root-onto-layer", lambda t: worlds.write_sweep_root(str(t / "b.usdc"), [str(t / "b.usdc")], 4), ValueError,
     ["also one of the batch layers", "another name"]),
    ("sample-n-float", lambda t: worlds.sample_worlds("bounce", {}, ["height=0.01:0.05"], 2.5, "random"),
     ValueError, ["sample_worlds n", "2.5"]),
    ("sample-n-huge", lambda t: worlds.sample_worlds("bounce", {}, ["height=0.01:0.05"], 2**63, "random"),
     ValueError, ["need about", "free"]),
    ("sample-seed-neg", lambda t: worlds.sample_worlds("bounce", {}, ["height=0.01:0.05"], 4, "random", -1),
     ValueError, ["sample_worlds seed", "-1"]),
    ("sample-vary-str", lambda t: worlds.sample_worlds("bounce", {}, "height=0.01:0.05", 4), TypeError,
     ["vary", "list"]),
    ("sample-fixed-list", lambda t: worlds.sample_worlds("bounce", ["height=1"], [], 2), TypeError,
     ["fixed", "dict"]),
    ("run-frames-float", lambda t: worlds.run_batch("bounce", [{}], frames=2.5, layer_path=t / "a.usdc",
                                                     device="cpu"), ValueError, ["run_batch frames", "2.5"]),
    ("run-params-int", lambda t: worlds.run_batch("bounce", [1], frames=2, layer_path=t / "a.usdc", device="cpu"),
     TypeError, ["world_params[0]", "dict"]),
    ("run-first-world-neg", lambda t: worlds.run_batch("bounce", [{}], frames=2, layer_path=t / "a.usdc",
                                                        device="cpu", first_world=-1), ValueError,
     ["run_batch first_world", "-1"]),
    ("root-world-count-text", lambda t: worlds.write_sweep_root(t / "r.usda", [], "3"), ValueError,
     ["write_sweep_root world_count"]),
    ("table-rows-none", lambda t: worlds.write_table(t / "t.csv", None), TypeError, ["write_table rows"]),
    # soft contact and torus meshes
    ("torus-text", lambda t: ws.torus_mesh(major_radius="big"), ValueError, ["torus_mesh major_radius", "'big'"]),
    ("torus-segments-inf", lambda t: ws.torus_mesh(segments=float("inf")), ValueError, ["torus_mesh segments"]),
    ("torus-segments-half", lambda t: ws.torus_mesh(segments=24.5), ValueError, ["torus_mesh segments", "24.5"]),
    ("torus-segments-huge", lambda t: ws.torus_mesh(segments=10**12), ValueError, ["torus_mesh segments", "<= 4096"]),
    ("contact-thickness-text", lambda t: ws.SoftContact([np.array([[0, 1, 2]])] * 2, thickness="thin"), ValueError,
     ["SoftContact thickness", "'thin'"]),
    ("contact-iterations-inf", lambda t: ws.SoftContact([np.array([[0, 1, 2]])] * 2, iterations=float("inf")),
     ValueError, ["SoftContact iterations"]),
    ("contact-iterations-half", lambda t: ws.SoftContact([np.array([[0, 1, 2]])] * 2, iterations=2.5), ValueError,
     ["SoftContact iterations", "2.5"]),
    ("contact-search-neg", lambda t: ws.SoftContact([np.array([[0, 1, 2]])] * 2, search=-1.0), ValueError,
     ["SoftContact search"]),
    # differentiable rollouts
    ("simulator-differentiable-no", lambda t: _simulator("no"), TypeError, ["differentiable", "'no'", "True"]),
    ("simulator-adaptive-text", lambda t: ws.Simulator(_simulator().model, adaptive="yes"), TypeError,
     ["adaptive", "'yes'"]),
    ("trajectory-target-short", lambda t: _rollout().trajectory_loss([np.zeros((1, 3))]), ValueError,
     ["target 0", "(1, 3)", "(2, 3)"]),
    ("trajectory-target-wp-short", lambda t: _rollout().trajectory_loss([wp.zeros(1, dtype=wp.vec3, device="cpu")]),
     ValueError, ["target 0", "shape (2,)"]),
    ("trajectory-target-single", lambda t: _rollout().trajectory_loss(np.zeros((2, 3))), TypeError,
     ["one array", "list"]),
    ("trajectory-step-out", lambda t: _rollout().trajectory_loss([np.zeros((2, 3))], steps=[5]), ValueError,
     ["trajectory_loss step", "5"]),
    # rendering
    ("render-only-nosuch", lambda t: ws_render(t, only=["nosuch"]), ValueError, ["'nosuch'", "drawn prims: ball"]),
    ("render-only-str", lambda t: ws_render(t, only="ball"), TypeError, ["only", "list"]),
    # viewer constructors: checked before a scene is built or a thread started
    ("viewer-draw-fps-0", lambda t: _viewer(draw_fps=0), ValueError, ["ws.Viewer draw_fps", "> 0"]),
    ("viewer-port-text", lambda t: _viewer(port="http"), ValueError, ["ws.Viewer port", "'http'"]),
    ("viewer-port-big", lambda t: _viewer(port=70000), ValueError, ["ws.Viewer port", "70000"]),
    ("viewer-host-none", lambda t: _viewer(host=None), TypeError, ["ws.Viewer host"]),
    ("viewer-max-points", lambda t: _viewer(max_points=0), ValueError, ["ws.Viewer max_points"]),
    ("playback-port", lambda t: _playback(t, port=-1), ValueError, ["PlaybackViewer port"]),
]


def _rollout():
    sim = _simulator(True)
    sim.rollout.reset()
    return sim.rollout


def ws_render(t, **kw):
    from warpsim.render.cache import render_cache

    return render_cache(_cache(t), str(t / "x.png"), device="cpu", **kw)


def _viewer(**kw):
    pytest.importorskip("viser")
    from warpsim.viewer.server import Viewer

    return Viewer("bounce", device="cpu", **kw)


def _playback(t, **kw):
    pytest.importorskip("viser")
    from warpsim.viewer.playback import PlaybackViewer

    return PlaybackViewer(_cache(t), **kw)


@pytest.mark.parametrize("case_id, call, exc_type, words", API, ids=[c[0] for c in API])
def test_bad_api_input_is_a_clear_error(tmp_path, case_id, call, exc_type, words):
    with pytest.raises(exc_type) as info:
        call(tmp_path)
    for word in words:
        assert word in str(info.value), (word, str(info.value))
    assert not (tmp_path / "x.png").exists()


def test_good_inputs_of_the_checked_apis_still_work(tmp_path):
    points, faces = ws.torus_mesh(0.1, 0.04, 8, 6)
    assert points.shape == (48, 3) and faces.shape == (96, 3)
    m = worlds.UserMetric("height", _height)
    assert m.name == "height"
    roll = _rollout()
    loss = roll.trajectory_loss([np.zeros((2, 3))])
    assert loss.numpy()[0] == pytest.approx(1.0 + 4.0)  # |(0,1,0)|^2 + |(0,2,0)|^2 at step 0
