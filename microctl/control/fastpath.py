"""The fast path of the EAFM controllers: a small SQP on eq. 4 with an exact active-set QP step.

Eq. 4 for one move is a tiny NLP: n_p = 3 variables, one nonlinear equality (the EAFM-mean tool
pose equals the target) and 2 n_q linear inequalities (every actuator in range), so the feasible
set is the 2-dimensional redundant set cut by the ranges. IPOPT solves it well but one call
costs milliseconds of set-up even on a trivial problem. :class:`FastSQP` takes Newton steps on
the Lagrangian instead (exact Hessian from the same CasADi graph), each step the solution of the
quadratic subproblem found by enumerating its active sets (at most n_p - 1 of the range
constraints can be active together with the equality: 33 small KKT systems for Table I, solved
in one batch). Started from a seed near a local minimum (the controller's grid), it converges
quadratically in a few iterations; its answer is accepted only when the first-order (KKT)
conditions hold to tolerance, the target is met and the command is in range, otherwise the
controller runs IPOPT from the same start (``tests/control/test_fastpath.py`` checks both paths
against IPOPT at random targets).
"""

from __future__ import annotations

import itertools
import math
from typing import Any, Callable, NamedTuple

import casadi as ca
import numpy as np

__all__ = ["ActiveSetQP", "FastSQP", "build_fast_function"]


def build_fast_function(u: ca.MX, s: ca.MX, J: ca.MX, t: ca.MX, name: str) -> ca.Function:
    """``f(u, s, lam) -> (J, dJ/du, t, dt/du, d2(J - lam t)/du2)`` from the NLP's expressions.

    Parameters
    ----------
    u, s : casadi.MX
        Symbols of the control signal, shape (n_p, 1), and the state, shape (n_s, 1).
    J, t : casadi.MX
        The (unscaled) objective and the EAFM-mean tool pose, scalars.
    name : str
    """
    lam = ca.MX.sym("lam")
    gJ = ca.gradient(J, u)
    gt = ca.gradient(t, u)
    H = ca.jacobian(gJ - lam * gt, u)
    return ca.Function(name, [u, s, lam], [J, gJ, t, gt, H])


class _Bound(NamedTuple):
    """A CasADi function bound to fixed NumPy arrays (:meth:`FastSQP._bind_buffer`)."""

    buffer: Any  #: the CasADi buffer; it holds pointers into the arrays below (kept alive here)
    run: Callable[[], None]  #: one evaluation: reads ``u``, ``s``, ``lam``, writes ``out``
    u: np.ndarray
    s: np.ndarray
    lam: np.ndarray
    out: np.ndarray


