"""jmocap.video without the models: SSD anchors, box and keypoint decoding, weighted NMS, the
region of interest and its affine crop, heatmap refinement, BlazePose -> BODY_25, the flip
Viterbi and the tracker's lost / bridged / split logic on synthetic landmark streams.

Every reference is worked by hand from MediaPipe's published settings (docstrings of
``jmocap.video.blazepose``); the tracker runs against a scripted estimator whose people are
known. Only the crop test needs OpenCV (the video extra); the rest is numpy.
"""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest

from jmocap.layouts import BODY25
from jmocap.video import blazepose as bp
from jmocap.video.blazepose import (
    BLAZEPOSE_NAMES,
    Detection,
    LandmarkResult,
    Roi,
    affine_for_roi,
    apply_affine,
    decode_detections,
    refine_from_heatmap,
    roi_from_points,
    ssd_anchors,
    weighted_nms,
)
from jmocap.video.extract import choose_tracks
from jmocap.video.flips import LIMB_PAIRS, LR_PAIRS, repair_flips, swap_left_right
from jmocap.video.mapping import to_body25
from jmocap.video.tracking import TrackOptions, track_people

N = BLAZEPOSE_NAMES.index


# =========================================================================================
# detector geometry
# =========================================================================================


def test_anchors_count_and_centres_by_hand():
    a = ssd_anchors()
    assert a.shape == (2254, 2)  # 28*28*2 + 14*14*2 + 7*7*6
    # stride 8: 28 cells a side, two anchors per cell, row-major (x fastest)
    np.testing.assert_allclose(a[0], [0.5 / 28, 0.5 / 28])
    np.testing.assert_allclose(a[1], [0.5 / 28, 0.5 / 28])
    np.testing.assert_allclose(a[2], [1.5 / 28, 0.5 / 28])
    np.testing.assert_allclose(a[56], [0.5 / 28, 1.5 / 28])  # second row
    # stride 16 starts after 1568 anchors
    np.testing.assert_allclose(a[1567], [27.5 / 28, 27.5 / 28])
    np.testing.assert_allclose(a[1568], [0.5 / 14, 0.5 / 14])
    # the three stride-32 layers share one 7 x 7 map: 6 anchors per cell
    np.testing.assert_allclose(a[1960:1966], np.tile([0.5 / 7, 0.5 / 7], (6, 1)))
    np.testing.assert_allclose(a[1966], [1.5 / 7, 0.5 / 7])
    np.testing.assert_allclose(a[-6:], np.tile([6.5 / 7, 6.5 / 7], (6, 1)))


def test_decode_box_keypoints_and_clipped_score():
    anchors = np.array([[0.5, 0.5], [0.25, 0.75]])
    raw = np.zeros((2, 12))
    # anchor 0: centre +(22.4, -11.2) px of 224 -> (0.6, 0.45); size (44.8, 89.6) px -> (0.2, 0.4)
    raw[0, :4] = [22.4, -11.2, 44.8, 89.6]
    raw[0, 4:12] = [0, 0, 0, -44.8, 11.2, -22.4, 0, -33.6]  # 4 keypoints relative to the anchor
    scores, boxes, kps = decode_detections(raw, np.array([0.0, 200.0]), anchors)
    np.testing.assert_allclose(boxes[0], [0.5, 0.25, 0.7, 0.65])
    np.testing.assert_allclose(kps[0], [[0.5, 0.5], [0.5, 0.3], [0.55, 0.4], [0.5, 0.35]])
    np.testing.assert_allclose(boxes[1], [0.25, 0.75, 0.25, 0.75])  # zero-size box at its anchor
    assert scores[0] == pytest.approx(0.5)
    assert scores[1] == pytest.approx(1.0 / (1.0 + math.exp(-100.0)))  # logit clipped to 100


