"""One frame timing (issue 35): ``FrameTiming`` resolved once from the scene, its parameters and
the options, the same for run, view, sweep and re-run; ``--substeps N`` keeps a dt scene's frame
rate; automatic steps in a sweep keep every world within half its own stability limit."""
import math

import numpy as np
import pytest
from pxr import Usd

from warpsim.cli import main
from warpsim.scenes import get_scene
from warpsim.scenes.timing import FrameTiming, resolve_timing


def run(*argv):
    import io

    out, err = io.StringIO(), io.StringIO()
    code = main([str(a) for a in argv], out=out, err=err)
    return code, out.getvalue(), err.getvalue()


# ---------------------------------------------------------------------------------- the rules
def test_a_dt_scene_keeps_its_frame_rate_and_splits_the_frame():
    bounce = get_scene("bounce")  # dt = 0.04 s, one step a frame: 25 fps
    p = bounce.resolve_params({})
    t = resolve_timing(bounce, p)
    assert (t.fps, t.frame_dt, t.steps, t.step_dt, t.chosen, t.note) == (25.0, 0.04, 1, 0.04, "default", "")
    t = resolve_timing(bounce, p, substeps=2)
    assert (t.fps, t.frame_dt, t.steps, t.step_dt, t.chosen) == (25.0, 0.04, 2, 0.02, "by hand")
    assert "--substeps 2" in t.note and "dt = 0.04" in t.note and "25 fps" in t.note
    assert t.scene_params(p)["dt"] == 0.02 and t.scene_params(p)["height"] == p["height"]
    teapot = get_scene("teapot")  # dt = 1/600 s, ten steps a frame, automatic by default
    q = teapot.resolve_params({})
    t = resolve_timing(teapot, q)
    assert (t.fps, t.steps, t.chosen, t.fixed) == (60.0, 10, "auto", False)
    assert t.step_dt == pytest.approx(1 / 600, rel=1e-12) and t.scene_params(q) == q
    t = resolve_timing(teapot, q, substeps=10)  # the scene's own count: consistent, no note
    assert (t.fps, t.steps, t.chosen, t.note) == (60.0, 10, "by hand", "")
    t = resolve_timing(teapot, q, substeps=1)  # the case: 60 fps kept (was 600)
    assert (t.fps, t.steps, t.step_dt) == (60.0, 1, pytest.approx(1 / 60)) and t.note


def test_dt_fps_and_substeps_given_together_agree_or_are_refused():
    bounce = get_scene("bounce")
    p = bounce.resolve_params({"dt": 0.01})
    t = resolve_timing(bounce, p, given={"dt": 0.01})  # --set dt: the step, frames dt x 1 apart
    assert (t.fps, t.steps, t.step_dt, t.chosen) == (100.0, 1, 0.01, "by hand")
    with pytest.raises(ValueError, match="--set dt=0.01 with --substeps 4"):
        resolve_timing(bounce, p, substeps=4, given={"dt": 0.01})
    t = resolve_timing(bounce, p, fps=25, substeps=4, given={"dt": 0.01})  # 0.01 x 4 x 25 = 1
    assert (t.fps, t.steps, t.step_dt) == (25.0, 4, pytest.approx(0.01))
    with pytest.raises(ValueError, match="give one of them"):
        resolve_timing(bounce, p, fps=10, given={"dt": 0.01})
    t = resolve_timing(bounce, bounce.resolve_params({}), fps=50, substeps=4)  # --fps sets dt: no note
    assert (t.fps, t.steps, t.step_dt, t.note) == (50.0, 4, pytest.approx(0.005), "")
    for bad, match in (({"substeps": 0}, "--substeps 0"), ({"substeps": 2.5}, "whole number"),
                       ({"fps": 0.0}, "--fps 0"), ({"fps": math.nan}, "--fps nan")):
        with pytest.raises(ValueError, match=match):
            resolve_timing(bounce, bounce.resolve_params({}), **bad)
    with pytest.raises(ValueError, match="FrameTiming chosen"):
        FrameTiming(fps=1.0, frame_dt=1.0, steps=1, step_dt=1.0, chosen="guess")


def test_automatic_steps_start_at_the_scenes_own_count():
    teapot = get_scene("teapot")
    q = teapot.resolve_params({})
    assert not resolve_timing(teapot, q, given={"dt": q["dt"]}).auto  # dt by hand: the step as given
    t = resolve_timing(teapot, q, substeps="auto", given={"dt": q["dt"]})
    assert (t.auto, t.steps, t.fixed) == (True, 10, False)
    cloth = get_scene("cloth")  # no dt parameter: frames 1 / fps apart
    t = resolve_timing(cloth, cloth.resolve_params({}), fps=30, substeps=3)
    assert (t.fps, t.frame_dt, t.steps, t.chosen) == (30.0, 1 / 30, 3, "by hand")
    assert resolve_timing(get_scene("pendulum"), get_scene("pendulum").resolve_params({}), substeps="auto").auto


def test_run_view_sweep_and_rerun_resolve_one_timing():
    from warpsim.sweeps.sweep import sweep_timing

    for name, opts in (("bounce", {"substeps": 3}), ("teapot", {"fps": 30.0}), ("cloth", {"substeps": 2}),
                       ("springs", {})):
        cls = get_scene(name)
        p = cls.resolve_params({})
        t = resolve_timing(cls, p, **opts)
        assert sweep_timing(cls, [{}], opts.get("fps"), opts.get("substeps")) == t


