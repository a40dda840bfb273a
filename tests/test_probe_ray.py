"""A ``--ray`` driver killed outright (SIGKILL) leaves no process of the local cluster it
started (issue 28); the watchdog that ensures it kills exactly the processes holding files of
that cluster's session folder."""

import glob
import os
import signal
import subprocess
import sys
import time

import pytest


def _wait(predicate, timeout):
    deadline = time.time() + timeout
    while time.time() < deadline:
        if predicate():
            return True
        time.sleep(0.25)
    return predicate()


def test_watchdog_kills_the_session_processes_when_the_driver_dies(tmp_path):
    from warpsim.distributed.watchdog import cluster_processes, start_watchdog

    session = tmp_path / "session_x"
    (session / "logs").mkdir(parents=True)
    holder = subprocess.Popen([sys.executable, "-c", f"f = open({str(session / 'logs' / 'a.log')!r}, 'w'); "
                               "import time; time.sleep(60)"])
    bystander = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    driver = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        assert _wait(lambda: cluster_processes(session) == [holder.pid], 10)
        watchdog = start_watchdog(str(session), driver_pid=driver.pid)
        time.sleep(1.0)
        assert holder.poll() is None  # nothing happens while the driver lives
        driver.send_signal(signal.SIGKILL)
        driver.wait()
        assert _wait(lambda: holder.poll() is not None, 10)
        assert bystander.poll() is None  # only the cluster's processes
        assert _wait(lambda: watchdog.poll() is not None, 10)
    finally:
        for p in (holder, bystander, driver):
            if p.poll() is None:
                p.kill()
                p.wait()


def test_killing_a_ray_driver_ends_the_local_cluster_it_started(tmp_path):
    pytest.importorskip("ray")
    from warpsim.distributed.watchdog import cluster_processes

    out = tmp_path / "s.usda"
    driver = subprocess.Popen([sys.executable, "-m", "warpsim", "sweep", "springs", "--worlds", "2", "--vary",
                               "stiffness=100,200", "--frames", "2000", "--device", "cpu", "--out", str(out),
                               "--no-progress", "--ray", "--ray-cpus", "1", "--batch-size", "1"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    sessions = []
    try:
        found = _wait(lambda: bool(glob.glob(f"/tmp/ray/session_*_{driver.pid}")) and
                      os.path.exists(tmp_path / "s.ray-manifest.json"), 120)
        assert found and driver.poll() is None, "the driver did not start its cluster and its batches"
        sessions = glob.glob(f"/tmp/ray/session_*_{driver.pid}")
        assert cluster_processes(sessions[0])  # the cluster runs
    finally:
        driver.send_signal(signal.SIGKILL)
        driver.wait()
    assert _wait(lambda: not cluster_processes(sessions[0]), 30), cluster_processes(sessions[0])