def test_weighted_nms_merges_overlaps_with_score_weights():
    boxes = np.array([[0.0, 0.0, 1.0, 1.0], [0.1, 0.0, 1.1, 1.0], [3.0, 3.0, 4.0, 4.0]])
    kps = np.array([[[0.0, 0.0]], [[1.0, 1.0]], [[5.0, 5.0]]])
    scores = np.array([0.9, 0.6, 0.7])
    out = weighted_nms(scores, boxes, kps, threshold=0.3)  # IoU(0, 1) = 0.9 / 1.1 > 0.3
    assert [s for s, _, _ in out] == [0.9, 0.7]
    np.testing.assert_allclose(out[0][1], [0.04, 0.0, 1.04, 1.0])  # (0.9 b0 + 0.6 b1) / 1.5
    np.testing.assert_allclose(out[0][2], [[0.4, 0.4]])
    np.testing.assert_allclose(out[1][1], boxes[2])


def test_roi_from_points_by_hand():
    # upright: the scale point 80 px above the hip centre -> side 2 * 80 * 1.25, no rotation
    r = roi_from_points((100.0, 200.0), (100.0, 120.0))
    assert (r.cx, r.cy, r.size) == (100.0, 200.0, 200.0)
    assert r.rotation == pytest.approx(0.0)
    # lying, head to the image right: pi/2 - atan2(0, 80) = pi/2
    assert roi_from_points((100.0, 200.0), (180.0, 200.0)).rotation == pytest.approx(math.pi / 2)
    # head to the left: pi/2 - pi = -pi/2; upside down: pi/2 - (-pi/2) = pi -> normalised to -pi
    assert roi_from_points((100.0, 200.0), (20.0, 200.0)).rotation == pytest.approx(-math.pi / 2)
    assert roi_from_points((100.0, 200.0), (100.0, 280.0)).rotation == pytest.approx(-math.pi)


def test_affine_crop_maps_by_hand():
    M = affine_for_roi(Roi(100.0, 200.0, 200.0, 0.0), 256)
    np.testing.assert_allclose(apply_affine(M, np.array([[128.0, 128.0], [256.0, 128.0], [0.0, 0.0]])),
                               [[100.0, 200.0], [200.0, 200.0], [0.0, 100.0]])
    # rotated by pi/2: the crop's x axis is the image's +y
    M = affine_for_roi(Roi(100.0, 200.0, 200.0, math.pi / 2), 256)
    np.testing.assert_allclose(apply_affine(M, np.array([[256.0, 128.0], [128.0, 0.0]])),
                               [[100.0, 300.0], [200.0, 200.0]], atol=1e-9)


def test_detection_to_roi_round_trip():
    """A detection's hip centre lands in the crop's centre and its scale point 256 / 2.5 crop
    pixels from it, along the crop's up axis, whatever the body's orientation."""
    for angle in (0.0, 0.7, -2.0, math.pi):
        c = np.array([320.0, 240.0])
        up = np.array([math.sin(angle), -math.cos(angle)])  # image direction of the head
        d = Detection(0.9, np.zeros(4), np.stack([c, c + 90.0 * up, c + 40 * up, c + 80 * up]))
        M = affine_for_roi(d.roi(), 256)
        A, t = M[:, :2], M[:, 2]
        crop = np.linalg.solve(A, (d.keypoints[:2] - t).T).T
        np.testing.assert_allclose(crop, [[128.0, 128.0], [128.0, 128.0 - 256 / 2.5]], atol=1e-9)


@pytest.mark.skipif(importlib.util.find_spec("cv2") is None, reason="OpenCV is the video extra: pip install 'jmocap[video]'")
def test_crop_samples_the_image_where_the_affine_map_says():
    """Bilinear sampling of a linear image is exact: crop pixel (u, v) holds f at M(u + 0.5, v + 0.5)."""
    H, W = 120, 160
    yy, xx = np.mgrid[0:H, 0:W] + 0.5  # pixel centres, origin at the image's corner
    f = lambda x, y: 2.0 * x + 3.0 * y  # noqa: E731
    img = np.repeat(f(xx, yy)[..., None], 3, axis=2).astype(np.float32)
    roi = Roi(80.0, 60.0, 64.0, 0.4)
    M = affine_for_roi(roi, 32)
    crop = bp.warp_image(img, M, 32, "replicate")
    g = np.arange(32) + 0.5
    uu, vv = np.meshgrid(g, g)
    p = apply_affine(M, np.stack([uu, vv], -1))
    # OpenCV rounds sample positions to 1/32 pixel: at most (2 + 3) / 64 off on this ramp
    np.testing.assert_allclose(crop[..., 0], f(p[..., 0], p[..., 1]), atol=5 / 64 + 1e-3)
    # zero border: outside the image is black
    far = bp.warp_image(img, affine_for_roi(Roi(-500.0, -500.0, 64.0, 0.0), 32), 32, "zero")
    assert not far.any()


