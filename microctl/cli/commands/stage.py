"""``microctl stage show``: the kinematic matrices, workspace and reachable range of a stage."""

from __future__ import annotations

import argparse

from microctl.models.afm import AnalyticForwardModel
from microctl.stage.config import load_stage_config
from microctl.stage.kinematics import contact_map, hinge_jacobian
from microctl.util.io import print_json

_UNITS = {"x": "µm", "y": "µm", "z": "µm", "rx": "mrad", "ry": "mrad", "rz": "mrad"}


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``stage`` command group."""
    p = subparsers.add_parser("stage", help="inspect a stage configuration")
    sub = p.add_subparsers(dest="stage_command", metavar="SUBCOMMAND")
    show = sub.add_parser("show", help="print kinematic matrices, workspace bounds and the reachable range of t")
    show.add_argument("--config", required=True, help="stage YAML file")
    show.add_argument("--json", action="store_true", help="machine-readable output on stdout")
    show.set_defaults(func=_show)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def stage_summary(config_path: str) -> dict:
    """Everything ``stage show`` reports, as plain data (units µm, mrad, mm)."""
    cfg = load_stage_config(config_path)
    afm = AnalyticForwardModel(cfg.stage)
    hrj, hrp = contact_map(cfg.stage)
    lo, hi = afm.t_range()
    return {
        "config": str(config_path),
        "name": cfg.stage.name,
        "dof": list(cfg.stage.dof),
        "dof_units": [_UNITS[d] for d in cfg.stage.dof],
        "actuators": list(cfg.stage.actuator_names),
        "output": cfg.stage.tool.name,
        "inverse_kinematics": afm.K.tolist(),
        "tool": afm.w.tolist(),
        "contact_map_HRJ": hrj.tolist(),
        "contact_map_HRP_Jh": (hrp @ hinge_jacobian(cfg.stage.dof)).tolist(),
        "actuator_range_um": [list(a.range_um) for a in cfg.stage.actuators],
        "workspace_u_bounds": {d: [float(a), float(b)] for d, a, b in zip(cfg.stage.dof, afm.workspace.u_lo, afm.workspace.u_hi)},
        "t_range_um": [lo, hi],
        "backend": cfg.backend.kind,
        "geometry_hash": cfg.stage.geometry_hash(),
    }


def _fmt_row(values, width: int = 10) -> str:
    return " ".join(f"{v:{width}.4f}" for v in values)


def _show(args: argparse.Namespace) -> int:
    info = stage_summary(args.config)
    if args.json:
        print_json(info)
        return 0
    dof, acts = info["dof"], info["actuators"]
    head = " ".join(f"{f'{d} [{u}]':>10}" for d, u in zip(dof, info["dof_units"]))
    print(f"stage {info['name']} ({info['config']}), backend {info['backend']}")
    print(f"\ninverse kinematics q = K u (eq. 12), q in µm:\n{'':>6} {head}")
    for name, row in zip(acts, info["inverse_kinematics"]):
        print(f"{name:>6} {_fmt_row(row)}")
    print(f"\ntool map {info['output']} = w · u (eq. 13), µm:\n{'':>6} {head}\n{'w':>6} {_fmt_row(info['tool'])}")
    print("\ncontact map H R^T J (eq. 10):")
    for name, row in zip(acts, info["contact_map_HRJ"]):
        print(f"{name:>6} {_fmt_row(row)}")
    print("\nworkspace (bounding box of {u : range_lo <= K u <= range_hi}):")
    for d, u in zip(dof, info["dof_units"]):
        a, b = info["workspace_u_bounds"][d]
        print(f"{d:>6} [{a:9.4f}, {b:9.4f}] {u}")
    print("actuator ranges (µm): " + ", ".join(f"{n} {r[0]:g}..{r[1]:g}" for n, r in zip(acts, info["actuator_range_um"])))
    lo, hi = info["t_range_um"]
    print(f"\nreachable {info['output']}: [{lo:.4f}, {hi:.4f}] µm (the AFM's, from the zero state; with a trained "
          "model `solve` reports the EAFM's range, which adds the model's correction)")
    return 0
