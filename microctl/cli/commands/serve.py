"""``microctl serve``: the controller as a long-running process speaking JSON lines on stdin/stdout.

One request per line, one response per line, in order (protocol: docs/cli.md, "serve"); with
``--tcp PORT`` the same protocol on a loopback TCP socket, one client at a time. A bad
request gets an error object, never a crash; a line longer than ``--max-request-bytes`` is
refused without being parsed (and the rest of it skipped). A thin layer over :mod:`microctl.api`.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any, BinaryIO, Callable, TextIO

from microctl.cli.commands._common import add_quiet, int_at_least

#: Default bound of one request line, bytes (a request is a few hundred bytes).
MAX_REQUEST_BYTES = 65536

#: Request fields each operation accepts (besides ``op`` and ``id``).
OPS: dict[str, frozenset[str]] = {
    "solve": frozenset({"target_um", "state", "baseline"}),
    "move": frozenset({"target_um"}),
    "state": frozenset(),
    "reload": frozenset({"model"}),
}


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``serve`` sub-command."""
    p = subparsers.add_parser(
        "serve",
        help="the controller as a long-running process: JSON lines on stdin/stdout (solve, move, state, reload)",
        description="Read one JSON request per line on stdin, answer one JSON line on stdout, until end of input. "
        'Requests: {"op": "solve", "target_um": T, "state": [..] (default: the stage\'s), "baseline": false}, '
        '{"op": "move", "target_um": T}, {"op": "state"}, {"op": "reload", "model": PATH (default: the same '
        'file)}; an optional "id" is echoed. Responses: {"id", "ok": true, "op", "result"} or {"id", "ok": false, '
        '"error": {"code", "message"}}. The stage is the configured backend, connected at start.',
    )
    p.add_argument("--config", required=True, metavar="STAGE.yaml", help="stage config (its backend is driven)")
    p.add_argument("--model", required=True, metavar="MODEL.npz", help="residual model from `microctl train`")
    p.add_argument("--log", default=None, metavar="LOG.csv",
                   help="measurement log executed moves are appended to; without it, move requests are refused")
    p.add_argument("--r-e", default=None, metavar="R", help="noise summary r_e of eq. 4 (default: as `solve`)")
    p.add_argument("--kappa", type=float, default=None, help="standard normal quantile of noise_quantile")
    p.add_argument("--tcp", type=int_at_least(0, "a port number in [0, 65535]", 65535), default=None, metavar="PORT",
                   help="serve on 127.0.0.1:PORT instead of stdin/stdout, one client at a time, until Ctrl-C "
                        "(0: a free port, printed on stderr)")
    p.add_argument("--max-request-bytes", type=int_at_least(64, "at least 64"), default=MAX_REQUEST_BYTES,
                   metavar="N", help=f"longest request line accepted (default {MAX_REQUEST_BYTES})")
    add_quiet(p)
    p.set_defaults(func=_run)


