"""A sweep split over several devices in one process (``warpsim sweep --devices``, issue 39): on
the CPU, ``--devices cpu,cpu`` (and three blocks) must give the table, the occupancy record and
every world's time samples of ``--device cpu`` byte for byte, for mass-spring (teapot, with
automatic sub-steps whose stiffest world sits in one block only), bounce and flock sweeps; the
split balances uneven counts and respects each device's room; a bad device name is one line and
exit 2; a block that fails stops the sweep naming its device, and ``--resume`` (also after a
SIGKILL) completes it sample for sample."""

import glob
import io
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("pxr")
from pxr import Usd

from warpsim.cli import main
from warpsim.distributed.devices import block_sizes, split_blocks

SWEEPS = {
    "teapot": ["teapot", "--worlds", "5", "--vary", "stiffness=20:60", "--set", "resolution=3", "--set",
               "springs=false", "--frames", "12"],
    "bounce": ["bounce", "--worlds", "5", "--vary", "height=0.02:0.05", "--vary", "restitution=0.3:0.9",
               "--sample", "lhs", "--frames", "40"],
    "flock": ["flock", "--worlds", "3", "--vary", "seed=0,1,2", "--set", "birds=12", "--set", "geese=3", "--set",
              "food=1", "--frames", "10"],
}


def sweep(out, name, *extra):
    err = io.StringIO()
    code = main(["sweep", *SWEEPS[name], "--chunk", "8", "--out", str(out), "--no-progress", *extra],
                out=io.StringIO(), err=err)
    return code, err.getvalue()


def world_samples(folder):
    """{world prim name: {attribute: bytes of every time sample}} over the sweep's batch layers."""
    out = {}
    for layer in sorted(glob.glob(os.path.join(folder, "s.batch_[0-9][0-9][0-9][0-9].usdc"))):
        stage = Usd.Stage.Open(layer)
        for world in stage.GetPrimAtPath("/Worlds").GetChildren():
            got = {}
            for prim in Usd.PrimRange(world):
                for attr in prim.GetAttributes():
                    times = attr.GetTimeSamples()
                    if times:
                        path = str(attr.GetPath()).split("/", 3)[-1]
                        got[path] = b"".join(np.asarray(attr.Get(t)).tobytes() for t in times)
            out[world.GetName()] = got
    return out


def files(folder):
    return {name: (folder / name).read_bytes() for name in ("s.csv", "s.occupancy.npz")}


@pytest.fixture(scope="module")
def one_device(tmp_path_factory):
    """Each sweep of SWEEPS on ``--device cpu``: {name: (folder, table/record bytes, samples)}."""
    out = {}
    for name in SWEEPS:
        folder = tmp_path_factory.mktemp(f"one_{name}")
        code, err = sweep(folder / "s.usda", name, "--device", "cpu")
        assert code == 0, err
        out[name] = (folder, files(folder), world_samples(folder))
    return out


def test_blocks_balance_uneven_counts_and_respect_each_devices_room():
    assert block_sizes(10, [None, None]) == [5, 5]
    assert block_sizes(7, [None, None, None]) == [3, 2, 2]  # sizes differ by at most one
    assert split_blocks(7, [None, None, None]) == [(0, 3), (3, 2), (5, 2)]
    assert block_sizes(9, [2, None, None]) == [2, 4, 3]  # a small device: the others take its excess
    assert block_sizes(9, [2, 100, 4]) == [2, 4, 3]
    assert block_sizes(9, [0, 5, 5]) == [0, 5, 4]
    assert sum(block_sizes(100_001, [30_000, None, None, None])) == 100_001
    with pytest.raises(ValueError, match="9 worlds do not fit: the devices hold about 5 together"):
        block_sizes(9, [2, 3])


