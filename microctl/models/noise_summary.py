"""The residual model's noise model in the diagnosis vocabulary's units (reports, ``microctl train``)."""

from __future__ import annotations

import math

import numpy as np

from microctl.gp.vhgpr import FittedVHGPR
from microctl.models.afm import AnalyticForwardModel

__all__ = ["noise_summary"]


def noise_summary(model: FittedVHGPR, afm: AnalyticForwardModel) -> dict:
    """The physical noise model's parameters in the diagnosis vocabulary's units.

    ``floor_std_um = sqrt(c_0) y_scale`` (gauge noise and driver accuracy together) and, per
    actuator, ``friction_std_per_um = sqrt(c_i) / |s_i|`` with ``s_i`` the AFM's tool
    sensitivity to actuator i (``w K^+``: how a slip of actuator i moves the tool when the four
    balls share it elastically), comparable with ``actuator_friction.std_per_um``.

    Returns
    -------
    dict
        ``{"noise_model", "floor_std_um", "actuators": {name: {"tool_std_per_um",
        "friction_std_per_um"}}}``; only ``noise_model`` for the ``hgp`` model.
    """
    out: dict = {"noise_model": model.noise_model}
    selection = model.info.get("noise_selection")
    if selection is not None:
        out["selection"] = selection
    if model.noise_model == "dictionary":
        out["floor_std_um"] = float(math.exp(0.5 * model.g_mu0) * model.y_scale)
        if model.g_feature_matrix is None:
            out["sources"] = {}
            return out
        c = np.exp(np.asarray(model.g_log_feature_coef))
        out["sources"] = {name: {"shape": shape, "params": list(par), "coef_um2": float(ci * model.y_scale**2)}
                          for name, shape, par, ci in zip(model.g_feature_names, model.g_feature_shapes,
                                                          model.g_feature_params, c)}
        return out
    if model.noise_model != "physical":
        return out
    sens_all = np.asarray(afm.w_pred) @ np.linalg.pinv(afm.K)  # (n_q,)
    sens = [sens_all[afm.actuator_names.index(f.removeprefix("d"))] for f in model.g_feature_names]
    c = np.exp(np.asarray(model.g_log_feature_coef))
    params = model.info.get("noise_parameters") or {}
    c_std = np.asarray(params.get("c_std", [math.nan] * (1 + c.size)), dtype=float)
    out["floor_std_um"] = float(math.exp(0.5 * model.g_mu0) * model.y_scale)
    out["actuators"] = {}
    for name, ci, sd, si in zip(model.g_feature_names, c, c_std[1:], sens):
        # std per µm = sqrt(c) (c in units of y_scale^2 per (µm / y_scale)^2 = per µm^2 of step);
        # its standard error by the delta method, bounded by sqrt(sd) where c is near zero
        se = min(0.5 * sd / math.sqrt(ci), math.sqrt(sd)) if ci > 0 and math.isfinite(sd) else math.nan
        out["actuators"][name.removeprefix("d")] = {
            "tool_std_per_um": float(math.sqrt(ci)), "tool_std_per_um_se": float(se),
            "friction_std_per_um": float(math.sqrt(ci) / max(abs(si), 1e-12)),
            "friction_std_per_um_se": float(se / max(abs(si), 1e-12))}
    return out