class RequestError(Exception):
    """A request that cannot be served: ``code`` and a one-line message for the error object."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


def _number(req: dict, key: str) -> float:
    v = req.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise RequestError("bad_request", f"'{key}' must be a number (µm), got {json.dumps(v)[:80]}")
    try:
        v = float(v)
    except OverflowError:
        v = math.inf
    if not math.isfinite(v):
        raise RequestError("bad_request", f"'{key}' must be finite")
    return v


class Service:
    """The request handler: one parsed request in, one response object out (never raises but KeyboardInterrupt).

    Parameters
    ----------
    controller : microctl.api.Controller
    operator : microctl.api.Operator
        Holds the backend (its state is the default state) and the log, if any.
    can_move : bool
        Whether move requests are served (a log was given).
    """

    def __init__(self, controller: Any, operator: Any, can_move: bool):
        self.controller = controller
        self.operator = operator
        self.can_move = can_move

    def handle_line(self, line: bytes) -> dict:
        """Parse and serve one request line (without its line break)."""
        try:
            try:
                text = line.decode("utf-8")
            except UnicodeDecodeError:
                raise RequestError("bad_encoding", "the request is not UTF-8") from None
            try:
                req = json.loads(text)
            except (ValueError, RecursionError) as exc:
                raise RequestError("bad_json", f"not JSON: {str(exc)[:120]}") from None
            return self.handle(req)
        except RequestError as exc:
            return _error(None, exc.code, str(exc))

    def handle(self, req: Any) -> dict:
        """Serve one parsed request."""
        rid = None
        try:
            if not isinstance(req, dict):
                raise RequestError("bad_request", 'a request is a JSON object such as {"op": "state"}')
            rid = _echo_id(req.get("id"))
            op = req.get("op")
            if not isinstance(op, str) or op not in OPS:
                raise RequestError("bad_request", f"'op' must be one of {', '.join(OPS)}, got {json.dumps(op)[:80]}")
            unknown = sorted(set(req) - OPS[op] - {"op", "id"})
            if unknown:
                raise RequestError("bad_request", f"unknown field(s) for {op}: {', '.join(map(str, unknown))[:200]}")
            result = getattr(self, f"_{op}")(req)
            return {"id": rid, "ok": True, "op": op, "result": result}
        except RequestError as exc:
            return _error(rid, exc.code, str(exc))
        except KeyboardInterrupt:
            raise
        except Exception as exc:  # noqa: BLE001 - an error object per request, never a crash
            return _error(rid, _code_of(exc), _one_line(exc))

    def _solve(self, req: dict) -> dict:
        target = _number(req, "target_um")
        state = req.get("state")
        if state is None:
            state = self.operator.state
        elif not isinstance(state, (list, dict)):
            raise RequestError("bad_request", "'state' must be a list of numbers or an object name -> number")
        baseline = req.get("baseline", False)
        if not isinstance(baseline, bool):
            raise RequestError("bad_request", "'baseline' must be true or false")
        res = self.controller.solve(target, state, baseline=baseline)
        return self.controller.to_dict(res)

    def _move(self, req: dict) -> dict:
        if not self.can_move:
            raise RequestError("no_log", "serve was started without --log: moves are refused (every executed move "
                               "must be logged)")
        return self.operator.move(_number(req, "target_um")).to_dict(self.controller.stage)

    def _state(self, req: dict) -> dict:
        stage = self.controller.stage
        s = self.operator.state
        lo, hi = self.controller.reachable_interval(s)
        return {"state": dict(zip(stage.state_names, map(float, s))), "reachable_um": [lo, hi],
                "moves": self.operator.moves, "model": self.controller.model_source, "n_train": self.controller.n_train,
                "log": None if self.operator.log_path is None else str(self.operator.log_path)}

    def _reload(self, req: dict) -> dict:
        model = req.get("model")
        if model is not None and (not isinstance(model, str) or not model or len(model) > 4096 or "\0" in model):
            raise RequestError("bad_request", "'model' must be a model file path")
        self.controller.reload(model)
        return {"model": self.controller.model_source, "n_train": self.controller.n_train}


def _echo_id(value: Any) -> Any:
    """The request's ``id`` if it is a short JSON scalar (echoed), else None."""
    if value is None or isinstance(value, bool):
        return value
    if isinstance(value, int) and abs(value) < 2**53:
        return value
    if isinstance(value, float) and math.isfinite(value):
        return value
    if isinstance(value, str) and len(value) <= 256:
        return value
    return None


def _code_of(exc: BaseException) -> str:
    from microctl.errors import BackendError, ConfigError, DataError, SolveError, UnreachableTargetError

    for cls, code in ((UnreachableTargetError, "unreachable"), (ConfigError, "input"), (DataError, "input"),
                      (BackendError, "backend"), (SolveError, "solve"), (OSError, "os")):
        if isinstance(exc, cls):
            return code
    return "internal"