def test_heatmap_refinement_by_hand():
    hm = np.full((64, 64, 2), -20.0, np.float32)
    hm[10, 20, 0] = hm[10, 21, 0] = 20.0  # two confident cells: mean column 20.5
    pts = np.array([[20.2 / 64, 10.3 / 64], [0.5, 0.5]])  # point 1: no confident cell near it
    out = refine_from_heatmap(pts, hm)
    np.testing.assert_allclose(out[0], [20.5 / 64, 10.0 / 64], atol=1e-6)  # MediaPipe: col / width
    np.testing.assert_allclose(out[1], pts[1])
    np.testing.assert_allclose(refine_from_heatmap(pts, hm, cell_offset=0.5)[0], [21.0 / 64, 10.5 / 64], atol=1e-6)


# =========================================================================================
# BlazePose -> BODY_25
# =========================================================================================


def test_body25_mapping_by_hand():
    rng = np.random.default_rng(0)
    P = rng.uniform(10, 500, (33, 2))
    C = rng.uniform(0.2, 1.0, 33)
    kp = to_body25(P, C)
    J = BODY25.joints
    assert kp.shape == (25, 3)
    direct = {"Nose": "nose", "RShoulder": "right_shoulder", "LElbow": "left_elbow", "RWrist": "right_wrist",
              "LHip": "left_hip", "RKnee": "right_knee", "LAnkle": "left_ankle", "REye": "right_eye",
              "LEar": "left_ear", "LBigToe": "left_foot_index", "RBigToe": "right_foot_index",
              "LHeel": "left_heel", "RHeel": "right_heel"}
    for j, b in direct.items():
        np.testing.assert_allclose(kp[J.index(j)], [*P[N(b)], C[N(b)]], rtol=1e-6)
    np.testing.assert_allclose(kp[J.index("Neck"), :2], (P[11] + P[12]) / 2, rtol=1e-6)
    assert kp[J.index("Neck"), 2] == pytest.approx(min(C[11], C[12]))
    np.testing.assert_allclose(kp[J.index("MidHip"), :2], (P[23] + P[24]) / 2, rtol=1e-6)
    for j in ("LSmallToe", "RSmallToe"):  # no BlazePose counterpart: missing
        assert not kp[J.index(j)].any()
    # a landmark with confidence 0 is missing (x = y = 0), as jmocap's readers write it
    C[N("left_knee")] = 0.0
    assert not to_body25(P, C)[J.index("LKnee")].any()


# =========================================================================================
# flip repair
# =========================================================================================


def walker(T=60, period=30.0, seed=0):
    """(T, 33, 2) points of a figure walking to the right: legs and arms swing in antiphase."""
    rng = np.random.default_rng(seed)
    P = np.zeros((T, 33, 2))
    for t in range(T):
        hip = np.array([100.0 + 3.0 * t, 300.0])
        phase = math.sin(2 * math.pi * (t + 0.5) / period)  # no frame exactly at a crossing
        for side, sgn in (("left", 1.0), ("right", -1.0)):
            s = sgn * phase
            P[t, N(f"{side}_hip")] = hip + [0.0, 0.0]
            P[t, N(f"{side}_knee")] = hip + [40 * s, 60]
            P[t, N(f"{side}_ankle")] = hip + [70 * s, 120]
            P[t, N(f"{side}_heel")] = hip + [70 * s - 8, 125]
            P[t, N(f"{side}_foot_index")] = hip + [70 * s + 15, 128]
            P[t, N(f"{side}_shoulder")] = hip + [0.0, -90]
            P[t, N(f"{side}_elbow")] = hip + [-25 * s, -50]
            P[t, N(f"{side}_wrist")] = hip + [-40 * s, -15]
    P[:, :11] = P[:, [N("left_shoulder")]] + [10.0, -40.0]  # a head
    return P + rng.normal(0.0, 1.0, P.shape)


