"""Serial hardware backend: PI GCS 2 subset for the PZT drivers, a line protocol for the gauge.

Contract: ``shared/spec/serial-protocol.md`` (see ``docs/serial-protocol.md``). Ports are
opened with pyserial's ``serial_for_url`` in the constructor, so a config may name a real
port (``/dev/ttyUSB0``), a TCP bridge (``socket://host:port``) or ``loop://``.

Start-up, from whatever state the devices are in: per controller ``*IDN?`` (one line must
come back); per controller that drives an actuator, ``ERR?`` (a stale error left by an
earlier session is read, which clears it, and reported in :attr:`SerialStage.notes`),
``SVO a 1 ...`` for its axes, ``ERR?`` must be 0, ``ONT?`` polled until its axes are on
target (an axis still moving is waited for), ``POS?`` read: the start positions, refused if
beyond an actuator's hardware ``limit_um``. Then the gauge is read (mean of ``samples``
queries): the start state s = [t; q] that the first move's log row carries as its previous
state. With ``zero_at_start`` the stage instead moves to the zero state (range-checked like
every move) and the gauge is tared there on the mean of ``tare_samples`` readings.

A move: range check of q = K u (nothing sent on failure); ``MOV a v ...`` to every
controller that drives an actuator, carrying all of its actuators (also those whose target
is unchanged: resending a target is a no-op for a GCS driver, and every axis is then
confirmed on target and error-free each move); ``ONT?`` polled until every axis reports 1
(timeout ``on_target_timeout_s``); ``ERR?`` on every controller that received the ``MOV``,
each failure naming its controller; then the gauge (mean of ``samples`` queries). A reply
that does not parse is re-queried up to ``retries`` times; no reply within the port's
timeout is an error at once. Every error names the device (controller name and URL), the
axes concerned and quotes the bytes received.
"""

from __future__ import annotations

import re
import time

import numpy as np

from microctl.backends.base import StageBackend, register_backend
from microctl.errors import BackendError, ConfigError
from microctl.measurement.log import Measurement
from microctl.stage.config import StageConfig
from microctl.util.tabular import NUMBER_PATTERN

#: Meanings of the GCS error codes this dialect uses.
GCS_ERRORS = {
    1: "parameter syntax error",
    2: "unknown command",
    7: "position out of limits",
    10: "controller not ready (servo off)",
}

_MAX_REPLY_LINES = 64

#: How far a position read with ``POS?`` at start may lie beyond an actuator's hardware
#: ``limit_um`` (servo error at a limit), µm; further out the start is refused.
POSITION_TOLERANCE_UM = 0.01


def _finite_decimal(text: str) -> bool:
    """Whether a device's reply field is a finite decimal number (a position, a gauge reading)."""
    return NUMBER_PATTERN.fullmatch(text) is not None and bool(np.isfinite(float(text)))


class _Port:
    """One serial device: a name for messages, the pyserial port and the line ending."""

    def __init__(self, label: str, url: str, baudrate: int, timeout_s: float, eol: bytes):
        import serial  # pyserial

        self.label = label
        self.url = url
        self.eol = eol
        self.terminator = eol[-1:]  # a reply line ends with the last byte of the line ending
        self.timeout_s = timeout_s
        try:
            self.port = serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s, write_timeout=timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            hint = ""
            if "refused" in str(exc).lower() and url.startswith("socket://"):
                hint = ("; nothing listens there: start the devices, or try the serial path with no hardware: "
                        "`microctl emulate --config STAGE.yaml` serves the simulated stage on loopback")
            raise BackendError(f"{label} ({url}): cannot open: {exc}{hint}") from None

    def fail(self, message: str) -> BackendError:
        return BackendError(f"{self.label} ({self.url}): {message}")

    def send(self, text: str) -> None:
        import serial

        try:
            self.port.reset_input_buffer()  # drop a late reply to an earlier query
            self.port.write(text.encode("ascii") + self.eol)
            self.port.flush()
        except (serial.SerialException, OSError) as exc:
            raise self.fail(f"connection lost while sending {text!r}: {exc}") from None

    def read_line(self, command: str, what: str, received: bytes = b"") -> bytes:
        """One reply line including its terminator; error if none arrives within the timeout."""
        import serial

        try:
            line = self.port.read_until(self.terminator)
        except (serial.SerialException, OSError) as exc:
            raise self.fail(
                f"connection lost waiting for the reply to {command!r} ({what}); received {received!r}: {exc}"
            ) from None
        if not line.endswith(self.terminator):
            got = received + line
            raise self.fail(
                f"no reply to {command!r} ({what}) within {self.timeout_s:g} s; received {got!r}"
            )
        return line

    def close(self) -> None:
        try:
            self.port.close()
        except Exception:  # noqa: BLE001 - closing must not raise
            pass


