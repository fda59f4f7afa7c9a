"""The one place where the app reaches into viser's internals (viser 1.1.1), to defend the server
against what browsers and web pages send (``docs/security.md``).

viser has no public hook for any of this, so each function below wraps one internal of
``viser.ViserServer`` at server start, from our code (site-packages are never edited):

- :func:`install_origin_check` wraps the ``process_request`` of the ``websockets`` server that
  viser runs, so that HTTP requests and websocket handshakes with a foreign ``Host`` (DNS
  rebinding) or a foreign ``Origin`` (any other web page) are refused with 403;
- :func:`install_upload_guard` sits in front of viser's two upload message handlers: an upload is
  refused on its announced size before any chunk is kept, its chunks are counted as they arrive
  and it is dropped past the limit or when its browser goes away;
- :func:`install_update_guard` sits in front of viser's GUI update handler: a client may only
  set a control's ``value``, and a value viser cannot even cast ends in a notice to that client
  instead of a traceback in the server log;
- :func:`push_value` sends a control's value to every browser, the sender included;
- :func:`add_slider_key_guard` adds the one piece of page script the app ships: arrow keys on a
  focused slider step the slider and no longer also move the camera.

Each function raises :class:`ViserHookError` when viser's internals are not what it expects (a
viser upgrade), so the app refuses to start rather than run unprotected;
``tests/app/test_security.py`` fails in that case.
"""

from __future__ import annotations

import asyncio
import dataclasses
import http
import ipaddress
import logging
import math
import socket
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any
from urllib.parse import urlsplit

logger = logging.getLogger(__name__)

LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})
"""Host names a browser on this machine (or at the local end of an SSH port-forward) uses."""

MAX_UPLOAD_NAME_CHARS = 255
"""Longest accepted upload file name (characters; the longest file name most systems allow)."""

MAX_UPLOADS_IN_FLIGHT = 2
"""Most uploads buffered at once over all browsers (each at most the upload limit; one per
browser)."""

UPLOAD_IDLE_S = 30.0
"""An upload whose last chunk is older than this (seconds) is dropped to make room."""


class ViserHookError(RuntimeError):
    """viser's internals differ from what :mod:`app.viser_hooks` wraps (a viser upgrade)."""


def _require(obj: Any, name: str) -> Any:
    value = getattr(obj, name, None)
    if value is None:
        raise ViserHookError(
            f"viser {_viser_version()} has no {type(obj).__name__}.{name}: the server's defences "
            "(app/viser_hooks.py, written for viser 1.1.1) cannot be installed; pin viser 1.1.1 "
            "or adapt app/viser_hooks.py"
        )
    return value


def _viser_version() -> str:
    import viser

    return str(getattr(viser, "__version__", "?"))


# ---------------------------------------------------------------------------------- origin


def host_name(host_header: str) -> str:
    """The host name of a ``Host`` header (``localhost:8080`` -> ``localhost``, ``[::1]:80`` ->
    ``::1``), lower case, without a trailing dot."""
    h = host_header.strip().lower()
    if h.startswith("["):
        h = h[1 : h.find("]")] if "]" in h else h[1:]
    elif h.count(":") == 1:
        h = h.split(":")[0]
    return h.rstrip(".")


def allowed_host_names(bind_host: str) -> frozenset[str]:
    """Host names accepted in ``Host`` headers for a server bound to ``bind_host``: the loopback
    names always; for a server bound beyond loopback also the bound address and this machine's
    names and addresses (the URL a browser on the network would use)."""
    names = set(LOOPBACK_NAMES)
    h = host_name(bind_host) if bind_host else "127.0.0.1"
    if not _is_loopback(h):
        if h not in ("0.0.0.0", "::", ""):
            names.add(h)
        for name in {socket.gethostname(), socket.getfqdn()}:
            if name:
                names.add(name.lower().rstrip("."))
                try:
                    names.update(a.lower() for a in socket.gethostbyname_ex(name)[2])
                except OSError:
                    pass
    return frozenset(names)


