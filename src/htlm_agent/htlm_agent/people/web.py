"""The person's page and its small API, without ROS (docs/usage.md, A person in the team): a Starlette app served by
uvicorn in a thread of the agent's process.

The API is apart from the page: the page (page.html, static) renders what `GET /api/state` returns and sends what
the person does to `POST /api/report`; every request carries the page's token (`Authorization: Bearer TOKEN`, the
page takes it from its address, `/?token=TOKEN`) and is refused without it (401, nothing shown, nothing taken).
The node and the web thread meet only in `Bridge`: the node puts the latest view there (`show`) and takes the
person's reports out (`take`), answering each (`answer`); the web thread never touches the agent's state.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import hmac
import json
import secrets
import threading
import time
from importlib import resources
from pathlib import Path
from typing import Any

TOKEN_BYTES = 16
"""Random bytes of a page's token (32 hex digits)."""

BODY_LIMIT = 4096
"""Largest report body the API reads, bytes."""

ANSWER_TIMEOUT = 5.0
"""Seconds the API waits for the agent to answer a report before it says so."""


def new_token() -> str:
    """A fresh page token."""
    return secrets.token_hex(TOKEN_BYTES)


def read_token(path: str | Path) -> str:
    """The token kept in `path` (one line), checked: at least 16 characters of [0-9a-zA-Z_-]."""
    text = Path(path).read_text(encoding="utf-8").strip()
    if len(text) < 16 or not all(c.isalnum() or c in "-_" for c in text):
        raise ValueError(f"{path}: not a page token (at least 16 letters, digits, - or _)")
    return text


def page(name: str) -> str:
    """The HTML of a page shipped with the package (person.html, commander.html)."""
    return resources.files("htlm_agent.people").joinpath(name).read_text(encoding="utf-8")


class Bridge:
    """Where the node and the web thread meet: the latest view, and the reports waiting for the node."""

    def __init__(self) -> None:
        """Nothing shown, nothing waiting."""
        self._lock = threading.Lock()
        self._view: dict[str, Any] = {"state": "waiting", "message": "waiting for the agent"}
        self._text = json.dumps(self._view)
        self._version = 0
        self._waiting: list[tuple[Any, concurrent.futures.Future[tuple[bool, str]]]] = []

    def show(self, view: dict[str, Any]) -> None:
        """The node's latest view (a new version when it changed)."""
        text = json.dumps({k: v for k, v in view.items() if k != "now"}, sort_keys=True)
        with self._lock:
            if text != self._text:
                self._text = text
                self._version += 1
            self._view = {**view, "version": self._version}

    def state(self) -> dict[str, Any]:
        """The latest view, with its version."""
        with self._lock:
            return self._view

    def submit(self, body: Any) -> concurrent.futures.Future[tuple[bool, str]]:
        """A report of the person for the node; the future gets (taken, message)."""
        fut: concurrent.futures.Future[tuple[bool, str]] = concurrent.futures.Future()
        with self._lock:
            if len(self._waiting) >= 16:
                fut.set_result((False, "too many reports at once: try again"))
            else:
                self._waiting.append((body, fut))
        return fut

    def take(self) -> list[tuple[Any, concurrent.futures.Future[tuple[bool, str]]]]:
        """The reports waiting (the node answers each with `fut.set_result`)."""
        with self._lock:
            out, self._waiting = self._waiting, []
        return out


def authorized(request: Any, token: str) -> bool:
    """Whether a request carries `token` (header `Authorization: Bearer TOKEN`, or `?token=TOKEN` for the page)."""
    got = request.headers.get("authorization", "")
    given = got[7:] if got.lower().startswith("bearer ") else request.query_params.get("token", "")
    return bool(given) and hmac.compare_digest(given.encode(), token.encode())


def make_app(bridge: Bridge, token: str, html: str, reports: bool = True) -> Any:
    """The Starlette app of one page: `/` (the page), `/api/state`, and with `reports` `/api/report`."""
    from starlette.applications import Starlette
    from starlette.requests import Request
    from starlette.responses import HTMLResponse, JSONResponse, PlainTextResponse, Response
    from starlette.routing import Route

    denied = "no access: this page needs its own token (printed by htlm launch, kept in the run directory)"

    async def index(request: Request) -> Response:
        if not authorized(request, token):
            return PlainTextResponse(denied, status_code=401)
        return HTMLResponse(html, headers={"Cache-Control": "no-store", "Referrer-Policy": "no-referrer"})

    async def state(request: Request) -> Response:
        if not authorized(request, token):
            return JSONResponse({"error": denied}, status_code=401)
        return JSONResponse(bridge.state(), headers={"Cache-Control": "no-store"})

    async def report(request: Request) -> Response:
        if not authorized(request, token):
            return JSONResponse({"ok": False, "message": denied}, status_code=401)
        raw = await request.body()
        if len(raw) > BODY_LIMIT:
            return JSONResponse({"ok": False, "message": f"report of {len(raw)} bytes > {BODY_LIMIT}"}, 413)
        try:
            body = json.loads(raw)
        except ValueError as e:
            return JSONResponse({"ok": False, "message": f"a report is JSON: {e}"}, status_code=400)
        fut = bridge.submit(body)
        try:
            ok, message = await asyncio.wait_for(asyncio.wrap_future(fut), ANSWER_TIMEOUT)
        except TimeoutError:
            return JSONResponse({"ok": False, "message": "the agent did not answer in time"}, status_code=503)
        return JSONResponse({"ok": ok, "message": message}, status_code=200 if ok else 400)

    routes = [Route("/", index), Route("/api/state", state)]
    if reports:
        routes.append(Route("/api/report", report, methods=["POST"]))
    return Starlette(routes=routes)


class PageServer:
    """An app served by uvicorn in a daemon thread (started by `start`, stopped by `stop`)."""

    def __init__(self, app: Any, host: str, port: int) -> None:
        """Serve `app` on `host`:`port` (port 0: any free port; `port` tells which once started)."""
        import uvicorn

        self.config = uvicorn.Config(app, host=host, port=port, log_level="warning", access_log=False, lifespan="off")
        self.server = uvicorn.Server(self.config)
        self.host = host
        self.port = port
        self.thread = threading.Thread(target=self.server.run, name="page-server", daemon=True)

    def start(self, timeout: float = 10.0) -> None:
        """Start serving; returns once the socket listens (raises RuntimeError when it did not within `timeout`:
        the port is taken, the address is not this host's)."""
        self.thread.start()
        end = time.monotonic() + timeout
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > end:
                raise RuntimeError(f"the page server could not listen on {self.host}:{self.port}")
            time.sleep(0.02)
        sockets = [s for srv in getattr(self.server, "servers", []) for s in srv.sockets]
        if sockets:
            self.port = int(sockets[0].getsockname()[1])

    def stop(self) -> None:
        """Stop serving (at most 5 s)."""
        self.server.should_exit = True
        self.thread.join(5.0)


class PageError(ValueError):
    """A page cannot be served: its token file, or its address and port (the node exits naming them)."""


def serve(bridge: Bridge, token_file: str, html: str, host: str, port: int, reports: bool = True) -> PageServer:
    """Serve one page (`make_app`) with the token kept in `token_file` on `host`:`port`, started.

    Raises:
        PageError: the token file cannot be read or holds no token, or the server cannot listen there.
    """
    try:
        server = PageServer(make_app(bridge, read_token(token_file), html, reports), host, port)
        server.start()
    except (OSError, ValueError, RuntimeError) as e:
        raise PageError(f"page_token_file {token_file!r}, page {host}:{port}: {e}") from None
    return server
