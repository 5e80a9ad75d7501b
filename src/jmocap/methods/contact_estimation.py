"""Foot-contact estimation from 2D keypoints: Rempe et al. (2020), Sec. 3.2 and Appendix A.2.

For every target frame ``t`` an MLP (:class:`jmocap.nets.ContactMLP`) reads a centred window
of ``w = 9`` frames of the 13 lower-body keypoints (x, y, confidence) and classifies the four
foot contact points (jmocap's order, :data:`jmocap.constants.CONTACT_SITES`: left heel, left toe,
right heel, right toe) on the 5 frames ``t-2 .. t+2``; a frame's label is the majority of the
(up to 5) overlapping predictions for it (:func:`vote`).

Features (:func:`contact_features`), per target frame ``t``:

* the window's frames are ``t-4 .. t+4``; a frame outside the clip or padded (``mask`` False)
  is replaced by the nearest real frame (edge replication);
* positions are relative to the root of the *target* frame: MidHip, or the mean of the
  detected hips where MidHip is undetected (then the mean of the detected lower-body joints of
  the target frame, then of the window);
* and divided by the window's body size ``s``: the median over the window's frames of the
  longer leg's 2D hip-knee-ankle length (both bones, pixels), counting only legs whose three
  joints are detected. A leg is about half the body's height, so feet lie within ~[-1, 1] of
  the root, whatever the person's distance to the camera and the image resolution (``s`` scales
  with both). Windows without a complete leg fall back to the extent of their detected
  joints, then to a quarter of the image height. Coordinates are clipped to +-4 (outliers);
* the confidence is appended; undetected joints (confidence 0) are all zeros.

jmocap's temporal refiner (:func:`refined_probabilities`, :class:`jmocap.nets.ContactTCN`) reads
the MLP's window probabilities, vote and last hidden layer over about a second on each side and
classifies every frame again (``estimate_contacts(..., refiner=...)``; docs/method.md, "The
temporal refiner"): F1 89.5 -> 90.1 % on the held-out archive.

Everything is a pure function of arrays with static shapes: ``jax.jit`` and ``jax.vmap`` apply
(:func:`estimate_contacts` over a batch of :class:`jmocap.inputs.ClipInputs`). Only the BODY_25
layout is supported (:data:`LOWER_BODY`).
"""

from __future__ import annotations

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jmocap.camera import Camera, project, unproject
from jmocap.inputs import ClipInputs
from jmocap.layouts import get_layout
from jmocap.methods.base import load_float32_params
from jmocap.nets import ContactMLP, ContactTCN

Array = jnp.ndarray

#: input window (frames) and its half width
WINDOW = 9
HALF_WINDOW = WINDOW // 2
#: frames classified per target (t-2 .. t+2) and its half width
OUT_FRAMES = 5
HALF_OUT = OUT_FRAMES // 2
#: the 13 lower-body joints of BODY_25 the network reads, in this order
LOWER_BODY: tuple[str, ...] = ("MidHip", "RHip", "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle",
                               "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel")
NUM_JOINTS = len(LOWER_BODY)
#: the feature vector's length: 9 frames x 13 joints x (x, y, confidence) = 351
NUM_FEATURES = WINDOW * NUM_JOINTS * 3
#: positions of the normalised coordinates are clipped to +-FEATURE_CLIP body sizes
FEATURE_CLIP = 4.0
#: left/right contact points swap under a horizontal flip: (L heel, L toe, R heel, R toe)
CONTACT_FLIP = (2, 3, 0, 1)

_ROOT = LOWER_BODY.index("MidHip")
_HIPS = (LOWER_BODY.index("RHip"), LOWER_BODY.index("LHip"))
# (hip, knee, ankle) right, left: indices into LOWER_BODY
_LEGS = tuple(tuple(LOWER_BODY.index(s + j) for j in ("Hip", "Knee", "Ankle")) for s in "RL")
#: left/right pairs among the 13 joints (indices into LOWER_BODY)
LOWER_BODY_FLIP = tuple((LOWER_BODY.index(n), LOWER_BODY.index("L" + n[1:])) for n in LOWER_BODY
                        if n.startswith("R"))

