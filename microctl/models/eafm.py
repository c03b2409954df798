"""The enhanced analytic forward model (EAFM) of the paper, eq. 1 and 3, as CasADi graphs.

The EAFM adds a heteroscedastic GP (VHGPR, :mod:`microctl.gp.vhgpr`) trained on the AFM
residual ``y = t' - T_t f_a(s, u)`` with input ``x = [s; u]`` (eq. 3) to the AFM
(:mod:`microctl.models.afm`, eq. 14):

    t' ~ N( T_t f_a(s, u) + g_e(s, u),  r_e(s, u) )                                   (eq. 1)

with ``g_e`` the GP mean of f and ``r_e = exp(g)`` the input-dependent noise variance. This
module builds, from an :class:`~microctl.models.afm.AnalyticForwardModel` and a
:class:`~microctl.gp.vhgpr.FittedVHGPR`:

- :attr:`EAFM.function`, one named CasADi Function ``eafm(s, u) -> (t_mean, f_mean, f_var,
  g_mean, g_var, q)`` (MX graph; exact first and second derivatives by CasADi's AD);
- :meth:`EAFM.expressions`, the same quantities as separate MX expressions of given
  symbols, so that an NLP pulls in only what its objective needs (the epistemic
  terms are never evaluated by an NLP that does not use them);
- :meth:`EAFM.predict`, the NumPy reference (``FittedVHGPR.predict`` + AFM);
- vectorised NumPy helpers for the controller's global seeding
  (:meth:`EAFM.mean_and_grad_u`, :meth:`EAFM.g_mean_np`).

The GP's quantities, in NumPy and as CasADi graphs alike, are those of the model's one
posterior, :class:`~microctl.gp.posterior.Posterior` (graph design, measured in
``docs/controller.md``: MX, not SX; the mean terms are ``k^T alpha`` with ``k`` built from
one dense (n x d) product; the variance terms are ``k** - ||L^-1 k||^2`` with ``L^-1`` a
constant lower-triangular (sparse) DM, or, for f with its SE part off, the same in the feature
form of its kernel, O(n p)); this module adds the AFM and the stage binding.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import casadi as ca
import numpy as np

from microctl.errors import ConfigError
from microctl.gp.fitted import FittedVHGPR
from microctl.gp.posterior import Posterior
from microctl.models.afm import AnalyticForwardModel, plausible_t_bound_um
from microctl.models.alternatives import Alternatives
from microctl.models.direction import initial
from microctl.models.noise_dictionary import candidate_features

__all__ = ["EAFM", "EAFMPrediction", "load_residual_model", "bind_to_stage"]


def load_residual_model(path: str | Path) -> FittedVHGPR:
    """Read a residual model file (``.npz`` written by :meth:`FittedVHGPR.save`)."""
    return FittedVHGPR.load(path)


def _check_output_scale(model: FittedVHGPR, afm: AnalyticForwardModel, source: str) -> None:
    """Refuse a residual model whose outputs no stage of this config can have produced.

    The residual y = t' − AFM t (µm) of a healthy or defective stage is at most of the size
    of the readings a log may hold (:func:`~microctl.models.afm.plausible_t_bound_um`);
    a model whose training residuals had a larger mean or spread (``y_mean``, ``y_scale``)
    was trained on something else, or edited, and would only make IPOPT fail.
    """
    bound = plausible_t_bound_um(afm.stage)
    for name in ("y_mean", "y_scale"):
        value = abs(float(getattr(model, name)))
        if value > bound:
            raise ConfigError(f"{source}: the residual model's {name} = {value:.4g} µm is beyond what stage "
                              f"'{afm.stage.name}' can produce (|t| ≤ {bound:.6g} µm in a log); it was not trained "
                              "on this stage's residuals, retrain it with `microctl train`")


def context_names(n_q: int) -> tuple[str, ...]:
    """Names of the move's context inputs: each actuator's last direction of motion
    (:mod:`microctl.models.direction`)."""
    return tuple(f"dir{i + 1}_prev" for i in range(int(n_q)))


def bind_to_stage(model: FittedVHGPR, afm: AnalyticForwardModel) -> FittedVHGPR:
    """Return ``model`` with ``geometry_hash`` and ``x_names`` of the AFM's stage (eq. 3 input,
    and the move's context when the model reads it)."""
    names = tuple(f"{n}_prev" for n in afm.state_names) + tuple(f"u_{n}" for n in afm.dof)
    if model.n_context:
        names = names + context_names(model.n_context)
    stage = afm.stage
    binding = {"name": stage.name, "shape_hash": stage.shape_hash(), "physics_hash": stage.physics_hash()}
    return replace(model, geometry_hash=stage.geometry_hash(), x_names=names, y_name="residual_um",
                   info={**model.info, "stage": binding})


