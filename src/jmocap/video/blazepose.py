"""BlazePose (MediaPipe Pose) on CPU: the person detector and the landmark model, run by LiteRT.

The two models ship in jmocap's wheel (``jmocap/assets/blazepose/``, copied unmodified from the
``mediapipe`` 0.10.21 wheel, Apache-2.0; ``NOTICE`` there gives their sha256). LiteRT
(``ai_edge_litert``, the ``video`` extra) runs them; everything around them is numpy (and OpenCV's
``warpAffine`` for the crops), re-implementing the settings of MediaPipe's published
graphs (``pose_detection_cpu``, ``pose_landmark_by_roi_cpu``, ``pose_detection_to_roi``,
``pose_landmarks_to_roi``):

* **detector** (:meth:`BlazePose.detect`): the frame letterboxed into a 224 x 224 square (black
  padding, aspect kept), RGB scaled to [-1, 1]; 2254 SSD anchors (:func:`ssd_anchors`); a box
  (centre, size) and 4 keypoints per anchor (:func:`decode_detections`): keypoint 0 the mid-hip
  centre, keypoint 1 a point whose distance from it is the full-body radius, keypoints 2 and 3
  the same for the upper body; score = sigmoid of the logit clipped to +-100; weighted
  non-maximum suppression at IoU 0.3 (:func:`weighted_nms`).
* **region of interest** (:func:`roi_from_points`): centre = keypoint 0, side = 2 x 1.25 x
  |keypoint 1 - keypoint 0| (square in pixels), rotation = pi/2 - atan2(-(y1 - y0), x1 - x0)
  (0 for an upright person). From the landmarks of a frame the same function on the auxiliary
  landmarks 33 and 34 gives the next frame's region (tracking without the detector).
* **landmarks** (:meth:`BlazePose.landmarks`): the region cropped to 256 x 256 by an affine warp
  (bilinear, border replicated), RGB in [0, 1]; the model gives 39 points x (x, y, z,
  visibility logit, presence logit) in crop pixels, a pose-presence probability, a 64 x 64 x 39
  heatmap (used to refine each point: the sigmoid-weighted mean of a 7 x 7 window where its
  maximum is >= 0.5, as MediaPipe's ``RefineLandmarksFromHeatmapCalculator``), a segmentation
  mask and world landmarks (not used). Points are mapped back to image pixels through the same
  affine transform.

Pixel coordinates are continuous with the origin at the top-left *corner* of the image (the
centre of pixel (i, j) is (j + 0.5, i + 0.5)), as jmocap's camera convention (docs/formats.md).
Frames are (H, W, 3) uint8 RGB arrays.
"""

from __future__ import annotations

import importlib
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "BLAZEPOSE_NAMES",
    "DETECTOR_INPUT",
    "LANDMARK_INPUT",
    "MODEL_DIR",
    "BlazePose",
    "Detection",
    "LandmarkResult",
    "Roi",
    "affine_for_roi",
    "apply_affine",
    "decode_detections",
    "iou",
    "refine_from_heatmap",
    "roi_from_points",
    "ssd_anchors",
    "warp_image",
    "weighted_nms",
]

VIDEO_INSTALL = "pip install 'jmocap[video]'"
MODEL_DIR = Path(__file__).resolve().parent.parent / "assets" / "blazepose"
DETECTOR_FILE = "pose_detection.tflite"
LANDMARK_FILE = "pose_landmark_full.tflite"

DETECTOR_INPUT = 224  # square input of the detector (pixels)
LANDMARK_INPUT = 256  # square input of the landmark model (pixels)
NUM_ANCHORS = 2254
ANCHOR_STRIDES = (8, 16, 32, 32, 32)
NMS_IOU = 0.3  # MediaPipe's min_suppression_threshold (weighted NMS)
ROI_SCALE = 1.25  # RectTransformationCalculator scale_x = scale_y (detection and landmarks)
HEATMAP_KERNEL = 7
HEATMAP_MIN_CONFIDENCE = 0.5
NUM_LANDMARKS = 39  # 33 BlazePose points + hip centre, body-scale point, 4 unused