@register_backend("serial")
class SerialStage(StageBackend):
    """The stage driven through serial devices (``backend.kind: serial``).

    Parameters
    ----------
    config : StageConfig
        Must have ``backend.serial``.
    zero_gauge : bool, optional
        If true, move to the zero state at start and subtract the gauge reading there (the
        mean of ``gauge.tare_samples`` readings) from every reading, for a gauge that is not
        tared at the zero state. Default: the config's ``backend.serial.gauge.zero_at_start``
        (false: the gauge is read as it is, as the emulator serves it).

    Attributes
    ----------
    start_state : ndarray, shape (1 + n_q,)
        s = [t; q] found at connect: ``POS?`` of every actuator and the gauge reading (after
        the tare: the zero state). :attr:`state` before the first move.
    tare_um : float
        The offset subtracted from every reading (0.0 without a tare).
    notes : list of str
        What the start-up found that a user should know (stale device errors cleared, the
        start state, the tare and its standard error).
    """

    def __init__(self, config: StageConfig, zero_gauge: bool | None = None):
        super().__init__(config)
        ser = config.backend.serial
        if ser is None:
            raise ConfigError(f"{config.source}: backend.serial: is required for the serial backend")
        if zero_gauge is None:
            zero_gauge = ser.gauge.zero_at_start
        self.settings = ser
        self._pattern = re.compile(ser.gauge.reply_pattern)
        self._ports: dict[str, _Port] = {}
        self._gauge: _Port | None = None
        # actuator index -> (controller name, axis)
        self._axes = [ser.axis_of(name) for name in config.stage.actuator_names]
        self._t0 = time.monotonic()
        self._offset = 0.0
        self.tare_um = 0.0
        try:
            for c in ser.controllers:
                self._ports[c.name] = _Port(f"controller '{c.name}'", c.url, c.baudrate, c.timeout_s, b"\n")
            g = ser.gauge
            self._gauge = _Port("gauge", g.url, g.baudrate, g.timeout_s, g.eol.encode("ascii"))
            for c in ser.controllers:
                port = self._ports[c.name]
                port.send("*IDN?")
                port.read_line("*IDN?", "identification")
            q0 = np.empty(config.stage.n_act)
            for c in ser.controllers:
                axes = self._controller_axes(c.name)
                if not axes:
                    continue
                stale = self._error_code(c.name, axes)
                if stale != 0:
                    self.notes.append(
                        f"controller '{c.name}' reported error {stale} ({GCS_ERRORS.get(stale, 'unknown error')}) left "
                        "from before this session; reading it cleared it"
                    )
                self._ports[c.name].send("SVO " + " ".join(f"{a} 1" for a in axes))
                self._check_errors([c.name], "switching the servo on")
                self._wait_on_target({c.name: axes}, "at start (an axis was still moving)")
                for axis, value in self._positions(c.name, axes).items():
                    q0[self._actuator_index(c.name, axis)] = value
            self._check_start_positions(q0)
            if zero_gauge:
                _, q_zero = self.command_for(np.zeros(config.stage.n_dof))  # range-checked like any move
                self._execute(q_zero)
                readings = np.array([self._read_gauge(samples=1) for _ in range(g.tare_samples)])
                self._offset = self.tare_um = float(readings.mean())
                se = float(readings.std(ddof=1) / np.sqrt(readings.size)) if readings.size > 1 else float("nan")
                self.notes.append(
                    f"gauge tared at the zero state: offset {self.tare_um:+.4f} µm, the mean of {readings.size} "
                    f"readings (tare_samples; standard error {se:.2g} µm); every reading is reported relative to it"
                )
                self.start_state = np.concatenate([[0.0], q_zero])
            else:
                t_start = self._read_gauge()
                self.start_state = np.concatenate([[t_start], q0])
                self.notes.append(
                    "start state read from the devices: "
                    + ", ".join(f"{n} = {v:.4f} µm" for n, v in zip(config.stage.actuator_names, q0))
                    + f" (POS?), {config.stage.tool.name} = {t_start:.4f} µm (gauge)"
                )
            self._set_state(self.start_state[0], self.start_state[1:])
        except BaseException:
            self.close()
            raise
        self._t0 = time.monotonic()

    # ---- helpers -------------------------------------------------------------------
    def _controller_axes(self, controller: str) -> list[str]:
        return [m.axis for m in self._axes if m.controller == controller]

    def _actuator_index(self, controller: str, axis: str) -> int:
        return next(i for i, m in enumerate(self._axes) if m.controller == controller and m.axis == axis)

    def _query_gcs(self, controller: str, command: str, axes: list[str], what: str) -> list[str]:
        """Send a GCS query and read its (possibly multi-line) reply, lines decoded and stripped."""
        port = self._ports[controller]
        port.send(command)
        raw = b""
        lines: list[str] = []
        for _ in range(_MAX_REPLY_LINES):
            line = port.read_line(command, f"axes {', '.join(axes)}" if axes else what, raw)
            raw += line
            lines.append(line.decode("ascii", errors="replace").strip())
            if not line.endswith(b" \n"):  # GCS: all but the last line end with a space
                return lines
        raise port.fail(f"reply to {command!r} has more than {_MAX_REPLY_LINES} lines; received {raw!r}")

    def _parse_axis_values(self, lines: list[str], axes: list[str]) -> dict[str, str] | None:
        out = {}
        for line in lines:
            m = re.fullmatch(r"(\S+)=(\S+)", line)
            if m is None:
                return None
            out[m.group(1)] = m.group(2)
        if set(out) != set(axes):
            return None
        return out

    def _query_axes(self, controller: str, query: str, axes: list[str], what: str, expected: str,
                    valid) -> dict[str, str]:
        """``<query> a b ..`` → {axis: value} with every value ``valid`` (unparsable replies re-queried)."""
        command = f"{query} " + " ".join(axes)
        received = []
        for _ in range(self.settings.retries + 1):
            lines = self._query_gcs(controller, command, axes, what)
            values = self._parse_axis_values(lines, axes)
            if values is not None and all(valid(v) for v in values.values()):
                return values
            received.append("\n".join(lines))
        raise self._ports[controller].fail(
            f"unparsable reply to {command!r} (axes {', '.join(axes)}) after {self.settings.retries + 1} "
            f"attempts; expected {expected}, received {received[-1]!r}"
        )

    def _on_target(self, controller: str, axes: list[str]) -> bool:
        """One ``ONT?`` poll: whether every axis is on target (retries an unparsable reply)."""
        values = self._query_axes(controller, "ONT?", axes, "on-target", "'<axis>=0|1' lines",
                                  lambda v: v in ("0", "1"))
        return all(v == "1" for v in values.values())

    def _positions(self, controller: str, axes: list[str]) -> dict[str, float]:
        """``POS?`` of ``axes``, µm (finite decimal numbers)."""
        values = self._query_axes(controller, "POS?", axes, "position", "'<axis>=<pos_um>' lines", _finite_decimal)
        return {a: float(v) for a, v in values.items()}

    def _check_start_positions(self, q0: np.ndarray) -> None:
        """Refuse to start when a position read at connect is beyond its actuator's hardware limit."""
        for i, (a, m) in enumerate(zip(self.stage.actuators, self._axes)):
            lo, hi = a.limit_um
            if not lo - POSITION_TOLERANCE_UM <= q0[i] <= hi + POSITION_TOLERANCE_UM:
                raise self._ports[m.controller].fail(
                    f"POS? reports axis {m.axis} (actuator {a.name}) at {q0[i]:.4f} µm, beyond its hardware limit "
                    f"[{lo:g}, {hi:g}] µm; check the axis mapping (backend.serial.axes) and the units; nothing was "
                    "moved"
                )

    def _error_code(self, controller: str, axes: list[str]) -> int:
        """``ERR?`` of one controller (reading it clears it); retries an unparsable reply."""
        last = ""
        for _ in range(self.settings.retries + 1):
            lines = self._query_gcs(controller, "ERR?", axes, "error code")
            last = "\n".join(lines)
            if len(lines) == 1 and re.fullmatch(r"-?\d+", lines[0]):
                return int(lines[0])
        raise self._ports[controller].fail(
            f"unparsable reply to 'ERR?' (axes {', '.join(axes)}) after {self.settings.retries + 1} attempts; "
            f"expected an integer, received {last!r}"
        )

    def _check_errors(self, controllers: list[str], context: str | dict[str, str]) -> None:
        """``ERR?`` must be 0 on each of ``controllers``; every one is queried (which clears its
        error), and the error names each controller that failed, its axes and code."""
        failures = []
        for ctrl in controllers:
            axes = self._controller_axes(ctrl)
            code = self._error_code(ctrl, axes)
            if code != 0:
                what = context[ctrl] if isinstance(context, dict) else context
                meaning = GCS_ERRORS.get(code, "unknown error")
                failures.append(self._ports[ctrl].fail(
                    f"error {code} ({meaning}) after {what} on axes {', '.join(axes)}; received '{code}'"))
        if failures:
            message = "; also ".join(str(f) for f in failures)
            raise BackendError(message)

    def _wait_on_target(self, pending: dict[str, list[str]], context: str) -> None:
        """Poll ``ONT?`` until every axis of ``pending`` (controller → axes) is on target."""
        pending = dict(pending)
        deadline = time.monotonic() + self.settings.on_target_timeout_s
        while pending:
            for ctrl in list(pending):
                if self._on_target(ctrl, pending[ctrl]):
                    del pending[ctrl]
            if not pending:
                break
            if time.monotonic() > deadline:
                ctrl, axes = next(iter(pending.items()))
                code = self._error_code(ctrl, axes)
                why = "" if code == 0 else f"; ERR? reports {code} ({GCS_ERRORS.get(code, 'unknown error')})"
                raise self._ports[ctrl].fail(
                    f"axes {', '.join(axes)} not on target within {self.settings.on_target_timeout_s:g} s "
                    f"{context}{why}"
                )
            time.sleep(self.settings.poll_interval_s)

    def _execute(self, q: np.ndarray) -> None:
        """MOV to every controller that drives an actuator, wait for on-target, check errors on each
        (q already range-checked)."""
        by_ctrl: dict[str, list[tuple[str, float]]] = {}
        for m, v in zip(self._axes, q):
            by_ctrl.setdefault(m.controller, []).append((m.axis, float(v)))
        for ctrl, pairs in by_ctrl.items():
            self._ports[ctrl].send("MOV " + " ".join(f"{a} {v:.6f}" for a, v in pairs))
        self._wait_on_target({c: [a for a, _ in pairs] for c, pairs in by_ctrl.items()}, "after MOV")
        context = {c: "MOV " + ", ".join(f"{a} -> {v:.4f} µm" for a, v in pairs) for c, pairs in by_ctrl.items()}
        self._check_errors(list(by_ctrl), context)

    def _read_gauge(self, samples: int | None = None) -> float:
        """The mean of ``samples`` (default: the config's) gauge queries, µm (not tared)."""
        g = self.settings.gauge
        port = self._gauge
        if port is None:
            raise BackendError("the gauge port is not open")
        n = g.samples if samples is None else samples
        total = 0.0
        for _ in range(n):
            value = None
            received = b""
            for _ in range(self.settings.retries + 1):
                port.send(g.query)
                received = port.read_line(g.query, "gauge reading")
                text = received.decode("ascii", errors="replace")
                text = text[: -len(g.eol)] if text.endswith(g.eol) else text.rstrip("\r\n")
                m = self._pattern.search(text)
                if m is not None:
                    number = (m.group(1) if self._pattern.groups else m.group(0)) or ""
                    number = number.strip()
                    if _finite_decimal(number):
                        value = float(number)
                if value is not None:
                    break
            if value is None:
                raise port.fail(
                    f"unparsable reply to {g.query!r} after {self.settings.retries + 1} attempts "
                    f"(pattern {g.reply_pattern!r}, a finite decimal number); received {received!r}"
                )
            total += value
        return total / n

    # ---- interface -----------------------------------------------------------------
    def move(self, u: np.ndarray) -> Measurement:
        """Execute one move (range-checked first) and read the gauge."""
        u, q = self.command_for(u)
        self._execute(q)
        t = self._read_gauge() - self._offset
        now = time.monotonic() - self._t0
        self._set_state(t, q)
        return Measurement(t_um=t, q_um=q, u=u, time_s=now)

    def read(self) -> float:
        """A gauge reading now (mean of ``samples`` queries), µm."""
        if self._closed:
            raise BackendError("the backend is closed")
        return self._read_gauge() - self._offset

    def close(self) -> None:
        """Close every port (idempotent)."""
        for port in self._ports.values():
            port.close()
        if self._gauge is not None:
            self._gauge.close()
        super().close()