def _binding_mismatch(model: FittedVHGPR, afm: AnalyticForwardModel, source: str) -> tuple[str | None, str | None]:
    """(error, note) comparing the stage a model was trained for with ``afm``'s.

    ``error``: the geometry hash differs; it says whether only the model corrections differ
    (e.g. the extended config ``diagnose`` writes) or the geometry itself. ``note``: the
    geometry matches but the stage's contact physics or name differ (another rig's config).
    """
    stage = afm.stage
    bound = model.info.get("stage") if isinstance(model.info, dict) else None
    bound = bound if isinstance(bound, dict) else {}
    if model.geometry_hash != stage.geometry_hash():
        if bound.get("shape_hash") == stage.shape_hash():
            return (f"{source}: the residual model was trained for the same geometry with other model corrections "
                    f"(stage '{bound.get('name')}'; stage.corrections of '{stage.name}' differ, e.g. the extended "
                    "config of `microctl diagnose`); train a model with this config (`microctl train LOG --config "
                    "...`)"), None
        return (f"{source}: the residual model was trained for another stage geometry "
                f"(geometry_hash {model.geometry_hash[:12]}… ≠ {stage.geometry_hash()[:12]}… of stage "
                f"'{stage.name}'); retrain it for this stage"), None
    if bound.get("physics_hash") not in (None, stage.physics_hash()):
        return None, (f"{source} was trained for stage '{bound.get('name')}', whose contact physics (stiffness, "
                      f"preload) differ from stage '{stage.name}''s; its correction may not hold here: retrain "
                      "it with `microctl train` on this rig's log")
    if bound.get("name") not in (None, stage.name):
        return None, f"{source} was trained for stage '{bound.get('name')}', used here for stage '{stage.name}'"
    return None, None


@dataclass(frozen=True)
class EAFMPrediction:
    """NumPy EAFM prediction at m points (µm, µm²).

    Attributes
    ----------
    t_mean : ndarray, shape (m,)
        AFM tool pose + GP mean (eq. 1).
    f_mean, f_var : ndarray, shape (m,)
        GP residual mean and epistemic variance.
    g_mean, g_var : ndarray, shape (m,)
        Mean and variance of the log noise variance ``g`` (µm² in the log).
    t_var : ndarray, shape (m,)
        Predictive variance ``f_var + exp(g_mean + g_var/2)``.
    q : ndarray, shape (m, n_q)
        Actuator commands ``K u`` (eq. 12).
    """

    t_mean: np.ndarray
    f_mean: np.ndarray
    f_var: np.ndarray
    g_mean: np.ndarray
    g_var: np.ndarray
    t_var: np.ndarray
    q: np.ndarray