#: the 33 BlazePose landmarks, in the model's order (left/right of the person)
BLAZEPOSE_NAMES = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
    "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
    "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip",
    "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel",
    "right_heel", "left_foot_index", "right_foot_index",
)
AUX_CENTRE, AUX_SCALE = 33, 34  # auxiliary alignment points: the next frame's region


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-np.clip(x, -100.0, 100.0)))


def _import(module: str, what: str):
    """Import a package of the ``video`` extra, or say how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise ImportError(
            f"{what} needs {e.name or module}, which is not installed; video input is the optional "
            f"video extra: {VIDEO_INSTALL}"
        ) from e


# ======================================================================================
# geometry: anchors, regions, warps
# ======================================================================================


def ssd_anchors(input_size: int = DETECTOR_INPUT, strides=ANCHOR_STRIDES) -> np.ndarray:
    """The detector's SSD anchor centres (N, 2), normalised to [0, 1] of its square input.

    MediaPipe's ``SsdAnchorsCalculator`` with the pose detector's options: one feature map per
    distinct stride (consecutive layers with the same stride share one), ``ceil(input / stride)``
    cells a side, anchor centres at ``((x + 0.5) / n, (y + 0.5) / n)``, two anchors per cell and
    layer (aspect ratio 1 and the interpolated scale; with ``fixed_anchor_size`` both have size
    1), cells in row-major order: 28 x 28 x 2 + 14 x 14 x 2 + 7 x 7 x 6 = 2254 for 224 pixels.
    """
    out = []
    i = 0
    while i < len(strides):
        j = i
        while j < len(strides) and strides[j] == strides[i]:
            j += 1
        per_cell = 2 * (j - i)
        n = math.ceil(input_size / strides[i])
        c = (np.arange(n) + 0.5) / n
        yy, xx = np.meshgrid(c, c, indexing="ij")
        cells = np.stack([xx.ravel(), yy.ravel()], -1)
        out.append(np.repeat(cells, per_cell, axis=0))
        i = j
    return np.concatenate(out)


@dataclass(frozen=True)
class Roi:
    """A square region of interest in image pixels: centre ``(cx, cy)``, side ``size``, and
    ``rotation`` (radians, in [-pi, pi)): the crop's x axis is the image's x axis rotated by it
    (clockwise on screen, as image y points down)."""

    cx: float
    cy: float
    size: float
    rotation: float

    def box(self) -> np.ndarray:
        """Axis-aligned bounding box (x0, y0, x1, y1) of the rotated square."""
        c, s = abs(math.cos(self.rotation)), abs(math.sin(self.rotation))
        h = 0.5 * self.size * (c + s)
        return np.array([self.cx - h, self.cy - h, self.cx + h, self.cy + h])


def _normalise_angle(a: float) -> float:
    return a - 2.0 * math.pi * math.floor((a + math.pi) / (2.0 * math.pi))


def roi_from_points(centre, scale_point, scale: float = ROI_SCALE) -> Roi:
    """The region MediaPipe crops for the landmark model, from two points in image pixels.

    ``centre`` (the mid-hip point) and ``scale_point`` (at the body's radius from it): side
    ``2 |scale_point - centre| * scale``, rotation ``pi/2 - atan2(-(y1 - y0), x1 - x0)``
    normalised to [-pi, pi) (``AlignmentPointsRectsCalculator`` with target angle 90 degrees,
    then ``RectTransformationCalculator`` with ``square_long``)."""
    x0, y0 = (float(v) for v in centre)
    x1, y1 = (float(v) for v in scale_point)
    size = 2.0 * math.hypot(x1 - x0, y1 - y0) * scale
    rotation = _normalise_angle(math.pi / 2.0 - math.atan2(-(y1 - y0), x1 - x0))
    return Roi(x0, y0, size, rotation)


def affine_for_roi(roi: Roi, out_size: int) -> np.ndarray:
    """The 2 x 3 affine map from crop pixels (continuous, ``out_size`` a side) to image pixels:
    ``image = c + R(rotation) ((u, v) - out_size / 2) * size / out_size``."""
    k = roi.size / out_size
    c, s = math.cos(roi.rotation), math.sin(roi.rotation)
    A = np.array([[c * k, -s * k], [s * k, c * k]])
    t = np.array([roi.cx, roi.cy]) - A @ np.array([out_size / 2.0, out_size / 2.0])
    return np.concatenate([A, t[:, None]], axis=1)


def apply_affine(M: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (..., 2) through a 2 x 3 affine map."""
    return points @ M[:, :2].T + M[:, 2]


def warp_image(image: np.ndarray, M: np.ndarray, out_size: int, border: str) -> np.ndarray:
    """Sample ``image`` (H, W, C) at the crop pixels' centres mapped by ``M`` (crop -> image,
    :func:`affine_for_roi`): an (out_size, out_size, C) float32 array in the image's units.
    Bilinear (OpenCV's ``warpAffine``, as MediaPipe's CPU path); ``border`` ``"zero"`` (black
    outside the image) or ``"replicate"`` (the nearest edge pixel)."""
    cv2 = _import("cv2", "BlazePose (jmocap video)")
    if border not in ("zero", "replicate"):
        raise ValueError(f"border must be 'zero' or 'replicate', got {border!r}")
    # OpenCV indexes pixel centres at integers: index map = M(crop index + 0.5) - 0.5
    A, t = M[:, :2], M[:, 2]
    Mi = np.concatenate([A, (A @ np.array([0.5, 0.5]) + t - 0.5)[:, None]], axis=1)
    out = cv2.warpAffine(
        np.ascontiguousarray(image), Mi, (out_size, out_size),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT if border == "zero" else cv2.BORDER_REPLICATE, borderValue=0,
    )
    return out.reshape(out_size, out_size, -1).astype(np.float32)


def iou(a, b) -> float:
    """Intersection over union of two boxes (x0, y0, x1, y1)."""
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    if w <= 0 or h <= 0:
        return 0.0
    inter = w * h
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0 else 0.0


# ======================================================================================
# detector post-processing
# ======================================================================================


@dataclass(frozen=True)
class Detection:
    """A person found by the detector, in image pixels: ``score`` in [0, 1], ``box`` (x0, y0,
    x1, y1), ``keypoints`` (4, 2): mid-hip centre, full-body scale point, mid-shoulder centre,
    upper-body scale point."""

    score: float
    box: np.ndarray
    keypoints: np.ndarray

    def roi(self) -> Roi:
        """The landmark model's region for this detection (:func:`roi_from_points`)."""
        return roi_from_points(self.keypoints[0], self.keypoints[1])


def decode_detections(raw: np.ndarray, logits: np.ndarray, anchors: np.ndarray,
                      input_size: int = DETECTOR_INPUT):
    """The detector's raw outputs -> (scores (N,), boxes (N, 4) x0 y0 x1 y1, keypoints (N, 4, 2)),
    all normalised to the detector's square input.

    ``raw`` (N, 12): box centre offset (x, y), box size (w, h), then 4 keypoints (x, y), in input
    pixels relative to the anchor centre (anchor size 1); ``logits`` (N,) score logits, clipped
    to +-100 before the sigmoid (``TensorsToDetectionsCalculator``)."""
    raw = np.asarray(raw, np.float64)
    centre = raw[:, 0:2] / input_size + anchors
    size = raw[:, 2:4] / input_size
    boxes = np.concatenate([centre - size / 2.0, centre + size / 2.0], axis=1)
    kps = raw[:, 4:12].reshape(-1, 4, 2) / input_size + anchors[:, None, :]
    scores = _sigmoid(np.asarray(logits, np.float64).reshape(-1))
    return scores, boxes, kps


def weighted_nms(scores, boxes, keypoints, threshold: float = NMS_IOU):
    """MediaPipe's weighted non-maximum suppression: repeatedly take the best remaining
    candidate, gather every remaining one whose IoU with it exceeds ``threshold`` (itself
    included), and output their score-weighted mean box and keypoints with the best score.
    Returns a list of (score, box (4,), keypoints (K, 2)), best first."""
    order = list(np.argsort(-np.asarray(scores), kind="stable"))
    out = []
    while order:
        top = order[0]
        group, rest = [], []
        for i in order:
            (group if iou(boxes[i], boxes[top]) > threshold or i == top else rest).append(i)
        w = np.asarray(scores)[group]
        w = w / w.sum() if w.sum() > 0 else np.full(len(group), 1.0 / len(group))
        out.append((float(scores[top]), (w[:, None] * boxes[group]).sum(0),
                    (w[:, None, None] * keypoints[group]).sum(0)))
        order = rest
    return out


# ======================================================================================
# landmark post-processing
# ======================================================================================


def refine_from_heatmap(points: np.ndarray, heatmap: np.ndarray, kernel: int = HEATMAP_KERNEL,
                        min_confidence: float = HEATMAP_MIN_CONFIDENCE, cell_offset: float = 0.0) -> np.ndarray:
    """Refine normalised landmark positions (N, 2) with the model's heatmap (h, w, N) logits:
    per point, the sigmoid-weighted mean cell position in a ``kernel`` x ``kernel`` window
    around its cell, where the window's maximum is >= ``min_confidence`` (else the point is
    kept), as MediaPipe's ``RefineLandmarksFromHeatmapCalculator``: a cell (row, col) stands for
    the normalised position ``((col + cell_offset) / w, (row + cell_offset) / h)``, with
    MediaPipe's ``cell_offset = 0`` by default."""
    h, w, n = heatmap.shape
    out = np.array(points, np.float64, copy=True)
    off = (kernel - 1) // 2
    for i in range(n):
        col, row = int(math.floor(out[i, 0] * w)), int(math.floor(out[i, 1] * h))
        if not (0 <= col < w and 0 <= row < h):
            continue
        r0, r1 = max(0, row - off), min(h, row + off + 1)
        c0, c1 = max(0, col - off), min(w, col + off + 1)
        conf = _sigmoid(heatmap[r0:r1, c0:c1, i].astype(np.float64))
        total = conf.sum()
        if conf.max() >= min_confidence and total > 0:
            rows, cols = np.mgrid[r0:r1, c0:c1]
            out[i, 0] = ((cols * conf).sum() / total + cell_offset) / w
            out[i, 1] = ((rows * conf).sum() / total + cell_offset) / h
    return out


@dataclass(frozen=True)
class LandmarkResult:
    """The landmark model on one region: ``points`` (39, 2) image pixels, ``z`` (39,) relative
    depth (pixels, MediaPipe's scale: the region's side over 256 per model unit), ``visibility``
    and ``presence`` (39,) probabilities, ``score`` the pose-presence probability, ``roi`` the
    region it ran on."""

    points: np.ndarray
    z: np.ndarray
    visibility: np.ndarray
    presence: np.ndarray
    score: float
    roi: Roi

    def next_roi(self) -> Roi:
        """The region for the next frame, from the auxiliary alignment points 33 and 34."""
        return roi_from_points(self.points[AUX_CENTRE], self.points[AUX_SCALE])

    def box(self) -> np.ndarray:
        """Bounding box (x0, y0, x1, y1) of the 33 body landmarks."""
        p = self.points[:33]
        return np.concatenate([p.min(0), p.max(0)])


# ======================================================================================
# the runner
# ======================================================================================


def _interpreter(path: Path, threads: int | None):
    litert = _import("ai_edge_litert.interpreter", "BlazePose (jmocap video)")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the BlazePose model is missing from the installed jmocap package")
    it = litert.Interpreter(model_path=str(path), num_threads=threads or min(4, os.cpu_count() or 1))
    it.allocate_tensors()
    return it


class BlazePose:
    """The detector and the landmark model, each loaded once (one LiteRT interpreter per model).

    ``threads``: CPU threads per model (default: the cores, at most 4). The outputs are matched
    to their meaning by shape, checked when the models load.
    """

    def __init__(self, threads: int | None = None, model_dir: str | os.PathLike | None = None):
        d = Path(model_dir) if model_dir is not None else MODEL_DIR
        self.anchors = ssd_anchors()
        self._det = _interpreter(d / DETECTOR_FILE, threads)
        self._lm = _interpreter(d / LANDMARK_FILE, threads)
        self._det_in = self._det.get_input_details()[0]["index"]
        self._lm_in = self._lm.get_input_details()[0]["index"]
        det_out = {tuple(o["shape"][1:]): o["index"] for o in self._det.get_output_details()}
        lm_out = {tuple(o["shape"][1:]): o["index"] for o in self._lm.get_output_details()}
        try:
            self._det_raw = det_out[(NUM_ANCHORS, 12)]
            self._det_logit = det_out[(NUM_ANCHORS, 1)]
            self._lm_points = lm_out[(NUM_LANDMARKS * 5,)]
            self._lm_flag = lm_out[(1,)]
            self._lm_heatmap = lm_out[(64, 64, NUM_LANDMARKS)]
        except KeyError as e:  # pragma: no cover - the shipped models have these outputs
            raise RuntimeError(f"BlazePose models in {d} do not have the expected outputs (missing {e})") from None

    # --- detector ------------------------------------------------------------------------
    def detect(self, frame: np.ndarray, min_score: float = 0.5) -> list[Detection]:
        """People in ``frame`` (H, W, 3 uint8 RGB), best first: detector scores >= ``min_score``
        after weighted non-maximum suppression, in image pixels."""
        H, W = frame.shape[:2]
        S = float(max(H, W))
        ox, oy = (S - W) / 2.0, (S - H) / 2.0
        # letterbox: input pixel (u, v) of the 224 square -> image (u * S / 224 - ox, ...)
        M = np.array([[S / DETECTOR_INPUT, 0.0, -ox], [0.0, S / DETECTOR_INPUT, -oy]])
        x = warp_image(frame, M, DETECTOR_INPUT, "zero") / 127.5 - 1.0
        self._det.set_tensor(self._det_in, x[None].astype(np.float32))
        self._det.invoke()
        raw = self._det.get_tensor(self._det_raw)[0]
        logits = self._det.get_tensor(self._det_logit)[0, :, 0]
        scores, boxes, kps = decode_detections(raw, logits, self.anchors)
        keep = scores >= min_score
        out = []
        for score, box, kp in weighted_nms(scores[keep], boxes[keep], kps[keep]):
            out.append(Detection(score, box * S - [ox, oy, ox, oy], kp * S - [ox, oy]))
        return out

    # --- landmarks -----------------------------------------------------------------------
    def landmarks(self, frame: np.ndarray, roi: Roi) -> LandmarkResult:
        """The landmark model on ``roi`` of ``frame`` (H, W, 3 uint8 RGB)."""
        M = affine_for_roi(roi, LANDMARK_INPUT)
        x = warp_image(frame, M, LANDMARK_INPUT, "replicate") / 255.0
        self._lm.set_tensor(self._lm_in, x[None].astype(np.float32))
        self._lm.invoke()
        raw = self._lm.get_tensor(self._lm_points)[0].reshape(NUM_LANDMARKS, 5).astype(np.float64)
        score = float(self._lm.get_tensor(self._lm_flag).reshape(-1)[0])
        heatmap = self._lm.get_tensor(self._lm_heatmap)[0]
        norm = refine_from_heatmap(raw[:, :2] / LANDMARK_INPUT, heatmap)
        points = apply_affine(M, norm * LANDMARK_INPUT)
        return LandmarkResult(
            points=points, z=raw[:, 2] * roi.size / LANDMARK_INPUT, visibility=_sigmoid(raw[:, 3]),
            presence=_sigmoid(raw[:, 4]), score=score, roi=roi,
        )