def _is_loopback(name: str) -> bool:
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


def refusal(headers: Any, allowed_hosts: Iterable[str], websocket: bool) -> str | None:
    """Why a request with these headers is refused, or ``None`` when it is accepted.

    ``Host`` must name one of ``allowed_hosts`` (any port: an SSH forward may use another local
    port). ``Origin``, when present, must be ``http(s)://`` + exactly that ``Host``: the page that
    opens the websocket was served by this server. A browser always sends ``Origin`` on a
    websocket handshake, so one without it comes from a program, not from a web page.
    """
    allowed = frozenset(allowed_hosts)
    host = headers.get("Host")
    if not host:
        return "no Host header"
    if host_name(host) not in allowed:
        return f"Host {host!r} is not this server (DNS rebinding?)"
    origin = headers.get("Origin")
    if origin is None:
        return None
    parts = urlsplit(origin)
    if parts.scheme not in ("http", "https") or parts.netloc.lower() != host.strip().lower():
        what = "websocket" if websocket else "request"
        return f"{what} from Origin {origin!r}, not from this server's page ({host})"
    return None


def websockets_server(server: Any) -> Any:
    """The ``websockets.asyncio.server.Server`` that ``server`` (a running ``ViserServer``)
    listens with. viser keeps it in a local variable of the coroutine that serves, so it is
    found among that coroutine's locals, on the server's own event loop."""
    from websockets.asyncio.server import Server, serve

    ws = _require(server, "_websock_server")
    loop = _require(ws, "_background_event_loop")

    async def find() -> Any:
        for task in asyncio.all_tasks():
            frame = getattr(task.get_coro(), "cr_frame", None)
            for value in frame.f_locals.values() if frame is not None else ():
                if isinstance(value, serve):
                    value = value.server
                if isinstance(value, Server):
                    return value
        return None

    found = asyncio.run_coroutine_threadsafe(find(), loop).result(timeout=10.0)
    if found is None:
        raise ViserHookError(
            f"the websockets server of viser {_viser_version()} was not found: the Origin/Host "
            "check cannot be installed; pin viser 1.1.1 or adapt app/viser_hooks.py"
        )
    return found


def install_origin_check(server: Any, allowed_hosts: Iterable[str]) -> None:
    """Refuse (403) every HTTP request and websocket handshake that :func:`refusal` refuses."""
    from websockets.datastructures import Headers
    from websockets.http11 import Response

    ws_server = websockets_server(server)
    inner = ws_server.process_request
    if getattr(inner, "pregrasp_origin_check", False):
        return
    allowed = frozenset(allowed_hosts)

    def process_request(connection: Any, request: Any) -> Any:
        is_ws = str(request.headers.get("Upgrade", "")).lower() == "websocket"
        why = refusal(request.headers, allowed, websocket=is_ws)
        if why is not None:
            logger.warning("refused %s: %s", request.path, why)
            body = f"403 Forbidden: {why}. Open the URL that `pregrasp view` printed.\n"
            headers = Headers({"Content-Type": "text/plain; charset=utf-8"})
            return Response(http.HTTPStatus.FORBIDDEN, "Forbidden", headers, body.encode())
        return inner(connection, request) if inner is not None else None

    process_request.pregrasp_origin_check = True  # type: ignore[attr-defined]
    ws_server.process_request = process_request


# ---------------------------------------------------------------------------------- uploads


@dataclasses.dataclass
class _Transfer:
    client_id: int
    filename: str
    declared: int
    received: int = 0
    last: float = dataclasses.field(default_factory=time.monotonic)


