"""Tests of jmocap.methods.contact_estimation (Rempe et al. 2020, Sec. 3.2 / Appendix A.2):
majority voting on a hand-worked example, the feature normalisation on hand-made poses (root,
body size, edge and padded-frame replication), invariance to 2D translation and to uniform image
scaling, the horizontal flip of keypoints, features and labels, jit + vmap over padded clips,
and the shipped weights on freshly generated synthetic clips against the majority class; jmocap's
temporal refiner over the MLP: its receptive field, padding, batching and mirror symmetry."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jmocap.constants import CONTACT_SITES
from jmocap.inputs import ClipInputs
from jmocap.layouts import BODY25
from jmocap.methods import contact_estimation as ce

J = BODY25.num_joints
# jitted once per shape: far faster than op-by-op dispatch
features = jax.jit(ce.contact_features, static_argnums=3)
vote = jax.jit(ce.vote)


def _pose(t_shift=(0.0, 0.0)) -> np.ndarray:
    """A BODY_25 frame (J, 3): lower body at hand-picked pixels, upper body undetected.

    Right leg hip (90, 100) - knee (90, 140) - ankle (90, 180): 40 + 40 = 80 px; left leg
    (110, 100) - (110, 130) - (110, 160): 30 + 30 = 60 px. So the body size is 80 px."""
    kp = np.zeros((J, 3), np.float32)
    pts = {"MidHip": (100, 100), "RHip": (90, 100), "RKnee": (90, 140), "RAnkle": (90, 180),
           "LHip": (110, 100), "LKnee": (110, 130), "LAnkle": (110, 160),
           "LBigToe": (120, 165), "LSmallToe": (118, 166), "LHeel": (108, 164),
           "RBigToe": (80, 185), "RSmallToe": (82, 186), "RHeel": (92, 184)}
    for name, (x, y) in pts.items():
        kp[BODY25.index(name)] = (x + t_shift[0], y + t_shift[1], 0.9)
    return kp


def _feat(f, t, slot, joint):
    """Feature (x, y, c) of window slot ``slot`` of target ``t`` for a joint name."""
    return np.asarray(f).reshape(-1, ce.WINDOW, ce.NUM_JOINTS, 3)[t, slot, ce.LOWER_BODY.index(joint)]


# ---------------------------------------------------------------------------------------
# voting
# ---------------------------------------------------------------------------------------


def test_vote_hand_worked():
    # votes[s, k] of contact 0 (target s predicts frame s + k - 2); 0.5 is *not* a vote for contact
    hi, lo = 0.9, 0.1
    p = np.zeros((6, 5, 4), np.float32)
    p[0, :, 0] = [hi, hi, hi, lo, lo]     # frames -2..2: frame 0 yes, 1 no, 2 no
    p[1, :, 0] = [hi, hi, hi, hi, hi]     # frames -1..3: 0, 1, 2, 3 yes
    p[2, :, 0] = [0.5] * 5                # frames 0..4: all no (0.5 is not > 0.5)
    p[3, :, 0] = [hi, hi, hi, hi, hi]     # frames 1..5: 1, 2, 3, 4 yes (5 is padded)
    p[4, :, 0] = [lo, hi, lo, hi, hi]     # frames 2..6: 2 no, 3 yes, 4 no
    p[5] = hi                             # a padded target: never votes
    mask = np.array([1, 1, 1, 1, 1, 0], bool)
    got = np.asarray(vote(p, mask))
    # frame 0: s=0,1,2 -> 1,1,0; frame 1: s=0..3 -> 0,1,0,1 (a tie); frame 2: s=0..4 -> 0,1,0,1,0;
    # frame 3: s=1..4 -> 1,0,1,1; frame 4: s=2..4 -> 0,1,0; frame 5 padded
    want = np.array([2 / 3, 2 / 4, 2 / 5, 3 / 4, 1 / 3, 0.0])
    np.testing.assert_allclose(got[:, 0], want, rtol=1e-6)
    np.testing.assert_array_equal(got[:, 1:], 0.0)
    # the majority decision: frame 1's tie is "not in contact"
    np.testing.assert_array_equal(got[:, 0] > 0.5, [True, False, False, True, False, False])


def test_vote_all_agree_is_one():
    p = np.full((7, 5, 4), 0.8, np.float32)
    np.testing.assert_array_equal(np.asarray(vote(p, np.ones(7, bool))), 1.0)


# ---------------------------------------------------------------------------------------
# features
# ---------------------------------------------------------------------------------------


def test_features_hand_worked_pose():
    kp = np.stack([_pose()] * 3)
    f = features(kp, np.array([640.0, 480.0]), np.ones(3, bool))
    assert f.shape == (3, 9 * 13 * 3)
    # root MidHip (100, 100), body size 80 px (the right leg, the longer one)
    np.testing.assert_allclose(_feat(f, 1, 4, "LAnkle"), [10 / 80, 60 / 80, 0.9], rtol=1e-6)
    np.testing.assert_allclose(_feat(f, 1, 0, "RBigToe"), [-20 / 80, 85 / 80, 0.9], rtol=1e-6)
    np.testing.assert_allclose(_feat(f, 1, 4, "MidHip"), [0.0, 0.0, 0.9], atol=1e-7)


def test_features_root_fallback_and_undetected_joints():
    kp = np.stack([_pose()] * 3)
    kp[:, BODY25.index("MidHip")] = 0.0  # undetected everywhere: the root is the mean of the hips
    kp[:, BODY25.index("LHip"), :2] = (112, 104)  # hips (90, 100), (112, 104): mean (101, 102)
    kp[1, BODY25.index("RHeel")] = 0.0  # undetected in the target frame
    f = features(kp, np.array([640.0, 480.0]), np.ones(3, bool))
    # left leg now 2 * ~30 px; the right leg (80 px) stays the longer
    np.testing.assert_allclose(_feat(f, 1, 4, "RAnkle"), [(90 - 101) / 80, (180 - 102) / 80, 0.9], rtol=1e-6)
    np.testing.assert_array_equal(_feat(f, 1, 4, "MidHip"), 0.0)
    np.testing.assert_array_equal(_feat(f, 1, 4, "RHeel"), 0.0)
    np.testing.assert_allclose(_feat(f, 1, 3, "RHeel"), [(92 - 101) / 80, (184 - 102) / 80, 0.9], rtol=1e-6)


def test_window_frames_replicate_edges_and_padded_frames():
    w = np.asarray(ce.window_frames(np.array([1, 1, 1, 1, 0, 0], bool)))
    np.testing.assert_array_equal(w[0], [0, 0, 0, 0, 0, 1, 2, 3, 3])
    np.testing.assert_array_equal(w[3], [0, 0, 1, 2, 3, 3, 3, 3, 3])
    np.testing.assert_array_equal(w[5], [1, 2, 3, 3, 3, 3, 3, 3, 3])
    # an interior hole: frame 2 is as near to 1 as to 3 (the earlier wins), frame 3 to 4
    w = np.asarray(ce.window_frames(np.array([1, 1, 0, 0, 1, 1], bool)))
    np.testing.assert_array_equal(w[2], [0, 0, 0, 1, 1, 4, 4, 5, 5])


def test_features_replicate_frames_at_edges_and_padding():
    # the person walks 10 px per frame to the right; frames 4, 5 are padding (garbage keypoints)
    kp = np.stack([_pose((10.0 * t, 0.0)) for t in range(6)])
    kp[4:, :, :2] = 1e4
    mask = np.array([1, 1, 1, 1, 0, 0], bool)
    f = features(kp, np.array([640.0, 480.0]), mask)
    x0 = [_feat(f, 0, s, "MidHip")[0] for s in range(9)]
    np.testing.assert_allclose(x0, np.array([0, 0, 0, 0, 0, 10, 20, 30, 30]) / 80, atol=1e-6)
    x3 = [_feat(f, 3, s, "MidHip")[0] for s in range(9)]
    np.testing.assert_allclose(x3, np.array([-30, -30, -20, -10, 0, 0, 0, 0, 0]) / 80, atol=1e-6)


def _random_clip(seed=0, T=20):
    rng = np.random.default_rng(seed)
    base = _pose((300.0, 200.0))
    kp = np.repeat(base[None], T, 0)
    kp[..., :2] += rng.normal(scale=6.0, size=(T, J, 2)) * (kp[..., 2:] > 0)
    kp[..., 2] = np.where(kp[..., 2] > 0, rng.uniform(0.3, 1.0, (T, J)), 0.0)
    drop = rng.uniform(size=(T, J)) < 0.15
    kp[drop] = 0.0
    return kp.astype(np.float32)


def test_features_invariant_to_translation_and_image_scale():
    kp = _random_clip()
    size = np.array([1280.0, 720.0])
    mask = np.arange(20) < 17
    f = np.asarray(features(kp, size, mask))
    vis = kp[..., 2:] > 0
    moved = kp.copy()
    moved[..., :2] += np.array([-137.0, 58.5]) * vis
    np.testing.assert_allclose(np.asarray(features(moved, size, mask)), f, atol=2e-5)
    scaled = kp.copy()
    scaled[..., :2] *= 2.5
    np.testing.assert_allclose(np.asarray(features(scaled, 2.5 * size, mask)), f, atol=2e-5)
    assert np.abs(f).max() <= ce.FEATURE_CLIP and np.any(f != 0)


def test_other_layouts_raise():
    with pytest.raises(ValueError, match="coco17"):
        ce.contact_features(np.zeros((5, 17, 3)), np.array([640.0, 480.0]), np.ones(5, bool), "coco17")


# ---------------------------------------------------------------------------------------
# flip augmentation
# ---------------------------------------------------------------------------------------


def test_flip_swaps_contact_labels_left_right():
    # jmocap's order: L heel, L toe, R heel, R toe
    assert CONTACT_SITES == ("contact_left_heel", "contact_left_toe", "contact_right_heel", "contact_right_toe")
    labels = np.array([[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 1.0, 1.0]])
    np.testing.assert_array_equal(np.asarray(ce.flip_contacts(labels)), [[0, 1, 1, 0], [1, 1, 0, 1]])


def test_flip_keypoints_mirrors_and_swaps_joints():
    kp = _pose()[None]
    kp[0, BODY25.index("Nose")] = (100.0, 20.0, 0.7)
    out = np.asarray(ce.flip_keypoints(kp, np.array([640.0, 480.0])))[0]
    # the new left heel is the mirrored right heel (92, 184) -> (640 - 92, 184)
    np.testing.assert_allclose(out[BODY25.index("LHeel")], [548.0, 184.0, 0.9])
    np.testing.assert_allclose(out[BODY25.index("RBigToe")], [520.0, 165.0, 0.9])
    np.testing.assert_allclose(out[BODY25.index("Nose")], [540.0, 20.0, 0.7])
    assert np.all(out[BODY25.index("Neck")] == 0)  # undetected stays zero


def test_flip_features_equal_features_of_flipped_keypoints():
    kp = _random_clip(1)
    size = np.array([1280.0, 720.0])
    mask = np.ones(20, bool)
    a = ce.flip_features(features(kp, size, mask))
    b = features(ce.flip_keypoints(kp, size), size, mask)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=2e-5)


# ---------------------------------------------------------------------------------------
# jit + vmap, and the shipped weights on synthetic clips
# ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def clips():
    """Three short synthetic clips tracked in simulation (force-and-floor contact labels, like the held-out
    archive), seed 2024 (neither the training seed 7 nor the held-out 123)."""
    from jmocap.data import synthetic as S

    cfg = S.SynthConfig(frames=40, physics=True)
    return [S.generate_clip(2024, i, cfg) for i in range(3)]


@pytest.fixture(scope="module")
def params():
    return ce.default_contact_params()


def test_shipped_weights_load_as_float32(params):
    leaves = jax.tree.leaves(params)
    assert leaves and all(np.asarray(x).dtype == np.float32 for x in leaves)
    assert ce.mlp_widths(params)[-1] == 32 and "batch_stats" in params
    assert ce.default_contact_params() is params  # cached


def test_jit_vmap_over_padded_clips_equals_per_clip(params, clips):
    a, b = clips[0].slice(0, 30), clips[1]
    batch = jax.tree.map(lambda *x: np.stack(x), ClipInputs.from_clip(a, 48), ClipInputs.from_clip(b, 48))
    got = np.asarray(jax.jit(jax.vmap(ce.estimate_contacts, in_axes=(None, 0)))(params, batch))
    assert got.shape == (2, 48, 4)
    one = jax.jit(ce.estimate_contacts)
    for i, c in enumerate((a, b)):
        own = np.asarray(one(params, ClipInputs.from_clip(c)))
        np.testing.assert_allclose(got[i, : c.num_frames], own, atol=1e-6)
        np.testing.assert_array_equal(got[i, c.num_frames:], 0.0)
        assert np.all((own >= 0) & (own <= 1))


def test_mirror_averaged_estimate_is_mirror_symmetric(params, clips):
    """With ``mirror`` the window probabilities of a mirrored clip are those of the clip with left
    and right swapped (the average over a clip and its mirror image is symmetric by
    construction); the network alone is not, so the plain estimate is not."""
    c = clips[0]
    inp = ClipInputs.from_clip(c, 64)
    flipped = inp.replace(keypoints=ce.flip_keypoints(inp.keypoints, inp.image_size))
    probs = jax.jit(ce.window_probabilities, static_argnums=(2, 3))
    for mirror in (True, False):
        a = np.asarray(probs(params, inp, "body25", mirror))
        b = np.asarray(ce.flip_contacts(probs(params, flipped, "body25", mirror)))
        gap = np.max(np.abs(a - b)[: c.num_frames])
        if mirror:
            assert gap < 1e-5, gap
        else:
            assert gap > 1e-3, gap
    # mirroring averages two estimates: between them, frame by frame
    plain = np.asarray(probs(params, inp, "body25", False))
    other = np.asarray(ce.flip_contacts(probs(params, flipped, "body25", False)))
    avg = np.asarray(probs(params, inp, "body25", True))
    np.testing.assert_allclose(avg, 0.5 * (plain + other), atol=1e-6)


def _f1(pred, gt):
    tp = np.sum(pred & gt)
    return 2 * tp / (2 * tp + np.sum(pred & ~gt) + np.sum(~pred & gt))


def test_shipped_weights_beat_the_majority_class(params, clips):
    est = jax.jit(ce.estimate_contacts)
    # one padded length: one compilation
    pred = np.concatenate([np.asarray(est(params, ClipInputs.from_clip(c, 48)))[: c.num_frames]
                           for c in clips]) > 0.5
    gt = np.concatenate([c.gt_contacts for c in clips]) > 0.5
    # the majority label of these very clips, per contact point (a baseline that sees the answers)
    majority = np.broadcast_to(gt.mean(0) > 0.5, gt.shape)
    f1, base = _f1(pred, gt), _f1(majority, gt)
    print(f"voted F1 {f1:.3f}, majority F1 {base:.3f}, accuracy {np.mean(pred == gt):.3f} vs "
          f"{np.mean(majority == gt):.3f}, kinds {[c.meta['kind'] for c in clips]}")
    assert f1 > base, (f1, base)
    assert np.mean(pred == gt) > np.mean(majority == gt)


def test_window_is_read_from_the_weights_and_other_windows_are_refused_by_the_methods(params):
    assert ce.window_of(params) == ce.WINDOW
    wide = ce.init_contact_params(jax.random.PRNGKey(0), (16, 8), window=15)
    assert ce.window_of(wide) == 15
    kp = np.stack([_pose((3.0 * t, 0.0)) for t in range(20)])
    f = np.asarray(jax.jit(ce.contact_features, static_argnums=(3, 4))(
        kp, np.array([640.0, 480.0]), np.ones(20, bool), "body25", 15))
    assert f.shape == (20, 15 * ce.NUM_JOINTS * 3)
    # slot 7 of a 15-frame window is the target frame, as slot 4 of the 9-frame one (the body
    # size is a median over constant leg lengths, so it is the same here)
    f9 = np.asarray(features(kp, np.array([640.0, 480.0]), np.ones(20, bool)))
    np.testing.assert_allclose(f.reshape(20, 15, -1)[:, 7], f9.reshape(20, 9, -1)[:, 4], atol=1e-6)
    inp = ClipInputs(keypoints=kp, intrinsics=np.array([500.0, 500.0, 320.0, 240.0], np.float32),
                     image_size=np.array([640.0, 480.0], np.float32), extrinsics=np.eye(4, dtype=np.float32),
                     fps=np.float32(30.0), mask=np.ones(20, bool))
    out = np.asarray(ce.estimate_contacts(wide, inp))
    assert out.shape == (20, 4) and np.all((out >= 0) & (out <= 1))
    with pytest.raises(ValueError, match="15-frame window"):
        ce.contact_params({"contacts": wide})
    with pytest.raises(ValueError, match="odd"):
        ce.contact_features(kp, np.array([640.0, 480.0]), np.ones(20, bool), "body25", 8)


# ---------------------------------------------------------------------------------------
# the temporal refiner (jmocap.nets.ContactTCN over the MLP's outputs)
# ---------------------------------------------------------------------------------------


def test_refiner_reads_its_receptive_field_and_ignores_padding():
    """Kernel 3 and dilations 1..16 read 2 (1 + 2 + 4 + 8 + 16) = 62 frames: an input change at
    frame 50 moves the outputs of frames 19..81 and no other; zero padding beyond a clip changes
    nothing (padded frames are zeros at every convolution's input, as 'SAME' pads the ends)."""
    r = ce.init_refiner_params(jax.random.PRNGKey(0), 56)
    assert ce.tcn_config(r) == {"width": 64, "kernel": 3, "dilations": (1, 2, 4, 8, 16)}
    x = np.asarray(jax.random.normal(jax.random.PRNGKey(1), (120, 56)))
    mask = np.ones(120, bool)
    logits = jax.jit(ce.refiner_logits)
    a = np.asarray(logits(r, x, mask))
    x2 = x.copy()
    x2[50] += 1.0
    moved = np.abs(np.asarray(logits(r, x2, mask)) - a).max(-1) > 1e-6
    assert moved[19:82].all() and not moved[:19].any() and not moved[82:].any()
    # the same clip padded (with garbage behind the mask) gives the same logits on its frames
    pad = np.concatenate([x, 100.0 * np.ones((40, 56), np.float32)])
    b = np.asarray(logits(r, pad, np.arange(160) < 120))
    np.testing.assert_allclose(b[:120], a, atol=2e-5)


#: one compiled program for the refined estimate of a 48-frame padded clip, shared by the tests
_refined = jax.jit(lambda p, r, inp: ce.estimate_contacts(p, inp, refiner=r))


def test_refined_estimate_batches_and_is_mirror_symmetric(params, clips):
    """vmapped over padded clips = one clip at a time (padding itself: the test above)."""
    r = ce.default_refiner_params()
    a, b = clips[0].slice(0, 30), clips[1]
    batch = jax.tree.map(lambda *x: np.stack(x), ClipInputs.from_clip(a, 48), ClipInputs.from_clip(b, 48))
    est = jax.jit(jax.vmap(lambda p, r, inp: ce.estimate_contacts(p, inp, refiner=r), in_axes=(None, None, 0)))
    got = np.asarray(est(params, r, batch))
    one = _refined
    for i, c in enumerate((a, b)):
        own = np.asarray(one(params, r, ClipInputs.from_clip(c, 48)))[: c.num_frames]
        np.testing.assert_allclose(got[i, : c.num_frames], own, atol=1e-5)
        np.testing.assert_array_equal(got[i, c.num_frames:], 0.0)
        assert np.all((own >= 0) & (own <= 1))
    inp = ClipInputs.from_clip(b, 48)
    flipped = inp.replace(keypoints=ce.flip_keypoints(inp.keypoints, inp.image_size))
    np.testing.assert_allclose(np.asarray(ce.flip_contacts(one(params, r, flipped))), got[1], atol=1e-5)


def test_shipped_refiner_loads_and_beats_the_majority_class(params, clips):
    r = ce.default_refiner_params()
    assert all(np.asarray(x).dtype == np.float32 for x in jax.tree.leaves(r))
    assert ce.tcn_config(r)["dilations"] == (1, 2, 4, 8, 16) and ce.default_refiner_params() is r
    assert ce.refiner_params({"contact_refiner": "own"}) == "own" and ce.refiner_params({}) is r
    pred = np.concatenate([np.asarray(_refined(params, r, ClipInputs.from_clip(c, 48)))[: c.num_frames]
                           for c in clips]) > 0.5
    gt = np.concatenate([c.gt_contacts for c in clips]) > 0.5
    majority = np.broadcast_to(gt.mean(0) > 0.5, gt.shape)
    assert _f1(pred, gt) > _f1(majority, gt) and np.mean(pred == gt) > np.mean(majority == gt)


# ---------------------------------------------------------------------------------------
# the learned support prior (jmocap.methods.support: the net vertical force, same TCN)
# ---------------------------------------------------------------------------------------


def test_support_network_batches_ignores_padding_and_is_mirror_symmetric(params, clips):
    """Fresh variables: a clip padded to 48 or 64 frames gives the same force on its frames and one
    body weight on the padding; vmapped over clips = one at a time; the mirror image (left and
    right swapped, x negated) gives the same vertical force."""
    from jmocap.methods import support as SP

    c = ce.contact_features(np.zeros((8, 25, 3), np.float32), np.array([640.0, 480.0]), np.ones(8, bool))
    channels = SP.support_inputs(params, c, np.ones(8, bool)).shape[-1]
    assert channels == 56 + c.shape[-1]
    v = SP.init_support_params(jax.random.PRNGKey(3), channels)
    run = jax.jit(lambda inp: SP.support_force(params, v, inp))
    a = clips[0].slice(0, 30)
    f48 = np.asarray(run(ClipInputs.from_clip(a, 48)))
    f64 = np.asarray(run(ClipInputs.from_clip(a, 64)))
    np.testing.assert_allclose(f48[:30], f64[:30], atol=1e-5)
    np.testing.assert_array_equal(f48[30:], 1.0)
    assert np.std(f48[:30]) > 1e-4  # it reads the clip
    batch = jax.tree.map(lambda *x: np.stack(x), ClipInputs.from_clip(a, 48), ClipInputs.from_clip(clips[1], 48))
    got = np.asarray(jax.jit(jax.vmap(lambda inp: SP.support_force(params, v, inp)))(batch))
    np.testing.assert_allclose(got[0], f48, atol=1e-5)
    inp = ClipInputs.from_clip(clips[1], 48)
    flipped = inp.replace(keypoints=ce.flip_keypoints(inp.keypoints, inp.image_size))
    np.testing.assert_allclose(np.asarray(run(flipped)), got[1], atol=1e-5)


def test_support_target_is_the_net_vertical_force_in_body_weights(clips):
    """The training target against the simulation: Newton in the clip's own ground truth (its
    contact forces plus the generator's residual balance m (c'' + g) of its centre of mass is
    tested in tests/test_synthetic.py); here the conversion: the sum of the four points' vertical
    forces over m g."""
    from jmocap.constants import GRAVITY
    from jmocap.methods import support as SP

    c = clips[0]
    want = np.array([c.gt_grf[t, :, 2].sum() for t in range(c.num_frames)]) / (c.mass_kg * GRAVITY)
    np.testing.assert_allclose(SP.target(c.gt_grf, c.mass_kg), want, rtol=1e-6)
    assert 0.3 < np.mean(want) < 1.5  # a person on their feet: about one body weight on average


def test_shipped_support_network_beats_one_body_weight(params, clips):
    """The shipped weights (experiments/train_support.py, seeds 17 and 18) on three clips of
    another seed simulated in MuJoCo: the estimated net vertical force is nearer the
    simulation's than one body weight in every frame (the prior before it), over the frames
    whose ground truth the contacts explain."""
    from jmocap.methods import support as SP

    v = SP.default_support_params()
    assert all(np.asarray(x).dtype == np.float32 for x in jax.tree.leaves(v))
    assert SP.support_params({"support": "own"}) == "own" and SP.support_params({}) is v
    run = jax.jit(lambda inp: SP.support_force(params, v, inp))
    est, gt = [], []
    for c in clips:
        ok = c.residual_percent_bw <= 1.0
        est.append(np.asarray(run(ClipInputs.from_clip(c, 48)))[: c.num_frames][ok])
        gt.append(SP.target(c.gt_grf, c.mass_kg)[ok])
    est, gt = np.concatenate(est), np.concatenate(gt)
    assert len(gt) > 40
    assert np.mean(np.abs(est - gt)) < 0.8 * np.mean(np.abs(1.0 - gt)), (np.mean(np.abs(est - gt)), np.mean(np.abs(1.0 - gt)))
