"""Every scene at full length on the CPU, as a user runs it (issue 49): no false alarm, every real
blow-up flagged.

The corpus and its runner are :mod:`warpsim.commands.corpus`, shared with
``benchmarks/check_scenes.py`` (full size, on a GPU): every scene of ``warpsim list`` at its defaults
for its default length (120 frames), every README ``warpsim run`` at its README length, each end of
the physical sliders (damping 0, restitution 1, the largest stiffness and wind, the smallest mass,
and the other ends) for the scene's default length, and each explicit integrator at 1.2x its
stability limit in springs, teapot, cloth and hair, which must be stopped within two frames of the
growth of an unchecked twin. Each case runs through ``warpsim run``'s own parsing, timing and
checks; the CPU lowers resolution-type parameters (``corpus.SMALL``), never frames, fps or steps.
"""

import io

import pytest

from warpsim.commands import corpus

SLIDER_FRAMES = corpus.DEFAULT_FRAMES
"""The CPU runs each slider end for the scenes' default length (``check_scenes.py`` for 600)."""

CASES = corpus.cases(kinds=("default", "slider", "readme", "issue", "blowup"), slider_frames=SLIDER_FRAMES)
LONG = corpus.long_cases(["cloth", "drape"])
"""The issue's goal: the default cloth and drape for 600 frames (the other scenes' long runs are
check_scenes.py's)."""


def _id(case):
    return case.name.replace(" ", "_")


@pytest.mark.parametrize("case", [c for c in CASES if c.kind == "default"], ids=_id)
def test_default_runs_its_length_clean(case):
    result = corpus.run_case(case, "cpu", small=True)
    assert result.passed, result.summary()
    assert result.frames_run == case.frames == corpus.DEFAULT_FRAMES


@pytest.mark.parametrize("case", LONG, ids=_id)
def test_default_cloth_and_drape_run_600_frames_clean(case):
    result = corpus.run_case(case, "cpu", small=True)
    assert result.passed, result.summary()
    assert result.frames_run == case.frames == 600


@pytest.mark.parametrize("case", [c for c in CASES if c.kind == "readme"], ids=_id)
def test_readme_run_at_its_length_is_clean(case):
    result = corpus.run_case(case, "cpu", small=True)
    assert result.passed, result.summary()
    assert result.frames_run == case.frames


@pytest.mark.parametrize("case", [c for c in CASES if c.kind == "slider"], ids=_id)
def test_slider_end_is_clean(case):
    """Clean (or refused by the scene before any frame: no alarm, counted apart by check_scenes.py); the
    time step's right end, where it is past the stability limit, flagged within two frames of the growth."""
    result = corpus.run_case(case, "cpu", small=True)
    assert result.passed, result.summary()
    if result.case.expect == "clean" and not result.refused:
        assert result.frames_run == case.frames


@pytest.mark.parametrize("case", [c for c in CASES if c.kind == "issue"], ids=_id)
def test_the_issues_runs_are_clean(case):
    """Issue 49's springs: damping 0 for 600 frames, and 24 fps for 48 frames."""
    result = corpus.run_case(case, "cpu", small=True)
    assert result.passed, result.summary()
    assert result.frames_run == case.frames


@pytest.mark.parametrize("case", [c for c in CASES if c.kind == "blowup"], ids=_id)
def test_blowup_is_flagged_within_two_frames_of_its_growth(case):
    result = corpus.run_case(case, "cpu", small=True)
    assert result.limit is not None, result.summary()
    assert result.step == pytest.approx(corpus.BLOWUP * result.limit, rel=1e-6), result.summary()
    assert result.growth is not None, f"the unchecked twin never grew: not a blow-up\n{result.summary()}"
    assert result.passed, result.summary()
    assert "unstable" in result.message or "blew up" in result.message, result.summary()


def test_the_corpus_covers_every_scene_readme_run_and_blowup():
    from warpsim.scenes import scenes

    shipped = {n for n, cls in scenes().items() if cls.__module__.startswith("warpsim.")}
    assert {c.scene for c in CASES if c.kind == "default"} == shipped
    assert all(c.frames == corpus.DEFAULT_FRAMES for c in CASES if c.kind == "default")
    readme = corpus.readme_commands()
    runs = [c for c in readme if "--from-sweep" not in c]
    assert len(runs) >= 7 and len([c for c in CASES if c.kind == "readme"]) == len(runs)
    cloth = next(c for c in CASES if c.kind == "readme" and c.scene == "cloth")
    assert cloth.frames == 240 and cloth.integrator == "implicit_euler"
    names = {c.name for c in CASES}
    for must in ("springs/damping=0", "teapot/restitution=1", "springs/stiffness=1000", "springs/mass=1e-05",
                 "cloth/wind=10", "teapot/mass=0.001"):
        assert must in names, must
    blowups = {(c.scene, c.case) for c in CASES if c.kind == "blowup"}
    assert blowups == {(s, f"blowup {i}") for s, ints in corpus.BLOWUP_SCENES.items() for i in ints}
    # the CPU's sizes lower resolution only: never frames, fps, steps or the integrator
    for case in CASES:
        small = case.sized(True)
        assert (small.frames, small.fps, small.substeps, small.integrator) == \
               (case.frames, case.fps, case.substeps, case.integrator)
        added = [s.split("=")[0] for s in small.sets if s not in case.sets]
        assert not set(added) & {"dt", "integrator", "explicit_substeps", "steps"}, (case.name, added)


@pytest.mark.parametrize("name", ["springs/blowup semi_implicit_euler", "bounce/restitution=1"])
def test_the_runner_agrees_with_warpsim_run(name, tmp_path):
    """The in-process runner and ``warpsim run`` itself: the same exit and, for an alarm, the same
    frame."""
    from warpsim import cli

    case = corpus.resolve_blowup(next(c for c in CASES if c.name == name), "cpu")
    result = corpus.run_case(case, "cpu", twin=False)
    out, err = io.StringIO(), io.StringIO()
    code = cli.main(case.argv(str(tmp_path / "run.usda")) + ["--device", "cpu"], out, err)
    if result.alarm_frame is None:
        assert code == 0 and result.exit == "ok", err.getvalue()
    else:
        assert code == 1, err.getvalue()
        assert f"simulation failed at frame {result.alarm_frame}:" in err.getvalue(), err.getvalue()
