"""Issue 51, sizes checked before building: every hair size (steps, segments, strands under a
memory limit, segments=1 with sag-free) and the donuts' box refused before anything is built, in
one line naming the parameter, the value, the estimate and a fix (exit 2); the memory a process
can get honours ``ulimit -v``; a long hair frame is estimated before the first step."""

import io
import time

import pytest

from warpsim.cli import main
from warpsim.strands import preflight as sp


def run(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = main([str(a) for a in argv], out=out, err=err)
    return code, out.getvalue(), err.getvalue()


def one_error_line(err):
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("warpsim: error: "), err
    assert "Traceback" not in err
    return lines[0]


@pytest.fixture
def no_build(monkeypatch):
    """Every builder of the hair and donuts scenes raises: a refusal must come before them."""
    import warpsim.scenes.fracture as fracture
    import warpsim.scenes.hair as hair

    def built(*_a, **_k):
        raise AssertionError("the scene was built before its sizes were checked")

    for mod, name in ((hair, "scalp_roots"), (hair, "groom"), (hair, "add_strands"), (fracture, "torus_mesh"),
                      (fracture, "add_soft_body")):
        monkeypatch.setattr(mod, name, built)


GIB = 1 << 30


@pytest.mark.parametrize("sets, words", [
    (["steps=1000000000", "strands=2", "segments=2"],
     ["steps=1,000,000,000", "head's poses", "GiB", "use at most about steps="]),
    (["steps=100000000", "strands=2", "segments=2"],  # fits in memory, but a frame takes hours
     ["steps=100,000,000", "takes about", " h on cpu", "use at most about steps="]),
    (["strands=1", "segments=100000"],
     ["segments=100000", "dense Jacobians", "1 x 300,000 x 300,000", "TiB", "use at most about segments="]),
    (["strands=2", "segments=3000"],  # fits in memory, but the dense solves take hours
     ["segments=3000", "dense Jacobians", "take at least", "use at most about segments="]),
    (["segments=1"], ["segments=1", "sag-free", "use segments>=2 or sag_free=false"]),
])
def test_hair_sizes_are_refused_before_building(tmp_path, no_build, monkeypatch, sets, words):
    monkeypatch.setattr(sp, "available_host_bytes", lambda *a, **k: 32 * GIB)
    argv = ["run", "hair", "--frames", 1, "--no-progress", "--device", "cpu", "--out", tmp_path / "h.usda"]
    for s in sets:
        argv += ["--set", s]
    t0 = time.monotonic()
    code, _, err = run(*argv)
    line = one_error_line(err)
    assert code == 2, err
    for w in words:
        assert w in line, (w, line)
    assert time.monotonic() - t0 < 30  # generous (imports on a loaded machine); the builders were not called
    assert not (tmp_path / "h.usda").exists()


def test_a_million_strands_under_a_4_gb_limit_are_refused_with_the_figure(tmp_path, no_build, monkeypatch):
    monkeypatch.setattr(sp, "available_host_bytes", lambda *a, **k: 3 * GIB)  # what ulimit -v 4 GB leaves
    code, _, err = run("run", "hair", "--set", "strands=1000000", "--set", "segments=4", "--frames", 1,
                       "--no-progress", "--device", "cpu", "--out", tmp_path / "h.usda")
    line = one_error_line(err)
    assert code == 2
    assert "strands=1000000 x segments=4" in line and "3 GiB free" in line and "use at most about strands=" in line
    fit = int(line.split("strands=")[-1].split(" ")[0].replace(",", ""))
    need = sp.estimate_strand_bytes(fit, 4)
    assert need["host"] + need["device"] < 3 * GIB  # the advised count fits


def test_the_groom_estimate_covers_the_grooms_arrays():
    """The per-strand host figure holds ``groom``'s peak (the (S, 160, 3) float64 polylines and their
    temporaries) for the curliest groom."""
    import tracemalloc

    from warpsim.scenes import hair

    roots, normals = hair.scalp_roots(2000, hair.HEAD_CENTER, hair.HEAD_RADIUS)
    tracemalloc.start()
    try:
        hair.groom(roots, normals, hair.HEAD_CENTER, hair.HEAD_RADIUS, 0.25, "curly", lift=0.005)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak <= 2000 * sp.STRAND_HOST_BYTES
    assert peak > 2000 * sp.STRAND_HOST_BYTES / 2  # the figure is not padded past use


def test_dense_jacobians_are_in_the_estimate():
    small, large = sp.estimate_strand_bytes(1, 10), sp.estimate_strand_bytes(1, 100000)
    assert large["dense"] == sp.DENSE_MATRICES["implicit"] * 300000 ** 2 * 8
    assert large["host"] > large["dense"] > 671 * GIB  # the matrix numpy failed to allocate
    assert small["dense"] < (1 << 20)
    with pytest.raises(ValueError, match=r"segments=100000: .* dense Jacobians"):
        sp.check_strand_memory(1, 100000, "cpu", available=64 * GIB)


def test_available_memory_honours_an_address_space_limit(monkeypatch):
    import resource

    from warpsim.core import memory

    monkeypatch.setattr(resource, "getrlimit", lambda what: (4 * GIB, resource.RLIM_INFINITY)
                        if what == resource.RLIMIT_AS else (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
    assert memory.available_host_bytes() < 4 * GIB


def test_default_hair_passes_its_checks():
    from warpsim.scenes import get_scene

    p = get_scene("hair").resolve_params({})
    need = sp.check_hair_params(p, "cpu", available=64 * GIB)
    assert need["vertices"] == p["strands"] * (p["segments"] + 1)
    assert sp.check_hair_steps(p["steps"], p["strands"], p["segments"]) < 1.0  # 4 steps a frame: well under a second


def test_explicit_64_segments_is_estimated_before_the_first_step():
    """The issue's explicit groom (2,000 strands x 64 segments, about 1,573 steps a frame measured)
    is estimated at tens of seconds a frame, and a scene's estimate is said before the first step."""
    from types import SimpleNamespace

    from warpsim.sweeps.preflight import steps_note

    assert sp.frame_seconds(1573, 2000 * 66, "explicit", "cpu") > 10.0
    scene = SimpleNamespace(frame_steps=lambda dt, n: 800, stability=lambda: None,
                            frame_seconds=lambda dt, n: sp.frame_seconds(800, 2000 * 66, "explicit", "cpu"))
    note = steps_note(scene, 1 / 60, 1, 120)
    assert note and "120 frames" in note and "take about" in note and "min" in note, note
    scene.frame_steps = lambda dt, n: 1573
    note = steps_note(scene, 1 / 60, 1, 120)
    assert note and "1,573 steps a frame" in note and "about" in note, note


def test_hair_frame_seconds_of_a_built_scene():
    from warpsim.scenes import get_scene

    scene = get_scene("hair")({"strands": 2, "segments": 2, "sag_free": False, "steps": 50}, device="cpu")
    seconds = scene.frame_seconds(1 / 60, 1)
    assert seconds == pytest.approx(sp.frame_seconds(50, scene.model.particle_count, "implicit", "cpu"))


def test_donuts_in_a_box_too_small_are_refused(tmp_path, no_build):
    t0 = time.monotonic()
    code, _, err = run("run", "donuts", "--set", "count=12", "--set", "box=0.05", "--frames", 1, "--no-progress",
                       "--device", "cpu", "--out", tmp_path / "d.usda")
    line = one_error_line(err)
    assert code == 2
    assert "box=0.05" in line and "0.28 m across" in line and "box>=0.15" in line and "box=0" in line, line
    assert time.monotonic() - t0 < 30
    assert not (tmp_path / "d.usda").exists()


def test_donut_box_check_passes_what_fits():
    from warpsim.scenes.fracture import check_donut_box

    assert check_donut_box(0.0, 0.1, 0.04) == pytest.approx(0.15)  # 0: sized to the count
    assert check_donut_box(0.15, 0.1, 0.04) == pytest.approx(0.15)
    with pytest.raises(ValueError, match="box=0.149"):
        check_donut_box(0.149, 0.1, 0.04)


def test_explicit_frame_of_hours_is_refused_before_sag_free_and_the_frame(monkeypatch):
    """solver=explicit: the measured stable step sets a frame's steps; a frame of hours is refused
    before the sag-free solve and the frame's arrays (its figures and solver=implicit named)."""
    import warpsim.scenes.hair as hair

    monkeypatch.setattr(hair, "strand_stable_dt", lambda *a, **k: 1.0e-9)
    monkeypatch.setattr(hair, "sag_free", lambda *a, **k: pytest.fail("sag-free solved before the refusal"))
    monkeypatch.setattr(hair, "HairFrame", lambda *a, **k: pytest.fail("the frame was built before the refusal"))
    from warpsim.scenes import get_scene

    with pytest.raises(ValueError, match=r"solver=explicit: at segments=2 .* 33,333,334 steps a frame .* about "
                                         r".* h a frame; use solver=implicit"):
        get_scene("hair")({"strands": 2, "segments": 2, "solver": "explicit"}, device="cpu")


def test_sag_free_rounds_are_bounded_and_its_error_names_the_scene_parameters(monkeypatch):
    import warpsim.scenes.hair as hair
    from warpsim.scenes import get_scene

    seen = {}

    def failing(sim, **kw):
        seen.update(kw)
        raise ValueError("sag_free: the bound max_strain=0.2 cannot be met: strand 0 ...")

    monkeypatch.setattr(hair, "sag_free", failing)
    with pytest.raises(ValueError, match=r"cannot be met.*segments=2, mass=0\.05.*a lighter mass.*sag_free=false"):
        get_scene("hair")({"strands": 2, "segments": 2, "mass": 0.05}, device="cpu")
    assert 5475 < seen["max_iterations"] <= 10000  # above the converging solves' need, far below 50,000


@pytest.mark.parametrize("scene, sets, words", [
    ("cloth", ["resolution=100000"], ["resolution=100000", "10,000,200,001 particles", "use at most about resolution="]),
    ("springs", ["count=100000000"], ["count=100000000", "100,000,000 particles", "use at most about count="]),
    ("springs", ["shape=lattice", "count=100000"], ["count=100000", "10,000,000,000 particles", "use at most about"]),
    ("wall", ["bricks=10000,10000"], ["bricks=10000,10000", "lattice nodes", "use at most about bricks="]),
])
def test_scene_counts_are_refused_before_building(tmp_path, monkeypatch, scene, sets, words):
    import warpsim
    import warpsim.scenes.cloth as cloth
    from warpsim.core import memory

    def built(*_a, **_k):
        raise AssertionError("the scene was built before its sizes were checked")

    monkeypatch.setattr(memory, "available_host_bytes", lambda *a, **k: 4 * GIB)
    monkeypatch.setattr(warpsim, "ModelBuilder", built)
    monkeypatch.setattr(cloth, "ModelBuilder", built)
    argv = ["run", scene, "--frames", 1, "--no-progress", "--device", "cpu", "--out", tmp_path / "s.usda"]
    for s in sets:
        argv += ["--set", s]
    code, _, err = run(*argv)
    line = one_error_line(err)
    assert code == 2
    for w in words:
        assert w in line, (w, line)
    assert "4 GiB free" in line


def test_build_memory_check_passes_what_fits_and_its_fix_fits():
    from warpsim.core.memory import check_build_memory

    assert check_build_memory("count", 10, 10, "particles", 500.0, lambda k: k, available=5000) == 5000
    with pytest.raises(ValueError, match=r"count=11: 11 particles .* use at most about count=8$"):
        check_build_memory("count", 11, 11, "particles", 500.0, lambda k: k, available=5000)


def test_an_allocation_failing_while_building_is_one_line(tmp_path, monkeypatch):
    """A size no check of the scene's caught still ends in one line (exit 2) naming the sizes."""
    def full(self, p):
        raise MemoryError("Unable to allocate 74.5 GiB for an array with shape (100001, 100001)")

    from warpsim.scenes import get_scene

    monkeypatch.setattr(get_scene("springs"), "build", full)
    code, _, err = run("run", "springs", "--set", "count=12", "--frames", 1, "--no-progress", "--device", "cpu",
                       "--out", tmp_path / "s.usda")
    line = one_error_line(err)
    assert code == 2 and "out of memory while building" in line and "74.5 GiB" in line and "count=12" in line, line
