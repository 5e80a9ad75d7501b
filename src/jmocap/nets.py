"""The networks of physionical motion capture (paper Sec. 3.3-3.4 and Appendix A), in flax.

* :class:`TemporalConvNet` — the temporal backbone of TPNet: an embedding block (replication
  padding 1, Conv1D kernel 3, normalisation, ReLU, dropout) and four residual blocks (replication
  padding 4, Conv1D kernel 5 dilation 2, normalisation, ReLU, dropout, skip), then a convolution
  over the whole causal window to one feature vector and a linear head. jmocap normalises with
  layer norm where the paper uses batch norm: every network stays a pure function of
  ``(params, input)`` with no running statistics, so vmapping over clips, streaming and
  training all see the same function.
* :class:`TPNet` — C_P (three replicated backbones: root orientation, joint angles, contact
  probabilities) on root-relative keypoints K_rr, and C_T (root translation) on the
  root-relative 3D joints P_rr of C_P's pose and the canonical keypoints K_c.
* :class:`DyNet` — gains and offsets of the neural PD controller (eq. 7).
* :class:`GRFNet` — ground reaction forces at the contact points.
* :class:`ContactMLP` — Rempe et al. (2020)'s foot-contact classifier (Sec. 3.2, Appendix A.2):
  an MLP on a window of lower-body 2D keypoints, with batch norm (running statistics in the
  ``batch_stats`` collection, the one network here that has them).
* :class:`ContactTCN` — jmocap's temporal refiner of those contacts over the whole clip.

Widths are configurable (:class:`NetConfig`); the defaults are narrower than the paper's 1024 so
that training fits a 2-core CPU (docs/method.md). Everything is a pure function of
``(variables, inputs)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import flax.linen as nn
import jax
import jax.numpy as jnp


@dataclass(frozen=True)
class NetConfig:
    window: int = 10  # causal window of TPNet (frames)
    tp_width: int = 128  # channels of the temporal backbones (paper: 1024)
    tp_blocks: int = 4
    dropout: float = 0.25
    dyn_width: int = 256  # DyNet hidden width (paper: 1024)
    grf_width: int = 256  # GRFNet hidden width (paper: 512)
    gamma: float = 10.0  # alpha = gamma * s_f (paper Appendix A)


def _replicate_pad(x: jnp.ndarray, pad: int) -> jnp.ndarray:
    """Replication padding of both ends of the time axis (axis -2)."""
    return jnp.pad(x, [(0, 0)] * (x.ndim - 2) + [(pad, pad), (0, 0)], mode="edge")


class TemporalConvNet(nn.Module):
    """Window (..., W, F) -> (..., out) through the paper's embedding and residual blocks."""

    out: int
    width: int = 256
    blocks: int = 4
    dropout: float = 0.25

    @nn.compact
    def __call__(self, x: jnp.ndarray, *, train: bool) -> jnp.ndarray:
        W = x.shape[-2]

        def bn():
            return nn.LayerNorm()

        h = nn.Conv(self.width, (3,), padding="VALID", use_bias=False)(_replicate_pad(x, 1))
        h = nn.Dropout(self.dropout, deterministic=not train)(nn.relu(bn()(h)))
        for _ in range(self.blocks):
            r = nn.Conv(self.width, (5,), kernel_dilation=(2,), padding="VALID", use_bias=False)(
                _replicate_pad(h, 4)
            )
            r = nn.Dropout(self.dropout, deterministic=not train)(nn.relu(bn()(r)))
            h = h + r
        h = nn.Conv(self.width, (W,), padding="VALID")(h)[..., 0, :]  # whole window -> one vector
        # normalised before the last ReLU: the residual stream's scale grows with training, and
        # without it the joint-angle head shipped until 2026-12-03 had every unit negative on every
        # input (a dead ReLU layer: a constant pose, whatever the keypoints)
        return nn.Dense(self.out)(nn.relu(bn()(h)))


class TPNet(nn.Module):
    """Target pose network: C_P (orientation, joint angles, contacts) and C_T (translation)."""

    n_hinges: int
    config: NetConfig = NetConfig()

    def setup(self):
        c = self.config
        kw = dict(width=c.tp_width, blocks=c.tp_blocks, dropout=c.dropout)
        self.c_ori = TemporalConvNet(out=6, **kw)  # 6D rotation representation
        self.c_ang = TemporalConvNet(out=self.n_hinges, **kw)
        self.c_con = TemporalConvNet(out=4, **kw)
        self.c_trans = TemporalConvNet(out=3, **kw)

    def pose(self, k_rr: jnp.ndarray, *, train: bool):
        """C_P on a window of root-relative keypoints (..., W, J, 3) (x, y, confidence).

        Returns ``(rot6d (..., 6), hinge_raw (..., n_hinges), contact_logits (..., 4))``.
        """
        x = k_rr.reshape(*k_rr.shape[:-2], -1)
        return (
            self.c_ori(x, train=train),
            self.c_ang(x, train=train),
            self.c_con(x, train=train),
        )

    def translation(self, features: jnp.ndarray, *, train: bool) -> jnp.ndarray:
        """C_T on a window of per-frame features (..., W, F) -> (..., 3) correction."""
        return self.c_trans(features, train=train)

    def __call__(self, k_rr, features, *, train: bool):  # for init: touches every submodule
        return self.pose(k_rr, train=train), self.translation(features, train=train)


