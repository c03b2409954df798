"""``microctl emulate``: serve the simulated stage in the serial dialect on loopback TCP."""

from __future__ import annotations

import argparse
import sys
import time

from microctl.backends.emulator import Emulator, default_ports
from microctl.cli.commands._common import add_quiet, seed
from microctl.errors import ConfigError
from microctl.stage.config import load_stage_config


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``emulate`` sub-command."""
    p = subparsers.add_parser(
        "emulate",
        help="serve the simulated stage in the serial dialect until interrupted",
        description="Serve the stage config's simulated stage on 127.0.0.1: one TCP port per PZT "
        "controller (PI GCS 2 subset) and one for the gauge, until Ctrl-C.",
    )
    p.add_argument("--config", required=True, metavar="STAGE.yaml", help="stage config with a backend.serial section")
    p.add_argument("--host", default="127.0.0.1", help="loopback address to listen on (only 127.0.0.1)")
    p.add_argument(
        "--ports",
        metavar="P1,P2,...",
        help="ports for the controllers (config order) then the gauge; default from the config's "
        "socket://127.0.0.1:P URLs",
    )
    p.add_argument("--seed", type=seed, default=None, help="override backend.simulated.seed (a non-negative integer)")
    p.add_argument("--start-q", metavar="Q1,Q2,...", default=None,
                   help="actuator positions (µm, config order) the emulated rig starts at (default: all 0)")
    add_quiet(p)
    p.set_defaults(func=_run)


def _parse_ports(text: str) -> list[int]:
    try:
        ports = [int(x) for x in text.split(",")]
    except ValueError:
        raise ConfigError(f"--ports '{text}': expected comma-separated port numbers") from None
    for port in ports:
        if not 0 <= port <= 65535:
            raise ConfigError(f"--ports: {port} is not a port number (0-65535)")
    return ports


def _check_distinct(ports: list[int], where: str) -> None:
    """Each device needs its own port (0: any free one)."""
    if not ports:
        raise ConfigError(f"{where}: no port to serve on; give one per device (controllers, then the gauge)")
    seen = [p for p in ports if p != 0]
    for p in seen:
        if seen.count(p) > 1:
            raise ConfigError(f"{where}: port {p} is given {seen.count(p)} times; each device (controllers, then "
                              "the gauge) needs its own port (0: any free one)")


def _parse_start_q(text: str | None) -> list[float] | None:
    if text is None:
        return None
    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        raise ConfigError(f"--start-q '{text}': expected comma-separated positions in µm") from None
    return values


def _run(args: argparse.Namespace, max_seconds: float | None = None) -> int:
    config = load_stage_config(args.config)
    ports = _parse_ports(args.ports) if args.ports else default_ports(config)
    _check_distinct(ports, "--ports" if args.ports else f"{args.config}: the devices' socket:// URLs")
    emu = Emulator(config, host=args.host, ports=ports, seed=args.seed, start_q_um=_parse_start_q(args.start_q))
    bound = emu.start()
    try:
        for dev, port in bound.items():
            print(f"emulate: {dev} on socket://127.0.0.1:{port}", flush=True)
        if not args.quiet:
            print("emulate: serving the simulated stage; Ctrl-C to stop", file=sys.stderr, flush=True)
        t0 = time.monotonic()
        while max_seconds is None or time.monotonic() - t0 < max_seconds:
            time.sleep(0.2)
    finally:  # Ctrl-C: the ports are closed, then main() says "microctl: interrupted", exit 130
        emu.stop()
    return 0
