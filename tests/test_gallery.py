"""The README's gallery (``docs/SCENE.gif``, made by ``python -m warpsim.render.gallery``): every
registered scene has a clip and a GIF, and each GIF's camera frames its subject. The subject is
what moves: the pixels that change during the clip (the camera and the background are fixed). Its
bounding box must cover a fair share of the frame, and the middle frame must show it there (a
clip framed on a floor or on debris metres away shows the subject as a speck: the wall and bounce
GIFs before the robust framing had boxes of 11 % and 1 % of the frame)."""

import pathlib

import numpy as np
import pytest

from warpsim.render import gallery
from warpsim.scenes import scenes

DOCS = pathlib.Path(__file__).resolve().parents[1] / "docs"
MIN_SHARE = 0.15  # of the frame's area (new framing: 0.17 (crowd) .. 0.60 (pour))
CHANGED = 24  # an 8-bit change that GIF quantisation of a still background never makes


def clip_frames(path):
    from PIL import Image

    with Image.open(path) as im:
        frames = []
        for k in range(im.n_frames):
            im.seek(k)
            frames.append(np.asarray(im.convert("RGB")).astype(np.int16))
    return np.stack(frames)


def test_every_scene_has_a_clip_and_a_gif():
    names = {n for n, cls in scenes().items() if cls.__module__.startswith("warpsim.")}  # not tests' own scenes
    assert names <= set(gallery.CLIPS), f"scenes without a gallery clip: {sorted(names - set(gallery.CLIPS))}"
    missing = [n for n in names if not (DOCS / f"{n}.gif").is_file()]
    assert not missing, f"run python -m warpsim.render.gallery --scenes {' '.join(sorted(missing))}"


@pytest.mark.parametrize("name", sorted(gallery.CLIPS))
def test_gif_frames_its_subject(name):
    path = DOCS / f"{name}.gif"
    if not path.is_file():
        pytest.skip(f"{path.name} not made yet (see test_every_scene_has_a_clip_and_a_gif)")
    frames = clip_frames(path)
    assert frames.shape[1:3] == (gallery.SIZE[1], gallery.SIZE[0]) and len(frames) >= 2
    moving = (frames.max(0) - frames.min(0)).max(-1) > CHANGED
    ys, xs = np.nonzero(moving)
    assert len(xs), f"{name}: nothing moves in the clip"
    h, w = moving.shape
    box = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
    share = (np.ptp(ys) + 1) * (np.ptp(xs) + 1) / (h * w)
    assert share >= MIN_SHARE, f"{name}: the subject's box covers {share:.0%} of the frame"
    middle = frames[len(frames) // 2]
    differs = np.abs(middle - frames[0]).max(-1) > CHANGED  # the subject has moved or changed by then
    shown = moving[box] & (differs[box] | (np.abs(middle - np.median(frames, 0)).max(-1)[box] > CHANGED))
    assert shown.any(), f"{name}: the middle frame shows nothing of the subject"