@pytest.mark.parametrize("name", list(SWEEPS))
def test_two_cpu_devices_equal_one_byte_for_byte(tmp_path, one_device, name):
    folder, expected, samples = one_device[name]
    code, err = sweep(tmp_path / "s.usda", name, "--devices", "cpu,cpu")
    assert code == 0, err
    assert os.path.exists(tmp_path / "s.batch_0001.usdc")  # two blocks, each its own layer
    assert files(tmp_path) == expected  # the table and the occupancy record, byte for byte
    got = world_samples(tmp_path)
    assert sorted(got) == sorted(samples) and len(got) == int(SWEEPS[name][2])
    for world in samples:
        assert got[world] == samples[world], world
    stage = Usd.Stage.Open(str(tmp_path / "s.usda"))  # the root spans both blocks
    assert len(stage.GetPrimAtPath("/World").GetVariantSets().GetVariantSet("world").GetVariantNames()) == \
        int(SWEEPS[name][2])
    assert not (tmp_path / "s.sweep-partial.json").exists()
    assert not glob.glob(str(tmp_path / "*.block*.npz"))


def test_teapot_blocks_take_the_whole_sweeps_steps():
    """The stiffest teapot is in the second block only: alone, the first block's worlds would
    take fewer steps a frame, so the byte equality above needs the sweep-wide count."""
    from warpsim.sweeps import sample_worlds
    from warpsim.sweeps.rerun import sweep_frame_steps

    worlds = sample_worlds("teapot", {"resolution": "3", "springs": False}, ["stiffness=20:60"], 5)
    first, second = split_blocks(5, [None, None])
    whole = sweep_frame_steps("teapot", worlds, device="cpu")
    assert sweep_frame_steps("teapot", worlds[: first[1]], device="cpu") < whole
    assert sweep_frame_steps("teapot", worlds[second[0]:], device="cpu") == whole


def test_three_blocks_of_an_uneven_count(tmp_path, one_device):
    folder, expected, samples = one_device["bounce"]
    code, err = sweep(tmp_path / "s.usda", "bounce", "--devices", "cpu, cpu,cpu")
    assert code == 0, err
    assert files(tmp_path) == expected and world_samples(tmp_path) == samples
    stages = [Usd.Stage.Open(str(tmp_path / f"s.batch_{k:04d}.usdc")) for k in range(3)]
    assert [len(s.GetPrimAtPath("/Worlds").GetChildren()) for s in stages] == [2, 2, 1]


@pytest.mark.parametrize("devices, words", [
    ("cpu,cuda:9", ["--devices", "'cuda:9' is not a device of this machine", "cpu"]),
    ("cpu,,cpu", ["an empty device name"]),
    ("gpu", ["'gpu' is not a device"]),
])
def test_a_bad_device_name_is_one_line_and_exit_2(tmp_path, devices, words):
    code, err = sweep(tmp_path / "s.usda", "bounce", "--devices", devices)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and all(w in lines[0] for w in words), err
    assert not os.listdir(tmp_path)  # nothing was written


def test_devices_with_device_or_ray_is_a_usage_error(tmp_path):
    for extra, words in ((["--device", "cpu"], "give one of them"), (["--ray"], "drop one of them")):
        code, err = sweep(tmp_path / "s.usda", "bounce", "--devices", "cpu,cpu", *extra)
        assert code == 2 and len(err.strip().splitlines()) == 1 and words in err, err


def test_a_failing_device_stops_the_sweep_naming_it_and_resume_completes_it(tmp_path, one_device, monkeypatch):
    from warpsim.sweeps.usd import BatchLayerWriter

    folder, expected, samples = one_device["bounce"]
    write = BatchLayerWriter.write_batch  # every world's frame at once (the scene's frame_arrays)

    def failing(self, frame, batched):  # the second block's device "fails" at frame 20
        if self.first_world == 3 and frame == 20:
            raise RuntimeError("CUDA error 700: an illegal memory access was encountered")
        return write(self, frame, batched)

    monkeypatch.setattr(BatchLayerWriter, "write_batch", failing)
    code, err = sweep(tmp_path / "s.usda", "bounce", "--devices", "cpu,cpu")
    assert code == 1
    line = err.strip().splitlines()[-1]
    assert line.startswith("warpsim: sweep failed: device cpu (block 1, worlds 3..4) failed after frame 19: "
                           "RuntimeError: CUDA error 700") and "--resume" in line, err
    assert not (tmp_path / "s.usda").exists() and not (tmp_path / "s.csv").exists()  # nothing half-published
    monkeypatch.setattr(BatchLayerWriter, "write_batch", write)
    code, err = sweep(tmp_path / "s.usda", "bounce", "--devices", "cpu,cpu", "--resume")
    assert code == 0, err
    assert "resuming: " in err and "block 1 on cpu: frames 0..15" in err  # chunks 0..7 and 8..15 were kept
    assert files(tmp_path) == expected and world_samples(tmp_path) == samples