ASSET = Path(__file__).resolve().parents[1] / "assets" / "contact_mlp.msgpack"
REFINER_ASSET = ASSET.with_name("contact_refiner.msgpack")
SUPPORTED_LAYOUTS = ("body25",)


def lower_body_indices(layout: str = "body25") -> np.ndarray:
    """Indices of :data:`LOWER_BODY` in ``layout`` (BODY_25 only; other layouts raise)."""
    lay = get_layout(layout)
    if lay.name not in SUPPORTED_LAYOUTS:
        raise ValueError(f"contact estimation reads the BODY_25 lower body (heels and toes); "
                         f"layout {lay.name!r} is not supported (supported: {SUPPORTED_LAYOUTS})")
    return np.array([lay.index(j) for j in LOWER_BODY])


def nearest_real_frame(mask: Array) -> Array:
    """Index (T,) of the nearest frame with ``mask`` True (the earlier one on a tie); the frame
    itself where it is real, the identity when no frame is."""
    mask = jnp.asarray(mask, bool)
    T = mask.shape[0]
    idx = jnp.arange(T)
    prev = jax.lax.cummax(jnp.where(mask, idx, -1), axis=0)
    nxt = jax.lax.cummin(jnp.where(mask, idx, T), axis=0, reverse=True)
    d_prev = jnp.where(prev >= 0, idx - prev, 2 * T + 1)
    d_next = jnp.where(nxt < T, nxt - idx, 2 * T + 1)
    near = jnp.where(d_prev <= d_next, prev, nxt)
    return jnp.where(jnp.any(mask), near, idx)


def window_frames(mask: Array, half: int = HALF_WINDOW) -> Array:
    """(T, 2 half + 1) frame indices of the window centred on each frame: edges replicated,
    padded frames replaced by the nearest real frame."""
    T = jnp.shape(mask)[0]
    near = nearest_real_frame(mask)
    raw = jnp.clip(jnp.arange(T)[:, None] + jnp.arange(-half, half + 1)[None, :], 0, T - 1)
    return near[raw]


def _root(xy: Array, vis: Array) -> Array:
    """Root (T, 2) of the target frames: window (T, w, 13, 2), visibility (T, w, 13)."""
    c = xy.shape[1] // 2
    c_xy, c_vis = xy[:, c], vis[:, c].astype(xy.dtype)  # (T, 13, 2), (T, 13)

    def mean(p, w):  # p (T, K, 2), w (T, K)
        n = jnp.sum(w, -1)
        return jnp.sum(p * w[..., None], -2) / jnp.maximum(n, 1)[..., None], n

    hips, n_hips = mean(c_xy[:, list(_HIPS)], c_vis[:, list(_HIPS)])
    frame, n_frame = mean(c_xy, c_vis)
    T = xy.shape[0]
    win, n_win = mean(xy.reshape(T, -1, 2), vis.reshape(T, -1).astype(xy.dtype))
    root = jnp.where((n_win > 0)[:, None], win, 0.0)
    root = jnp.where((n_frame > 0)[:, None], frame, root)
    root = jnp.where((n_hips > 0)[:, None], hips, root)
    return jnp.where((c_vis[:, _ROOT] > 0)[:, None], c_xy[:, _ROOT], root)


def body_size(xy: Array, vis: Array, image_size: Array) -> Array:
    """Body size (T,) in pixels of each window (T, 9, 13, 2): the median over the window's frames
    of the longer leg's hip-knee + knee-ankle 2D length (legs with all three joints detected);
    without any such leg the extent of the window's detected joints, then a quarter of the image
    height; at least 1e-3 of the image's larger side."""
    legs = []
    for hip, knee, ankle in _LEGS:
        ok = vis[..., hip] & vis[..., knee] & vis[..., ankle]
        length = (jnp.linalg.norm(xy[..., hip, :] - xy[..., knee, :], axis=-1)
                  + jnp.linalg.norm(xy[..., knee, :] - xy[..., ankle, :], axis=-1))
        legs.append(jnp.where(ok, length, -1.0))
    leg = jnp.maximum(legs[0], legs[1])  # (T, 9); -1 where neither leg is complete
    size = jnp.nanmedian(jnp.where(leg > 0, leg, jnp.nan), axis=1)
    T = xy.shape[0]
    flat, fvis = xy.reshape(T, -1, 2), vis.reshape(T, -1)
    big = jnp.finfo(xy.dtype).max
    lo = jnp.min(jnp.where(fvis[..., None], flat, big), axis=1)
    hi = jnp.max(jnp.where(fvis[..., None], flat, -big), axis=1)
    extent = jnp.where(jnp.any(fvis, axis=1), jnp.max(hi - lo, axis=-1), 0.0)
    image_size = jnp.asarray(image_size, xy.dtype)
    fallback = jnp.where(extent > 0, extent, image_size[1] / 4.0)
    size = jnp.where(jnp.isfinite(size) & (size > 0), size, fallback)
    return jnp.maximum(size, 1e-3 * jnp.max(image_size))


