"""Reference solver for the projection QP (Clarabel, interior point, float64) and instance maker.

``clarabel_projection(W, G, v, lower)`` solves ``min 1/2 (x - v)^T W (x - v) s.t. G x >= lower``
as Clarabel's ``min 1/2 x^T P x + q^T x s.t. A x + s = b, s >= 0`` with ``P = W``, ``q = -W v``,
``A = -G``, ``b = -lower`` (rows with ``lower = -inf`` and zero rows with ``lower <= 0`` dropped), at gap/feasibility tolerances of
1e-14 (it reaches about 1e-9 in x on these problems; 1e-12 gave errors up to 2e-6).  Used by tests/test_qp.py and experiments/bench_projection.py; never by the solver itself.

``polished_projection`` adds the classic polishing step of interior-point references (as in
OSQP's "solution polishing"): on the humanoid's contact QPs, whose corner rows are linearly
dependent (four coplanar corners of a rigid foot have rank 3) and whose mass matrix has a
condition number of ~1e5, Clarabel stops 1e-5..2e-4 from the optimum.  Polishing takes the rows
Clarabel leaves (nearly) tight, solves the equality-constrained QP on them exactly in float64 (a
least-squares KKT solve, so dependent rows are fine) and keeps the result only when it is
feasible and its objective is not worse; it is a reference built from Clarabel's active set,
independent of jmocap's solver.
"""

from __future__ import annotations

import clarabel
import numpy as np
import scipy.sparse as sp


def clarabel_projection(W, G, v, lower, tol: float = 1e-14):
    """Return (x, lam, status) from Clarabel in float64; lam has one entry per row of G."""
    W = np.asarray(W, np.float64)
    G = np.asarray(G, np.float64)
    v = np.asarray(v, np.float64)
    lower = np.asarray(lower, np.float64)
    n = W.shape[0]
    # rows with lower = -inf, and zero rows with lower <= 0, constrain nothing: drop them (a zero
    # row kept as 0 >= 0 is a degenerate constraint that costs Clarabel several digits)
    zero = ~np.any(G != 0, axis=1)
    keep = np.isfinite(lower) & ~(zero & (lower <= 0))
    Gk, lk = G[keep], lower[keep]
    P = sp.csc_matrix(np.triu(0.5 * (W + W.T)))
    q = -(0.5 * (W + W.T)) @ v
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.tol_gap_abs = tol
    settings.tol_gap_rel = tol
    settings.tol_feas = tol
    settings.tol_ktratio = 1e-12
    # the default static regularisation (1e-8) limits the accuracy on degenerate QPs (duplicated
    # or dependent rows) to about 1e-5; 1e-13 is still enough for the quasi-definite KKT factor
    settings.static_regularization_constant = 1e-13
    settings.max_iter = 400
    if Gk.shape[0] == 0:
        return v.copy(), np.zeros(G.shape[0]), "Solved"
    A = sp.csc_matrix(-Gk)
    b = -lk
    solver = clarabel.DefaultSolver(P, q, A, b, [clarabel.NonnegativeConeT(Gk.shape[0])], settings)
    sol = solver.solve()
    x = np.asarray(sol.x, np.float64).reshape(n)
    lam = np.zeros(G.shape[0])
    lam[keep] = np.asarray(sol.z, np.float64)
    return x, lam, str(sol.status)


def polished_projection(W, G, v, lower, tol: float = 1e-14, tight: float = 1e-6):
    """Clarabel's solution, polished on its active set (see the module docstring).

    Returns (x, status) with status ``"polished"`` or Clarabel's own when polishing was rejected.
    """
    W = 0.5 * (np.asarray(W, np.float64) + np.asarray(W, np.float64).T)
    G = np.asarray(G, np.float64)
    v = np.asarray(v, np.float64)
    lower = np.asarray(lower, np.float64)
    x, lam, status = clarabel_projection(W, G, v, lower, tol)
    fin = np.isfinite(lower)
    Gf = np.where(fin[:, None], G, 0.0)
    lf = np.where(fin, lower, 0.0)
    scale = np.abs(lf) + np.abs(Gf) @ np.abs(x) + 1e-300
    slack = Gf @ x - lf
    S = fin & np.any(Gf != 0, axis=1) & ((slack <= tight * scale) | (lam > tight))
    if not S.any():
        return x, status
    n, k = W.shape[0], int(S.sum())
    K = np.block([[W, -Gf[S].T], [Gf[S], np.zeros((k, k))]])
    rhs = np.concatenate([W @ v, lf[S]])
    sol = np.linalg.lstsq(K, rhs, rcond=None)[0]
    xp = sol[:n]
    slack_p = Gf @ xp - lf
    def obj(z):
        return 0.5 * (z - v) @ W @ (z - v)
    feasible = slack_p.min(initial=0.0) >= -1e-12 * (1.0 + np.abs(lf).max(initial=0.0))
    if feasible and obj(xp) <= obj(x) + 1e-12 * (1.0 + abs(obj(x))):
        return xp, "polished"
    return x, status