class FastSQP:
    """SQP with exact Hessian and an enumerated active-set QP for ``min J s.t. t(u) = t_d, lo <= K u <= hi``.

    Parameters
    ----------
    fun : casadi.Function
        From :func:`build_fast_function`.
    K : ndarray, shape (n_q, n_p)
    lo, hi : ndarray, shape (n_q,)
    max_iter : int
        SQP iterations at most.
    constraint_tol : float
        |t(u) - t_d| accepted (µm).
    kkt_tol : float
        Largest accepted stationarity residual of the scaled problem (J / J_ref).
    """

    def __init__(self, fun: ca.Function, K: np.ndarray, lo: np.ndarray, hi: np.ndarray, *, max_iter: int = 30,
                 constraint_tol: float = 1e-8, kkt_tol: float = 1e-7):
        # the five outputs as one dense vector: one conversion to NumPy per evaluation, not five;
        # "cse" merges the graph's repeated subexpressions (the exact Hessian's AD repeats many
        # kernel terms): each is then evaluated once, the same operations on the same inputs, so
        # the same numbers to the last bit with about 30 % fewer instructions
        self._packed = ca.Function(f"{fun.name()}_packed", fun.mx_in(),
                                   [ca.vertcat(*[ca.vec(o) for o in fun.call(fun.mx_in())])], {"cse": True})
        self._buffer = self._bind_buffer()
        self.K = np.asarray(K, dtype=float)
        self.lo, self.hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
        self._lo_tol, self._hi_tol = self.lo - 1e-9, self.hi + 1e-9  # the accepted ranges, computed once
        self.max_iter = max_iter
        self.constraint_tol = constraint_tol
        self.kkt_tol = kkt_tol
        self._qp = ActiveSetQP(self.K, self.lo, self.hi)
        self.A, self.b, self.usable = self._qp.A, self._qp.b, self._qp.usable

    # ------------------------------------------------------------------ evaluation
    def _bind_buffer(self) -> _Bound | None:
        """The packed function bound to fixed NumPy arrays (``casadi.Function.buffer``): an
        evaluation then copies three small inputs in and one vector out, without converting
        them to and from DM on every call (a sizeable part of a Table I call, which
        ``python scripts/bench_solve.py`` times; the same numbers to the last bit). None where
        this CasADi has no buffers (the plain call). The
        arrays are this instance's: like the controller that owns it, one FastSQP serves one
        thread."""
        try:
            buf, run = self._packed.buffer()
        except (AttributeError, NotImplementedError, RuntimeError):
            return None
        f = self._packed
        args = tuple(np.zeros(f.nnz_in(i)) for i in range(f.n_in()))
        out = np.zeros(f.nnz_out(0))
        for i, a in enumerate(args):
            buf.set_arg(i, memoryview(a))
        buf.set_res(0, memoryview(out))
        return _Bound(buf, run, *args, out)

    def _eval(self, u: np.ndarray, s: np.ndarray, lam: float):
        n = u.size
        if self._buffer is not None:
            b = self._buffer
            b.u[:], b.s[:], b.lam[0] = u.ravel(), np.ravel(s), lam  # u: the solve's own array
            b.run()
            v = b.out.copy()
        else:
            v = self._packed(u, s, lam).full().ravel()
        # v = [J; dJ/du; t; dt/du; vec(H)] (H column-major)
        return (float(v[0]), v[1:1 + n], float(v[1 + n]), v[2 + n:2 + 2 * n],
                v[2 + 2 * n:].reshape(n, n, order="F"))

    # ------------------------------------------------------------------ the solve
    def solve(self, u0: np.ndarray, s: np.ndarray, target: float, jref: float | None = None
              ) -> tuple[np.ndarray, dict]:
        """Run the SQP from ``u0`` (shape (n_p,)) for ``target`` from state ``s`` (shape (n_s,)).

        Parameters
        ----------
        jref : float, optional
            Scale of the objective (default: its value at ``u0``, as the IPOPT NLP is scaled).

        Returns
        -------
        u : ndarray, shape (n_p,)
        info : dict
            ``success`` (only when the KKT conditions of the scaled problem hold to ``kkt_tol``,
            the target is met to ``constraint_tol`` and every range holds within 1e-9 µm),
            ``iter``, ``status``, ``kkt`` and ``objective`` (unscaled, at u).
        """
        u = np.asarray(u0, dtype=float).copy()
        lam = 0.0
        info = {"success": False, "iter": 0, "status": "fast: not converged", "kkt": np.inf}
        if not self.usable:
            info["status"] = "fast: too many active sets"
            return u, info
        J, gJ, t, gt, H = self._eval(u, s, 0.0)
        if jref is None:
            jref = J if J > 1e-300 else 1.0
        Au = self.A @ u  # the ranges at u: the step's slack, and the complementarity at the next point
        for it in range(self.max_iter):
            info["iter"] = it + 1
            g, B = gJ / jref, _reduced_convex(H / jref, gt)
            step = self._qp.solve(B, g, gt, t - target, self.b - Au)
            if step is None:
                info["status"] = "fast: infeasible step"
                return u, info
            d, lam_new, mu = step
            u, J, gJ, t, gt, H = self._line_search(u, d, s, target, jref, J, t, g, lam_new)
            lam = lam_new
            kkt, Au = self._kkt(gJ / jref, gt, lam, mu, u)
            info["kkt"], info["objective"] = kkt, J
            # the step's multipliers certify first-order optimality at the new point (no extra step)
            if kkt <= self.kkt_tol and abs(t - target) <= self.constraint_tol:
                if self._in_range(u):
                    info.update(success=True, status="fast: converged")
                return u, info
        return u, info

    def _line_search(self, u, d, s, target, jref, J, t, g, lam):
        """Backtracking on the l1 merit ``J / J_ref + nu |t - t_d|``; the accepted point and its evaluation."""
        nu = 2.0 * abs(lam) + 1.0
        merit0 = J / jref + nu * abs(t - target)
        slope = g @ d - nu * abs(t - target)  # directional derivative of the merit (a'd = -c)
        # differences below this are round-off (of J, and of t at the constraint's tolerance)
        noise = 1e-12 * max(1.0, abs(merit0)) + nu * 1e-2 * self.constraint_tol
        polish = np.abs(d).max() <= 1e-7 * (1.0 + np.abs(u).max())  # a last correction: taken whole
        alpha = 1.0
        for _ in range(12):
            un = u + d if alpha == 1.0 else u + alpha * d  # 1.0 * d is d: the full step without the product
            Jn, gJn, tn, gtn, Hn = self._eval(un, s, lam * jref)
            if polish or Jn / jref + nu * abs(tn - target) <= merit0 + 1e-4 * alpha * min(slope, 0.0) + noise:
                return un, Jn, gJn, tn, gtn, Hn
            alpha *= 0.5
        return un, Jn, gJn, tn, gtn, Hn

    def _kkt(self, g: np.ndarray, gt: np.ndarray, lam: float, mu: np.ndarray, u: np.ndarray
             ) -> tuple[float, np.ndarray]:
        """Stationarity and complementarity residual of the scaled problem at u, and ``A u`` (the
        next step's slack reads it)."""
        stat = g - lam * gt - self.A.T @ mu
        Au = self.A @ u
        comp = np.abs(mu * (Au - self.b))
        return float(max(np.abs(stat).max(), comp.max(initial=0.0))), Au

    def _in_range(self, u: np.ndarray) -> bool:
        q = self.K @ u
        return bool((q >= self._lo_tol).all() and (q <= self._hi_tol).all())


