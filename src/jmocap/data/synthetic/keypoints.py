"""2D keypoints of the synthetic clips: detector-like corruption and the clean projection.

:class:`Corruption` configures pixel noise (temporally correlated, scaled with the person's
size), outliers, dropped joints in bursts, left/right swaps and confidences;
:func:`corrupt_keypoints` applies it to exact projections; :func:`clean_keypoints2d` recovers
the exact projection of a clip's 3D ground truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from jmocap.data.clip import Clip
from jmocap.data.synthetic.cameras import project_points


@dataclass(frozen=True)
class Corruption:
    """Detector-like corruption of the projected 2D keypoints.

    Pixel noise is Gaussian with std ``noise_px + noise_rel * person height in pixels``
    (times a per-joint factor: ``joint_scale`` for wrists/ankles/feet), temporally correlated
    (AR(1) coefficient ``noise_corr``). Per joint and frame: an *outlier* (probability
    ``outlier_prob``) jumps by ``outlier_scale`` * person height; a *dropped* joint
    (fraction ``drop_prob`` of joint-frames, in bursts of mean length ``drop_burst`` frames)
    gets confidence 0 and coordinates 0. A left/right *swap* event starts at a frame with
    probability ``swap_prob`` and lasts ``swap_burst`` frames on average; it exchanges one
    random left/right pair (``layout.flip_pairs``), or all of them with probability
    ``swap_all``. Joints projecting outside the image are dropped when ``drop_outside``.
    Confidences: clean joints draw from ``conf_clean`` and lose up to 0.3 with their noise
    (relative to 3 std); outliers draw from ``conf_outlier``, swapped joints from
    ``conf_swap``.

    *Occlusion bursts* (off by default; the extended generator's :meth:`extended`): an event
    starts at a frame with probability ``occlusion_prob`` and lasts ``occlusion_burst`` frames
    on average; it hides one limb (an arm: shoulder, elbow, wrist; a leg: knee, ankle, foot
    points) or, with probability ``occlusion_side``, one whole side (arm and leg), as a body
    part behind the torso or an object does. Each hidden joint-frame is dropped (confidence 0)
    with probability ``occlusion_drop``, else guessed by the detector: extra noise of std
    ``occlusion_noise_rel`` * person height and a confidence from ``conf_occluded``.
    """

    noise_px: float = 1.5
    noise_rel: float = 0.005
    joint_scale: float = 1.5
    noise_corr: float = 0.5
    outlier_prob: float = 0.01
    outlier_scale: float = 0.15
    drop_prob: float = 0.03
    drop_burst: float = 3.0
    swap_prob: float = 0.005
    swap_burst: float = 4.0
    swap_all: float = 0.2
    drop_outside: bool = True
    conf_clean: tuple[float, float] = (0.75, 0.98)
    conf_outlier: tuple[float, float] = (0.1, 0.5)
    conf_swap: tuple[float, float] = (0.3, 0.7)
    occlusion_prob: float = 0.0
    occlusion_burst: float = 12.0
    occlusion_side: float = 0.3
    occlusion_drop: float = 0.5
    occlusion_noise_rel: float = 0.04
    conf_occluded: tuple[float, float] = (0.05, 0.4)

    @classmethod
    def extended(cls) -> Corruption:
        """The extended generator's corruption: the default one plus occlusion bursts (about
        one every 6 s at 30 fps, 0.4 s long on average)."""
        return cls(occlusion_prob=0.006)

    @classmethod
    def none(cls) -> Corruption:
        """No corruption: exact projections with confidence 1."""
        return cls(noise_px=0.0, noise_rel=0.0, outlier_prob=0.0, drop_prob=0.0, swap_prob=0.0,
                   drop_outside=False, conf_clean=(1.0, 1.0))


def _bursts(rng, T, p_frac, mean_len, shape):
    """Boolean (T, *shape) masks of random bursts covering about ``p_frac`` of the entries."""
    out = np.zeros((T,) + shape, bool)
    if p_frac <= 0 or T == 0:
        return out
    mean_len = max(1.0, mean_len)
    p_start = p_frac / mean_len
    starts = rng.uniform(size=(T,) + shape) < p_start
    lengths = rng.geometric(1.0 / mean_len, size=(T,) + shape)
    idx = np.argwhere(starts)
    for i in idx:
        t = i[0]
        L = lengths[tuple(i)]
        out[(slice(t, t + L),) + tuple(i[1:])] = True
    return out


SIDE_PREFIXES = ("left", "right")
_ARM = ("shoulder", "elbow", "wrist")
_LEG = ("knee", "ankle", "foot", "toe", "heel")


def _limb_groups(layout) -> dict:
    """Joint indices of each (side, "arm" | "leg") of a layout, from its left/right
    ``flip_pairs`` (so the sides are the layout's own pairing)."""
    out = {(sd, part): [] for sd in SIDE_PREFIXES for part in ("arm", "leg")}
    for pair in sorted(layout.flip_pairs):
        n = layout.joints[pair[0]].lower()
        part = "arm" if any(k in n for k in _ARM) else ("leg" if any(k in n for k in _LEG) else None)
        if part is not None:
            for sd, j in zip(SIDE_PREFIXES, pair, strict=True):
                out[(sd, part)].append(j)
    for v in out.values():
        v.sort()
    return out


def corrupt_keypoints(rng: np.random.Generator, uv: np.ndarray, layout, image_size,
                      corruption: Corruption = Corruption()) -> tuple[np.ndarray, dict]:
    """Detector-like 2D keypoints (T, J, 3) = (x, y, confidence) from clean projections
    ``uv`` (T, J, 2). Returns the keypoints and counts of what was done."""
    c = corruption
    T, J, _ = uv.shape
    W, H = float(image_size[0]), float(image_size[1])
    kp = np.zeros((T, J, 3))
    kp[..., :2] = uv
    # person height in pixels per frame
    ph = np.maximum(uv[..., 1].max(axis=1) - uv[..., 1].min(axis=1), 1.0)
    names = [n.lower() for n in layout.joints]
    jscale = np.array([c.joint_scale if any(k in n for k in ("wrist", "ankle", "foot", "toe", "heel"))
                       else 1.0 for n in names])
    sigma = (c.noise_px + c.noise_rel * ph)[:, None] * jscale[None, :]  # (T, J)
    noise = np.zeros((T, J, 2))
    if np.any(sigma > 0):
        white = rng.normal(size=(T, J, 2))
        rho = float(np.clip(c.noise_corr, 0.0, 0.99))
        noise[0] = white[0]
        for t in range(1, T):
            noise[t] = rho * noise[t - 1] + math.sqrt(1 - rho * rho) * white[t]
        noise *= sigma[..., None]
    kp[..., :2] += noise
    lo, hi = c.conf_clean
    base = rng.uniform(lo, hi, size=(T, J))
    mag = np.linalg.norm(noise, axis=-1) / np.maximum(3 * sigma, 1e-9)
    conf = base - 0.3 * np.clip(mag, 0, 1) * (sigma > 0)
    # outliers
    out_mask = rng.uniform(size=(T, J)) < c.outlier_prob
    if out_mask.any():
        n = int(out_mask.sum())
        ang = rng.uniform(0, 2 * np.pi, n)
        r = np.abs(rng.normal(size=n)) * c.outlier_scale * ph[np.nonzero(out_mask)[0]] + 5.0
        kp[out_mask, 0] += r * np.cos(ang)
        kp[out_mask, 1] += r * np.sin(ang)
        conf[out_mask] = rng.uniform(*c.conf_outlier, size=n)
    # left/right swaps
    swapped = np.zeros((T, J), bool)
    n_swaps = 0
    if c.swap_prob > 0 and layout.flip_pairs:
        t = 0
        while t < T:
            if rng.uniform() < c.swap_prob:
                L = int(rng.geometric(1.0 / max(c.swap_burst, 1.0)))
                pairs = list(layout.flip_pairs) if rng.uniform() < c.swap_all else \
                    [layout.flip_pairs[int(rng.integers(len(layout.flip_pairs)))]]
                sl = slice(t, min(T, t + L))
                for a, b in pairs:
                    kp[sl, a, :2], kp[sl, b, :2] = kp[sl, b, :2].copy(), kp[sl, a, :2].copy()
                    swapped[sl, a] = swapped[sl, b] = True
                n_swaps += 1
                t += L
            else:
                t += 1
        if swapped.any():
            conf[swapped] = rng.uniform(*c.conf_swap, size=int(swapped.sum()))
    # occlusion bursts
    n_occ = 0
    occluded = np.zeros((T, J), bool)
    if c.occlusion_prob > 0:
        groups = _limb_groups(layout)
        t = 0
        while t < T:
            if rng.uniform() < c.occlusion_prob:
                L = int(rng.geometric(1.0 / max(c.occlusion_burst, 1.0)))
                side = SIDE_PREFIXES[int(rng.integers(2))]
                if rng.uniform() < c.occlusion_side:
                    idx = groups[(side, "arm")] + groups[(side, "leg")]
                else:
                    idx = groups[(side, str(rng.choice(["arm", "leg"])))]
                occluded[t:t + L, idx] = True
                n_occ += 1
                t += L
            else:
                t += 1
        if occluded.any():
            n = int(occluded.sum())
            ti = np.nonzero(occluded)[0]
            kp[occluded, :2] += rng.normal(size=(n, 2)) * (c.occlusion_noise_rel * ph[ti])[:, None]
            conf[occluded] = rng.uniform(*c.conf_occluded, size=n)
    # drops
    drop = _bursts(rng, T, c.drop_prob, c.drop_burst, (J,))
    if occluded.any():
        drop |= occluded & (rng.uniform(size=(T, J)) < c.occlusion_drop)
    if c.drop_outside:
        x, y = kp[..., 0], kp[..., 1]
        drop |= (x < 0) | (x >= W) | (y < 0) | (y >= H)
    conf = np.clip(conf, 0.01, 1.0)
    conf[drop] = 0.0
    kp[..., 2] = conf
    kp[drop, :2] = 0.0
    stats = dict(dropped=float(drop.mean()), outliers=int(out_mask.sum()), swap_events=n_swaps,
                 noise_std_px=float(np.mean(sigma)))
    if c.occlusion_prob > 0:
        stats.update(occlusion_events=n_occ, occluded=float(occluded.mean()))
    return kp.astype(np.float32), stats


def clean_keypoints2d(clip: Clip) -> np.ndarray:
    """The exact projection (T, J, 2) of a synthetic clip's ``gt_keypoints3d`` with its camera
    (every frame's, for a moving camera): what the 2D keypoints are before corruption."""
    if clip.gt_keypoints3d is None or clip.extrinsics is None:
        raise ValueError(f"clip {clip.name!r} has no 3D ground truth or no extrinsics")
    uv, _ = project_points(clip.intrinsics, clip.world_to_camera(), clip.gt_keypoints3d.astype(np.float64))
    return uv