def kkt_optimal(W, G, v, lower, x, tight: float = 1e-8, tol: float = 1e-9) -> bool:
    """Whether ``x`` solves ``min 0.5 (x - v)^T W (x - v)  s.t.  G x >= lower`` (W positive
    definite), checked from the KKT conditions in float64 numpy, independently of any solver:
    feasible (slack >= -tol scale), and the gradient ``W (x - v)`` a non-negative combination of
    the active rows (slack <= ``tight`` scale; least-squares multipliers >= -tol |grad|, relative
    stationarity residual <= tol). For a strictly convex QP these conditions are sufficient.
    The fallback reference where Clarabel stalls (MaxIterations) on an instance."""
    W = 0.5 * (np.asarray(W, np.float64) + np.asarray(W, np.float64).T)
    G, v, lower, x = (np.asarray(a, np.float64) for a in (G, v, lower, x))
    fin = np.isfinite(lower) & np.any(G != 0, axis=1)
    Gf, lf = G[fin], lower[fin]
    scale = 1.0 + np.abs(lf) + np.abs(Gf) @ np.abs(x)
    slack = Gf @ x - lf
    if slack.size and slack.min() < -tol * scale.max():
        return False
    grad = W @ (x - v)
    gnorm = max(np.linalg.norm(grad), 1e-300)
    active = slack <= tight * scale
    if not active.any():
        return np.linalg.norm(grad) <= tol * (1.0 + np.linalg.norm(W @ v))
    A = Gf[active]
    lam = np.linalg.lstsq(A.T, grad, rcond=None)[0]
    return bool(lam.min() >= -tol * gnorm and np.linalg.norm(A.T @ lam - grad) <= tol * gnorm)


def random_spd(rng, n: int, cond: float):
    """Random SPD matrix with eigenvalues log-spaced in [1, cond], in a random orthogonal basis."""
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    eig = np.logspace(0.0, np.log10(cond), n)
    rng.shuffle(eig)
    W = (Q * eig) @ Q.T
    return 0.5 * (W + W.T)


def random_instance(rng, n: int, m: int, *, cond: float | None = None, degenerate: bool = True,
                    feasible_at_v: bool | None = None):
    """A random projection QP (W, Winv, G, v, lower) that is always feasible.

    Rows: random normals of random length, plus (when ``degenerate``) zero rows (lower 0 or
    -inf), exact duplicates of earlier rows (with the same lower, or a looser one) and random
    combinations of two earlier rows.  ``lower = G x0 - slack`` for a random point x0, so the QP
    is feasible.  v is either x0 plus a large random step (most constraints violated; half of the
    original rows tight at x0) or x0 itself with every slack >= 0.01 (``feasible_at_v``; random,
    20 %, when None).  Combination rows get a slack >= 0.01, so that no row is tight with a zero
    multiplier at the solution by construction: such weakly active rows cost an interior-point
    reference (Clarabel) several digits; they are tested against KKT certificates instead.
    """
    if cond is None:
        cond = float(10 ** rng.uniform(0, 4))
    if feasible_at_v is None:
        feasible_at_v = rng.random() < 0.2
    W = random_spd(rng, n, cond)
    Winv = np.linalg.inv(W)
    Winv = 0.5 * (Winv + Winv.T)
    x0 = rng.normal(size=n)
    G = rng.normal(size=(m, n))
    G /= np.linalg.norm(G, axis=1, keepdims=True)
    G *= rng.uniform(0.2, 3.0, size=(m, 1))
    if feasible_at_v:
        slack = rng.uniform(0.01, 1.0, size=m)
    else:
        slack = np.where(rng.random(m) < 0.5, 0.0, rng.uniform(0.0, 1.0, size=m))
    kinds = rng.integers(0, 5, size=m) if (degenerate and m >= 3) else np.zeros(m, int)
    kinds[0] = 0
    lower = np.empty(m)
    for i in range(m):
        k = kinds[i]
        if k == 1:  # zero row: no constraint
            G[i] = 0.0
            lower[i] = -np.inf if rng.random() < 0.5 else 0.0
            continue
        if k == 2:  # exact duplicate of an earlier row, same or looser bound
            a = rng.integers(0, i)
            G[i] = G[a]
            if rng.random() < 0.5 or not np.isfinite(lower[a]):
                slack[i] = max(slack[a], 0.0) + rng.uniform(0.01, 1.0)
            else:
                lower[i] = lower[a]
                continue
        elif k == 3 and i >= 2:  # combination of two earlier rows
            a, c = rng.choice(i, size=2, replace=False)
            G[i] = rng.uniform(-1, 1) * G[a] + rng.uniform(-1, 1) * G[c]
            slack[i] = rng.uniform(0.01, 1.0)
        lower[i] = G[i] @ x0 - slack[i]
    v = x0.copy() if feasible_at_v else x0 + rng.normal(scale=2.0, size=n)
    return W, Winv, G, v, lower
