"""Server-side logic of the live viewer (no browser): the viewer sink draws what the USD writer
records, picking and the camera-facing drag plane, live parameters versus rebuilds, dragging
with a DragSpring (implicit Euler stable where semi-implicit blows up), recording, playback of
chunked and flattened caches, blow-ups that pause, and the command line's usage errors."""
from __future__ import annotations

import io
import socket

import numpy as np
import pytest
import warp as wp

from warpsim import cli
from warpsim.scenes import get_scene
from warpsim.usd.validate import cache_info, validate_cache
from warpsim.viewer.geometry import curve_segments, triangulate
from warpsim.viewer.picking import camera_plane_target, pick_mesh_vertex, pick_point, ray_triangles
from warpsim.viewer.playback import CacheReader
from warpsim.viewer.session import Session
from warpsim.viewer.sink import ViewerSink

RESTING_TEAPOT = {"velocity": "0,0,0", "tilt": "0", "height": "0.05", "resolution": "3"}


def test_triangulate_and_segments():
    tris = triangulate([3, 4, 5], np.arange(12))
    # a triangle, a quad as 2 fans, a pentagon as 3 fans; every fan shares its polygon's first vertex
    assert sorted(map(tuple, tris.tolist())) == sorted([(0, 1, 2), (3, 4, 5), (3, 5, 6), (7, 8, 9), (7, 9, 10),
                                                        (7, 10, 11)])
    pts = np.arange(15, dtype=np.float32).reshape(5, 3)
    segs = curve_segments(pts, [3, 2])  # a polyline of 3 vertices and one of 2
    assert segs.shape == (3, 2, 3)
    assert np.array_equal(segs[1], pts[[1, 2]]) and np.array_equal(segs[2], pts[[3, 4]])


def test_ray_picking_and_drag_plane():
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, -1], [1, 0, -1], [0, 1, -1]], float)
    tris = np.array([[0, 1, 2], [3, 4, 5]])
    t, k, hit = ray_triangles((0.2, 0.2, 5.0), (0, 0, -1), verts, tris)
    assert k == 0 and t == pytest.approx(5.0) and np.allclose(hit, (0.2, 0.2, 0.0))  # the nearer triangle
    assert pick_mesh_vertex((0.2, 0.2, 5.0), (0, 0, -1), verts, tris) == 0
    grabbable = np.array([False, True, True, True, True, True])  # vertex 0 pinned: the next nearest corner
    assert pick_mesh_vertex((0.2, 0.2, 5.0), (0, 0, -1), verts, tris, grabbable) in (1, 2)
    assert pick_mesh_vertex((3.0, 3.0, 5.0), (0, 0, -1), verts, tris) == -1
    assert pick_point((0, 0, 5), (0, 0, -1), verts, radius=0.05) == 0
    assert pick_point((0.5, 0.5, 5), (0, 0, -1), verts, radius=0.05) == -1
    # the pointer ray meets the plane facing the camera (normal = view direction) through the grab
    target = camera_plane_target((0, 0, 5), (0.1, 0.2, -1.0), (7.0, -3.0, 1.0), (0, 0, -1))
    assert target[2] == pytest.approx(1.0)
    assert np.allclose(target[:2], (0.4, 0.8))  # 4 m along z from the eye: x = 0.1 * 4, y = 0.2 * 4


@pytest.mark.parametrize("name", ["bounce", "pendulum", "teapot", "cloth", "flock", "metaballs"])
def test_viewer_sink_draws_what_the_writer_records(tmp_path, name):
    """The viewer and the USD writer see the same declarations and frame data: every animated
    prim of the recording reads back as the points the viewer drew."""
    cls = get_scene(name)
    session = Session(cls, cls.smoke_params, device="cpu", record_dir=str(tmp_path))
    drawn = [session.items]
    path = session.start_recording(str(tmp_path / f"{name}.usda"))
    for _ in range(3):
        assert session.advance()
        drawn.append(session.items)
    assert session.stop_recording() == path
    assert validate_cache(path) == []
    reader = CacheReader(path)
    assert len(reader) == 4
    assert set(reader.static) == set(session.static)
    for prim, item in session.static.items():  # see-through containers stay see-through in both
        assert reader.static[prim].opacity == item.opacity
        np.testing.assert_allclose(reader.static[prim].points, item.points, atol=1e-5)
    for frame in (0, 3):
        read = reader.items(frame)
        assert set(read) == set(drawn[frame])
        for prim, item in read.items():
            assert item.kind == drawn[frame][prim].kind
            np.testing.assert_allclose(item.points, drawn[frame][prim].points, atol=1e-6)
            if item.kind == "instances":  # w, x, y, z from USD's quaternions equals the live conversion
                np.testing.assert_allclose(item.orientations, drawn[frame][prim].orientations, atol=2e-3)
                assert np.array_equal(item.proto, drawn[frame][prim].proto)


