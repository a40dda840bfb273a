"""``warpsim sweep``: bad --vary specs exit 2 with one line; a sweep writes the variant root, the
batch layer and the table; --rank/--top/--where print the picked worlds and write a cache of
only those; --layout grid writes a gallery."""
import csv
import io

import numpy as np
import pytest

pytest.importorskip("pxr")
from pxr import Usd, UsdGeom

from warpsim.cli import main


def run(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = main(list(argv), out=out, err=err)
    return code, out.getvalue(), err.getvalue()


@pytest.mark.parametrize("args, words", [
    (["--worlds", "4", "--vary", "hieght=0.01:0.05"], ["no parameter 'hieght'", "Did you mean 'height'"]),
    (["--worlds", "4", "--vary", "height=0.05:0.01"], ["lo 0.05 > hi 0.01"]),
    (["--worlds", "4", "--vary", "mass=0:2:log"], ["log range needs bounds > 0"]),
    (["--worlds", "4", "--vary", "mass=-1:2:log"], ["log range needs bounds > 0"]),
    (["--worlds", "0", "--vary", "height=0.01:0.05"], ["--worlds 0", ">= 1"]),
    (["--worlds", "-3", "--vary", "height=0.01:0.05"], ["--worlds -3"]),
    (["--worlds", "4", "--vary", "height"], ["malformed"]),
    (["--worlds", "4", "--vary", "height=a:b"], ["not a valid float"]),
    (["--worlds", "5", "--vary", "height=0.01:0.05", "--vary", "mass=1,2"], ["use --worlds 2 or 4 or 6"]),
    (["--worlds", "4", "--vary", "height=0.01:0.05", "--sample", "sobol"], ["sobol", "grid, random, lhs"]),
    (["--worlds", "2", "--vary", "height=0.01:0.05", "--where", "speed<1"], ["unknown metric 'speed'"]),
    (["--worlds", "2", "--vary", "height=0.01:0.05", "--where", "peak_speed<os"], ["not a number"]),
    (["--worlds", "2", "--vary", "height=0.01:0.05", "--top", "2"], ["--top needs --rank"]),
    (["--worlds", "2", "--vary", "dt=0.01:0.02"], ["dt changes nothing"]),
])
def test_bad_sweeps_exit_2_with_one_line(tmp_path, args, words):
    code, out, err = run("sweep", "bounce", *args, "--frames", "2", "--no-progress", "--out",
                         str(tmp_path / "s.usda"))
    assert code == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("warpsim: error:"), err
    for word in words:
        assert word in lines[0]
    assert not (tmp_path / "s.usda").exists()


def test_sweep_writes_variants_table_and_picked_worlds(tmp_path):
    out_path = tmp_path / "drop.usda"
    code, out, err = run("sweep", "bounce", "--worlds", "6", "--vary", "height=0.02:0.08",
                         "--vary", "restitution=0.2,0.9", "--set", "friction=0.1", "--frames", "15", "--no-progress",
                         "--out", str(out_path), "--track", "ball=0", "--rank", "peak_speed:desc", "--top", "2",
                         "--where", "center_y<0.05")
    assert code == 0, err
    with open(tmp_path / "drop.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["world"]) for r in rows] == list(range(6))
    assert {r["friction"] for r in rows} == {"0.1"}
    heights = sorted({float(r["height"]) for r in rows})
    assert heights == pytest.approx([0.02, 0.05, 0.08])
    assert all(float(r["peak_center_y"]) >= float(r["height"]) - 1e-6 for r in rows)  # frame 0 counts
    assert all(r["ball_peak_y"] == r["peak_center_y"] and r["ball_y"] == r["center_y"] for r in rows)  # one ball
    # the picked worlds: center_y < 0.05, largest peak speed first, two of them
    passing = [r for r in rows if float(r["center_y"]) < 0.05]
    best = sorted(passing, key=lambda r: -float(r["peak_speed"]))[:2]
    assert "picked 2 of 6 worlds" in out
    printed = [int(line.split()[0]) for line in out.splitlines() if line.startswith("  ") and line.split()[0].isdigit()]
    assert printed == [int(r["world"]) for r in best]
    stage = Usd.Stage.Open(str(out_path))
    vset = stage.GetPrimAtPath("/World").GetVariantSets().GetVariantSet("world")
    assert len(vset.GetVariantNames()) == 6
    vset.SetVariantSelection("world_000005")
    top = UsdGeom.Points(stage.GetPrimAtPath("/World/ball")).GetPointsAttr().Get(0)
    assert top[0][1] == pytest.approx(float(rows[5]["height"]), abs=1e-6)
    picked = Usd.Stage.Open(str(tmp_path / "drop.picked.usda"))
    names = picked.GetPrimAtPath("/World").GetVariantSets().GetVariantSet("world").GetVariantNames()
    assert sorted(names) == sorted(f"world_{int(r['world']):06d}" for r in best)


def test_sweep_grid_gallery_and_random_sampling(tmp_path):
    args = ["sweep", "springs", "--worlds", "4", "--vary", "stiffness=100:1000:log", "--sample", "lhs", "--seed",
            "7", "--set", "count=3", "--frames", "3", "--no-progress", "--layout", "grid"]
    code, _, err = run(*args, "--out", str(tmp_path / "a.usda"))
    assert code == 0, err
    code, _, err = run(*args, "--out", str(tmp_path / "b.usda"))
    assert code == 0, err
    assert (tmp_path / "a.csv").read_text() == (tmp_path / "b.csv").read_text()  # same seed, same worlds
    stage = Usd.Stage.Open(str(tmp_path / "a.usda"))
    prims = [p.GetName() for p in stage.GetPrimAtPath("/World").GetChildren()]
    assert prims == [f"world_{g:06d}" for g in range(4)]
    starts = [np.array(UsdGeom.Points(stage.GetPrimAtPath(f"/World/{p}/masses")).GetPointsAttr().Get(0))
              for p in prims]
    assert all(np.array_equal(starts[0], s) for s in starts)  # same start, placed by the grid transform
    offsets = [UsdGeom.Xformable(stage.GetPrimAtPath(f"/World/{p}")).ComputeLocalToWorldTransform(0)
               .ExtractTranslation() for p in prims]
    assert len({tuple(np.round(o, 6)) for o in offsets}) == 4


def test_a_sweep_says_its_first_worlds_scene_line_before_the_first_frame(tmp_path):
    """A scene's own line about its step (``Scene.scene_warning``: the donuts' fall faster than fast mass-spring's
    contact follows at one step of 1/60 s a frame) is said by a sweep too, of world 0, the one the batch builds;
    at the steps it names there is none."""
    common = ["sweep", "donuts", "--set", "integrator=fast_mass_spring", "--set", "count=2", "--fps", "60",
              "--frames", "1", "--vary", "gravity=5,9.81", "--no-progress", "--no-thumbnails"]
    code, _, err = run(*common, "--substeps", "1", "--out", str(tmp_path / "a.usda"))
    assert code == 0, err
    assert "warning: world 0 (gravity=5.0; the others not checked): donuts: a torus falling from 0.425 m" in err, err
    assert "take --substeps 2 at least" in err
    code, _, err = run(*common, "--substeps", "2", "--out", str(tmp_path / "b.usda"))
    assert code == 0 and "meets the heap" not in err, err


def test_a_fast_mass_spring_sweep_of_stiffness_is_refused_and_leaves_nothing(tmp_path):
    """FastMassSpring shares one matrix among the tori of all worlds: a sweep that varies their
    stiffness exits 2 with one line naming the key and the remedy, before any frame, and leaves no
    progress file behind (``--resume`` would have nothing to go on from); one that varies gravity runs."""
    common = ["sweep", "donuts", "--set", "integrator=fast_mass_spring", "--set", "count=2", "--set",
              "dt=0.0041666667", "--frames", "1", "--no-progress", "--no-thumbnails"]
    code, _, err = run(*common, "--vary", "stiffness=100,200", "--out", str(tmp_path / "a.usda"))
    assert code == 2, err
    assert err.count("\n") == 1 and "stiffness changes the springs" in err and "integrator=implicit_euler" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    code, _, err = run(*common, "--vary", "gravity=5,9.81", "--out", str(tmp_path / "b.usda"))
    assert code == 0, err
    assert not (tmp_path / "b.sweep-partial.json").exists() and (tmp_path / "b.batch_0000.usdc").exists()
