"""The app's security guards: what the browser may open, who may connect, what it may upload.

GUIDE ("Security"): the app binds 127.0.0.1 unless told otherwise, viser's share tunnel is off,
file access from the browser is limited to allowed folders and sizes. Concretely:

* :func:`resolve_allowed`: a path typed in the browser is resolved (``~``, symlinks, ``..``)
  and, for a glob, every match is resolved, and each result must lie inside an allowed folder;
  a folder's images are checked one by one (a symlink inside an allowed folder may point out).
* :func:`make_server`: a ``viser.ViserServer`` whose HTTP and websocket handshakes are checked
  by :class:`OriginPolicy`: the ``Host`` header must name this machine as served (a DNS-rebinding
  page names its own domain) and a browser's ``Origin`` must be the page viser itself served
  (another local web page cannot drive the app).
* :func:`refuse_share_tunnel`: a client's ``ShareUrlRequest`` is refused on the server (hiding
  the button is not enough: any client can send the message).
* :func:`install_upload_limit`: uploads larger than the limit are refused from their declared
  size before any part is kept, and a client whose parts exceed what it declared is cut off;
  viser would otherwise hold the whole file in memory before the app could look at it.

viser hooks (viser 1.1.1, pinned ``<1.2`` in pyproject.toml; each is small and tested in
tests/app/test_security.py, because an upgrade may move them):

1. viser builds its websocket server inside ``ViserServer.__init__`` by calling
   ``websockets.asyncio.server.serve(..., process_request=viser_http_server)``; :func:`make_server`
   replaces that module attribute for the duration of the constructor (under a lock) with a
   function that wraps ``process_request`` in :meth:`OriginPolicy.process_request`.
2. ``ViserServer`` answers ``ShareUrlRequest`` by calling ``self.request_share_url``;
   :func:`refuse_share_tunnel` replaces that bound method on the instance.
3. ``GuiApi`` registers ``_handle_file_transfer_start`` / ``_handle_file_transfer_part`` as the
   websocket handlers of ``FileTransferStartUpload`` / ``FileTransferPart`` and keeps transfers
   in ``_current_file_upload_states``; :func:`install_upload_limit` swaps the two handlers for
   checking wrappers that call the originals.
"""

from __future__ import annotations

import contextlib
import glob as globlib
import html
import http
import ipaddress
import logging
import socket
import threading
from collections.abc import Callable
from pathlib import Path
from urllib.parse import urlsplit

log = logging.getLogger(__name__)

GLOB_CHARS = "*?["
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}


# --------------------------------------------------------------------------------------------
# Paths typed in the browser


def _inside(path: Path, roots: list[Path]) -> bool:
    return any(path == r or r in path.parents for r in roots)


def resolve_allowed(path_text: str, allowed: list[Path]) -> Path | str:
    """Check a path typed in the browser against the allowed folders.

    Every file the path can make the app read is resolved (``~``, ``..``, symlinks) and must lie
    inside one of ``allowed`` (themselves resolved): a plain file; each image of a folder; each
    match of a glob pattern (the pattern is expanded here, not only checked up to its first
    wildcard, so ``ALLOWED/*/../../x/*.png`` and symlinks matched by ``?`` are caught).

    Returns:
        The resolved path, or for a glob the pattern itself (absolute), which
        ``registration.io.frames.open_frames`` expands to the files checked here.

    Raises:
        ValueError: naming the path when it is empty or anything it reaches lies outside every
            allowed folder.
        FileNotFoundError: naming the path when nothing exists there (a glob: no match).
    """
    text = path_text.strip()
    if not text:
        raise ValueError("empty path")
    roots = [Path(a).expanduser().resolve() for a in allowed]
    where = ", ".join(str(r) for r in roots) or "none"

    def refuse(target: Path | str) -> ValueError:
        extra = "" if str(target) == text else f" (it reaches {target})"
        return ValueError(f"path {text!r} is outside the allowed folders ({where}){extra}")

    p = Path(text).expanduser()
    if any(ch in text for ch in GLOB_CHARS):
        pattern = str(p if p.is_absolute() else Path.cwd() / p)
        matches = sorted(globlib.glob(pattern))
        if not matches:
            raise FileNotFoundError(f"no such file or folder: {text!r} matches nothing")
        for m in matches:
            real = Path(m).resolve()
            if not _inside(real, roots):
                raise refuse(real)
        return pattern
    try:
        real = p.resolve(strict=True)
    except FileNotFoundError:
        # Refuse first when even the non-existent target lies outside: no probing of what
        # exists outside the allowed folders.
        if not _inside(p.resolve(), roots):
            raise refuse(p.resolve()) from None
        raise FileNotFoundError(f"no such file or folder: {text!r}") from None
    if not _inside(real, roots):
        raise refuse(real)
    if real.is_dir():
        for q in real.iterdir():
            if q.suffix.lower() in IMAGE_SUFFIXES and not _inside(q.resolve(), roots):
                raise refuse(q.resolve())
    return real