class ActiveSetQP:
    """The exact QP of one step over the ranges ``lo <= K (u + d) <= hi`` with one equality, by
    enumerating its active sets (at most n_p - 1 ranges active with the equality).

    Held by :class:`FastSQP` for its steps and by the AFM baseline for its convex QP.

    Parameters
    ----------
    K : ndarray, shape (n_q, n_p)
    lo, hi : ndarray, shape (n_q,)
    """

    def __init__(self, K: np.ndarray, lo: np.ndarray, hi: np.ndarray):
        K = np.asarray(K, dtype=float)
        n_q, n_p = K.shape
        self.A = np.vstack([K, -K])  # inequalities A (u + d) >= b, b = [lo; -hi]
        self.b = np.concatenate([np.asarray(lo, dtype=float), -np.asarray(hi, dtype=float)])
        sets = [()]
        for r in range(1, n_p):
            sets += [c for c in itertools.combinations(range(2 * n_q), r)
                     if not any(i + n_q in c for i in c if i < n_q)]  # not both bounds of one actuator
        self._groups = [np.array([w for w in sets if len(w) == r], dtype=int).reshape(-1, r) if r else
                        np.zeros((1, 0), dtype=int) for r in range(n_p)]
        self.usable = len(sets) <= 2000
        self._At = self.A.T
        # each group's KKT matrices without the step's B and a: the active rows of A do not
        # change between steps, so they are filled once here and copied per step (the same numbers),
        # with each matrix's largest |entry| among them (the step's B and a add theirs: a maximum)
        self._templates = []
        for W in self._groups:
            k, size = W.shape
            m = n_p + 1 + size
            M = np.zeros((k, m, m))
            if size:
                AW = self.A[W]  # (k, size, n)
                M[:, :n_p, n_p + 1:] = -AW.transpose(0, 2, 1)
                M[:, n_p + 1:, :n_p] = AW
            self._templates.append((W, M, np.abs(M).max(axis=(1, 2))))

    def solve(self, B: np.ndarray, g: np.ndarray, a: np.ndarray, c: float, slack: np.ndarray
              ) -> tuple[np.ndarray, float, np.ndarray] | None:
        """``min 1/2 d'Bd + g'd s.t. a'd = -c, A d >= slack`` (B positive definite) by its active sets.

        A strictly convex QP has one KKT point, its minimum: the active sets are tried by size
        (none, one range, two ranges), each size's KKT systems solved in one batch, and the first
        primal and dual feasible solution is returned.

        Parameters
        ----------
        B : ndarray, shape (n_p, n_p)
        g, a : ndarray, shape (n_p,)
        c : float
        slack : ndarray, shape (2 n_q,)
            ``b - A u``: the inequalities on the step.

        Returns
        -------
        (d, lam, mu) or None
            Step (n_p,), multiplier of the equality, multipliers of the inequalities (2 n_q,);
            None when no active set gives a KKT point (an infeasible linearisation).
        """
        n = B.shape[0]
        abs_slack = np.abs(slack)
        tol = 1e-9 * (1.0 + abs_slack)
        low = slack - tol
        neg_a, neg_g = -a, -g
        # the largest |entry| of each KKT matrix and right-hand side from their parts, the step's
        # (B, a; g, c) found once for every group (a maximum is exact: the values of
        # np.abs(M).max(axis=(1, 2)) and np.abs(rhs).max(axis=1); NaN propagates alike)
        m_step = np.maximum(np.abs(B).max(), np.abs(a).max())
        r_step = np.maximum(np.abs(g).max(), abs(c))
        for W, M0, m_fixed in self._templates:
            k, size = W.shape
            if not size:  # the equality alone: one system, checked on Python floats
                step = self._equality_step(M0, B, neg_a, a, neg_g, c, low, float(np.maximum(m_fixed[0], m_step)),
                                           float(r_step))
                if step is not None:
                    return step
                continue
            M = M0.copy()
            rhs = np.zeros((k, n + 1 + size))
            M[:, :n, :n] = B
            M[:, :n, n] = neg_a
            M[:, n, :n] = a
            rhs[:, :n] = neg_g
            rhs[:, n] = -c
            r_max = r_step
            if size:
                rhs[:, n + 1:] = slack[W]
                r_max = np.maximum(abs_slack[W].max(axis=1), r_step)
            X, ok = _solve_batch(M, rhs, (np.maximum(m_fixed, m_step), r_max))
            D = X[:, :n]
            good = ok & (D @ self._At >= low).all(axis=1)
            if size:  # the multipliers of the active ranges (none in the first group)
                good &= (X[:, n + 1:] >= -1e-12).all(axis=1)
            if good.any():
                MU = X[:, n + 1:]
                j = int(good.argmax())  # the first good active set
                mu = np.zeros(self.A.shape[0])
                mu[W[j]] = MU[j]
                return D[j], float(X[j, n]), mu
        return None


    def _equality_step(self, M0: np.ndarray, B: np.ndarray, neg_a: np.ndarray, a: np.ndarray, neg_g: np.ndarray,
                       c: float, low: np.ndarray, m_max: float, r_max: float
                       ) -> tuple[np.ndarray, float, np.ndarray] | None:
        """The first group of :meth:`solve` (no range active) as a KKT point, or None: the same system
        (``M0`` its (1, m, m) template), solution and tests as :func:`_solve_batch` and the group's
        feasibility test make for a batch of one, in fewer NumPy calls (``m_max``, ``r_max``: the
        largest |entry| of the matrix and of the right-hand side)."""
        n = B.shape[0]
        M = M0.copy()
        M[:, :n, :n] = B
        M[:, :n, n] = neg_a
        M[:, n, :n] = a
        rhs = np.empty((1, n + 1))
        rhs[:, :n] = neg_g
        rhs[:, n] = -c
        try:
            X = np.linalg.solve(M, rhs[..., None])[..., 0]
        except np.linalg.LinAlgError:
            return None
        r = np.einsum("kij,kj->ki", M, X)
        r -= rhs
        res = float(np.abs(r).max())
        x_max = float(np.abs(X).max())  # not finite exactly when X has a non-finite entry
        if not (math.isfinite(x_max) and res <= 1e-9 * ((m_max * x_max + r_max) + 1e-300)):
            return None
        D = X[:, :n]
        if not (D @ self._At >= low).all():
            return None
        return D[0], float(X[0, n]), np.zeros(self.A.shape[0])


