"""The worlds/ split (issue 41): the names ``warpsim.worlds`` exported before still resolve there,
to the very objects of their new packages, and nothing else does; ``--track`` takes a scene's
named particles through the scene's own hook (``Scene.track_anchors`` / ``anchor_particle``), not
a check of the scene's name in the sweep command."""

import pytest

import warpsim.browse
import warpsim.sweeps
import warpsim.worlds
from warpsim.scenes import get_scene
from warpsim.sweeps.command import resolve_track

MOVED = {"run_batch": warpsim.sweeps, "sample_worlds": warpsim.sweeps, "write_table": warpsim.sweeps,
         "write_sweep_root": warpsim.sweeps, "UserMetric": warpsim.sweeps, "WorldMetrics": warpsim.sweeps,
         "rerun_world": warpsim.sweeps, "OccupancyRecord": warpsim.browse, "OccupancyRecorder": warpsim.browse,
         "Region": warpsim.browse, "answer_region": warpsim.browse, "parse_region": warpsim.browse,
         "pick_world": warpsim.browse}


@pytest.mark.parametrize("name", sorted(MOVED))
def test_a_moved_name_resolves_in_worlds_to_its_new_home(name):
    assert getattr(warpsim.worlds, name) is getattr(MOVED[name], name)
    assert name in MOVED[name].__all__


def test_worlds_invents_no_names():
    with pytest.raises(AttributeError, match="no attribute 'run_sweep'"):
        warpsim.worlds.run_sweep  # noqa: B018


def test_track_takes_the_scenes_anchors_and_indices():
    from warpsim.scenes.teapot import ANCHORS, anchor_vertex

    cls = get_scene("teapot")
    params = cls.resolve_params({"resolution": 3, "springs": False})
    scene = cls(params, device="cpu")
    assert cls.track_anchors == ANCHORS
    expected = {name: anchor_vertex(scene.rest_points, name) for name in ANCHORS}
    assert resolve_track(cls, params, [*ANCHORS, "tip=7", "12"], "cpu") == {**expected, "tip": 7, "p12": 12}
    with pytest.raises(ValueError, match="not an index or one of spout, handle, knob, bottom"):
        resolve_track(cls, params, ["lid"], "cpu")


def test_a_scene_without_anchors_asks_for_an_index():
    cls = get_scene("bounce")
    assert cls.track_anchors == ()
    assert resolve_track(cls, cls.resolve_params({}), ["ball=0"], "cpu") == {"ball": 0}
    with pytest.raises(ValueError, match=r"--track 'spout': give a particle index \(NAME=INDEX\)"):
        resolve_track(cls, cls.resolve_params({}), ["spout"], "cpu")
    with pytest.raises(ValueError, match="has no anchor 'spout'"):
        cls(cls.resolve_params({}), device="cpu").anchor_particle("spout")
