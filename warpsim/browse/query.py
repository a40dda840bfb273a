"""Spacetime queries over an occupancy record: IN / NOT IN a box during a window.

``--inside "x0,y0,z0,x1,y1,z1@t0:t1"`` keeps the worlds in which some recorded particle is
inside the box (corners [m], inclusive) at some frame of the window (seconds; frame f lies at
f / fps; ``@t0:`` runs to the end, ``@:t1`` from the start, no ``@`` the whole run);
``--outside`` keeps the worlds in which none is. Regions combine with AND. Each ``--inside``
(the k-th, counted from 1) adds columns a world can be ranked or filtered by:

  insideK_time    time inside during the window [s] (frames with a particle inside / fps)
  insideK_entry   first time inside during the window [s] (nan: never)
  insideK_share   largest share of the world's recorded particles inside at one frame of the
                  window, in [0, 1] (exact answers only; nan otherwise)

Answers come from the cells of :class:`warpsim.browse.occupancy.OccupancyRecord`: conservative to
one cell (a world whose particles come within one cell of the box may be kept by IN and dropped
by NOT IN). The worlds the cells leave in doubt are then decided exactly where that is cheap:
from the exact positions the record keeps (few particles per world), or else read back from the
sweep's USD cache (:class:`CachedPositions`) when at most :data:`REFINE_BUDGET` world-frames
are in doubt. Each answer says whether it is exact.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from .occupancy import parse_bounds

__all__ = ["CachedPositions", "Region", "RegionAnswer", "answer_region", "answers_note", "apply_regions",
           "cached_positions", "check_window", "parse_region", "region_columns"]


@dataclass(frozen=True)
class Region:
    """A box lo..hi [m] during t0..t1 [s] (None: open end); ``inside`` True for IN, False for NOT IN."""

    inside: bool
    lo: tuple
    hi: tuple
    t0: float | None
    t1: float | None
    text: str

    @property
    def flag(self) -> str:
        return "--inside" if self.inside else "--outside"


NEGATIVE_START = re.compile(r"^-\d*\.?\d+([eE][-+]?\d+)?(,|@|$)")
"""Arguments argparse must read as values, not options: ``-0.1,0,0,...`` (a box whose first
corner is negative). Set as a parser's ``_negative_number_matcher`` (see :func:`accept_negative_boxes`)."""


def accept_negative_boxes(parser):
    """Let ``--inside -0.1,0,0,0.1,1,0.1@0:1`` parse (argparse takes a leading '-' for an option
    unless the whole word is a negative number); ``--inside=...`` always works."""
    parser._negative_number_matcher = NEGATIVE_START
    return parser


def parse_region(text, inside=True) -> Region:
    """A :class:`Region` from ``"x0,y0,z0,x1,y1,z1[@t0:t1]"``; ValueError (one line) naming the item."""
    flag = "--inside" if inside else "--outside"
    text = str(text).strip()
    box, at, window = text.partition("@")
    lo, hi = parse_bounds(box, f"{flag} box")
    t0 = t1 = None
    if at:
        a, colon, b = window.partition(":")
        if not colon:
            raise ValueError(f"{flag} {text!r}: write the window as @T0:T1 in seconds (e.g. @0.5:1), or leave it out "
                             "for the whole run")
        try:
            t0 = float(a) if a.strip() else None
            t1 = float(b) if b.strip() else None
        except ValueError:
            raise ValueError(f"{flag} {text!r}: the window {window!r} is not T0:T1 in seconds") from None
        for t in (t0, t1):
            if t is not None and not math.isfinite(t):
                raise ValueError(f"{flag} {text!r}: window times must be finite seconds")
        if t0 is not None and t1 is not None and t1 < t0:
            raise ValueError(f"{flag} {text!r}: the window ends ({t1:g} s) before it starts ({t0:g} s); give T0 <= T1")
    return Region(bool(inside), tuple(lo), tuple(hi), t0, t1, text)