def stabilise_window(xy: Array, frames: Array, intrinsics: Array, cameras: Array, depth: Array) -> Array:
    """Keypoints (T, w, K, 2) of each target frame's window (``frames`` (T, w): the frame each
    came from) as the target frame's own camera would have seen them: every point is lifted to
    its frame's person depth ``depth`` (T,) (m, along its camera's optical axis) through its
    frame's camera ``cameras`` (T, 4, 4) world -> camera, and projected through the target
    frame's. A camera's rotation is undone exactly (the depth drops out); its translation to
    the precision of the depth (the points of one body are taken at one depth). Frames whose
    depth is below 0.1 m, and points that would land behind the target camera, stay as seen."""
    dtype = xy.dtype
    intrinsics, cameras = jnp.asarray(intrinsics, dtype), jnp.asarray(cameras, dtype)
    size = jnp.zeros(2, dtype)
    d = jnp.broadcast_to(depth[frames].astype(dtype)[..., None], xy.shape[:-1])  # (T, w, K)
    Xw = unproject(Camera(intrinsics, size, cameras[frames]), xy, d)  # through each point's own frame
    uv, z = project(Camera(intrinsics, size, cameras[:, None]), Xw, return_depth=True)  # the target's
    ok = (d > 0.1) & (z > 1e-3)
    return jnp.where(ok[..., None], uv, xy)


