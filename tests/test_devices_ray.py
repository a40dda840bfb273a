"""The Ray path of a sweep split over devices (issue 39): one Ray task per device, each building
its worlds against the whole sweep, gives the one-process table and every world's samples byte
for byte. Teapots varied in drop height and wall restitution are the case where a batch built
from its own worlds alone differs from the whole sweep in the last bit (5.7e-7 m after 20
frames); on the CPU each task holds one CPU where on GPUs it holds one GPU (``num_gpus=1``)."""

import io
import os

import numpy as np
import pytest

pytest.importorskip("pxr")
from pxr import Usd

from warpsim.cli import main
from warpsim.distributed.ray_sweep import DEFAULT_BATCH_SIZE, default_batch_size
from warpsim.sweeps import sample_worlds

FIXED = {"resolution": "3", "springs": False}
VARY = ["height=0.4:0.6", "restitution=0.2:0.8"]
WORLDS, FRAMES = 4, 8


def samples(root):
    """{world variant: bytes of every time sample of its points} through the root's variant set."""
    stage = Usd.Stage.Open(str(root))
    vset = stage.GetPrimAtPath("/World").GetVariantSets().GetVariantSet("world")
    out = {}
    for name in vset.GetVariantNames():
        vset.SetVariantSelection(name)
        attr = stage.GetPrimAtPath("/World/teapot").GetAttribute("points")
        out[name] = b"".join(np.asarray(attr.Get(t)).tobytes() for t in attr.GetTimeSamples())
    return out


def test_one_task_per_gpu_by_default_only_with_cuda_on_a_local_cluster():
    assert default_batch_size(100_000, "cpu") == DEFAULT_BATCH_SIZE
    assert default_batch_size(100_000, "cuda", "10.0.0.5:6379") == DEFAULT_BATCH_SIZE  # a remote cluster's GPUs
    import warp as wp

    gpus = wp.get_cuda_device_count()
    assert default_batch_size(100_001, "cuda") == (-(-100_001 // gpus) if gpus else DEFAULT_BATCH_SIZE)


def test_ray_tasks_build_against_the_whole_sweep_and_equal_one_process_byte_for_byte(tmp_path):
    import logging

    import ray

    from warpsim.distributed.ray_sweep import run_ray_sweep

    args = ["sweep", "teapot", "--worlds", str(WORLDS), "--sample", "lhs", "--frames", str(FRAMES), "--no-progress",
            "--device", "cpu", "--out", str(tmp_path / "one" / "s.usda")]
    args += [f"--vary={v}" for v in VARY] + [f"--set={k}={str(v).lower()}" for k, v in FIXED.items()]
    err = io.StringIO()
    assert main(args, out=io.StringIO(), err=err) == 0, err.getvalue()
    worlds = sample_worlds("teapot", FIXED, VARY, WORLDS, sample="lhs")
    mode = os.environ.get("RAY_AUTH_MODE")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    try:
        result = run_ray_sweep("teapot", worlds, frames=FRAMES, out_path=str(tmp_path / "ray" / "s.usda"),
                               table_path=str(tmp_path / "ray" / "s.csv"), device="cpu", batch_size=WORLDS // 2)
    finally:
        ray.shutdown()
        if mode is None:
            os.environ.pop("RAY_AUTH_MODE", None)
    assert result["ran"] == [0, 1]  # two tasks, one per "device"
    assert (tmp_path / "ray" / "s.csv").read_bytes() == (tmp_path / "one" / "s.csv").read_bytes()
    one, two = samples(tmp_path / "one" / "s.usda"), samples(result["root"])
    assert sorted(one) == sorted(two) and len(one) == WORLDS
    for name in one:
        assert two[name] == one[name], name  # bit for bit, not only to float32 rounding
