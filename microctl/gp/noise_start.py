"""A start for g from the data: a GP fitted to the log squared residuals of the start's f.

The VHGPR's usual start (notes/vhgpr.md, [N]) is the homoscedastic GP: Lambda = 1/2, so g's
posterior mean is its prior mean everywhere, with g's kernel at unit signal variance. From there
L-BFGS-B tends to shrink g's signal variance before Lambda has moved the mean anywhere: the
bound's KL and trace terms pay for a large prior variance at once, the likelihood rewards it only
after mu follows the data. Once the signal variance is at its lower bound the gradient in
Lambda vanishes (mu - mu0 = K_g (Lambda - I/2) 1) and the run ends with a flat g, whatever the
noise does. Measured on the bench rigs (scripts/bench_rigs.py): every fitted residual model had
g's signal variance at its bound, including the paper's ``hgp`` model on rigs where a noise
model with the right features gains many nats of bound.

This start puts g where the residuals say the noise is (the idea of Kersting et al. 2007,
"most likely heteroscedastic GP", used here only as a start of the variational fit):

1. the residuals of the start's f, ``e = y - K_f alpha = R alpha`` (alpha = (K_f + R)^-1 y);
2. ``z_i = log e_i^2 + 1.2704``: an unbiased estimate of the log noise variance
   (E log chi^2_1 = -1.2704);
3. a homoscedastic GP on z with g's kernel (its inputs, mapped or not) minus g's prior mean m at
   the training inputs (for a constant prior mean, mu0 = mean z first): its lengthscales and
   signal variance start g's kernel;
4. Lambda so that g's variational mean is that GP's posterior mean,
   ``mu - m = K_g (Lambda - I/2) 1 = K_g (K_g + s^2 I)^-1 (z - m)``, i.e.
   ``Lambda = 1/2 + w``, ``w = (K_g + s^2 I)^-1 (z - m)``. Lambda must be positive: where
   some ``1/2 + w_i`` falls below 0.05 the whole w is scaled down until it does not, so mu
   keeps the posterior mean's shape at a smaller amplitude (clipping single entries instead
   changes the shape: on the tilt of tests/gp/test_noise_start.py it turned a strong positive
   correlation with the planted log variance into a negative one).

The optimiser then starts with g already following the data, and the bound decides.
"""

from __future__ import annotations

import math

import numpy as np

from microctl.gp.bound import Layout, mv_bound, prior_mean_terms
from microctl.gp.homoscedastic import fit_homoscedastic
from microctl.gp.kernels import KernelSpec

__all__ = ["log_residual_start", "E_LOG_CHI2_1"]

#: E[log chi^2_1] = -(Euler's gamma) - log 2.
E_LOG_CHI2_1 = -0.5772156649015329 - math.log(2.0)
#: Range of Lambda at the start.
LAMBDA_RANGE = (0.05, 50.0)


def _shrink(w: np.ndarray) -> float:
    """The largest t in (0, 1] with ``1/2 + t w`` inside :data:`LAMBDA_RANGE` everywhere."""
    lo, hi = LAMBDA_RANGE[0] - 0.5, LAMBDA_RANGE[1] - 0.5
    t = 1.0
    if w.min() < lo:
        t = min(t, lo / float(w.min()))
    if w.max() > hi:
        t = min(t, hi / float(w.max()))
    return t


def log_residual_start(x0: np.ndarray, Xs: np.ndarray, ys: np.ndarray, layout: Layout,
                       Phi: np.ndarray | None, rng: np.random.Generator) -> np.ndarray:
    """The start ``x0`` with g's kernel block, Lambda and (constant prior mean) mu0 from the log
    squared residuals of x0's f (module docstring).

    Parameters
    ----------
    x0 : ndarray, shape (layout.size,)
        A start of the bound (its f is used; its g is replaced).
    Xs : ndarray, shape (n, d)
        Standardised inputs.
    ys : ndarray, shape (n,)
        Standardised outputs.
    layout : Layout
    Phi : ndarray, shape (n, p), or None
        g's prior-mean design (None: the constant mu0).
    rng : numpy.random.Generator
        For the homoscedastic fit's subset (above its size limit).

    Returns
    -------
    ndarray, shape (layout.size,)
        Inside the layout's bounds.
    """
    n = layout.n
    _, _, state = mv_bound(x0, Xs, ys, layout, want_grad=False, want_state=True, Phi=Phi)
    e = state["r"] * state["f_alpha"]  # y - K_f alpha
    z = np.log(e * e + 1e-12) - E_LOG_CHI2_1
    x = np.array(x0, dtype=float)
    if layout.p == 0:  # the constant prior mean starts at the residuals' mean log variance
        x[layout.mean_slice.start] = float(np.mean(z))
    m, _ = prior_mean_terms(x[layout.mean_slice], Phi)
    zc = z - m
    Zg = layout.g.unpack(x0[layout.g_slice]).inputs(Xs)  # g's kernel inputs (mapped, if g has a map)
    spec = KernelSpec(d=layout.g.d, bias=layout.g.bias)
    theta, _, _ = fit_homoscedastic(Zg, zc, spec, rng)
    x[layout.g_slice] = theta[:spec.size]
    kz = spec.unpack(theta[:spec.size])
    A = kz.matrix(Zg, Zg)
    A[np.diag_indices(n)] += math.exp(float(theta[-1]))
    w = np.linalg.solve(A, zc)
    x[:n] = np.log(0.5 + _shrink(w) * w)
    lo, hi = (np.array(b) for b in zip(*layout.bounds()))
    return np.clip(x, lo, hi)