class UploadGuard:
    """Admits uploads by their announced size and counts their chunks (see
    :func:`install_upload_guard`). ``in_flight`` is the number of uploads being received."""

    def __init__(
        self,
        server: Any,
        max_bytes: Callable[[], int],
        max_in_flight: int = MAX_UPLOADS_IN_FLIGHT,
    ) -> None:
        from viser import _messages

        self.server = server
        self.max_bytes = max_bytes
        self.max_in_flight = int(max_in_flight)
        self._messages = _messages
        gui = server.gui
        self._gui_states: dict[str, Any] = _require(gui, "_current_file_upload_states")
        self._inner_start = _require(gui, "_handle_file_transfer_start")
        self._inner_part = _require(gui, "_handle_file_transfer_part")
        self._transfers: dict[str, _Transfer] = {}
        self._lock = threading.Lock()
        self.refused: list[str] = []
        """The reasons of the refused uploads, oldest first (for the log and the tests)."""

    @property
    def in_flight(self) -> int:
        """Uploads admitted and not finished or dropped."""
        return len(self._transfers)

    def on_start(self, client_id: int, msg: Any) -> None:
        name, size, parts = msg.filename, msg.size_bytes, msg.part_count
        limit = int(self.max_bytes())
        with self._lock:
            why = None
            if not isinstance(msg.transfer_uuid, str) or msg.transfer_uuid in self._transfers:
                why = "the browser sent a malformed upload request"
            elif not isinstance(name, str) or len(name) > MAX_UPLOAD_NAME_CHARS:
                why = f"the file name is longer than {MAX_UPLOAD_NAME_CHARS} characters"
            elif not all(isinstance(v, int) and not isinstance(v, bool) for v in (size, parts)):
                why = "the browser sent a malformed upload request"
            elif size > limit:
                why = (
                    f"{name!r} is {size / 2**20:.1f} MiB; the upload limit is "
                    f"{limit / 2**20:.1f} MiB: subsample the cloud or decimate the mesh, or run "
                    "`pregrasp view FILE` on the machine that has the file"
                )
            elif size < 0 or parts < 0 or parts > size or (parts == 0) != (size == 0):
                why = "the browser sent a malformed upload request"
            elif any(t.client_id == client_id for t in self._transfers.values()):
                why = "this browser's previous upload has not finished: wait for it"
            elif not self._make_room():
                why = "another upload is in progress: try again when it has finished"
            if why is None:
                self._transfers[msg.transfer_uuid] = _Transfer(client_id, name, size)
        if why is not None:
            self._refuse(client_id, msg, why)
            return
        self._inner_start(client_id, msg)
        self._forget_finished(msg.transfer_uuid)

    def on_part(self, client_id: int, msg: Any) -> None:
        with self._lock:
            t = (
                self._transfers.get(msg.transfer_uuid)
                if isinstance(msg.transfer_uuid, str)
                else None
            )
            if t is None or t.client_id != client_id:
                return  # refused or unknown: dropped unread
            content = msg.content
            t.received += len(content) if isinstance(content, bytes | bytearray) else 0
            t.last = time.monotonic()
            over = not isinstance(content, bytes | bytearray) or t.received > t.declared
            if over:
                self._drop(msg.transfer_uuid)
        if over:
            self._refuse(client_id, msg, f"{t.filename!r} sent more bytes than it announced")
            return
        self._inner_part(client_id, msg)
        self._forget_finished(msg.transfer_uuid)

    def drop_client(self, client_id: int) -> None:
        """Drop the uploads of a browser that went away."""
        with self._lock:
            for uuid in [u for u, t in self._transfers.items() if t.client_id == client_id]:
                self._drop(uuid)

    def _forget_finished(self, uuid: str) -> None:
        with self._lock:
            if uuid not in self._gui_states:
                self._transfers.pop(uuid, None)

    def _make_room(self) -> bool:
        if len(self._transfers) < self.max_in_flight:
            return True
        now = time.monotonic()
        for uuid in [u for u, t in self._transfers.items() if now - t.last > UPLOAD_IDLE_S]:
            self._drop(uuid)
        return len(self._transfers) < self.max_in_flight

    def _drop(self, uuid: str) -> None:
        self._transfers.pop(uuid, None)
        self._gui_states.pop(uuid, None)  # frees the chunks viser has kept

    def _refuse(self, client_id: int, msg: Any, why: str) -> None:
        self.refused.append(why)
        logger.warning("upload refused: %s", why)
        client = self.server.get_clients().get(client_id)
        if client is None:
            return
        # tell the browser's upload button that the transfer is over, so it can upload again
        size = msg.size_bytes if isinstance(getattr(msg, "size_bytes", None), int) else 0
        conn = getattr(client, "_websock_connection", None)
        if conn is not None:
            conn.queue_message(
                self._messages.FileTransferPartAck(
                    source_component_uuid=msg.source_component_uuid,
                    transfer_uuid=msg.transfer_uuid,
                    transferred_bytes=size,
                    total_bytes=size,
                )
            )
        client.add_notification("Upload refused", why, auto_close_seconds=10.0, color="red")