def test_live_parameters_and_rebuilds():
    cls = get_scene("bounce")
    s = Session(cls, {}, device="cpu")
    assert s.set_param("restitution", "0.9") == "live"
    assert s.scene.sim.colliders[0].restitution == pytest.approx(0.9)
    assert s.set_param("restitution", 0.9) == "unchanged"
    for _ in range(3):
        s.advance()
    assert s.set_param("height", 0.08) == "rebuilt"  # not live: a new scene at frame 0
    assert s.frame == 0 and s.scene.sim.state.positions.numpy()[0, 1] == pytest.approx(0.08)
    assert s.scene.sim.colliders[0].restitution == pytest.approx(0.9)  # kept across the rebuild
    with pytest.raises(ValueError, match="restitution"):
        s.set_param("restitution", 1.5)
    with pytest.raises(ValueError, match="no parameter 'nope'"):
        s.set_param("nope", 1.0)
    # a live restitution change is physics: the ball's rebound speed follows the new coefficient
    s2 = Session(cls, {"dt": "0.001"}, device="cpu")
    s2.set_param("restitution", 0.25)
    v_before = v_after = None
    for _ in range(200):
        v = float(s2.scene.sim.state.velocities.numpy()[0, 1])
        s2.advance()
        w = float(s2.scene.sim.state.velocities.numpy()[0, 1])
        if v < 0 < w:
            v_before, v_after = v, w
            break
    assert v_before is not None and v_after / -v_before == pytest.approx(0.25, rel=0.05)


@pytest.mark.parametrize("name,prim", [("teapot", "teapot"), ("cloth", "cloth"), ("drape", "cloth"),
                                       ("springs", "masses")])
def test_drag_pulls_the_picked_vertex_toward_the_pointer(name, prim):
    cls = get_scene(name)
    params = dict(RESTING_TEAPOT) if name == "teapot" else dict(cls.smoke_params)
    s = Session(cls, params, device="cpu")
    item = s.items[prim]
    # a ray straight down onto the drawn vertex nearest the middle of the prim
    centre = item.points.mean(0)
    _, ok = s._grabbable(prim)
    v0 = int(np.argmin(np.where(ok, np.linalg.norm(item.points - centre, axis=1), np.inf)))
    eye = item.points[v0] + np.array([0.0, 2.0, 0.0])
    picked = s.pick(prim, eye, (0.0, -1.0, 0.0))
    assert picked >= 0
    particle = s.grab(prim, picked, client=7)
    assert particle >= 0
    x0 = s.grabbed_position()
    # the pointer moves 0.15 m sideways; the target is where its ray meets the plane facing the camera
    target = s.drag_ray(eye, (x0 + [0.15, 0.0, 0.0]) - eye, (0.0, -1.0, 0.0))
    np.testing.assert_allclose(target, x0 + [0.15, 0.0, 0.0], atol=1e-9)
    free = Session(cls, params, device="cpu")  # the same scene, nobody dragging
    for _ in range(30):
        assert s.advance(), s.error
        free.advance()
    x1 = s.grabbed_position()
    x_free = free.scene.sim.state.positions.numpy()[particle]
    pull = (target - x0) / np.linalg.norm(target - x0)
    assert (x1 - x_free) @ pull > 0.5 * 0.15  # the drag moved it over half way toward the pointer
    assert not s.release(client=8) and s.grabbed is not None  # another browser's release is not ours
    assert s.release(client=7) and s.grabbed is None and s.drag.particle == -1


