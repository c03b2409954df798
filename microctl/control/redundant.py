"""The redundant set of a target: null-space coordinates of the tool map over the workspace
polytope, the seeding grid on it, and the local minima of a score over that grid."""

from __future__ import annotations

import itertools

import numpy as np

from microctl.models.afm import AnalyticForwardModel

__all__ = ["RedundantSet", "grid_local_minima"]


#: Polytopes already enumerated, by the bytes of (K, lo, hi).
_POLYTOPES: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


class RedundantSet:
    """Null-space coordinates of the tool map over the workspace polytope (for seeding).

    With ``D = diag(u_hi - u_lo) / 2`` and ``u = D v``, the AFM tool constraint is
    ``(D w)·v = d``; ``v = v_hat d / |D w| + N c`` with N an orthonormal basis of the null
    space of ``D w``. The section of the workspace polytope by that plane is bounded by the
    crossings of the polytope's edges with the plane (vertices and edges precomputed).

    Parameters
    ----------
    afm : AnalyticForwardModel
    """

    def __init__(self, afm: AnalyticForwardModel):
        self.afm = afm
        ws = afm.workspace
        self.D = np.maximum((ws.u_hi - ws.u_lo) / 2.0, 1e-12)
        self.w = np.asarray(afm.w_pred, dtype=float)
        wt = self.D * self.w
        self.wt_norm = float(np.linalg.norm(wt))
        self.v_hat = wt / self.wt_norm
        # orthonormal complement of v_hat
        _, _, Vt = np.linalg.svd(self.v_hat[None, :])
        self.N = Vt[1:].T  # (n_p, n_p - 1)
        self.dir_u = self.D * self.v_hat  # moving u along D v_hat changes w·u by wt_norm per unit
        self.vertices, self.edges = self._polytope(afm)

    @staticmethod
    def _polytope(afm: AnalyticForwardModel) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (m, n_p) of {lo <= K u <= hi} and edges as index pairs (e, 2), enumerated once
        per (K, lo, hi) (a controller and its AFM baseline share them; read-only arrays)."""
        key = (afm.K.tobytes(), afm.K.shape, afm.lo.tobytes(), afm.hi.tobytes())
        if key not in _POLYTOPES:
            V, E = RedundantSet._enumerate(afm.K, afm.lo, afm.hi)
            V.setflags(write=False)
            E.setflags(write=False)
            _POLYTOPES[key] = (V, E)
        return _POLYTOPES[key]

    @staticmethod
    def _enumerate(K: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        A = np.vstack([K, -K])
        b = np.concatenate([hi, -lo])
        n_p = K.shape[1]
        verts: list[np.ndarray] = []
        active: list[frozenset] = []
        for combo in itertools.combinations(range(A.shape[0]), n_p):
            Ac = A[list(combo)]
            if abs(np.linalg.det(Ac)) < 1e-12:
                continue
            v = np.linalg.solve(Ac, b[list(combo)])
            if np.all(A @ v <= b + 1e-9):
                act = frozenset(np.flatnonzero(np.abs(A @ v - b) <= 1e-9).tolist())
                if not any(np.allclose(v, w) for w in verts):
                    verts.append(v)
                    active.append(act)
        edges = [(i, j) for i, j in itertools.combinations(range(len(verts)), 2)
                 if len(active[i] & active[j]) >= n_p - 1
                 and np.linalg.matrix_rank(A[sorted(active[i] & active[j])]) >= n_p - 1]
        return np.array(verts), np.array(edges, dtype=int).reshape(-1, 2)

    def d_of_target(self, target: float) -> float:
        """Linear tool displacement d = w·u whose gauge reading is ``target`` (:meth:`Sensor.inverse`)."""
        return float(self.afm.sensor.inverse(target))

    def section_box(self, d: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Bounding box of the plane section {w·u = d} of the workspace in c coordinates."""
        V = self.vertices
        vals = V @ self.w - d
        pts = [V[vals == 0.0]]
        i, j = self.edges[:, 0], self.edges[:, 1]
        cross = (np.sign(vals[i]) * np.sign(vals[j])) < 0  # signs: no overflow for a huge d
        if np.any(cross):
            a, b = vals[i[cross]], vals[j[cross]]
            lam = (a / (a - b))[:, None]
            pts.append(V[i[cross]] + lam * (V[j[cross]] - V[i[cross]]))
        P = np.vstack(pts)
        if P.shape[0] == 0:
            return None
        C = (P / self.D) @ self.N
        return C.min(axis=0), C.max(axis=0)

    def grid(self, target: float, n: int, margin: float = 0.02) -> tuple[np.ndarray, tuple[int, ...]]:
        """Grid of u on the AFM plane section for ``target``.

        Returns
        -------
        U : ndarray, shape (n**(n_p-1), n_p)
            Grid points (row-major over the null axes), possibly outside the workspace.
        shape : tuple of int
            The grid's shape (for neighbour tests).
        """
        d = self.d_of_target(target)
        r = self.N.shape[1]
        v0 = self.v_hat * d / self.wt_norm
        if r == 0:
            return (self.D * v0)[None, :], (1,)
        box = self.section_box(d)
        if box is None:
            # beyond the AFM's range: grid the nearest section (Newton decides reachability)
            ends = self.vertices @ self.w
            box = self.section_box(float(np.clip(d, ends.min(), ends.max())))
        lo, hi = box
        pad = margin * np.maximum(hi - lo, 1e-9)
        axes = [np.linspace(a - p, b + p, n) for a, b, p in zip(lo, hi, pad)]
        # the "ij" mesh of the axes, one coordinate per last index (np.stack(np.meshgrid(...),
        # axis=-1)'s values, copied in by broadcasting without the intermediate grids)
        mesh = np.empty((n,) * r + (r,))
        for k, a in enumerate(axes):
            mesh[..., k] = a.reshape(tuple(-1 if j == k else 1 for j in range(r)))
        C = mesh.reshape(-1, r)
        V = v0[None, :] + C @ self.N.T
        return V * self.D, tuple([n] * r)



def grid_local_minima(obj: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Indices of grid points not larger than any finite neighbour (inf = infeasible)."""
    J = obj.reshape(shape)
    # J inside a border of inf (np.pad's values; np.pad's own set-up costs more than the comparisons)
    padded = np.full(tuple(s + 2 for s in shape), np.inf)
    padded[tuple(slice(1, 1 + s) for s in shape)] = J
    is_min = np.isfinite(J)
    r = len(shape)
    for off in itertools.product((-1, 0, 1), repeat=r):
        if not any(off):
            continue
        sl = tuple(slice(1 + o, 1 + o + s) for o, s in zip(off, shape))
        is_min &= J <= padded[sl]
    return np.flatnonzero(is_min.ravel())