class DyNet(nn.Module):
    """Neural PD gains: input vector -> (s_g in (0, 1), s_f in [-1, 1]) per dof (Appendix A)."""

    nv: int
    width: int = 256

    @nn.compact
    def __call__(self, x: jnp.ndarray):
        h = nn.leaky_relu(nn.Dense(self.width)(x), 0.1)
        h = nn.leaky_relu(nn.Dense(self.width)(h), 0.1)
        s_g = nn.sigmoid(nn.Dense(self.nv, kernel_init=nn.initializers.zeros)(h))
        s_f = jnp.tanh(nn.Dense(self.nv, kernel_init=nn.initializers.zeros)(h))
        return s_g, s_f


class GRFNet(nn.Module):
    """Ground reaction forces: input vector -> (C, 3) forces in units of body weight."""

    n_points: int = 4
    width: int = 256

    @nn.compact
    def __call__(self, x: jnp.ndarray):
        h = x
        for _ in range(3):
            h = nn.leaky_relu(nn.Dense(self.width)(h), 0.1)
        out = nn.Dense(3 * self.n_points, kernel_init=nn.initializers.zeros)(h)
        return out.reshape(*x.shape[:-1], self.n_points, 3)


class ContactMLP(nn.Module):
    """Rempe et al. (2020) Appendix A.2: an MLP from a window of lower-body keypoints to the
    contact logits of 5 frames x 4 contact points (``(..., 20)``, frame-major).

    Every hidden layer is Dense -> BatchNorm -> ReLU (batch norm follows all but the last layer),
    with one dropout (``dropout`` = 0.3) before the third hidden layer. The paper's widths are
    (1024, 512, 128, 32); jmocap's default (512, 256, 128, 32) halves the first two so that the
    weights are 0.35 M parameters (0.7 MB shipped as float16, 1.4 MB float32) instead of
    0.95 M, and so that training on a single CPU core finishes in minutes (docs/method.md).
    BatchNorm momentum 0.9 is PyTorch's default (0.1 there). With ``train=True`` call it with
    ``mutable=["batch_stats"]`` and a ``"dropout"`` rng.
    """

    widths: tuple[int, ...] = (512, 256, 128, 32)
    out: int = 20
    dropout: float = 0.3
    dropout_before: int = 2  # index of the hidden layer the dropout precedes (the third)
    momentum: float = 0.9

    #: return ``(last hidden layer, logits)`` instead of the logits (the contact refiner's input)
    return_hidden: bool = False

    @nn.compact
    def __call__(self, x: jnp.ndarray, *, train: bool = False):
        h = x
        for i, w in enumerate(self.widths):
            if i == self.dropout_before:
                h = nn.Dropout(self.dropout, deterministic=not train)(h)
            h = nn.Dense(w)(h)
            h = nn.BatchNorm(use_running_average=not train, momentum=self.momentum)(h)
            h = nn.relu(h)
        logits = nn.Dense(self.out)(h)
        return (h, logits) if self.return_hidden else logits


class ContactTCN(nn.Module):
    """A temporal refiner of per-frame contact estimates over a whole clip (jmocap's addition to
    Rempe et al.'s estimator: docs/method.md, "The temporal refiner").

    Input ``x`` (..., T, C) per frame (the contact MLP's window probabilities, vote and last
    hidden layer) and ``mask`` (..., T) real frames; output the contact logits (..., T, 4). A
    linear embedding, then residual blocks of non-causal dilated 1D convolutions (kernel
    ``kernel``, dilations ``dilations``: with (1, 2, 4, 8, 16) and kernel 3 every output frame
    reads 31 frames on each side, about a second at 30 fps: a gait cycle), each
    LayerNorm -> ReLU -> Conv -> dropout with a skip, and a linear head. Padded frames are zero
    at every convolution's input, so a clip's result does not depend on how far it is padded
    (tested); layer norm, not batch norm, so it stays a pure function of ``(params, x, mask)``.
    """

    width: int = 64
    dilations: tuple[int, ...] = (1, 2, 4, 8, 16)
    kernel: int = 3
    dropout: float = 0.1
    out: int = 4

    @nn.compact
    def __call__(self, x: jnp.ndarray, mask: jnp.ndarray, *, train: bool = False) -> jnp.ndarray:
        m = jnp.asarray(mask, x.dtype)[..., None]
        h = nn.Dense(self.width)(x * m)
        for d in self.dilations:
            r = nn.relu(nn.LayerNorm()(h)) * m
            r = nn.Conv(self.width, (self.kernel,), kernel_dilation=(d,), padding="SAME")(r)
            h = h + nn.Dropout(self.dropout, deterministic=not train)(r)
        return nn.Dense(self.out)(nn.relu(nn.LayerNorm()(h)))


def rot6d_to_mat(x: jnp.ndarray) -> jnp.ndarray:
    """Continuous 6D rotation representation (Zhou et al. 2019) -> rotation matrix (..., 3, 3).

    The two 3-vectors are orthonormalised by Gram-Schmidt; they are the matrix's first two
    columns.
    """
    from jmocap.numerics import safe_normalize

    a, b = x[..., :3], x[..., 3:]
    e1 = safe_normalize(a + jnp.array([1e-6, 0.0, 0.0], x.dtype))
    b = b - jnp.sum(e1 * b, -1, keepdims=True) * e1
    e2 = safe_normalize(b + jnp.array([0.0, 1e-6, 0.0], x.dtype))
    e3 = jnp.cross(e1, e2)
    return jnp.stack([e1, e2, e3], -1)


def count_params(tree) -> int:
    return int(sum(x.size for x in jax.tree.leaves(tree)))