def test_flip_pairs():
    assert (N("left_eye_inner"), N("right_eye_inner")) in LR_PAIRS and (N("mouth_left"), N("mouth_right")) in LR_PAIRS
    assert len(LR_PAIRS) == 16 and len(LIMB_PAIRS) == 8
    P = walker(2)
    S = swap_left_right(P)
    np.testing.assert_array_equal(S[:, N("left_knee")], P[:, N("right_knee")])
    np.testing.assert_array_equal(swap_left_right(S), P)
    np.testing.assert_array_equal(S[:, N("nose")], P[:, N("nose")])


def test_viterbi_repairs_an_injected_flipped_segment():
    P = walker()
    V = np.ones(P.shape[:2])
    assert not repair_flips(P, V).any()  # the detector's labels where nothing is wrong
    bad = P.copy()
    seg = slice(20, 41)  # 21 frames; starts and ends with the legs apart
    bad[seg] = swap_left_right(P[seg])
    labels = repair_flips(bad, V)
    expect = np.zeros(len(P), bool)
    expect[seg] = True
    np.testing.assert_array_equal(labels, expect)
    fixed = np.where(labels[:, None, None], swap_left_right(bad), bad)
    np.testing.assert_allclose(fixed, P)
    # the first frames flipped: the labelling of the majority wins
    bad = P.copy()
    bad[:12] = swap_left_right(P[:12])
    np.testing.assert_array_equal(np.nonzero(repair_flips(bad, V))[0], np.arange(12))
    # across a gap in the observations (frames 30-34 lost), the link still holds
    keep = np.r_[0:30, 35:60]
    bad = P.copy()
    bad[35:50] = swap_left_right(P[35:50])
    labels = repair_flips(bad[keep], V[keep], keep)
    np.testing.assert_array_equal(keep[labels], np.arange(35, 50))


def test_viterbi_keeps_the_detector_where_there_is_no_evidence():
    """A person seen exactly side-on with the legs together: left and right coincide, a swap
    costs only its price, so nothing is swapped."""
    P = walker()
    for i, j in LR_PAIRS:
        P[:, j] = P[:, i]
    assert not repair_flips(P, np.ones(P.shape[:2])).any()
    with pytest.raises(ValueError, match="increasing"):
        repair_flips(P[:3], np.ones((3, 33)), [0, 2, 1])


# =========================================================================================
# tracking on scripted landmark streams
# =========================================================================================


class Scripted:
    """An estimator whose people are known: ``people[k] = (hip centre function t -> (x, y),
    set of frames where visible)``; body radius 100 px (scale point 100 px above the hips).
    The frame object is its number."""

    R = 100.0

    def __init__(self, people):
        self.people = people
        self.detector_frames = []

    def _points(self, c):
        rng = np.random.default_rng(int(c[0] * 7 + c[1]))
        P = c + rng.uniform(-60, 60, (39, 2))
        P[33] = c
        P[34] = c + [0.0, -self.R]
        return P

    def detect(self, t, min_score):
        self.detector_frames.append(t)
        out = []
        for centre, frames in self.people:
            if t in frames:
                c = np.asarray(centre(t), float)
                out.append(Detection(0.9, np.array([*c - 20, *c + 20]),
                                     np.stack([c, c + [0, -self.R], c + [0, -60], c + [0, -90]])))
        return out

    def landmarks(self, t, roi):
        for centre, frames in self.people:
            c = np.asarray(centre(t), float)
            if t in frames and math.hypot(roi.cx - c[0], roi.cy - c[1]) < self.R:
                P = self._points(c)
                return LandmarkResult(P, np.zeros(39), np.ones(39), np.ones(39), 0.99, roi)
        return LandmarkResult(np.zeros((39, 2)), np.zeros(39), np.zeros(39), np.zeros(39), 0.01, roi)


def walking(x0, speed=2.0, y=300.0):
    return lambda t: (x0 + speed * t, y)