# --------------------------------------------------------------------------------------------
# Who may connect


def _split_host_port(value: str, default_port: int | None) -> tuple[str, int | None]:
    """``"host:port"`` / ``"[::1]:port"`` / ``"host"`` -> (lower-case host, port)."""
    value = value.strip().lower()
    if value.startswith("["):
        host, _, rest = value[1:].partition("]")
        port = rest[1:] if rest.startswith(":") else ""
    elif value.count(":") == 1:
        host, _, port = value.partition(":")
    else:
        host, port = value, ""
    try:
        return host, int(port) if port else default_port
    except ValueError:
        return host, -1


def _is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


class OriginPolicy:
    """Which ``Host`` and ``Origin`` headers the app's server accepts.

    * ``Host`` must be a name of this machine as served: the bound address, or for loopback
      binds ``127.0.0.1`` / ``localhost`` / ``::1``, or for ``0.0.0.0`` any IP literal and this
      machine's host names. A DNS-rebinding page sends its own domain and is refused.
    * ``Origin`` (sent by every browser on a websocket handshake) must be ``http(s)://`` plus the
      same host and port as ``Host``: only the page this server delivered can connect. Requests
      without ``Origin`` come from non-browser clients (no web page can omit it) and pass.

    Attributes:
        refused: the reasons of refused handshakes (newest last; tests read them).
    """

    def __init__(self, bind_host: str) -> None:
        self.bind_host = (bind_host or "0.0.0.0").strip("[]").lower()
        self.any_interface = self.bind_host in ("0.0.0.0", "::", "")
        names = {"127.0.0.1", "localhost", "::1"}
        if self.any_interface:
            for name in (socket.gethostname(), socket.getfqdn()):
                if name:
                    names.add(name.lower())
        else:
            names.add(self.bind_host)
        self.names = names
        self.refused: list[str] = []

    def refusal(self, headers) -> str | None:
        """Why a request with these headers is refused, or None when it is accepted."""
        host_header = headers.get("Host")
        if not host_header:
            return "no Host header"
        host, port = _split_host_port(host_header, 80)
        if host not in self.names and not (self.any_interface and _is_ip(host)):
            return f"Host {host_header!r} is not this server"
        origin = headers.get("Origin")
        if origin is None:
            return None
        parts = urlsplit(origin)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            return f"Origin {origin!r} is not a web page of this server"
        default = 443 if parts.scheme == "https" else 80
        try:
            o_port = parts.port or default
        except ValueError:
            return f"Origin {origin!r} has an invalid port"
        if (parts.hostname.lower(), o_port) != (host, port):
            return f"Origin {origin!r} differs from the served address {host_header!r}"
        return None

    def wrap(self, inner: Callable | None) -> Callable:
        """A websockets ``process_request`` that checks first, then calls ``inner``."""

        def process_request(connection, request):
            reason = self.refusal(request.headers)
            if reason is not None:
                self.refused.append(reason)
                del self.refused[:-20]
                log.warning("refused a connection: %s", reason)
                return connection.respond(http.HTTPStatus.FORBIDDEN, f"Forbidden: {reason}\n")
            return inner(connection, request) if inner is not None else None

        return process_request


_SERVE_PATCH_LOCK = threading.Lock()


