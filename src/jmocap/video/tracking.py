"""Following people across the frames of a video: one track per person.

MediaPipe's scheme, extended to several people. Per frame:

1. every live track runs the landmark model on the region its previous frame's landmarks give
   (the auxiliary alignment points, :meth:`LandmarkResult.next_roi`); a pose-presence score
   below ``min_presence`` (MediaPipe's 0.5) loses the track for that frame;
2. two live tracks that now cover the same person (their regions overlap by more than
   ``duplicate_iou``) are one: the younger one ends;
3. the detector runs on the first frame, whenever a track is lost, when nobody is tracked, and
   every ``detect_every`` frames (to find people who walk in). A detection whose region overlaps
   a track followed in this frame by more than ``match_iou`` is that track. Otherwise the
   landmark model runs on it; a pose found there resumes the lost track it overlaps best (more
   than ``match_iou`` with the track's last region), else starts a new track;
4. a track lost for more than ``max_gap`` frames ends; the same person found later starts a new
   track (the track is split). Shorter gaps are *bridged*: the track keeps its identity and the
   frames in between are written as missing (confidence 0).

Tracks with fewer than ``min_frames`` frames with a pose are dropped at the end. Regions are
compared by the IoU of their axis-aligned bounding boxes (the rotated square of
:func:`~jmocap.video.blazepose.roi_from_points`, centred on the hips, 1.25 x the body's
diameter a side). The estimator is anything with BlazePose's ``detect(frame, min_score)`` and
``landmarks(frame, roi)`` (the tests drive the logic with synthetic streams).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from jmocap.video.blazepose import LandmarkResult, Roi, iou

__all__ = ["Track", "TrackOptions", "track_people"]


@dataclass(frozen=True)
class TrackOptions:
    """Options of :func:`track_people` (defaults: MediaPipe's thresholds)."""

    min_detection_score: float = 0.5  # detector score to accept a person
    min_presence: float = 0.5  # pose-presence score below which a track is lost
    detect_every: int = 15  # run the detector every N frames to find new people (0: never)
    max_gap: int = 15  # frames a track may be lost and still be bridged (longer: split)
    min_frames: int = 10  # tracks with fewer frames with a pose are dropped
    match_iou: float = 0.3  # a detection overlapping a track's region by more is that track
    duplicate_iou: float = 0.6  # two tracks overlapping by more follow the same person
    max_tracks: int = 20  # live tracks at most (more detections are ignored)

    def __post_init__(self):
        for name in ("min_detection_score", "min_presence", "match_iou", "duplicate_iou"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"TrackOptions.{name} must be in [0, 1], got {v}")
        for name in ("detect_every", "max_gap", "min_frames"):
            if getattr(self, name) < 0:
                raise ValueError(f"TrackOptions.{name} must be >= 0, got {getattr(self, name)}")
        if self.max_tracks < 1:
            raise ValueError(f"TrackOptions.max_tracks must be >= 1, got {self.max_tracks}")

    def replace(self, **changes) -> TrackOptions:
        return dataclasses.replace(self, **changes)


@dataclass
class Track:
    """One person over the frames where the landmark model found them.

    ``frames`` (increasing frame numbers) and ``results`` (a :class:`LandmarkResult` per frame)
    are parallel; ``start``/``end`` the first and last frame; frames in between without a pose
    are the track's gaps (all shorter than ``max_gap``)."""

    id: int
    frames: list[int] = field(default_factory=list)
    results: list[LandmarkResult] = field(default_factory=list)
    next_roi: Roi | None = None  # where to look in the next frame (None: lost)
    ended: bool = False

    @property
    def start(self) -> int:
        return self.frames[0]

    @property
    def end(self) -> int:
        return self.frames[-1]

    def add(self, t: int, r: LandmarkResult) -> None:
        self.frames.append(t)
        self.results.append(r)
        self.next_roi = r.next_roi()

    def region_box(self) -> np.ndarray:
        """Bounding box of the region the last frame's landmarks give."""
        return self.results[-1].next_roi().box()

    @property
    def missing_frames(self) -> int:
        """Frames between ``start`` and ``end`` without a pose."""
        return self.end - self.start + 1 - len(self.frames)

    def size(self) -> float:
        """Sum over its frames of the body's diameter in pixels (2 x the distance of the
        alignment points): how large and how long the person is seen."""
        return float(sum(r.next_roi().size / 1.25 for r in self.results))


def track_people(frames: Iterable, estimator, options: TrackOptions = TrackOptions(),
                 progress: Callable[[int], None] | None = None) -> tuple[list[Track], dict]:
    """Track every person through ``frames`` (an iterable of frames, consumed once: a video is
    streamed). Returns the tracks with at least ``min_frames`` poses, ordered by first frame and
    then by their first hip centre's x, and statistics: ``frames``, ``detector_runs``,
    ``landmark_runs``, ``tracks_dropped`` (too short), ``lost_events`` (a track lost in a frame).
    ``progress(t)`` is called after each frame."""
    o = options
    tracks: list[Track] = []
    stats = {"frames": 0, "detector_runs": 0, "landmark_runs": 0, "lost_events": 0}
    for t, frame in enumerate(frames):
        live = [tr for tr in tracks if not tr.ended]
        followed: list[Track] = []
        # 1. follow the live tracks from their previous frame's landmarks
        for tr in live:
            if tr.next_roi is None:
                continue
            r = estimator.landmarks(frame, tr.next_roi)
            stats["landmark_runs"] += 1
            if r.score >= o.min_presence:
                tr.add(t, r)
                followed.append(tr)
            else:
                tr.next_roi = None
                stats["lost_events"] += 1
        # 2. two tracks on one person: the younger one ends
        for a in list(followed):
            for b in list(followed):
                if a.id < b.id and b in followed and a in followed and \
                        iou(a.region_box(), b.region_box()) > o.duplicate_iou:
                    _drop_last(b)
                    b.ended = True
                    followed.remove(b)
        # 3. detection
        lost = [tr for tr in tracks if not tr.ended and tr.next_roi is None]
        if t == 0 or lost or not followed or (o.detect_every and t % o.detect_every == 0):
            stats["detector_runs"] += 1
            for d in estimator.detect(frame, o.min_detection_score):
                box = d.roi().box()
                if any(iou(box, tr.region_box()) > o.match_iou for tr in followed):
                    continue
                r = estimator.landmarks(frame, d.roi())
                stats["landmark_runs"] += 1
                if r.score < o.min_presence:
                    continue
                rbox = r.next_roi().box()
                if any(iou(rbox, tr.region_box()) > o.match_iou for tr in followed):
                    continue
                best, best_iou = None, o.match_iou
                for tr in lost:
                    v = iou(rbox, tr.region_box())
                    if v > best_iou:
                        best, best_iou = tr, v
                if best is not None:
                    lost.remove(best)
                    best.add(t, r)
                    followed.append(best)
                elif sum(not tr.ended for tr in tracks) < o.max_tracks:
                    tr = Track(id=len(tracks))
                    tr.add(t, r)
                    tracks.append(tr)
                    followed.append(tr)
        # 4. tracks lost too long end
        for tr in tracks:
            if not tr.ended and tr.next_roi is None and t - tr.end > o.max_gap:
                tr.ended = True
        stats["frames"] = t + 1
        if progress is not None:
            progress(t)
    kept = [tr for tr in tracks if len(tr.frames) >= max(1, o.min_frames)]
    stats["tracks_dropped"] = len(tracks) - len(kept)
    kept.sort(key=lambda tr: (tr.start, float(tr.results[0].points[33, 0])))
    return kept, stats


def _drop_last(tr: Track) -> None:
    """Remove the frame just added to a track that turned out to duplicate another."""
    tr.frames.pop()
    tr.results.pop()
    tr.next_roi = tr.results[-1].next_roi() if tr.results else None
