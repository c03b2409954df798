"""Serial hardware backend: PI GCS 2 subset for the PZT drivers, a line protocol for the gauge.

Contract: ``shared/spec/serial-protocol.md`` (see ``docs/serial-protocol.md``). Ports are
opened with pyserial's ``serial_for_url`` in the constructor, so a config may name a real
port (``/dev/ttyUSB0``), a TCP bridge (``socket://host:port``) or ``loop://``.

Start-up, per controller: ``*IDN?`` (one line must come back), ``SVO a 1 ...`` for its axes,
``ERR?`` must be 0. A move: range check of q = K u (nothing sent on failure), ``MOV a v ...``
to each controller holding a moved axis, poll ``ONT?`` until every axis reports 1 (timeout
``on_target_timeout_s``), ``ERR?`` must be 0 on each, then read the gauge (mean of
``samples`` queries). A reply that does not parse is re-queried up to ``retries`` times;
no reply within the port's timeout is an error at once. Every error names the device
(controller name and URL), the axes concerned and quotes the bytes received.
"""

from __future__ import annotations

import re
import time

import numpy as np

from microctl.backends.base import Measurement, StageBackend
from microctl.config import StageConfig
from microctl.errors import BackendError, ConfigError

#: Meanings of the GCS error codes this dialect uses.
GCS_ERRORS = {
    1: "parameter syntax error",
    2: "unknown command",
    7: "position out of limits",
    10: "controller not ready (servo off)",
}

_MAX_REPLY_LINES = 64


class _Port:
    """One serial device: a name for messages, the pyserial port and the line ending."""

    def __init__(self, label: str, url: str, baudrate: int, timeout_s: float, eol: bytes):
        import serial  # pyserial

        self.label = label
        self.url = url
        self.eol = eol
        self.timeout_s = timeout_s
        try:
            self.port = serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s, write_timeout=timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise BackendError(f"{label} ({url}): cannot open: {exc}") from None

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
        """One reply line including its LF; error if none arrives within the timeout."""
        import serial

        try:
            line = self.port.read_until(b"\n")
        except (serial.SerialException, OSError) as exc:
            raise self.fail(
                f"connection lost waiting for the reply to {command!r} ({what}); received {received!r}: {exc}"
            ) from None
        if not line.endswith(b"\n"):
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