@contextlib.contextmanager
def _checked_handshakes(policy: OriginPolicy):
    """Hook 1 (module docstring): wrap viser's ``process_request`` while viser starts."""
    import websockets.asyncio.server as ws_server

    original = ws_server.serve

    def serve(*args, **kwargs):
        kwargs["process_request"] = policy.wrap(kwargs.get("process_request"))
        return original(*args, **kwargs)

    with _SERVE_PATCH_LOCK:
        ws_server.serve = serve
        try:
            yield
        finally:
            ws_server.serve = original


def make_server(host: str = "127.0.0.1", port: int = 8080, **kwargs):
    """A ``viser.ViserServer`` whose handshakes :class:`OriginPolicy` checks (and whose share
    tunnel is refused, :func:`refuse_share_tunnel`). ``server.origin_policy`` is the policy."""
    import viser

    policy = OriginPolicy(host)
    with _checked_handshakes(policy):
        server = viser.ViserServer(host=host, port=port, **kwargs)
    server.origin_policy = policy
    refuse_share_tunnel(server)
    return server


def refuse_share_tunnel(server) -> None:
    """Hook 2 (module docstring): a client's ``ShareUrlRequest`` opens no public tunnel.

    ``server.share_requests_refused`` counts the refused requests."""
    server.share_requests_refused = 0

    def request_share_url(verbose: bool = True) -> None:
        server.share_requests_refused += 1
        log.warning("refused a request for viser's public share tunnel")
        return None

    server.request_share_url = request_share_url


# --------------------------------------------------------------------------------------------
# Uploads


def install_upload_limit(
    server, max_bytes: int, on_refused: Callable[[int, str, int], None] | None = None
) -> None:
    """Hook 3 (module docstring): refuse uploads over ``max_bytes`` while they arrive.

    A transfer whose declared size exceeds the limit gets no buffer (its parts are dropped as
    they arrive); a transfer whose parts add up to more than it declared (or the limit) is
    dropped at that part. ``on_refused(client_id, filename, size)`` is told either way. The
    client gets a final acknowledgement so its upload button does not stay locked.
    """
    from viser import _messages

    gui = server.gui
    ws = server._websock_server
    start, part = gui._handle_file_transfer_start, gui._handle_file_transfer_part
    states = gui._current_file_upload_states

    def release_client(message, total: int) -> None:
        ws.queue_message(
            _messages.FileTransferPartAck(
                source_component_uuid=message.source_component_uuid,
                transfer_uuid=message.transfer_uuid,
                transferred_bytes=total,
                total_bytes=total,
            )
        )

    def refuse(client_id: int, name: str, size: int) -> None:
        log.warning("refused upload %r of %d bytes (limit %d)", name, size, max_bytes)
        if on_refused is not None:
            on_refused(client_id, name, size)

    def guarded_start(client_id, message) -> None:
        size = int(message.size_bytes)
        if size > max_bytes or size < 0:
            release_client(message, max(size, 0))
            refuse(client_id, message.filename, size)
            return
        start(client_id, message)

    def guarded_part(client_id, message) -> None:
        state = states.get(message.transfer_uuid)
        if state is None:
            return  # refused or unknown: drop the part now
        budget = min(int(state["total_bytes"]), max_bytes)
        if state["transferred_bytes"] + len(message.content) > budget:
            states.pop(message.transfer_uuid, None)
            release_client(message, int(state["total_bytes"]))
            refuse(client_id, state["filename"], state["transferred_bytes"] + len(message.content))
            return
        part(client_id, message)

    ws.unregister_handler(_messages.FileTransferStartUpload, start)
    ws.unregister_handler(_messages.FileTransferPart, part)
    ws.register_handler(_messages.FileTransferStartUpload, guarded_start)
    ws.register_handler(_messages.FileTransferPart, guarded_part)


# --------------------------------------------------------------------------------------------
# Text shown in the browser


def escape_md(text: object) -> str:
    """``text`` safe inside viser markdown: viser renders raw HTML in markdown unsanitised, so
    names that come from files, paths or errors must not carry tags; table pipes are escaped."""
    return html.escape(str(text), quote=False).replace("|", "\\|")