def _reduced_convex(B: np.ndarray, a: np.ndarray) -> np.ndarray:
    """B with its curvature on the tangent space of ``a'd = 0`` made positive (the rest untouched).

    Only the reduced Hessian ``Z'BZ`` (Z an orthonormal basis of a's null space) matters to the
    QP step; a negative eigenvalue there is flipped (a descent direction out of a saddle) and a
    vanishing one raised to a floor 1e-12 times the largest, so the step's KKT system is regular.
    Curvature along the valley of the redundant set is often tiny: a floor relative to the full
    Hessian (large across the valley) would cut the Newton step to a crawl.

    Parameters
    ----------
    B : ndarray, shape (n_p, n_p)
    a : ndarray, shape (n_p,)

    Returns
    -------
    ndarray, shape (n_p, n_p)
    """
    B = 0.5 * (B + B.T)
    Z = _null_basis(a)
    R = Z.T @ B @ Z
    if _clearly_regular(R):
        return B  # positive definite on the tangent space: nothing to change
    w, V = np.linalg.eigh(R)
    floor = 1e-12 * max(1e-300, float(np.max(np.abs(w))))
    target = np.maximum(np.abs(w), floor)
    if np.all(target == w):
        return B
    return B + Z @ ((V * (target - w)) @ V.T) @ Z.T