class SerialStage(StageBackend):
    """The stage driven through serial devices (``backend.kind: serial``).

    Parameters
    ----------
    config : StageConfig
        Must have ``backend.serial``.
    zero_gauge : bool, optional
        If true, move to the zero state at start and subtract that gauge reading from every
        reading (for a gauge that is not tared at the zero state). Default: the config's
        ``backend.serial.gauge.zero_at_start`` (false: the gauge is read as it is, as the
        emulator serves it).
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
        try:
            for c in ser.controllers:
                self._ports[c.name] = _Port(f"controller '{c.name}'", c.url, c.baudrate, c.timeout_s, b"\n")
            g = ser.gauge
            self._gauge = _Port("gauge", g.url, g.baudrate, g.timeout_s, g.eol.encode("ascii"))
            for c in ser.controllers:
                axes = self._controller_axes(c.name)
                port = self._ports[c.name]
                port.send("*IDN?")
                port.read_line("*IDN?", "identification")
                if axes:
                    port.send("SVO " + " ".join(f"{a} 1" for a in axes))
                    self._check_error(c.name, axes, "switching the servo on")
            if zero_gauge:
                self._execute(np.zeros(config.stage.n_act))
                self._offset = self._read_gauge()
        except BaseException:
            self.close()
            raise
        self._t0 = time.monotonic()

    # ---- helpers -------------------------------------------------------------------
    def _controller_axes(self, controller: str) -> list[str]:
        return [m.axis for m in self._axes if m.controller == controller]

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

    def _on_target(self, controller: str, axes: list[str]) -> bool:
        """One ``ONT?`` poll: whether every axis is on target (retries an unparsable reply)."""
        command = "ONT? " + " ".join(axes)
        port = self._ports[controller]
        received = []
        for _ in range(self.settings.retries + 1):
            lines = self._query_gcs(controller, command, axes, "on-target")
            values = self._parse_axis_values(lines, axes)
            if values is not None and all(v in ("0", "1") for v in values.values()):
                return all(v == "1" for v in values.values())
            received.append("\n".join(lines))
        raise port.fail(
            f"unparsable reply to {command!r} (axes {', '.join(axes)}) after {self.settings.retries + 1} "
            f"attempts; expected '<axis>=0|1' lines, received {received[-1]!r}"
        )

    def _check_error(self, controller: str, axes: list[str], context: str) -> None:
        """``ERR?`` must be 0; 7 names the axes out of limits."""
        port = self._ports[controller]
        code = None
        last = ""
        for _ in range(self.settings.retries + 1):
            lines = self._query_gcs(controller, "ERR?", axes, "error code")
            last = "\n".join(lines)
            if len(lines) == 1 and re.fullmatch(r"-?\d+", lines[0]):
                code = int(lines[0])
                break
        if code is None:
            raise port.fail(
                f"unparsable reply to 'ERR?' (axes {', '.join(axes)}) after {self.settings.retries + 1} attempts; "
                f"expected an integer, received {last!r}"
            )
        if code != 0:
            meaning = GCS_ERRORS.get(code, "unknown error")
            raise port.fail(f"error {code} ({meaning}) after {context} on axes {', '.join(axes)}; received {last!r}")

    def _execute(self, q: np.ndarray) -> None:
        """MOV, wait for on-target, check errors (q already range-checked)."""
        by_ctrl: dict[str, list[tuple[str, float]]] = {}
        for m, v in zip(self._axes, q):
            by_ctrl.setdefault(m.controller, []).append((m.axis, float(v)))
        for ctrl, pairs in by_ctrl.items():
            self._ports[ctrl].send("MOV " + " ".join(f"{a} {v:.6f}" for a, v in pairs))
        deadline = time.monotonic() + self.settings.on_target_timeout_s
        pending = dict(by_ctrl)
        while pending:
            for ctrl in list(pending):
                if self._on_target(ctrl, [a for a, _ in pending[ctrl]]):
                    del pending[ctrl]
            if not pending:
                break
            if time.monotonic() > deadline:
                ctrl = next(iter(pending))
                port = self._ports[ctrl]
                axes = ", ".join(a for a, _ in pending[ctrl])
                raise port.fail(
                    f"axes {axes} not on target within {self.settings.on_target_timeout_s:g} s"
                )
            time.sleep(self.settings.poll_interval_s)
        for ctrl, pairs in by_ctrl.items():
            desc = ", ".join(f"{a} -> {v:.4f} µm" for a, v in pairs)
            self._check_error(ctrl, [a for a, _ in pairs], f"MOV {desc}")

    def _read_gauge(self) -> float:
        g = self.settings.gauge
        port = self._gauge
        if port is None:
            raise BackendError("the gauge port is not open")
        total = 0.0
        for _ in range(g.samples):
            value = None
            received = b""
            for _ in range(self.settings.retries + 1):
                port.send(g.query)
                received = port.read_line(g.query, "gauge reading")
                text = received.decode("ascii", errors="replace")
                text = text[: -len(g.eol)] if text.endswith(g.eol) else text.rstrip("\r\n")
                m = self._pattern.search(text)
                if m is not None:
                    try:
                        value = float(m.group(1) if self._pattern.groups else m.group(0))
                    except ValueError:
                        value = None
                if value is not None:
                    break
            if value is None:
                raise port.fail(
                    f"unparsable reply to {g.query!r} after {self.settings.retries + 1} attempts "
                    f"(pattern {g.reply_pattern!r}); received {received!r}"
                )
            total += value
        return total / g.samples

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
