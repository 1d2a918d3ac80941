"""Who may talk to the panel: host check, token, and no cross-site commands.

- Bound to a loopback address (the default), only Host headers naming the loopback are accepted, which
  stops DNS-rebinding pages from reaching the panel through the operator's browser.
- Bound to any other address, every request needs the token printed at start: as `?token=` (the printed
  URL; the page then keeps it in a same-site cookie), an `X-Hilcal-Token` header, or that cookie.
- Every command (POST) needs the `X-Hilcal-Panel` header, which a form or an image on another site cannot
  send and a cross-site script cannot send without a CORS preflight that this server never grants; an
  `Origin` header, if present, must name this server.
"""

from __future__ import annotations

import ipaddress
import secrets
from http.cookies import SimpleCookie
from urllib.parse import parse_qs, urlsplit

from starlette.datastructures import Headers
from starlette.responses import PlainTextResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

COOKIE = "hilcal_panel_token"
COMMAND_HEADER = "x-hilcal-panel"
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1", "[::1]")


def is_loopback(host: str) -> bool:
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def new_token() -> str:
    return secrets.token_urlsafe(24)


def _hostname(host_header: str) -> str:
    if host_header.startswith("["):
        return host_header[: host_header.find("]") + 1]
    return host_header.rsplit(":", 1)[0] if host_header.count(":") == 1 else host_header


class Guard:
    """ASGI middleware enforcing the rules in this module's docstring (streams pass through untouched)."""

    def __init__(self, app: ASGIApp, token: str | None, loopback_only: bool) -> None:
        self.app = app
        self.token = token
        self.loopback_only = loopback_only

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        host = headers.get("host", "")
        if self.loopback_only and not is_loopback(_hostname(host)):
            await PlainTextResponse("unknown host: the panel answers on the loopback address", 421)(
                scope, receive, send)
            return
        from_query = parse_qs(scope.get("query_string", b"").decode()).get("token", [None])[0]
        if self.token is not None:
            cookie = SimpleCookie(headers.get("cookie", "")).get(COOKIE)
            offered = from_query or headers.get("x-hilcal-token") or (cookie.value if cookie else None)
            if offered is None or not secrets.compare_digest(offered.encode(), self.token.encode()):
                await PlainTextResponse("token required: open the URL printed when the panel started", 401)(
                    scope, receive, send)
                return
        if scope["method"] not in ("GET", "HEAD"):
            origin = headers.get("origin")
            if headers.get(COMMAND_HEADER) != "1" or (origin and urlsplit(origin).netloc != host):
                await PlainTextResponse("commands are accepted from the panel page only", 403)(scope, receive, send)
                return
        if self.token is not None and from_query:
            send = _with_cookie(send, self.token)
        await self.app(scope, receive, send)


def _with_cookie(send: Send, token: str) -> Send:
    async def wrapped(message: Message) -> None:
        if message["type"] == "http.response.start":
            cookie = f"{COOKIE}={token}; Path=/; HttpOnly; SameSite=Strict"
            message = {**message, "headers": [*message.get("headers", []), (b"set-cookie", cookie.encode())]}
        await send(message)

    return wrapped