def test_a_short_gap_is_bridged_and_a_long_one_splits():
    frames = set(range(0, 30)) | set(range(35, 60))  # lost for 5 frames
    est = Scripted([(walking(100.0), frames)])
    tracks, stats = track_people(range(60), est, TrackOptions(max_gap=10, min_frames=5, detect_every=0))
    assert len(tracks) == 1
    tr = tracks[0]
    assert (tr.start, tr.end, tr.missing_frames, len(tr.frames)) == (0, 59, 5, 55)
    assert stats["lost_events"] == 1
    assert est.detector_frames[0] == 0 and 35 in est.detector_frames  # re-detected where found again
    # 30 frames lost with max_gap 10: two tracks
    frames = set(range(0, 20)) | set(range(50, 80))
    tracks, _ = track_people(range(80), Scripted([(walking(100.0), frames)]),
                             TrackOptions(max_gap=10, min_frames=5, detect_every=0))
    assert [(t.start, t.end, t.missing_frames) for t in tracks] == [(0, 19, 0), (50, 79, 0)]
    # a gap of exactly max_gap frames is still bridged; one more frame splits
    for gap, n in ((10, 1), (11, 2)):
        frames = set(range(0, 20)) | set(range(20 + gap, 50))
        tracks, _ = track_people(range(50), Scripted([(walking(100.0), frames)]),
                                 TrackOptions(max_gap=10, min_frames=5, detect_every=0))
        assert len(tracks) == n, gap


def test_two_people_two_tracks_left_to_right_and_short_tracks_dropped():
    everyone = set(range(40))
    est = Scripted([(walking(900.0, -1.0), everyone), (walking(200.0, 1.0), everyone),
                    (walking(600.0, 0.0, 100.0), set(range(10, 14)))])  # seen for 4 frames only
    tracks, stats = track_people(range(40), est, TrackOptions(min_frames=5, detect_every=5))
    assert [(t.start, t.end, len(t.frames)) for t in tracks] == [(0, 39, 40), (0, 39, 40)]
    assert tracks[0].results[0].points[33, 0] == pytest.approx(200.0)  # left first
    assert stats["tracks_dropped"] == 1
    # a person walking in later is found by the periodic detector run
    est = Scripted([(walking(200.0), everyone), (walking(900.0), set(range(12, 40)))])
    tracks, _ = track_people(range(40), est, TrackOptions(min_frames=5, detect_every=5))
    assert [(t.start, t.end) for t in tracks] == [(0, 39), (15, 39)]
    assert choose_tracks(tracks, "largest", "v") == [0] and choose_tracks(tracks, "all", "v") == [0, 1]
    assert choose_tracks(tracks, 1, "v") == [1]
    with pytest.raises(ValueError, match="only 2 track"):
        choose_tracks(tracks, 2, "v")


def test_track_options_are_checked():
    with pytest.raises(ValueError, match="min_presence"):
        TrackOptions(min_presence=1.5)
    with pytest.raises(ValueError, match="max_gap"):
        TrackOptions(max_gap=-1)


def test_people_crossing_one_track_absorbs_the_other_which_starts_again():
    """Two people walk through each other: while they overlap, both tracks find the same person
    (the front one); the younger track ends there, and the other person starts a new track
    once the detector sees them apart again (a documented limit: identity is not kept through
    an occlusion)."""
    everyone = set(range(40))
    est = Scripted([(walking(100.0, 10.0), everyone), (walking(500.0, -10.0), everyone)])
    tracks, _ = track_people(range(40), est, TrackOptions(min_frames=5, detect_every=5))
    assert [(t.start, t.end) for t in tracks] == [(0, 39), (0, 15), (30, 39)]
    assert tracks[1].results[-1].points[33, 0] == pytest.approx(350.0)  # the second person, not the first
    seen = {}
    for k, tr in enumerate(tracks):  # never two tracks on one person in one frame
        for t, r in zip(tr.frames, tr.results, strict=True):
            key = (t, round(float(r.points[33, 0])))
            assert key not in seen, (k, seen.get(key), t)
            seen[key] = k


def test_without_the_video_extra_the_command_says_how_to_install(monkeypatch, tmp_path, capsys):
    from jmocap import cli, video

    monkeypatch.setattr(video, "missing_video_packages", lambda: ["ai_edge_litert"])
    assert cli.main(["video", str(tmp_path / "v.mp4"), str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "ai_edge_litert" in err and "pip install 'jmocap[video]'" in err
    with pytest.raises(ImportError, match=r"pip install 'jmocap\[video\]'"):
        bp._import("jmocap_no_such_module", "BlazePose")