def install_upload_guard(server: Any, max_bytes: Callable[[], int]) -> UploadGuard:
    """Put an :class:`UploadGuard` in front of viser's upload handlers of ``server``."""
    from viser import _messages

    guard = UploadGuard(server, max_bytes)
    ws = _require(server, "_websock_server")
    for cls, inner, outer in (
        (_messages.FileTransferStartUpload, guard._inner_start, guard.on_start),
        (_messages.FileTransferPart, guard._inner_part, guard.on_part),
    ):
        handlers = _require(ws, "_incoming_handlers").get(cls, [])
        if inner not in handlers:
            raise ViserHookError(
                f"viser {_viser_version()} does not handle {cls.__name__} where "
                "app/viser_hooks.py expects it: the upload limit cannot be enforced"
            )
        ws.unregister_handler(cls, inner)
        ws.register_handler(cls, outer)
    server.on_client_disconnect(lambda client: guard.drop_client(client.client_id))
    return guard


# ---------------------------------------------------------------------------------- updates


def value_refusal(handle: Any, value: Any) -> str | None:
    """Why ``value`` sent by a browser for control ``handle`` is refused, or ``None``.

    The value must cast to the control's type as viser casts it; a number must be finite and
    within the control's min and max (which are the parameter's bounds, see ``app.gui``); a
    dropdown's value must be one of its options. viser would otherwise store and send on to
    every browser whatever it got: an integer too large for msgpack broke every connection.
    """
    current = handle._impl.value
    if isinstance(current, tuple) or handle._impl.is_button:
        return None
    try:
        v = type(current)(value)  # the cast viser does
    except (TypeError, ValueError, OverflowError) as exc:
        return f"{value!r} is not a {type(current).__name__} ({exc})"
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        lo, hi = getattr(handle, "min", None), getattr(handle, "max", None)
        if not math.isfinite(v):
            return f"{value!r} is not a finite number"
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            return f"{value!r} is outside [{lo:g}, {hi:g}]"
    options = getattr(handle, "options", None)
    if isinstance(options, tuple) and v not in options:
        return f"{str(value)[:80]!r} is not one of the options"
    return None


def install_update_guard(
    server: Any,
    on_bad_value: Callable[[int, Any, str], None],
    on_edit: Callable[[Any], None] | None = None,
) -> Callable[..., Any]:
    """Put a guard in front of viser's GUI update handler: updates of anything but a control's
    ``value`` are dropped, and a value that :func:`value_refusal` refuses calls
    ``on_bad_value(client_id, handle, reason)`` instead of reaching viser (which would fail in
    its event loop or pass the value on to every browser).

    ``on_edit(handle)`` is called for each accepted edit that viser will pass to the control's
    callbacks (a button press, or a value that differs from the one held), before viser stores
    the value: viser runs the callbacks later on its thread pool and they read the control's
    value then, so until they have run the app must not set that control's value itself (it
    would replace the browser's edit before the callback reads it: a lost click)."""
    from viser import _messages

    gui = server.gui
    inner = _require(gui, "_handle_gui_updates")
    handles: dict[str, Any] = _require(gui, "_gui_input_handle_from_uuid")
    ws = _require(server, "_websock_server")
    if inner not in _require(ws, "_incoming_handlers").get(_messages.GuiUpdateMessage, []):
        raise ViserHookError(
            f"viser {_viser_version()} does not handle GuiUpdateMessage where "
            "app/viser_hooks.py expects it: GUI values cannot be checked"
        )

    async def guarded(client_id: int, message: Any) -> None:
        handle = handles.get(message.uuid)
        if handle is None:
            return
        updates = message.updates
        if not isinstance(updates, dict) or set(updates) != {"value"}:
            logger.warning("dropped a GUI update of %r from client %s", updates, client_id)
            return
        why = value_refusal(handle, updates["value"])
        if why is not None:
            on_bad_value(client_id, handle, why)
            return
        if on_edit is not None and _will_fire(handle, updates["value"]):
            on_edit(handle)
        await inner(client_id, message)

    ws.unregister_handler(_messages.GuiUpdateMessage, inner)
    ws.register_handler(_messages.GuiUpdateMessage, guarded)
    return guarded