def test_implicit_euler_keeps_a_stiff_drag_stable():
    """A stiff drag spring (omega h = 2.9 on a teapot vertex) diverges with semi-implicit Euler
    and stays bounded with implicit Euler; both move the target 5 mm per frame. (Sub-steps given by
    hand: the scene's automatic ones would otherwise step inside the drag spring's limit too.)"""
    outcome = {}
    for integrator in ("semi_implicit_euler", "implicit_euler"):
        s = Session(get_scene("teapot"), dict(RESTING_TEAPOT, integrator=integrator), device="cpu", substeps=10)
        s.drag_stiffness = 1.0e4
        x = s.items["teapot"].points
        s.grab("teapot", int(np.argmax(x[:, 1])))
        x0 = s.grabbed_position()
        for k in range(1, 21):
            s.drag_to(x0 + [0.0, 0.005 * k, 0.0])
            if not s.advance() or s.exploding:  # a blow-up is shown for a moment, then pauses
                break
        error = s.error or (str(s.exploding["error"]) if s.exploding else None)
        outcome[integrator] = (error, s.grabbed_position() if error is None else None, x0)
    assert outcome["semi_implicit_euler"][0] is not None and "blew up" in outcome["semi_implicit_euler"][0]
    err, x1, x0 = outcome["implicit_euler"]
    assert err is None
    assert abs(x1[1] - (x0[1] + 0.1)) < 0.03  # it followed the target up 10 cm


def test_blow_up_pauses_and_keeps_the_message(tmp_path):
    s = Session(get_scene("springs"), {"dt": "0.05", "stiffness": "4000"}, device="cpu", record_dir=str(tmp_path))
    s.start_recording()
    for _ in range(50):
        if not s.advance():
            break
    assert s.error is not None and "blew up" in s.error and not s.playing
    assert s.recorder is None and validate_cache(s.last_recording) == []  # the recording was completed
    assert not s.advance()  # stays paused until reset
    s.set_param("dt", 1 / 480)  # a rebuild clears the failure
    assert s.error is None and s.advance()


def test_playback_reads_flattened_caches(tmp_path):
    out = io.StringIO()
    assert cli.main(["run", "bounce", "--frames", "30", "--flatten", "--no-progress", "--out",
                     str(tmp_path / "b.usda")], out, io.StringIO()) == 0
    reader = CacheReader(str(tmp_path / "b.usdc"))
    assert len(reader) == 31 == cache_info(str(tmp_path / "b.usdc"))["frames"]
    y = [reader.items(i)["ball"].points[0, 1] for i in (0, 1)]
    assert y == pytest.approx([0.04, 0.024304], abs=1e-6)  # the seed's frame table


def test_view_command_usage_errors():
    err = io.StringIO()
    assert cli.main(["view", "teapott"], io.StringIO(), err) == 2 and "unknown scene 'teapott'" in err.getvalue()
    err = io.StringIO()
    assert cli.main(["view", "teapot", "--set", "stifness=3"], io.StringIO(), err) == 2
    assert "no parameter 'stifness'" in err.getvalue() and "stiffness" in err.getvalue()
    err = io.StringIO()
    assert cli.main(["view", "missing.usda"], io.StringIO(), err) == 2 and "missing.usda" in err.getvalue()
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        err = io.StringIO()
        assert cli.main(["view", "bounce", "--port", str(port)], io.StringIO(), err) == 2
    line = err.getvalue().strip()
    assert line.count("\n") == 0 and f"port {port}" in line and "try --port" in line
    free = int(line.rsplit("--port", 1)[1])
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", free))  # the port it names is free