class EAFM:
    """The EAFM of eq. 1 built from an AFM and a fitted residual VHGPR.

    Parameters
    ----------
    afm : AnalyticForwardModel
    model : FittedVHGPR or str or Path
        The residual model (or its ``.npz`` file), trained with ``x = [s; u]`` (eq. 3).
    check_geometry : bool
        Refuse a model whose ``geometry_hash`` differs from ``afm.stage.geometry_hash()``
        (default True). A model with no geometry hash is refused too.
    direction : ndarray, shape (n_q,), optional
        Each actuator's last direction of motion before the moves this EAFM predicts (+1 or -1;
        default all +1, the zero state's), read only by a model with a reversal noise source
        (:attr:`uses_direction`; :meth:`with_direction`).

    Raises
    ------
    ConfigError
        Geometry-hash mismatch, wrong input dimension, or (for a model file) output mean or
        scale beyond what the stage can produce, naming the model file.

    Attributes
    ----------
    function : casadi.Function
        ``eafm(s, u) -> (t_mean, f_mean, f_var, g_mean, g_var, q)``; s shape (n_s, 1),
        u shape (n_p, 1); every output (1, 1) except q (n_q, 1). Built lazily.
    """

    def __init__(self, afm: AnalyticForwardModel, model: FittedVHGPR | str | Path, *, check_geometry: bool = True,
                 direction: np.ndarray | None = None):
        source = "<in-memory model>"
        if not isinstance(model, FittedVHGPR):
            source = str(model)
            model = load_residual_model(model)
            _check_output_scale(model, afm, source)
        self.afm = afm
        self.model = model
        self.source = source
        #: A model trained for the same geometry but another stage (physics, name): said, not refused.
        self.binding_note: str | None = None
        self.n_p, self.n_q, self.n_s = afm.n_p, afm.n_q, afm.n_s
        self.n_x = self.n_s + self.n_p
        if check_geometry:
            if model.geometry_hash is None:
                raise ConfigError(f"{source}: the residual model is not bound to a stage geometry "
                                  f"(no geometry_hash); train it with `microctl train` for this stage")
            error, self.binding_note = _binding_mismatch(model, afm, source)
            if error:
                raise ConfigError(error)
        if model.n_inputs - model.n_context != self.n_x or model.n_context not in (0, self.n_q):
            raise ConfigError(f"{source}: the residual model has {model.n_inputs} inputs ({model.n_context} of them "
                              f"context); the EAFM of stage '{afm.stage.name}' needs x = [s; u] with {self.n_x} "
                              f"(eq. 3), optionally followed by the {self.n_q} actuators' last directions")
        self.direction = self._checked_direction(direction)
        #: the context columns :meth:`_x` appends (the actuators' last directions), counted once
        self._n_context_cols = self.n_q if self.uses_direction else 0
        self.posterior: Posterior = model.posterior
        self._function: ca.Function | None = None
        self._alternatives: Alternatives | None = None

    @property
    def uses_direction(self) -> bool:
        """Whether the model reads the move's context, each actuator's last direction of motion
        (a reversal noise source was selected; :mod:`microctl.models.direction`)."""
        return self.model.n_context > 0

    def _checked_direction(self, direction: np.ndarray | None) -> np.ndarray:
        if direction is None:
            return initial(self.n_q)
        d = np.asarray(direction, dtype=float).reshape(-1)
        if d.shape != (self.n_q,) or not np.all(np.isin(d, (-1.0, 1.0))):
            raise ConfigError(f"the actuators' last directions must be {self.n_q} values of +1 or -1, got "
                             f"{np.asarray(direction).tolist()}")
        return d

    def with_direction(self, direction: np.ndarray | None) -> "EAFM":
        """This EAFM for moves made after the actuators last moved in ``direction`` (n_q values of
        +1 or -1; None: the zero state's, all +1): a new EAFM sharing the model, or ``self`` when
        the model does not read the direction or it is already this one. Its CasADi graph has
        the direction built in, so a controller for each direction is a controller of its EAFM."""
        d = self._checked_direction(direction)
        if not self.uses_direction or np.array_equal(d, self.direction):
            return self
        other = copy.copy(self)
        other.direction = d
        other._function = None
        return other

    @property
    def alternatives(self) -> Alternatives:
        """The unselected noise sources of the model's dictionary selection, weighed by evidence
        (:mod:`microctl.models.alternatives`; none for a model without stored alternatives)."""
        if self._alternatives is None:
            self._alternatives = Alternatives(self.model.info, candidate_features(self.afm))
        return self._alternatives

    def alt_var(self, s: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The model-averaged extra noise variance of the unselected sources, µm², shape (m,)
        (:meth:`Alternatives.values`; s shape (n_s,) or (m, n_s), u shape (n_p,) or (m, n_p))."""
        return self.alternatives.values(self._x(s, u)[:, :self.n_x])

    @property
    def function(self) -> ca.Function:
        """``eafm(s, u) -> (t_mean, f_mean, f_var, g_mean, g_var, q)``, built on first use.

        Building the variance branches costs O(n^2) memory and time (seconds at n = 2000),
        which a controller using only the mean and g_mean never pays.
        """
        if self._function is None:
            s = ca.MX.sym("s", self.n_s)
            u = ca.MX.sym("u", self.n_p)
            e = self.expressions(s, u)
            names = ["t_mean", "f_mean", "f_var", "g_mean", "g_var", "q"]
            self._function = ca.Function("eafm", [s, u], [e[k] for k in names], ["s", "u"], names)
        return self._function

    @classmethod
    def from_file(cls, afm: AnalyticForwardModel, path: str | Path, **kw: Any) -> "EAFM":
        """Build from a model file (see the class parameters)."""
        return cls(afm, path, **kw)

    @property
    def n_train(self) -> int:
        """Number of training points n of the residual GP."""
        return int(self.model.X.shape[0])

    # ---- CasADi ------------------------------------------------------------------
    def expressions(self, s: ca.MX, u: ca.MX, which: tuple[str, ...] | None = None) -> dict[str, ca.MX]:
        """EAFM quantities as MX expressions of the symbols ``s`` (n_s, 1) and ``u`` (n_p, 1).

        Parameters
        ----------
        s, u : casadi.MX
        which : tuple of str, optional
            Subset of ``("t_mean", "f_mean", "f_var", "g_mean", "g_var", "q", "t_afm")`` to
            build (default all), and ``"alt_var"`` (:meth:`alt_var`; only on request). Only the
            requested branches enter the graph.

        Returns
        -------
        dict of str to casadi.MX
        """
        allq = ("t_mean", "f_mean", "f_var", "g_mean", "g_var", "q", "t_afm")
        which = allq if which is None else tuple(which)
        x = ca.vertcat(s, u)  # eq. 3: x = [s; u]
        xc = ca.vertcat(x, ca.DM(self.direction)) if self.uses_direction else x  # and the move's context
        post = self.posterior
        xs = (xc - ca.DM(post.x_mean)) / ca.DM(post.x_scale)
        t_afm, q = self.afm.f_a(s, u)  # eq. 14
        gp_which = tuple(k for k in ("f_mean", "f_var", "g_mean", "g_var") if k in which or (k == "f_mean"
                                                                                            and "t_mean" in which))
        out = post.casadi(xs, gp_which)  # notes/vhgpr.md prediction
        if "t_mean" in which:
            out["t_mean"] = t_afm + out["f_mean"]  # eq. 1: T_t (f_a + g_e)
        if "q" in which:
            out["q"] = q
        if "t_afm" in which:
            out["t_afm"] = t_afm
        if "alt_var" in which:
            out["alt_var"] = self.alternatives.casadi(x)
        return {k: out[k] for k in which}

    # ---- NumPy reference -----------------------------------------------------------
    def _x(self, s: np.ndarray, u: np.ndarray) -> np.ndarray:
        u = np.asarray(u, dtype=float)
        s = np.asarray(s, dtype=float)
        # one row where a vector is given (np.atleast_2d's values, without its call overhead)
        u = u.reshape(1, -1) if u.ndim < 2 else u
        s = s.reshape(1, -1) if s.ndim < 2 else s
        m = u.shape[0] if s.shape[0] == 1 else s.shape[0]
        ns, nu = self.n_s, u.shape[1]
        # filled column blocks (a state row broadcast down its block): the values np.hstack gives
        X = np.empty((m, ns + nu + self._n_context_cols))
        X[:, :ns] = s
        X[:, ns:ns + nu] = u
        if self._n_context_cols:  # the move's context after x = [s; u]
            X[:, ns + nu:] = self.direction
        return X

    def predict(self, s: np.ndarray, u: np.ndarray) -> EAFMPrediction:
        """Reference prediction with :meth:`FittedVHGPR.predict` and the AFM (eq. 1).

        Parameters
        ----------
        s : ndarray, shape (n_s,) or (m, n_s)
        u : ndarray, shape (n_p,) or (m, n_p)
        """
        X = self._x(s, u)
        p = self.model.predict(X)
        U = X[:, self.n_s:self.n_x]
        t_mean = np.asarray(self.afm.t_of(U)) + p.f_mean
        return EAFMPrediction(t_mean=t_mean, f_mean=p.f_mean, f_var=p.f_var, g_mean=p.g_mean,
                              g_var=p.g_var, t_var=p.y_var, q=self.afm.q_of(U))

    def f_var_np(self, s: np.ndarray, U: np.ndarray) -> np.ndarray:
        """The mean correction's posterior variance at many u, µm², shape (m,): :meth:`predict`'s
        ``f_var`` (to the last bit) without g's part of the prediction (U shape (m, n_p))."""
        return self._f_var_of(self._xs(s, U))

    def _f_var_of(self, xs: np.ndarray) -> np.ndarray:
        c2 = self.posterior.f_var_std(xs)
        np.maximum(c2, 0.0, out=c2)
        return self.model.y_scale ** 2 * c2

    def mean_and_grad_u(self, s: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """EAFM mean t_mean and its gradient in u at many u (vectorised, for seeding).

        Parameters
        ----------
        s : ndarray, shape (n_s,)
        U : ndarray, shape (m, n_p)

        Returns
        -------
        t_mean : ndarray, shape (m,)
        dt_du : ndarray, shape (m, n_p)
        """
        t, grad = self.mean_lazy_grad_u(s, U)
        return t, grad()

    def mean_lazy_grad_u(self, s: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, Callable[[], np.ndarray]]:
        """:meth:`mean_and_grad_u` with the gradient computed only when asked for: ``t_mean``,
        shape (m,), and a function returning ``dt_du``, shape (m, n_p) (the same numbers; the
        kernel rows are computed once, a Newton step's convergence check skips the gradient)."""
        X = self._x(s, U)
        f, dfx = self.posterior.f_mean_lazy_grad(self.posterior.standardise(X))
        d = U @ self.afm.w_pred
        t = self.afm.sensor.forward(d) + f  # eq. 13: the gauge reading of the tool displacement

        def grad() -> np.ndarray:
            return self.afm.sensor.derivative(d)[:, None] * self.afm.w_pred[None, :] + dfx()[:, self.n_s:self.n_x]
        return t, grad

    # ---- g's posterior (notes/vhgpr.md, prediction): thin calls of the model's Posterior ----
    def _xs(self, s: np.ndarray, U: np.ndarray) -> np.ndarray:
        return self.posterior.standardise(self._x(s, U))

    def g_mean_np(self, s: np.ndarray, U: np.ndarray) -> np.ndarray:
        """Mean of the log noise variance at many u (O(m n), vectorised), shape (m,)."""
        xs = self._xs(s, U)
        return self.posterior.g_mean(xs, self.posterior.g_kernel_rows(xs))

    def noise_uncertainty(self, s: np.ndarray, U: np.ndarray) -> np.ndarray:
        """How uncertain the predicted log noise variance is at many u, shape (m,): g's GP
        variance plus the parametric prior mean's parameter variance, whether or not the model
        propagates the latter into ``g_var`` (:attr:`FittedVHGPR.g_prior_mean_with_uncertainty`)."""
        return self.posterior.g_uncertainty(self._xs(s, U))

    def g_joint(self, s: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Joint posterior of the log noise variance at the rows of U: mean (m,), covariance (m, m).

        ``cov = K_g(X*, X*) - V^T V + cov of the prior mean``, ``V = L_g^-1 K_g(X, X*)``
        (notes/vhgpr.md prediction, for several points at once); the prior mean's parameter
        covariance is included whether or not the model propagates it into ``g_var`` (this
        is for comparing poses on the evidence: :func:`microctl.control.controller.compare_noise`).
        """
        return self.posterior.g_joint(self._xs(s, U))

    def g_joint_and_f_var(self, s: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`g_joint` (mean (m,), covariance (m, m)) and :meth:`f_var_np` (m,) at the rows of U,
        the same numbers from one standardisation of the inputs (the least-motion rule reads all three)."""
        xs = self._xs(s, U)
        mean, cov = self.posterior.g_joint(xs)
        return mean, cov, self._f_var_of(xs)

    def g_np_pairs(self, S: np.ndarray, U: np.ndarray, *, with_gp_var: bool = True
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Mean and variance of the log noise variance for every pair (state S[i], pose U[j]).

        The transition costs of sequence control (:mod:`microctl.control.sequence`): the noise of a
        move depends on where the previous move left the actuators (x = [s; u], eq. 3), so a
        move to each candidate pose is scored from each candidate previous state. The kernel
        of g (ARD SE plus a bias; no linear part, :attr:`FittedVHGPR.g_kernel`) is separable
        over x = [s; u] (the SE part is a product over inputs), so ``k([s_i; u_j], X) . beta = sf2 (A_s o beta) A_u^T + ...`` with
        ``A_s`` (m1, n) and ``A_u`` (m2, n): one (m1 x n)(n x m2) product instead of m1 m2
        kernel rows. The prior mean (``noise_prior`` eq. 1) is evaluated on the pairwise
        features ``a_j . x + b_j`` (linear: a sum of an s part and a u part).

        Parameters
        ----------
        S : ndarray, shape (m1, n_s)
        U : ndarray, shape (m2, n_p)
        with_gp_var : bool
            As :meth:`g_np`. When g's GP variance is not negligible its exact O(m1 m2 n^2)
            term is computed row by row (:meth:`g_np`), so callers keep m1 m2 n^2 small.

        Returns
        -------
        mean, var : ndarray, shape (m1, m2)
            Equal to ``g_np(S[i], U)`` row by row.
        """
        S = np.atleast_2d(np.asarray(S, dtype=float))
        U = np.atleast_2d(np.asarray(U, dtype=float))
        post, ns = self.posterior, self.n_s
        xs_s = (S - post.x_mean[:ns]) / post.x_scale[:ns]
        if self.uses_direction:  # the move's context, the same for every pair, goes with u
            U = np.hstack([U, np.broadcast_to(self.direction, (U.shape[0], self.n_q))])
        xs_u = (U - post.x_mean[ns:]) / post.x_scale[ns:]
        return post.g_pairs(xs_s, xs_u, with_gp_var=with_gp_var)

    def g_np(self, s: np.ndarray, U: np.ndarray, *, with_gp_var: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Mean and variance of the log noise variance at many u, shapes (m,), (m,).

        ``with_gp_var=False`` leaves out the GP's O(m n^2) variance term ``k** - ||L_g^-1
        k||^2`` and keeps the prior mean's parameter variance (O(m)): a cheap proxy for
        seeding at large n.
        """
        return self.posterior.g_mean_var(self._xs(s, U), with_gp_var=with_gp_var)