def _will_fire(handle: Any, value: Any) -> bool:
    """Whether viser runs ``handle``'s callbacks for ``value`` (a button always; an input when
    the value, cast as viser casts it, differs from the one held)."""
    impl = handle._impl
    if impl.is_button:
        return True
    current = impl.value
    try:
        v = tuple(value) if isinstance(current, tuple) else type(current)(value)
    except (TypeError, ValueError, OverflowError):
        return False
    return bool(current != v)


def push_value(handle: Any, value: Any) -> None:
    """Set a control's ``value`` without running its callbacks and send it to every browser,
    the one that sent the last edit included (viser skips the send when the server already holds
    the value, which leaves that browser showing its own edit)."""
    from viser import _messages

    impl = handle._impl
    if impl.is_button:
        return
    impl.value = type(impl.value)(value) if not isinstance(impl.value, tuple) else impl.value
    impl.gui_api._websock_interface.queue_message(
        _messages.GuiUpdateMessage(impl.uuid, {"value": impl.value})
    )


SLIDER_KEY_GUARD_JS = (
    "if(!window.__pregraspSliderKeys){window.__pregraspSliderKeys=1;"
    "document.body.addEventListener('keydown',function(e){var t=e.target;"
    "if(t&&t.getAttribute&&t.getAttribute('role')==='slider'&&e.code&&"
    "e.code.indexOf('Arrow')===0){e.stopPropagation();}});}"
)
"""Stops arrow-key events whose target is a slider handle at ``document.body``, after the slider
(React listens on its root element, inside the body) has stepped and before viser's camera
controls (they listen on ``document`` and skip only ``input``, ``textarea`` and ``select``
targets, and a Mantine slider handle is a ``div`` with ``role="slider"``). Installed once per
page (the flag), whatever the number of times the element is drawn."""


def add_slider_key_guard(gui: Any) -> Any:
    """Add, as a hidden HTML element of the panel, :data:`SLIDER_KEY_GUARD_JS`: viser 1.1.1 has
    no API for page script, and its HTML element is set as ``innerHTML``, where an ``<img>``
    whose source fails to load runs its ``onerror`` handler. The script is a constant of this
    module; no user text ever reaches it (``docs/security.md``)."""
    if '"' in SLIDER_KEY_GUARD_JS:
        raise ViserHookError("the slider key guard must not hold a double quote")
    return gui.add_html(
        f'<img src="data:," alt="" style="display:none" onerror="{SLIDER_KEY_GUARD_JS}">'
    )


__all__ = [
    "LOOPBACK_NAMES",
    "SLIDER_KEY_GUARD_JS",
    "MAX_UPLOADS_IN_FLIGHT",
    "MAX_UPLOAD_NAME_CHARS",
    "UPLOAD_IDLE_S",
    "UploadGuard",
    "ViserHookError",
    "add_slider_key_guard",
    "allowed_host_names",
    "host_name",
    "install_origin_check",
    "install_update_guard",
    "install_upload_guard",
    "push_value",
    "refusal",
    "value_refusal",
]