# ---------------------------------------------------------------------------------- the command line
def test_substeps_1_keeps_the_scenes_fps_and_warns_and_strict_refuses(tmp_path):
    path = tmp_path / "t.usda"
    code, _, err = run("run", "teapot", "--substeps", 1, "--frames", 1, "--out", path, "--device", "cpu",
                       "--no-progress", "--set", "resolution=3")
    assert code == 0, err
    assert Usd.Stage.Open(str(path)).GetTimeCodesPerSecond() == 60.0  # was 600
    assert "warpsim: warning: --substeps 1 keeps the scene's 60 fps" in err
    assert "above the stability limit" in err  # 1/60 s a step: the limit says so too
    code, _, err = run("run", "teapot", "--substeps", 1, "--strict", "--frames", 1, "--out", tmp_path / "s.usda",
                       "--device", "cpu", "--no-progress", "--set", "resolution=3")
    assert code == 2 and err.count("warpsim: error: --strict: --substeps 1") == 1, err
    assert not (tmp_path / "s.usda").exists()
    code, _, err = run("run", "bounce", "--substeps", 2, "--set", "dt=0.04", "--frames", 1, "--out", tmp_path / "x.usda",
                       "--no-progress")
    assert code == 2 and "--set dt=0.04 with --substeps 2" in err and len(err.strip().splitlines()) == 1, err


def test_bounce_with_two_substeps_takes_two_steps_of_half_the_frame(tmp_path):
    from warpsim.viewer.session import Session

    path = tmp_path / "b.usda"
    code, _, err = run("run", "bounce", "--substeps", 2, "--frames", 1, "--out", path, "--device", "cpu",
                       "--no-progress")
    assert code == 0, err
    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == 25.0
    y = np.asarray(stage.GetPrimAtPath("/World/ball").GetAttribute("points").Get(1))[0][1]
    # semi-implicit Euler, h = 0.02 s from rest at 0.04 m: y = 0.04 - h^2 g (1 + 2) = 0.028228 m (one step: 0.024304)
    assert y == pytest.approx(0.04 - 0.02 ** 2 * 9.81 * 3, rel=1e-5)
    # the viewer: the same timing and the same frame
    bounce = get_scene("bounce")
    session = Session(bounce, {}, device="cpu", substeps=2)
    assert session.timing == resolve_timing(bounce, bounce.resolve_params({}), substeps=2)
    assert (session.fps, session.substeps, session.stability()["step"]) == (25.0, 2, 0.02)
    assert session.advance()
    assert session.scene.sim.state.positions.numpy()[0][1] == np.float32(y)
    # a dt set on the page is the step: with --substeps 2 frames are 2 dt apart (not a refusal)
    assert session.set_param("dt", 0.01) == "rebuilt"
    assert (session.frame_dt, session.substeps, session.stability()["step"]) == (0.02, 2, 0.01)
    assert session.timing.chosen == "by hand" and not session.timing.note


# ---------------------------------------------------------------------------------- automatic steps in a sweep
DAMPING = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.25, 5.0]  # 0 to 0.5 and one outlier at 5 N s/m


def test_a_damping_sweep_steps_every_world_within_half_its_own_limit(tmp_path):
    from warpsim.sweeps.rerun import sweep_frame_steps
    from warpsim.sweeps.sweep import run_batch, sweep_timing

    cls = get_scene("teapot")
    worlds = [{"resolution": "2", "damping": d} for d in DAMPING]
    timing = sweep_timing(cls, worlds)
    assert timing.auto
    steps = sweep_frame_steps("teapot", worlds, device="cpu")
    step = timing.frame_dt / steps
    alone = [cls(w, device="cpu").sim.stable_dt() for w in worlds]  # each world built alone
    for w, limit in enumerate(alone):
        assert step <= 0.5 * limit * (1 + 1e-6), (w, worlds[w], step, limit)
    # and no more than the most any world needs alone
    assert steps == max(timing.steps, *(math.ceil(timing.frame_dt / (0.5 * limit) - 1e-9) for limit in alone))
    # without the outlier the damping-0.5 world sets the count (the old estimate averaged it: 0.9 x its limit)
    steps = sweep_frame_steps("teapot", worlds[:-1], device="cpu")
    assert steps == max(timing.steps, *(math.ceil(timing.frame_dt / (0.5 * limit) - 1e-9) for limit in alone[:-1]))
    assert all(timing.frame_dt / steps <= 0.5 * limit * (1 + 1e-6) for limit in alone[:-1])
    steps = sweep_frame_steps("teapot", worlds, device="cpu")
    # the count is the most any world needs alone: the same for a batch of the outlier world alone
    assert sweep_frame_steps("teapot", [worlds[-1]], device="cpu") == steps
    got = {}
    rows = run_batch("teapot", worlds, frames=3, device="cpu", layer_path=tmp_path / "b.usdc", timing=got)
    assert got["frame_steps"] == steps
    # the outlier at damping 5 too (the old single estimate averaged the damping: 23 steps a frame,
    # 10 x the outlier's limit, and it blew up within these 3 frames)
    assert [r["blown_up"] for r in rows] == [0] * len(worlds), rows