def test_viewer_sink_subsamples_large_point_sets():
    sink = ViewerSink(max_points=1000)
    sink.add_points("p", radius=0.01)
    pts = np.random.default_rng(0).random((10_000, 3)).astype(np.float32)
    item = sink.draw({"p": {"points": pts, "velocities": pts}})["p"]
    assert len(item.points) == 1000 and np.array_equal(item.points, pts[item.shown])


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_python_viewer_of_a_simulator_the_caller_steps():
    """ws.Viewer(sim): the caller steps, update() draws; the mouse drag works on its particles."""
    import warpsim as ws

    b = ws.ModelBuilder()
    b.add_particle((0.0, 1.0, 0.0), mass=0.0)
    b.add_particle((0.1, 1.0, 0.0), mass=0.1, radius=0.02)
    b.add_spring(0, 1, 50.0, 0.1)
    sim = ws.Simulator(b.finalize(device="cpu"), forces=[ws.Gravity()])
    viewer = ws.Viewer(sim, port=_free_port()).start()
    try:
        assert viewer.session.playing is False and set(viewer.session.items) == {"particles", "springs"}
        for _ in range(10):
            sim.step(1 / 60)
        viewer.update()
        np.testing.assert_allclose(viewer.session.items["particles"].points, sim.state.positions.numpy(), atol=0)
        assert viewer.session.grab("particles", 0) == -1  # pinned: not grabbable
        assert viewer.session.grab("particles", 1) == 1
        viewer.session.drag_to((0.5, 1.0, 0.0))
        for _ in range(120):
            sim.step(1 / 240)
        assert sim.state.positions.numpy()[1, 0] > 0.15  # pulled toward x = 0.5 against the spring
    finally:
        viewer.stop()


def test_playback_viewer_serves_and_advances(tmp_path):
    from warpsim.viewer.playback import PlaybackViewer

    assert cli.main(["run", "springs", "--frames", "12", "--chunk", "5", "--no-progress", "--out",
                     str(tmp_path / "s.usda")], io.StringIO(), io.StringIO()) == 0
    pv = PlaybackViewer(str(tmp_path / "s.usda"), port=_free_port()).start()
    try:
        import time

        t0 = time.time()
        while pv._shown in (None, 0) and time.time() - t0 < 10:
            time.sleep(0.05)
        assert pv._shown not in (None, 0)  # playing at the cache's fps, frames read as shown
        pv.playing = False
        pv.show(12)
        chain = pv.reader.items(12)["masses"].points
        assert chain[-1, 1] < chain[0, 1]  # the chain has swung down from the horizontal
    finally:
        pv.stop()


def test_live_wind_pushes_the_cloth_downwind():
    """cloth/drape's wind is live: turned on mid-run it pushes the sheet along +z, against a run
    without it; at 0 its force is exactly zero (coefficient 0), so the default scene is unchanged."""
    cls = get_scene("drape")
    calm, windy = (Session(cls, {"resolution": 6}, device="cpu") for _ in range(2))
    for s in (calm, windy):
        for _ in range(5):
            s.advance()
    wind = calm.scene.wind
    f = wp.zeros(calm.scene.sim.model.particle_count, dtype=wp.vec3, device="cpu")
    st = calm.scene.sim.state
    wind.eval(st.positions, st.velocities, calm.scene.sim._time, 0.0, f)
    assert not f.numpy().any()  # no force at all while calm, whatever the velocities
    assert windy.set_param("wind", 8.0) == "live" and windy.frame == 5
    for _ in range(20):
        calm.advance()
        windy.advance()
    dz = windy.scene.sim.state.positions.numpy()[:, 2].mean() - calm.scene.sim.state.positions.numpy()[:, 2].mean()
    assert dz > 0.02  # [m] downwind after 1/3 s


def test_the_rate_readout_follows_a_slow_scene_at_once():
    """A frame that takes far longer than the smoothing window replaces the estimate (the readout
    said 0.2-0.6 sim s per wall s for many 3.5 s frames after a change to mass 0.001), and a
    rebuild measures afresh."""
    s = Session(get_scene("bounce"), {}, device="cpu")
    for _ in range(20):
        s.measure(1, s.frame_dt)  # real time: 1 sim s per wall s
    assert s.sim_rate == pytest.approx(1.0)
    s.measure(1, 100.0 * s.frame_dt)
    assert s.sim_rate == pytest.approx(0.01, rel=0.05)  # not 0.7 x 1 + 0.3 x 0.01
    s.set_param("height", 0.08)  # rebuilt
    assert s.sim_rate == 0.0
    from warpsim.viewer.controls import format_status

    assert "0.00123 sim s per wall s" in format_status({**s.status(), "sim_rate": 0.00123})