def _one_line(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    return text.replace("\r", "\\r").replace("\n", "\\n")[:1000]


def _error(rid: Any, code: str, message: str) -> dict:
    return {"id": rid, "ok": False, "error": {"code": code, "message": message}}


def serve_lines(service: Service, inp: BinaryIO, out: TextIO, max_bytes: int,
                on_error: Callable[[dict], None] | None = None) -> int:
    """Answer every request line of ``inp`` on ``out`` until end of input; the number of requests.

    A line over ``max_bytes`` is answered with a ``too_large`` error and skipped to its end
    without being kept in memory.
    """
    from microctl.util.io import to_jsonable

    n = 0
    while True:
        line = inp.readline(max_bytes + 1)
        if not line:
            return n
        if len(line) > max_bytes and not line.endswith(b"\n"):
            while line and not line.endswith(b"\n"):  # skip the rest of the line
                line = inp.readline(max_bytes + 1)
            resp = _error(None, "too_large", f"request longer than {max_bytes} bytes; refused unread")
        else:
            body = line.rstrip(b"\r\n")
            if not body.strip():
                continue
            resp = service.handle_line(body)
        n += 1
        out.write(json.dumps(to_jsonable(resp), allow_nan=False) + "\n")
        out.flush()
        if on_error is not None and not resp["ok"]:
            on_error(resp)


def _run(args: argparse.Namespace) -> int:
    from microctl import api
    from microctl.cli.commands.move import controller_settings

    stage = api.load_stage(args.config)
    ctl = api.Controller(stage, args.model, controller_settings(args))
    with api.Operator(ctl, stage.open_backend(), log=args.log) as op:
        if not args.quiet:
            for note in op.backend.notes:
                print(f"serve: {note}", file=sys.stderr)
            print(f"serve: ready (stage '{stage.name}', {stage.config.backend.kind} backend, model {args.model}, "
                  f"{'moves logged to ' + args.log if args.log else 'moves refused: no --log'})", file=sys.stderr)
        service = Service(ctl, op, args.log is not None)
        if args.tcp is not None:
            return serve_tcp(service, args.tcp, args.max_request_bytes, args.quiet)
        n = serve_lines(service, sys.stdin.buffer, sys.stdout, args.max_request_bytes)
        if not args.quiet:
            print(f"serve: end of input after {n} request(s), {op.moves} move(s)", file=sys.stderr)
    return 0


def serve_tcp(service: Service, port: int, max_bytes: int, quiet: bool = False) -> int:
    """Serve JSON lines on 127.0.0.1:``port`` (loopback only), one client at a time, until Ctrl-C.

    Each connection is answered as stdin is (:func:`serve_lines`) until the client closes it;
    then the next client is accepted. A client that drops mid-request costs only its connection.
    The ``listening on`` line on stderr names the port (also with ``--quiet``: a client needs it).
    """
    import socket

    from microctl.errors import ConfigError

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as srv:
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            srv.bind(("127.0.0.1", port))
        except OSError as exc:
            raise ConfigError(f"--tcp {port}: cannot listen on 127.0.0.1:{port} ({exc.strerror}); "
                              "choose a free port, or 0 for any") from None
        srv.listen(1)
        print(f"serve: listening on 127.0.0.1:{srv.getsockname()[1]}", file=sys.stderr, flush=True)
        while True:
            conn, peer = srv.accept()
            with conn, conn.makefile("rb") as inp, conn.makefile("w", encoding="ascii", newline="\n") as out:
                try:
                    n = serve_lines(service, inp, out, max_bytes)
                except OSError as exc:  # the client went away mid-answer
                    n = None
                    if not quiet:
                        print(f"serve: client {peer[0]}:{peer[1]} dropped ({exc.strerror or exc})", file=sys.stderr)
            if not quiet and n is not None:
                print(f"serve: client {peer[0]}:{peer[1]} closed after {n} request(s)", file=sys.stderr, flush=True)
