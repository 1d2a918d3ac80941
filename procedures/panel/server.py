"""The panel's web server: uvicorn in a background thread, so the engine keeps the main thread (and Ctrl-C).

The socket is bound here, before the thread starts, so a busy port is a clear error at once. Loopback
binds need no token; any other address gets a fresh token, which is part of the printed URL.
"""

from __future__ import annotations

import socket
import threading
import time

import uvicorn

from procedures.panel.app import PanelContext, build_app
from procedures.panel.security import is_loopback, new_token

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765


class PanelStartError(RuntimeError):
    """The panel could not listen (port in use, bad address)."""


class PanelServer:
    """Serves one `PanelContext`; `start()` returns once it accepts connections, `stop()` ends it."""

    def __init__(self, ctx: PanelContext, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT) -> None:
        self.ctx = ctx
        self.host = host
        self.token = None if is_loopback(host) else new_token()
        family = socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET
        try:
            self._socket = socket.create_server((host.strip("[]"), port), family=family)
        except (OSError, OverflowError) as e:
            raise PanelStartError(f"the panel cannot listen on {host}:{port}: {e}") from None
        self.port = self._socket.getsockname()[1]
        app = build_app(ctx, token=self.token, loopback_only=self.token is None)
        config = uvicorn.Config(app, log_level="warning", access_log=False, lifespan="off", ws="none",
                                timeout_graceful_shutdown=2)
        self._server = uvicorn.Server(config)
        self._thread = threading.Thread(target=self._server.run, kwargs={"sockets": [self._socket]},
                                        name="panel-http", daemon=True)

    @property
    def url(self) -> str:
        name = f"[{self.host.strip('[]')}]" if ":" in self.host.strip("[]") else self.host
        return f"http://{name}:{self.port}/" + (f"?token={self.token}" if self.token else "")

    def start(self, timeout_s: float = 10.0) -> PanelServer:
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                self.stop()
                raise PanelStartError(f"the panel did not start on {self.host}:{self.port}")
            time.sleep(0.02)
        return self

    def stop(self) -> None:
        """End every live stream, then the server (bounded: a few seconds at most)."""
        self.ctx.live.close()
        self._server.should_exit = True
        if self._thread.is_alive():
            self._thread.join(5.0)
        self._socket.close()

    def __enter__(self) -> PanelServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
