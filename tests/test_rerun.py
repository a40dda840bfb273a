"""A picked world re-runs exactly (issue 27): ``warpsim run SCENE --from-sweep ROOT --world N``,
``warpsim sweep ... --rerun N`` and ``rerun_world`` write caches whose samples equal world N's
samples in the sweep bit for bit; other settings warn; bad input is one line with exit 2."""

import io
import json
import os

import pytest

from warpsim.cli import main
from warpsim.sweeps.rerun import first_difference, manifest_path, rerun_world

pytest.importorskip("pxr")


def cli(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = main([str(a) for a in argv], out=out, err=err)
    return code, out.getvalue(), err.getvalue()


SWEEPS = {  # small sweeps: 3 worlds by LHS, a few frames
    "bounce": (["--vary", "restitution=0.2:0.9", "--vary", "height=0.5:2"], 12),
    "teapot": (["--vary", "stiffness=20:60", "--vary", "restitution=0.2:0.8"], 4),
    "cloth": (["--set", "integrator=semi_implicit_euler", "--set", "resolution=6", "--set", "explicit_substeps=10",
               "--vary", "density=0.1:0.3", "--vary", "structural=200:600"], 4),
    "wall": (["--set", "bricks=2,2", "--vary", "ball_speed=2:9"], 4),
    "donuts": (["--set", "count=2", "--set", "segments=8", "--set", "sides=6", "--vary", "stiffness=100:200"], 3),
}


def sweep(tmp_path, scene, *extra):
    args, frames = SWEEPS[scene]
    root = tmp_path / f"{scene}.usda"
    code, out, err = cli("sweep", scene, *args, "--worlds", 3, "--sample", "lhs", "--frames", frames, "--device",
                         "cpu", "--out", root, "--no-progress", *extra)
    assert code == 0, err
    return root


@pytest.mark.parametrize("scene", sorted(SWEEPS))
def test_a_rerun_world_equals_its_samples_in_the_sweep_bit_for_bit(tmp_path, scene):
    root = sweep(tmp_path, scene)
    cache = tmp_path / "world2.usda"
    code, out, err = cli("run", scene, "--from-sweep", root, "--world", 2, "--out", cache, "--no-progress")
    assert code == 0, err
    assert "warning" not in err
    assert first_difference(root, 2, cache) is None
    assert first_difference(root, 1, cache) is not None  # the comparison sees another world's samples


def test_the_python_and_sweep_rerun_equivalents(tmp_path):
    root = sweep(tmp_path, "bounce")
    path = rerun_world(root, 1)  # the sweep's frames, device and settings; beside the root
    assert path.endswith("bounce.world_000001.usda") and first_difference(root, 1, path) is None
    # the sweep command itself, re-running one of the worlds its arguments describe
    code, out, err = cli("sweep", "bounce", *SWEEPS["bounce"][0], "--worlds", 3, "--sample", "lhs", "--frames",
                         SWEEPS["bounce"][1], "--device", "cpu", "--out", root, "--no-progress", "--rerun", 0)
    assert code == 0, err
    assert first_difference(root, 0, tmp_path / "bounce.world_000000.usda") is None
    # a scene with automatic sub-steps: each world takes its own count, the one its re-run takes
    args, frames = SWEEPS["cloth"]
    root = sweep(tmp_path, "cloth")
    code, out, err = cli("sweep", "cloth", *args, "--worlds", 3, "--sample", "lhs", "--frames", frames, "--device",
                         "cpu", "--out", root, "--no-progress", "--rerun", 1)
    assert code == 0, err
    assert first_difference(root, 1, tmp_path / "cloth.world_000001.usda") is None


def test_other_settings_warn_that_the_world_will_differ(tmp_path):
    root = sweep(tmp_path, "bounce")
    code, out, err = cli("run", "bounce", "--from-sweep", root, "--world", 0, "--substeps", 2, "--out",
                         tmp_path / "b2.usda", "--no-progress")
    assert code == 0
    assert "warning" in err and "--substeps 2" in err and "differ" in err
    assert first_difference(root, 0, tmp_path / "b2.usda") is not None  # and it does differ
    with pytest.warns(UserWarning, match="--fps 50"):
        rerun_world(root, 0, fps=50.0, frames=2, out=tmp_path / "b3.usda")


def _edit_manifest(root, **changes):
    path = manifest_path(root)
    with open(path) as f:
        data = json.load(f)
    for key, value in changes.items():
        if key == "default_restitution":
            data["defaults"]["params"]["restitution"] = value
        else:
            data[key] = value
    with open(path, "w") as f:
        json.dump(data, f)


@pytest.mark.parametrize("case, words", [
    ("world", "out of range"),
    ("negative", "out of range"),
    ("not_a_sweep", "not a warpsim sweep root"),
    ("missing", "does not exist"),
    ("version", "made by warpsim 0.0.1"),
    ("defaults", "changed since the sweep"),
    ("scene", "is of scene 'bounce'"),
    ("set", "--set cannot be used with --from-sweep"),
    ("no_world", "go together"),
    ("sweep_rerun", "--rerun"),
])
def test_bad_reruns_exit_2_with_one_line(tmp_path, case, words):
    root = sweep(tmp_path, "bounce")
    args = ["run", "bounce", "--from-sweep", root, "--world", 1, "--no-progress", "--out", tmp_path / "x.usda"]
    if case == "world":
        args[5] = 3
    elif case == "negative":
        args[5] = -1
    elif case == "not_a_sweep":
        assert cli("run", "bounce", "--frames", 1, "--device", "cpu", "--out", tmp_path / "plain.usda",
                   "--no-progress")[0] == 0
        args[3] = tmp_path / "plain.usda"
    elif case == "missing":
        args[3] = tmp_path / "nothing.usda"
    elif case == "version":
        _edit_manifest(root, warpsim="0.0.1")
    elif case == "defaults":
        _edit_manifest(root, default_restitution=0.75)
    elif case == "scene":
        args[1] = "springs"
    elif case == "set":
        args += ["--set", "mass=2"]
    elif case == "no_world":
        args = args[:4] + args[6:]
    elif case == "sweep_rerun":
        args = ["sweep", "bounce", *SWEEPS["bounce"][0], "--worlds", 3, "--sample", "lhs", "--frames", 2, "--out",
                root, "--device", "cpu", "--rerun", 7]
    code, out, err = cli(*args)
    assert code == 2, (out, err)
    assert len(err.strip().splitlines()) == 1 and err.startswith("warpsim: error:") and words in err, err
    assert not os.path.exists(tmp_path / "x.usda")