def test_resume_after_a_kill_in_a_two_device_sweep(tmp_path):
    args = ["bounce", "--worlds", "4", "--vary", "height=0.02:0.05", "--frames", "240", "--chunk", "8",
            "--no-progress"]
    ref = tmp_path / "ref"
    err = io.StringIO()
    assert main(["sweep", *args, "--device", "cpu", "--out", str(ref / "s.usda")], out=io.StringIO(), err=err) == 0
    out = tmp_path / "two" / "s.usda"
    proc = subprocess.Popen([sys.executable, "-m", "warpsim", "sweep", *args, "--devices", "cpu,cpu", "--out",
                             str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    indexes = [str(tmp_path / "two" / f"s.batch_{k:04d}.run*.chunks.jsonl") for k in range(2)]
    deadline = time.time() + 300  # generous: the machine may be loaded
    listed = [0, 0]
    while proc.poll() is None and time.time() < deadline and min(listed) < 2:  # both blocks have chunks
        found = [glob.glob(p) for p in indexes]
        listed = [sum(1 for _ in open(f[0])) if f else 0 for f in found]
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the sweep finished before it could be killed: make it longer"
    assert min(listed) >= 2, f"chunks listed per block at the kill: {listed}"
    assert not out.exists()
    err = io.StringIO()
    assert main(["sweep", *args, "--devices", "cpu,cpu", "--out", str(out), "--resume"], out=io.StringIO(),
                err=err) == 0, err.getvalue()
    assert "resuming: block 0 on cpu: frames 0.." in err.getvalue()
    assert files(out.parent) == files(ref) and world_samples(out.parent) == world_samples(ref)
    assert not (out.parent / "s.sweep-partial.json").exists()
    tokens = {p.split(".run")[1].split(".")[0] for p in os.listdir(out.parent) if ".run" in p}
    assert len(tokens) == 1  # only the published run's chunks remain


def test_a_gallery_root_over_several_blocks_spaces_worlds_by_their_union(tmp_path):
    """Two blocks whose worlds sit side by side (each 1 m wide, together 2 m): the grid root
    spaces the worlds by the union's extent, as one layer of every world would, not by the
    larger block's own extent."""
    from pxr import Sdf, Vt

    from warpsim.browse.roots import write_sweep_root

    layers = []
    for k, (lo, hi) in enumerate((((0, 0, 0), (1, 0.1, 0.1)), ((1, 0, 0), (2, 0.1, 0.1)))):
        layer = Sdf.Layer.CreateNew(str(tmp_path / f"s.batch_{k:04d}.usda"))
        Sdf.CreatePrimInLayer(layer, f"/Worlds/world_{k:06d}").specifier = Sdf.SpecifierDef
        layer.customLayerData = {"warpsim": {"firstWorld": k, "worldCount": 1, "span": 1.0,
                                             "lo": Vt.DoubleArray(lo), "hi": Vt.DoubleArray(hi)}}
        layer.Save()
        layers.append(layer.identifier)
    stage = Usd.Stage.Open(write_sweep_root(tmp_path / "s.usda", layers, 2, layout="grid"))
    translate = stage.GetPrimAtPath("/World/world_000001").GetAttribute("xformOp:translate").Get()
    assert tuple(translate) == pytest.approx((2.5, 0.0, 0.0))  # 1.25 x the union's 2 m