def check_window(region, fps, frame_count, first_frame=0):
    """(f0, f1): the first and last frame index (from ``first_frame``) inside the region's
    window; ValueError when the window misses every frame of the run (0 .. (F - 1) / fps s)."""
    end = (first_frame + frame_count - 1) / fps
    t0 = first_frame / fps if region.t0 is None else region.t0
    t1 = end if region.t1 is None else region.t1
    tol = 1e-9 * max(1.0, abs(end))
    if t1 < first_frame / fps - tol or t0 > end + tol:
        raise ValueError(f"{region.flag} {region.text!r}: the window {t0:g}..{t1:g} s is outside the sweep's time "
                         f"{first_frame / fps:g}..{end:g} s ({frame_count} frames at {fps:g} fps)")
    f0 = max(math.ceil(t0 * fps - 1e-6), first_frame) - first_frame
    f1 = min(math.floor(t1 * fps + 1e-6), first_frame + frame_count - 1) - first_frame
    if f1 < f0:
        raise ValueError(f"{region.flag} {region.text!r}: no frame lies in {t0:g}..{t1:g} s (frames every "
                         f"{1 / fps:g} s); widen the window")
    return f0, f1


def answers_note(record, regions, answers) -> str:
    """One line saying how exact the answers are."""
    loose = [r.flag for r, a in zip(regions, answers) if not a.exact]
    if not loose:
        return "answers: exact (" + ("the record's positions" if record.exact else "the cached positions") + ")"
    return (f"answers: conservative to one cell ({record.grid.cell_size:.3g} m) for {', '.join(loose)} (too many "
            "worlds in doubt to read back, or no cached points of the recorded particles); --track a few "
            "particles for exact answers")


def region_columns(regions) -> list:
    """Names of the columns the ``--inside`` regions add (see the module docstring)."""
    names = []
    k = 0
    for r in regions:
        if r.inside:
            k += 1
            names += [f"inside{k}_time", f"inside{k}_entry", f"inside{k}_share"]
    return names


@dataclass
class RegionAnswer:
    """Per world of a record: ``match`` (IN: inside at some frame of the window; NOT IN: never),
    ``time`` [s], ``entry`` [s] (nan: never inside), ``share`` in [0, 1] (nan: no exact positions),
    ``exact`` (whether decided from exact positions)."""

    match: np.ndarray
    time: np.ndarray
    entry: np.ndarray
    share: np.ndarray
    exact: bool


def _cell_hits(record, region, f0, f1):
    """(W, F_window) bool: frames of the window at which a world occupies a cell the box touches."""
    W = record.world_count
    nwords = record.pair_bits.shape[1]
    window = np.zeros(nwords * 32, dtype=bool)
    window[f0:f1 + 1] = True
    wmask = np.packbits(window, bitorder="little").view(np.uint32)
    touched = record.grid.box_cells(region.lo, region.hi)
    sel = np.flatnonzero(touched[record.pair_cell])
    sub = record.pair_bits[sel] & wmask
    keep = sub.any(axis=1)
    sel, sub = sel[keep], sub[keep]
    hits = np.zeros((W, nwords), dtype=np.uint32)
    if len(sel):
        worlds = record.pair_world[sel]
        starts = np.flatnonzero(np.r_[True, worlds[1:] != worlds[:-1]])
        hits[worlds[starts]] = np.bitwise_or.reduceat(sub, starts, axis=0)
    frames = np.unpackbits(hits.view(np.uint8), axis=1, bitorder="little").astype(bool)
    return frames[:, f0:f1 + 1]


REFINE_BUDGET = 20_000
"""World-frames of cached positions read at most to refine one answer (beyond: cells only)."""