def contact_features(keypoints: Array, image_size: Array, mask: Array, layout: str = "body25",
                     window: int = WINDOW, stabilise: tuple[Array, Array, Array] | None = None) -> Array:
    """Network input (T, window x 39) per target frame: a window of ``window`` frames (odd,
    centred; 9 by default) x 13 lower-body joints x (x, y, confidence), positions relative to
    the target frame's root and divided by the window's body size (module docstring);
    undetected joints are zeros.

    ``keypoints`` (T, J, 3): pixels and confidence in the ``layout`` (BODY_25); ``image_size``
    (2,) width, height; ``mask`` (T,) real frames (padded frames replicate the nearest real one).
    ``layout`` and ``window`` are static. ``stabilise``, ``(intrinsics (4,), cameras (T, 4, 4),
    depth (T,))`` of a moving camera, first moves every window into its target frame's camera
    (:func:`stabilise_window`): the network was trained on static cameras, where a foot at rest
    stays still in the image.
    """
    if window < 1 or window % 2 == 0:
        raise ValueError(f"the contact window must be an odd number of frames, got {window}")
    sel = lower_body_indices(layout)
    kp = jnp.asarray(keypoints)[:, sel]
    kp = kp.astype(jnp.promote_types(kp.dtype, jnp.float32))
    T = kp.shape[0]
    frames = window_frames(jnp.asarray(mask, bool), window // 2)
    win = kp[frames]  # (T, w, 13, 3)
    xy, conf = win[..., :2], win[..., 2]
    vis = conf > 0
    if stabilise is not None:
        intrinsics, cameras, depth = stabilise
        xy = jnp.where(vis[..., None], stabilise_window(xy, frames, jnp.asarray(intrinsics, xy.dtype),
                                                        jnp.asarray(cameras), jnp.asarray(depth)), xy)
    root = _root(xy, vis)
    size = body_size(xy, vis, image_size)
    rel = (xy - root[:, None, None, :]) / size[:, None, None, None]
    rel = jnp.clip(rel, -FEATURE_CLIP, FEATURE_CLIP)
    feats = jnp.concatenate([rel, conf[..., None]], axis=-1) * vis[..., None]
    return feats.reshape(T, window * NUM_JOINTS * 3)


def flip_features(features: Array) -> Array:
    """The features of the horizontally mirrored keypoints: x negated, left/right joints
    swapped (equal to :func:`contact_features` of :func:`flip_keypoints`)."""
    f = jnp.asarray(features).reshape(*jnp.shape(features)[:-1], -1, NUM_JOINTS, 3)
    perm = np.arange(NUM_JOINTS)
    for a, b in LOWER_BODY_FLIP:
        perm[a], perm[b] = b, a
    f = f[..., perm, :] * jnp.array([-1.0, 1.0, 1.0], f.dtype)
    return f.reshape(jnp.shape(features))


def flip_keypoints(keypoints: Array, image_size: Array, layout: str = "body25") -> Array:
    """Horizontally mirrored keypoints (..., J, 3): ``x -> width - x`` for detected joints and
    every left/right pair of the layout swapped (undetected joints stay zeros)."""
    lay = get_layout(layout)
    kp = jnp.asarray(keypoints)
    perm = np.arange(lay.num_joints)
    for a, b in lay.flip_pairs:
        perm[a], perm[b] = b, a
    kp = kp[..., perm, :]
    width = jnp.asarray(image_size, kp.dtype)[0]
    x = jnp.where(kp[..., 2] > 0, width - kp[..., 0], 0.0)
    return kp.at[..., 0].set(x)


def flip_contacts(labels: Array) -> Array:
    """Contact labels (..., 4) of the mirrored clip: left and right swapped."""
    return jnp.asarray(labels)[..., list(CONTACT_FLIP)]


def mlp_widths(params) -> tuple[int, ...]:
    """The hidden widths of a :class:`~jmocap.nets.ContactMLP` from its parameters."""
    p = params["params"]
    n = sum(1 for k in p if k.startswith("Dense_"))
    return tuple(int(np.shape(p[f"Dense_{i}"]["kernel"])[1]) for i in range(n - 1))


def window_of(params) -> int:
    """The input window (frames) of a :class:`~jmocap.nets.ContactMLP` from its parameters."""
    rows = int(np.shape(params["params"]["Dense_0"]["kernel"])[0])
    if rows % (NUM_JOINTS * 3) or (rows // (NUM_JOINTS * 3)) % 2 == 0:
        raise ValueError(f"contact-MLP input of {rows} features is not an odd window of "
                         f"{NUM_JOINTS} joints x 3")
    return rows // (NUM_JOINTS * 3)


def init_contact_params(key, widths: tuple[int, ...] = ContactMLP.widths, window: int = WINDOW) -> dict:
    """Fresh variables ``{"params", "batch_stats"}`` of the contact MLP for a ``window``-frame input."""
    return ContactMLP(widths=tuple(widths)).init(key, jnp.zeros((1, window * NUM_JOINTS * 3)), train=False)


def window_logits(params, features: Array, train: bool = False, rngs=None):
    """Contact logits (..., 5, 4) of frames ``t-2 .. t+2`` for the features (..., w x 39) of
    target frames ``t``. ``params`` are the MLP's variables (``params`` and ``batch_stats``).

    With ``train=True`` (dropout on, batch statistics of this batch; ``rngs={"dropout": key}``)
    returns ``(logits, {"batch_stats": updated running statistics})``.
    """
    net = ContactMLP(widths=mlp_widths(params))
    shape = (*jnp.shape(features)[:-1], OUT_FRAMES, 4)
    if train:
        out, upd = net.apply(params, features, train=True, rngs=rngs, mutable=["batch_stats"])
        return out.reshape(shape), upd
    return net.apply(params, features, train=False).reshape(shape)


def refiner_inputs(params, features: Array, mask: Array) -> Array:
    """The temporal refiner's per-frame input (T, 24 + H) from the contact MLP's variables
    ``params`` and the features (T, w x 39) of every target frame: the MLP's window
    probabilities of frames ``t-2 .. t+2`` (20) and Rempe's vote (4), both mapped to [-1, 1],
    then the MLP's last hidden layer (H = 32 for the shipped widths). Padded frames (``mask``
    False) are zeros."""
    net = ContactMLP(widths=mlp_widths(params), return_hidden=True)
    hidden, logits = net.apply(params, features, train=False)
    p = jax.nn.sigmoid(logits).reshape(*logits.shape[:-1], OUT_FRAMES, 4)
    v = vote(p, mask)
    seq = jnp.concatenate([2.0 * p.reshape(*p.shape[:-2], -1) - 1.0, 2.0 * v - 1.0, hidden], -1)
    return seq * jnp.asarray(mask, seq.dtype)[:, None]


def refiner_logits(refiner, seq: Array, mask: Array, train: bool = False, rngs=None) -> Array:
    """Contact logits (T, 4) of :class:`~jmocap.nets.ContactTCN` (variables ``refiner``) over a
    clip's refiner input ``seq`` (T, C) (:func:`refiner_inputs`)."""
    return ContactTCN(**tcn_config(refiner)).apply(refiner, seq, mask, train=train, rngs=rngs)


def tcn_config(refiner) -> dict:
    """The :class:`~jmocap.nets.ContactTCN` architecture of a refiner's variables: width and
    kernel from the first convolution's weights, dilations 1, 2, 4, ... one per convolution."""
    p = refiner["params"]
    n = sum(1 for k in p if k.startswith("Conv_"))
    kernel = np.shape(p["Conv_0"]["kernel"])
    return {"width": int(kernel[-1]), "kernel": int(kernel[0]), "dilations": tuple(2 ** i for i in range(n))}


def init_refiner_params(key, channels: int, width: int = 64, blocks: int = 5, kernel: int = 3) -> dict:
    """Fresh refiner variables ``{"params"}`` for ``channels`` input features per frame:
    ``blocks`` convolutions of dilations 1, 2, 4, ... (receptive field ``(kernel - 1)
    (2^blocks - 1)`` frames on each side)."""
    net = ContactTCN(width=width, dilations=tuple(2 ** i for i in range(blocks)), kernel=kernel)
    return net.init(key, jnp.zeros((8, channels)), jnp.ones(8, bool))


def refined_probabilities(params, refiner, features: Array, mask: Array, mirror: bool = True) -> Array:
    """Refined contact probabilities (T, 4) of one clip: the temporal refiner over the contact
    MLP's outputs; with ``mirror`` (static) the mean with the mirror image's, left and right
    swapped back, as for :func:`window_probabilities`. Padded frames 0."""
    p = jax.nn.sigmoid(refiner_logits(refiner, refiner_inputs(params, features, mask), mask))
    if mirror:
        ff = flip_features(features)
        pf = jax.nn.sigmoid(refiner_logits(refiner, refiner_inputs(params, ff, mask), mask))
        p = 0.5 * (p + flip_contacts(pf))
    return p * jnp.asarray(mask, p.dtype)[:, None]


def vote(window_probs: Array, mask: Array) -> Array:
    """Rempe et al.'s majority voting over overlapping predictions.

    ``window_probs`` (T, 5, 4): for target frame ``s``, entry ``k`` is the probability of
    contact at frame ``s + k - 2``. Frame ``t`` collects the votes ``window_probs[s, t - s + 2]
    > 0.5`` of the targets ``s = t-2 .. t+2`` inside the clip with ``mask[s]`` True. Returns
    (T, 4) the fraction of its votes saying "in contact": ``> 0.5`` is the majority decision,
    and a tie (2 of 4 votes, at the second and second-to-last frames) is 0.5, i.e. *not* in
    contact. Padded frames (``mask`` False) get 0.
    """
    p = jnp.asarray(window_probs)
    mask = jnp.asarray(mask, bool)
    T = p.shape[0]
    t = jnp.arange(T)
    votes = (p > 0.5).astype(p.dtype)
    total = jnp.zeros((T, p.shape[-1]), p.dtype)
    count = jnp.zeros((T,), p.dtype)
    for k in range(OUT_FRAMES):
        s = t + HALF_OUT - k
        sc = jnp.clip(s, 0, T - 1)
        ok = (s >= 0) & (s < T) & mask[sc]
        total = total + jnp.where(ok[:, None], votes[sc, k], 0.0)
        count = count + ok
    frac = total / jnp.maximum(count, 1.0)[:, None]
    return jnp.where((mask & (count > 0))[:, None], frac, 0.0)


def window_probabilities(params, inputs: ClipInputs, layout: str = "body25", mirror: bool = True,
                         depth: Array | None = None) -> Array:
    """Contact probabilities (T, 5, 4) of every target frame's 5-frame window. With ``mirror``
    (static), the mean of the MLP's probabilities for the keypoints and for their horizontal
    mirror image (:func:`flip_features`, its left and right contacts swapped back): the network
    was trained on both, and a person and their mirror image make the same contacts. On the
    validation archives (shipped weights of stop 42) voted F1 89.5 -> 89.6 % (``data/val``),
    86.7 -> 87.3 % (``data/val_walk``), 85.2 -> 85.4 % (``data/val_flight``), for a second pass
    of the MLP (docs/method.md, "Contact estimation"). With ``depth`` (T,), the person's depth
    in every frame's camera, each window is first seen from its target frame's camera
    (:func:`contact_features`' ``stabilise``): a moving camera's motion taken out."""
    f = window_features(params, inputs, layout, depth)
    p = jax.nn.sigmoid(window_logits(params, f))
    if mirror:
        p = 0.5 * (p + flip_contacts(jax.nn.sigmoid(window_logits(params, flip_features(f)))))
    return p


def window_features(params, inputs: ClipInputs, layout: str = "body25", depth: Array | None = None) -> Array:
    """The MLP's input (T, w x 39) of one clip (:func:`contact_features`), each window seen from
    its target frame's camera where ``depth`` (T,) is given (:func:`window_probabilities`)."""
    stab = None if depth is None else (inputs.intrinsics, inputs.world_to_camera(), depth)
    return contact_features(inputs.keypoints, inputs.image_size, inputs.mask, layout, window_of(params), stab)


def estimate_contacts(params, inputs: ClipInputs, layout: str = "body25", mirror: bool = True,
                      depth: Array | None = None, refiner=None) -> Array:
    """Contact estimates (T, 4) in [0, 1] of one clip (``> 0.5``: in contact; L heel, L toe,
    R heel, R toe); padded frames 0. Without ``refiner``, Rempe et al.'s voted fractions of the
    contact MLP (variables ``params``); with the temporal refiner's variables ``refiner``, its
    probabilities over the MLP's outputs (:func:`refined_probabilities`). ``mirror`` (static)
    and ``depth`` (the person's depth per frame, for a moving camera): see
    :func:`window_probabilities`. ``jax.jit`` / ``jax.vmap`` over clips apply (``layout`` and
    ``mirror`` static)."""
    if refiner is not None:
        return refined_probabilities(params, refiner, window_features(params, inputs, layout, depth), inputs.mask, mirror)
    return vote(window_probabilities(params, inputs, layout, mirror, depth), inputs.mask)


#: the foot keypoints of each contact point for the velocity baseline (L heel, L toe, R heel,
#: R toe; a toe is the mean of the big and small toe)
_FOOT_KEYPOINTS = (("LHeel",), ("LBigToe", "LSmallToe"), ("RHeel",), ("RBigToe", "RSmallToe"))


def foot_speed(keypoints: Array, image_size: Array, mask: Array, layout: str = "body25") -> Array:
    """The 2D-velocity baseline's input (T, 4): each contact point's keypoint displacement per
    frame (central difference, edges and padded frames replicated) in body sizes
    (:func:`body_size` of the frame's 9-frame window); ``inf`` where a keypoint of it is
    undetected in a frame the difference reads."""
    sel = lower_body_indices(layout)
    kp = jnp.asarray(keypoints)[:, sel].astype(jnp.float32)
    mask = jnp.asarray(mask, bool)
    win = kp[window_frames(mask)]
    size = body_size(win[..., :2], win[..., 2] > 0, image_size)
    nb = kp[window_frames(mask, half=1)]  # (T, 3, 13, 3)
    out = []
    for names in _FOOT_KEYPOINTS:
        idx = [LOWER_BODY.index(n) for n in names]
        p = jnp.mean(nb[:, :, idx, :2], axis=2)  # (T, 3, 2)
        ok = jnp.all(nb[:, :, idx, 2] > 0, axis=(1, 2))
        d = jnp.linalg.norm(p[:, 2] - p[:, 0], axis=-1) / 2.0 / size
        out.append(jnp.where(ok, d, jnp.inf))
    return jnp.stack(out, -1)


def velocity_contacts(keypoints: Array, image_size: Array, mask: Array, threshold: float,
                      layout: str = "body25") -> Array:
    """Rempe et al.'s 2D-velocity baseline (Sec. 4.1): a contact point is in contact (1.0) when its
    foot keypoint moves less than ``threshold`` body sizes per frame (:func:`foot_speed`);
    undetected keypoints and padded frames give 0."""
    speed = foot_speed(keypoints, image_size, mask, layout)
    return jnp.where(jnp.asarray(mask, bool)[:, None] & (speed < threshold), 1.0, 0.0)


def load_contact_params(path) -> dict:
    """Contact-MLP variables from a msgpack file (float16 or float32), as float32 arrays."""
    return load_float32_params(path)


def contact_params(params) -> dict:
    """The contact MLP's variables a method uses: ``params["contacts"]`` where a run's
    parameters carry their own, else the shipped ones (:func:`default_contact_params`).

    The methods' history and lookahead (``pip``'s chunking) are sized for :data:`WINDOW`, so
    weights with another input window are refused here rather than run with too little context."""
    if isinstance(params, dict) and "contacts" in params:
        got = window_of(params["contacts"])
        if got != WINDOW:
            raise ValueError(f"params['contacts'] reads a {got}-frame window; the methods are sized for "
                             f"jmocap.methods.contact_estimation.WINDOW = {WINDOW}")
        return params["contacts"]
    return default_contact_params()


def refiner_params(params) -> dict:
    """The temporal refiner's variables a method uses: ``params["contact_refiner"]`` where a
    run's parameters carry their own, else the shipped ones (:func:`default_refiner_params`)."""
    if isinstance(params, dict) and "contact_refiner" in params:
        return params["contact_refiner"]
    return default_refiner_params()


@functools.cache
def default_refiner_params() -> dict:
    """The shipped refiner variables (``jmocap/assets/contact_refiner.msgpack``, float16 on
    disk, float32 here), made by ``experiments/train_contact_refiner.py --ship``."""
    if not REFINER_ASSET.exists():
        raise FileNotFoundError(f"no shipped contact refiner at {REFINER_ASSET}; train it with "
                                f"experiments/train_contact_refiner.py --ship")
    return load_float32_params(REFINER_ASSET)


@functools.cache
def default_contact_params() -> dict:
    """The shipped contact-MLP variables (``jmocap/assets/contact_mlp.msgpack``, float16 on disk,
    float32 here), made by ``experiments/train_contacts.py --ship``."""
    if not ASSET.exists():
        raise FileNotFoundError(f"no shipped contact weights at {ASSET}; train them with "
                                f"experiments/train_contacts.py --ship")
    return load_contact_params(ASSET)


__all__ = [
    "CONTACT_FLIP",
    "contact_params",
    "HALF_OUT",
    "HALF_WINDOW",
    "LOWER_BODY",
    "LOWER_BODY_FLIP",
    "NUM_FEATURES",
    "OUT_FRAMES",
    "WINDOW",
    "body_size",
    "contact_features",
    "default_contact_params",
    "default_refiner_params",
    "estimate_contacts",
    "flip_contacts",
    "foot_speed",
    "flip_features",
    "flip_keypoints",
    "init_contact_params",
    "init_refiner_params",
    "load_contact_params",
    "lower_body_indices",
    "mlp_widths",
    "nearest_real_frame",
    "refined_probabilities",
    "refiner_inputs",
    "refiner_logits",
    "refiner_params",
    "tcn_config",
    "velocity_contacts",
    "vote",
    "window_frames",
    "window_logits",
    "window_of",
    "window_probabilities",
]
