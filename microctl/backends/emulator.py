"""Serve the simulated stage on loopback TCP in the serial dialect (``microctl emulate``).

One TCP port per PZT controller (PI GCS 2 subset) and one for the gauge (line protocol),
exactly as ``shared/spec/serial-protocol.md`` describes, so the serial backend can run end
to end with ``socket://127.0.0.1:PORT`` URLs and no hardware.

Physics: one :class:`~microctl.backends.simulated.SimulatedStage` shared by all devices.
``MOV`` only stores targets (checked against the actuator's hardware ``limit_um``: outside
→ the command is rejected and ``ERR?`` answers 7) and marks a move pending; the pending move
is settled (one physical move, with its actuator-noise draws and clock step) by the next
gauge query, which then answers with one gauge-noise draw. So a serial-backend move (MOV on
each controller, ONT? polls, ERR?, one gauge query) consumes the same random draws as
``SimulatedStage.move`` and gives the same reading for the same seed.

Start state: by default the actuators stand at 0 with the servo off and no error stored.
For tests of a backend that must cope with any starting state, the emulated rig can start
elsewhere (``start_q_um``: settled there physically, so the gauge reads that pose), with
its axes still moving (``start_ont_polls``) and with an error left from an earlier session
(``stale_errors``).

Faults for tests (:class:`Fault`): a device that answers garbage, stays silent, reports
``ERR?`` 7, or drops the connection, from a given number of completed moves on.
"""

from __future__ import annotations

import re
import socket
import socketserver
import threading
from dataclasses import dataclass, replace

import numpy as np

from microctl.backends.simulated import SimulatedStage
from microctl.errors import ConfigError
from microctl.stage.config import StageConfig

FAULT_KINDS = ("garbled", "silent", "err7", "drop")

#: Loopback hosts the emulator may bind to.
LOOPBACK_HOSTS = ("127.0.0.1", "localhost")

_POLL_S = 0.05
_MAX_LINE = 4096


@dataclass(frozen=True)
class Fault:
    """A misbehaviour injected into one emulated device.

    Attributes
    ----------
    kind : str
        ``garbled`` (queries get a garbage line), ``silent`` (queries get no reply),
        ``err7`` (``ERR?`` answers 7 and MOV is rejected; controllers only), ``drop``
        (the connection is closed on the next command).
    device : str
        A controller name, or ``gauge``.
    after_moves : int
        Active once this many moves have been completed (settled) by the emulator.
    """

    kind: str
    device: str
    after_moves: int = 0


def _url_port(url: str) -> int | None:
    m = re.fullmatch(r"socket://(?:127\.0\.0\.1|localhost):(\d+)", url.strip())
    return int(m.group(1)) if m else None


def default_ports(config: StageConfig) -> list[int]:
    """Ports to serve on: controllers in config order, then the gauge.

    Taken from the config's ``socket://127.0.0.1:P`` URLs; a device with another URL gets
    50101 + its index.
    """
    ser = config.backend.serial
    if ser is None:
        raise ConfigError(f"{config.source}: backend.serial: is needed to emulate (controllers, axes and gauge)")
    urls = [c.url for c in ser.controllers] + [ser.gauge.url]
    return [(_url_port(u) or 50101 + k) for k, u in enumerate(urls)]


class _Server(socketserver.ThreadingTCPServer):
    allow_reuse_address = True
    daemon_threads = True

    def __init__(self, emulator: "Emulator", device: str, address: tuple[str, int]):
        self.emulator = emulator
        self.device = device
        super().__init__(address, _Handler)