def test_pause_answers_while_a_frame_is_being_simulated():
    """Pause does not wait for the lock a slow frame holds (3.5 s at mass 0.001): the stepping
    loop reads the flag before the next frame."""
    import threading

    s = Session(get_scene("bounce"), {}, device="cpu")
    held, done = threading.Event(), threading.Event()

    def slow_frame():
        with s.lock:
            held.set()
            done.wait(60.0)

    t = threading.Thread(target=slow_frame)
    t.start()
    held.wait(10.0)
    pauser = threading.Thread(target=s.set_playing, args=(False,))
    pauser.start()
    pauser.join(30.0)
    paused_while_held = not pauser.is_alive() and not s.playing and not done.is_set()
    done.set()
    t.join()
    assert paused_while_held


def test_ctrl_c_on_the_viewer_does_not_claim_frames(monkeypatch):
    """Ctrl-C before the viewer serves (building, compiling): 'interrupted', exit 130, and no word
    of frames written (it writes none); a run keeps saying its frames are kept."""

    from warpsim.viewer import command as view_command

    def interrupted(*_):
        raise KeyboardInterrupt

    monkeypatch.setattr(view_command, "run", interrupted)
    err = io.StringIO()
    assert cli.main(["view", "bounce", "--device", "cpu"], out=io.StringIO(), err=err) == 130
    assert err.getvalue().strip() == "warpsim: interrupted"
    from warpsim.commands import run as run_command

    monkeypatch.setattr(run_command, "run", interrupted)
    err = io.StringIO()
    assert cli.main(["run", "bounce", "--frames", "1"], out=io.StringIO(), err=err) == 130
    assert "the frames written so far are kept" in err.getvalue()


def test_pause_between_sub_steps_resumes_the_same_frame():
    """A Pause during a frame stops after the sub-step under way (the flag is read between
    sub-steps) and the frame resumes there: the same steps, the same bits as frames not paused."""
    params = {"stiffness": "4000"}
    whole = Session(get_scene("springs"), params, device="cpu")
    for _ in range(3):
        assert whole.advance()
    s = Session(get_scene("springs"), params, device="cpu")
    n = s.scene.frame_steps(s.frame_dt, s.substeps)
    assert n >= 4
    step, calls = s.scene.sim.step, []

    def stepping(pause_after):
        def counted(h):  # a Pause click arriving while sub-step ``pause_after`` runs
            step(h)
            calls.append(h)
            if len(calls) == pause_after:
                s.set_playing(False)
        return counted

    s.scene.sim.step = stepping(3)
    assert not s.advance(interruptible=True) and s.frame == 0 and len(calls) == 3  # stopped inside frame 1
    s.set_playing(True)
    assert s.advance(interruptible=True) and s.frame == 1 and len(calls) == n  # resumed: the frame's other n - 3 steps
    assert s.advance(interruptible=True) and s.frame == 2
    calls.clear()
    s.scene.sim.step = stepping(2)
    assert not s.advance(interruptible=True) and s.frame == 2  # paused inside frame 3
    assert s.step_once() and s.frame == 3 and len(calls) == n  # Step finishes that frame
    assert np.array_equal(s.scene.sim.state.positions.numpy(), whole.scene.sim.state.positions.numpy())
    assert np.array_equal(s.scene.sim.state.velocities.numpy(), whole.scene.sim.state.velocities.numpy())


def test_the_viewer_prints_no_server_banner(capfd):
    """viser's address box and its 'Server stopped' line stay out of the output (``warpsim view``
    prints the URL once itself); ``verbose=True`` lets them through."""
    from warpsim.viewer.server import Viewer

    for verbose in (False, True):
        v = Viewer("bounce", device="cpu", port=_free_port(), paused=True, verbose=verbose).start()
        v.stop()
        said = capfd.readouterr().out
        assert (str(v.port) in said and "Server stopped" in said) == verbose, said