class CachedPositions:
    """The recorded particles' positions read back from a sweep's batch layers (the points of
    the record's ``source_prim``): ``positions(world, f0, f1)`` -> (f1 - f0 + 1, K, 3) float32 for
    the record's world index ``world`` and frames f0..f1 counted from its first frame."""

    def __init__(self, root, record):
        from .roots import sweep_root_files

        self.owner = dict(sweep_root_files(root)["worlds"])
        self.record = record
        self._layers = {}

    def __call__(self, world, f0, f1):
        from pxr import Usd

        g = self.record.first_world + int(world)
        path = self.owner[g]
        stage = self._layers.get(path)
        if stage is None:  # a stage, not the layer: batch layers keep their samples in chunk files (clips)
            stage = self._layers[path] = Usd.Stage.Open(path)
            stage.SetInterpolationType(Usd.InterpolationTypeHeld)  # no sample at a frame: the one from before
        prim = stage.GetPrimAtPath(f"/Worlds/world_{g:06d}/{self.record.source_prim}")
        attr = prim.GetAttribute("points") if prim else None
        out = []
        for f in range(self.record.first_frame + f0, self.record.first_frame + f1 + 1):
            value = attr.Get(float(f)) if attr else None
            if value is None:
                raise ValueError(f"world {g} has no cached {self.record.source_prim} points at frame {f}")
            out.append(np.asarray(value, np.float32)[self.record.particles])
        return np.stack(out)


def cached_positions(root, record):
    """A :class:`CachedPositions` for a record that keeps no exact positions but whose
    particles are found in the cache (``record.source_prim``); None otherwise."""
    if record.exact or not record.source_prim:
        return None
    return CachedPositions(root, record)


def answer_region(record, region, positions=None, budget=REFINE_BUDGET) -> RegionAnswer:
    """Answer one region over every world of ``record`` (see the module docstring).
    ``positions``: a :class:`CachedPositions` (or any callable like it) that decides the worlds
    the cells leave in doubt exactly when at most ``budget`` world-frames are in doubt."""
    f0, f1 = check_window(region, record.fps, record.frame_count, record.first_frame)
    frames = _cell_hits(record, region, f0, f1)
    W = record.world_count
    share = np.full(W, np.nan)
    doubt = np.flatnonzero(frames.any(axis=1))
    s = None
    if record.exact:  # decide the worlds the cells leave in doubt from their exact positions
        s = record.samples[doubt, f0:f1 + 1]  # (D, Fw, K, 3)
    elif positions is not None and len(doubt) * (f1 - f0 + 1) <= budget:  # from the cache
        s = np.stack([positions(w, f0, f1) for w in doubt]) if len(doubt) else \
            np.zeros((0, f1 - f0 + 1, len(record.particles), 3), np.float32)
    exact = s is not None
    if s is not None:
        s = s.astype(np.float64)
        inside = ((s >= np.asarray(region.lo)) & (s <= np.asarray(region.hi))).all(axis=-1)
        frames = np.zeros_like(frames)
        frames[doubt] = inside.any(axis=-1)
        share[:] = 0.0
        if inside.shape[-1]:
            share[doubt] = inside.mean(axis=-1).max(axis=-1, initial=0.0)
    count = frames.sum(axis=1)
    ever = count > 0
    entry = np.full(W, np.nan)
    entry[ever] = (record.first_frame + f0 + frames[ever].argmax(axis=1)) / record.fps
    return RegionAnswer(ever if region.inside else ~ever, count / record.fps, entry, share, exact)


def apply_regions(rows, record, regions, positions=None, answers=None):
    """The rows (one per world, ``row["world"]`` its global index) that pass every region, each
    with the columns of :func:`region_columns` added; ValueError for a world the record lacks.
    ``positions``: see :func:`answer_region`; ``answers``: the regions' answers if already made."""
    if not regions:
        return list(rows)
    if answers is None:
        answers = [answer_region(record, r, positions) for r in regions]
    out = []
    names = region_columns(regions)
    for row in rows:
        w = int(row["world"]) - record.first_world
        if not 0 <= w < record.world_count:
            raise ValueError(f"world {row['world']} is not in the occupancy record (worlds {record.first_world}.."
                             f"{record.first_world + record.world_count - 1}); run the sweep again")
        if not all(a.match[w] for a in answers):
            continue
        extra, k = {}, 0
        for r, a in zip(regions, answers):
            if r.inside:
                extra.update({names[3 * k]: float(a.time[w]), names[3 * k + 1]: float(a.entry[w]),
                              names[3 * k + 2]: float(a.share[w])})
                k += 1
        out.append({**row, **extra})
    return out