class _Handler(socketserver.BaseRequestHandler):
    def handle(self) -> None:  # noqa: D401 - socketserver API
        server: _Server = self.server  # type: ignore[assignment]
        emu = server.emulator
        sock: socket.socket = self.request
        sock.settimeout(_POLL_S)
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError:
            pass
        buf = b""
        term = emu._terminator(server.device)
        while not emu._stopping.is_set():
            try:
                chunk = sock.recv(4096)
            except socket.timeout:
                continue
            except OSError:
                return
            if not chunk:
                return
            buf += chunk
            if len(buf) > _MAX_LINE and term not in buf:
                buf = b""
            while term in buf:
                raw, buf = buf.split(term, 1)
                line = raw.decode("ascii", errors="replace").strip()
                if not line:
                    continue
                fault = emu._fault_for(server.device)
                if fault is not None and fault.kind == "drop":
                    emu.dropped.append(server.device)
                    try:
                        sock.shutdown(socket.SHUT_RDWR)
                    except OSError:
                        pass
                    return
                reply = emu._respond(server.device, line, fault)
                if reply:
                    try:
                        sock.sendall(reply)
                    except OSError:
                        return


class Emulator:
    """The simulated stage behind emulated serial devices on loopback TCP.

    Parameters
    ----------
    config : StageConfig
        The stage; ``backend.serial`` (if present) gives the controllers, axis mapping and
        gauge query/line ending; ``backend.simulated`` the physics and noise.
    host : str
        Loopback address only (127.0.0.1).
    ports : list of int, optional
        One per controller (config order) then the gauge; 0 = pick a free port.
        Default: all 0 (ephemeral).
    seed : int, optional
        Overrides ``backend.simulated.seed``.
    faults : sequence of Fault
        Misbehaviours to inject.
    ont_polls : int
        How many ``ONT?`` polls after a MOV answer 0 before the axes report on target.
    gauge_offset_um : float
        Constant added to every gauge reply (an un-tared gauge).
    start_q_um : sequence of float, optional
        Where the actuators stand when the emulator starts (config order, within each
        ``limit_um``); ``POS?`` reports it and the platform is settled there (one physical
        move, not counted in ``stage.moves``; the clock restarts at 0). Default: all 0.
    start_ont_polls : int
        How many ``ONT?`` polls per controller answer 0 before the first ``MOV`` (axes still
        moving when a backend connects).
    stale_errors : mapping of str to int, optional
        Controller → GCS error code stored at start (left by an earlier session).

    Attributes
    ----------
    stage : SimulatedStage
    ports : dict
        Device name → bound port (after :meth:`start`).
    """

    def __init__(
        self,
        config: StageConfig,
        host: str = "127.0.0.1",
        ports: list[int] | None = None,
        seed: int | None = None,
        faults: tuple[Fault, ...] | list[Fault] = (),
        ont_polls: int = 1,
        gauge_offset_um: float = 0.0,
        start_q_um: "list[float] | tuple[float, ...] | np.ndarray | None" = None,
        start_ont_polls: int = 0,
        stale_errors: "dict[str, int] | None" = None,
    ):
        if host not in LOOPBACK_HOSTS:
            raise ConfigError(f"emulator host '{host}': only loopback (127.0.0.1) is served")
        ser = config.backend.serial
        if ser is None:
            raise ConfigError(
                f"{config.source}: backend.serial: is needed to emulate (controllers, axes and gauge)"
            )
        self.config = config
        self.host = "127.0.0.1"
        self.stage = SimulatedStage(config, seed=seed)
        self.devices = [c.name for c in ser.controllers] + ["gauge"]
        if "gauge" in self.devices[:-1]:
            raise ConfigError(f"{config.source}: backend.serial.controllers: the name 'gauge' is reserved")
        ports = [0] * len(self.devices) if ports is None else list(ports)
        if len(ports) != len(self.devices):
            raise ConfigError(
                f"give {len(self.devices)} ports (controllers {', '.join(self.devices[:-1])}, then the gauge), "
                f"got {len(ports)}"
            )
        self._requested = dict(zip(self.devices, ports))
        for f in faults:
            if f.kind not in FAULT_KINDS:
                raise ConfigError(f"fault kind '{f.kind}' is not one of {', '.join(FAULT_KINDS)}")
            if f.device not in self.devices:
                raise ConfigError(f"fault device '{f.device}' is not one of {', '.join(self.devices)}")
        self.faults = tuple(faults)
        self.ont_polls = int(ont_polls)
        self.gauge_offset_um = float(gauge_offset_um)
        self.gauge = ser.gauge
        self.names = config.stage.actuator_names
        # (controller, axis) -> actuator index
        self._axis_index = {(ser.axis_of(n).controller, ser.axis_of(n).axis): i for i, n in enumerate(self.names)}
        self._limits = [a.limit_um for a in config.stage.actuators]
        self._q = np.zeros(len(self.names))
        if start_q_um is not None:
            q0 = np.asarray(start_q_um, dtype=float).reshape(-1)
            if q0.size != len(self.names) or not np.all(np.isfinite(q0)):
                raise ConfigError(f"start_q_um: give {len(self.names)} finite positions ({', '.join(self.names)}), "
                                  f"got {list(np.atleast_1d(start_q_um))}")
            for i, (name, (lo, hi)) in enumerate(zip(self.names, self._limits)):
                if not lo <= q0[i] <= hi:
                    raise ConfigError(f"start_q_um: {name} = {q0[i]:g} µm is beyond its limit_um [{lo:g}, {hi:g}]")
            if np.any(q0 != 0):
                self.stage.settle(q0)  # the rig stands there: the gauge reads that pose
                self.stage.moves = 0
                self.stage.time_s = 0.0
            self._q = q0.copy()
        self._servo = np.zeros(len(self.names), dtype=bool)
        self._pending = False
        self._ont_wait = {c: int(start_ont_polls) for c in self.devices[:-1]}
        self._err = {c: 0 for c in self.devices[:-1]}
        for ctrl, code in (stale_errors or {}).items():
            if ctrl not in self._err:
                raise ConfigError(f"stale_errors: '{ctrl}' is not a controller ({', '.join(self.devices[:-1])})")
            self._err[ctrl] = int(code)
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._servers: dict[str, _Server] = {}
        self._threads: list[threading.Thread] = []
        self.ports: dict[str, int] = {}
        self.dropped: list[str] = []
        self.log: list[tuple[str, str]] = []

    # ---- lifecycle -----------------------------------------------------------------
    def start(self) -> dict[str, int]:
        """Bind every device and serve in background threads; returns device → port."""
        try:
            for dev in self.devices:
                srv = _Server(self, dev, (self.host, self._requested[dev]))
                self._servers[dev] = srv
                self.ports[dev] = srv.server_address[1]
        except OSError as exc:
            self.stop()
            raise ConfigError(f"cannot listen on {self.host}: {exc}") from None
        for dev, srv in self._servers.items():
            th = threading.Thread(
                target=srv.serve_forever, kwargs={"poll_interval": _POLL_S}, name=f"emulate-{dev}", daemon=True
            )
            th.start()
            self._threads.append(th)
        return dict(self.ports)

    def stop(self) -> None:
        """Stop serving and close every socket (idempotent)."""
        self._stopping.set()
        for srv in self._servers.values():
            srv.shutdown()
            srv.server_close()
        for th in self._threads:
            th.join(timeout=2.0)
        self._servers.clear()
        self._threads.clear()

    def __enter__(self) -> "Emulator":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def url(self, device: str) -> str:
        """``socket://127.0.0.1:PORT`` of a started device."""
        return f"socket://{self.host}:{self.ports[device]}"

    def pointed_at(self, config: StageConfig | None = None) -> StageConfig:
        """``config`` (default: the emulated one) as a serial config whose controllers and gauge
        are this started emulator's devices: what a serial backend connects with."""
        config = self.config if config is None else config
        ser = config.backend.serial
        if ser is None:
            raise ConfigError(f"{config.source}: backend.serial: is needed to connect to the emulator")
        ser = replace(ser, controllers=tuple(replace(c, url=self.url(c.name)) for c in ser.controllers),
                      gauge=replace(ser.gauge, url=self.url("gauge")))
        return replace(config, backend=replace(config.backend, kind="serial", serial=ser))

    # ---- protocol ------------------------------------------------------------------
    def _terminator(self, device: str) -> bytes:
        """The byte that ends a command line: LF for a controller, the gauge's eol's last byte."""
        return self.gauge.eol.encode("ascii")[-1:] if device == "gauge" else b"\n"

    def _fault_for(self, device: str) -> Fault | None:
        for f in self.faults:
            if f.device == device and self.stage.moves >= f.after_moves:
                return f
        return None

    def _respond(self, device: str, line: str, fault: Fault | None) -> bytes:
        with self._lock:
            self.log.append((device, line))
            if device == "gauge":
                return self._gauge_reply(line, fault)
            return self._gcs_reply(device, line, fault)

    def _gauge_reply(self, line: str, fault: Fault | None) -> bytes:
        eol = self.gauge.eol.encode("ascii")
        if line != self.gauge.query.strip():
            return b"?" + eol
        if fault is not None and fault.kind == "silent":
            return b""
        if fault is not None and fault.kind == "garbled":
            return b"#\x15E\xffRR" + eol
        if self._pending:
            self.stage.settle(self._q)
            self._pending = False
        value = self.stage.read() + self.gauge_offset_um
        return f"{value:+.9f}".encode("ascii") + eol

    def _gcs_reply(self, ctrl: str, line: str, fault: Fault | None) -> bytes:
        parts = line.split()
        cmd, args = parts[0].upper(), parts[1:]
        query = cmd.endswith("?")
        if query and fault is not None and fault.kind == "silent":
            return b""
        if query and fault is not None and fault.kind == "garbled" and cmd != "*IDN?":
            return b"\x15\xfe1=?garbage\n"
        if cmd == "*IDN?":
            return f"microctl emulator, {ctrl}, simulated PZT driver\n".encode("ascii")
        if cmd == "ERR?":
            code = 7 if (fault is not None and fault.kind == "err7") else self._err[ctrl]
            self._err[ctrl] = 0
            return f"{code}\n".encode("ascii")
        if cmd in ("SVO", "MOV"):
            pairs = self._pairs(ctrl, args)
            if pairs is None:
                return b""
            if cmd == "SVO":
                for i, v in pairs:
                    self._servo[i] = v != 0
                return b""
            if fault is not None and fault.kind == "err7":
                self._err[ctrl] = 7
                return b""
            if not all(self._servo[i] for i, _ in pairs):
                self._err[ctrl] = 10
                return b""
            for i, v in pairs:
                lo, hi = self._limits[i]
                if not (lo <= v <= hi):
                    self._err[ctrl] = 7
                    return b""
            for i, v in pairs:
                self._q[i] = v
            self._pending = True
            self._ont_wait[ctrl] = self.ont_polls
            return b""
        if cmd in ("ONT?", "POS?"):
            idx = self._axes(ctrl, args)
            if idx is None:
                return b""
            if cmd == "ONT?":
                on = self._ont_wait[ctrl] <= 0
                self._ont_wait[ctrl] -= 1
                values = ["1" if on else "0"] * len(idx)
            else:
                values = [f"{self._q[i]:.6f}" for _, i in idx]
            lines = [f"{a}={v}" for (a, _), v in zip(idx, values)]
            return (" \n".join(lines) + "\n").encode("ascii")  # GCS multi-line rule
        self._err[ctrl] = 2
        return b""

    def _pairs(self, ctrl: str, args: list[str]) -> list[tuple[int, float]] | None:
        if not args or len(args) % 2:
            self._err[ctrl] = 1
            return None
        out = []
        for a, v in zip(args[::2], args[1::2]):
            if (ctrl, a) not in self._axis_index:
                self._err[ctrl] = 1
                return None
            try:
                value = float(v)
            except ValueError:
                self._err[ctrl] = 1
                return None
            if not np.isfinite(value):
                self._err[ctrl] = 1
                return None
            out.append((self._axis_index[(ctrl, a)], value))
        return out

    def _axes(self, ctrl: str, args: list[str]) -> list[tuple[str, int]] | None:
        if not args:
            args = [a for (c, a) in self._axis_index if c == ctrl]
        out = []
        for a in args:
            if (ctrl, a) not in self._axis_index:
                self._err[ctrl] = 1
                return None
            out.append((a, self._axis_index[(ctrl, a)]))
        return out