def _clearly_regular(R: np.ndarray) -> bool:
    """Whether R has a Cholesky factor (``np.linalg.cholesky`` succeeds) and its diagonal's
    smallest entry exceeds 1e-12 times its largest |entry|: the reduced Hessian needs no change.

    For the 2 x 2 R of Table I (n_p = 3) the diagonal test is made on Python floats (the same
    comparisons) and the factor's existence decided by its second pivot ``r11 - r10^2 / r00``
    where that is positive or negative by far more than LAPACK's round-off (a relative 1e-8);
    in between, and for any other size or a non-finite entry, ``np.linalg.cholesky`` decides.
    """
    if R.shape == (2, 2):
        (r00, r01), (r10, r11) = R.tolist()
        if math.isfinite(r00 + r01 + r10 + r11):
            if not min(r00, r11) > 1e-12 * max(abs(r00), abs(r01), abs(r10), abs(r11)):
                return False
            # here r00 > 0 and r11 > 0 (the first pivot is r00 itself)
            off = max(r01 * r01, r10 * r10) / r00
            if off < r11 * (1.0 - 1e-8):
                return True
            if min(r01 * r01, r10 * r10) / r00 > r11 * (1.0 + 1e-8):
                return False
    try:
        np.linalg.cholesky(R)
    except np.linalg.LinAlgError:
        return False
    return bool(R.diagonal().min() > 1e-12 * np.abs(R).max())


def _solve_batch(M: np.ndarray, rhs: np.ndarray, maxima: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Solve the systems ``M[k] x = rhs[k]``; the solutions (k, m) and which are valid (k,).

    A singular system (dependent active constraints) is marked invalid, and so is a solution
    whose residual shows it is not one (a nearly singular system). Scale-free: the KKT systems
    mix the Hessian (up to ~1e3) with unit-scale constraint rows, so a determinant test misjudges.
    ``maxima``: the largest |entry| of each M[k] and rhs[k] (shape (k,) or scalars), when the
    caller knows them (:meth:`ActiveSetQP.solve`: from their parts), else found here.
    """
    try:
        X = np.linalg.solve(M, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        X = np.zeros_like(rhs)
        for k in range(M.shape[0]):
            try:
                X[k] = np.linalg.solve(M[k], rhs[k])
            except np.linalg.LinAlgError:
                X[k] = np.nan
    res = np.abs(np.einsum("kij,kj->ki", M, X) - rhs).max(axis=1)
    m_max, r_max = (np.abs(M).max(axis=(1, 2)), np.abs(rhs).max(axis=1)) if maxima is None else maxima
    scale = m_max * np.abs(X).max(axis=1) + r_max
    ok = np.isfinite(X).all(axis=1) & (res <= 1e-9 * (scale + 1e-300))
    return np.where(ok[:, None], X, 0.0), ok


def _null_basis(a: np.ndarray) -> np.ndarray:
    """An orthonormal basis of the vectors orthogonal to ``a`` (shape (n,)), shape (n, n - 1), by one
    Householder reflection (the identity's last n - 1 columns when a = 0)."""
    n = a.shape[0]
    na = math.sqrt(float(a.dot(a)))  # np.linalg.norm's own arithmetic, without its call overhead
    if na == 0.0:
        return np.eye(n)[:, 1:]
    w = a / na  # v = a / |a|, turned into w in place (v is not read again)
    w[0] += 1.0 if w[0] >= 0 else -1.0  # reflect v onto -+e1 (no cancellation)
    H = np.eye(n) - 2.0 * (w[:, None] * w[None, :]) / float(w @ w)  # np.outer's products
    return H[:, 1:]

