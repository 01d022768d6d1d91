"""In-process tests of the app's security guards (app/gui/security.py), one per finding of issue 12.

The viser hooks are exercised through the real wire: a websockets client speaking viser's
protocol (msgpack messages), raw HTTP requests with chosen headers, a real ``ViserServer``.
"""

from __future__ import annotations

import http.client
import os
import time
from pathlib import Path

import numpy as np
import pytest

viser = pytest.importorskip("viser")
msgspec = pytest.importorskip("msgspec")
ws_client = pytest.importorskip("websockets.sync.client")

from app.gui import security  # noqa: E402
from app.gui.security import OriginPolicy, escape_md, resolve_allowed  # noqa: E402

SUBPROTOCOL = f"viser-v{viser.__version__}"


# ---------------------------------------------------------------- paths


@pytest.fixture
def tree(tmp_path):
    """allowed/{a.png, sub/b.png, link?.png -> ../secret/s.png, dir_with_link/}; secret/s.png."""
    allowed, secret = tmp_path / "allowed", tmp_path / "secret"
    (allowed / "sub").mkdir(parents=True)
    secret.mkdir()
    for p in (allowed / "a.png", allowed / "sub" / "b.png", secret / "s.png"):
        p.write_bytes(b"x")
    os.symlink(secret / "s.png", allowed / "link1.png")
    (allowed / "dir_with_link").mkdir()
    (allowed / "dir_with_link" / "ok.png").write_bytes(b"x")
    os.symlink(secret / "s.png", allowed / "dir_with_link" / "z.png")
    return allowed, secret


def test_plain_paths_inside_pass_and_outside_refused(tree):
    allowed, secret = tree
    assert resolve_allowed(str(allowed / "a.png"), [allowed]) == (allowed / "a.png").resolve()
    assert resolve_allowed(str(allowed / "sub"), [allowed]) == (allowed / "sub").resolve()
    with pytest.raises(ValueError, match="outside the allowed folders"):
        resolve_allowed(str(secret / "s.png"), [allowed])
    with pytest.raises(ValueError, match="outside the allowed folders"):
        resolve_allowed(str(allowed / ".." / "secret" / "s.png"), [allowed])
    with pytest.raises(ValueError, match="outside the allowed folders"):
        resolve_allowed(str(allowed / "link1.png"), [allowed])  # symlink out
    with pytest.raises(FileNotFoundError, match="no such file"):
        resolve_allowed(str(allowed / "missing.png"), [allowed])
    # A missing file outside is refused as outside (no probing of what exists there).
    with pytest.raises(ValueError, match="outside"):
        resolve_allowed(str(secret / "missing.png"), [allowed])
    with pytest.raises(ValueError, match="empty path"):
        resolve_allowed("  ", [allowed])


def test_glob_is_expanded_and_every_match_checked(tree):
    allowed, secret = tree
    # The fixed part of this pattern lies inside, but its matches do not.
    with pytest.raises(ValueError, match="outside the allowed folders"):
        resolve_allowed(str(allowed / "*" / ".." / ".." / "secret" / "*.png"), [allowed])
    # A symlink matched by a wildcard.
    with pytest.raises(ValueError, match="outside the allowed folders"):
        resolve_allowed(str(allowed / "link?.png"), [allowed])
    assert resolve_allowed(str(allowed / "sub" / "*.png"), [allowed]) == str(
        allowed / "sub" / "*.png"
    )
    with pytest.raises(FileNotFoundError, match="matches nothing"):
        resolve_allowed(str(allowed / "nothing*.png"), [allowed])


def test_folder_with_a_symlinked_image_out_is_refused(tree):
    allowed, _ = tree
    with pytest.raises(ValueError, match="outside the allowed folders"):
        resolve_allowed(str(allowed / "dir_with_link"), [allowed])


def test_current_folder_is_not_implicitly_allowed(tree, monkeypatch):
    allowed, secret = tree
    monkeypatch.chdir(secret)
    with pytest.raises(ValueError, match="outside"):
        resolve_allowed("s.png", [allowed])
    with pytest.raises(ValueError, match="outside"):
        resolve_allowed("*.png", [allowed])


def test_escape_md_defuses_html_and_pipes():
    assert escape_md("<img src=x onerror=alert(1)>|a") == "&lt;img src=x onerror=alert(1)&gt;\\|a"


# ---------------------------------------------------------------- connections


@pytest.mark.parametrize(
    ("bind", "headers", "ok"),
    [
        ("127.0.0.1", {"Host": "127.0.0.1:8080"}, True),
        ("127.0.0.1", {"Host": "localhost:8080", "Origin": "http://localhost:8080"}, True),
        ("127.0.0.1", {"Host": "127.0.0.1:8080", "Origin": "http://127.0.0.1:8080"}, True),
        ("127.0.0.1", {"Host": "127.0.0.1:8080", "Origin": "http://127.0.0.1:9999"}, False),
        ("127.0.0.1", {"Host": "127.0.0.1:8080", "Origin": "http://localhost:8080"}, False),
        ("127.0.0.1", {"Host": "127.0.0.1:8080", "Origin": "null"}, False),
        ("127.0.0.1", {"Host": "evil.example:8080", "Origin": "http://evil.example:8080"}, False),
        ("127.0.0.1", {}, False),
        # Bound to loopback, an IP-literal Host of another machine is not this server (a
        # rebinding page served from 10.0.0.9 must get 403 too).
        ("127.0.0.1", {"Host": "10.0.0.9:8080"}, False),
        ("127.0.0.1", {"Host": "10.0.0.9:8080", "Origin": "http://10.0.0.9:8080"}, False),
        ("127.0.0.1", {"Host": "[::2]:8080"}, False),
        ("0.0.0.0", {"Host": "192.168.1.5:8080", "Origin": "http://192.168.1.5:8080"}, True),
        ("0.0.0.0", {"Host": "192.168.1.5:8080", "Origin": "http://10.0.0.9:8080"}, False),
        ("0.0.0.0", {"Host": "rebind.example:8080", "Origin": "http://rebind.example:8080"}, False),
        ("::1", {"Host": "[::1]:8080", "Origin": "http://[::1]:8080"}, True),
    ],
)
def test_origin_policy(bind, headers, ok):
    assert (OriginPolicy(bind).refusal(headers) is None) == ok


@pytest.fixture
def guarded():
    server = security.make_server("127.0.0.1", 0, verbose=False)
    yield server
    server.stop()


def _connect(port: int, origin: str | None):
    return ws_client.connect(
        f"ws://127.0.0.1:{port}", origin=origin, subprotocols=[SUBPROTOCOL], open_timeout=10
    )


def test_websocket_refuses_other_origins(guarded):
    port = guarded.get_port()
    for origin in ("http://127.0.0.1:1", "http://evil.example", f"http://localhost:{port}"):
        with pytest.raises(Exception, match="403"):
            _connect(port, origin)
    assert "differs from the served address" in guarded.origin_policy.refused[-1]
    # The page the server itself delivered, and non-browser clients, connect.
    _connect(port, f"http://127.0.0.1:{port}").close()
    _connect(port, None).close()


def test_http_refuses_a_rebound_host(guarded):
    port = guarded.get_port()
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.request("GET", "/", headers={"Host": f"rebind.example:{port}"})
    assert conn.getresponse().status == 403
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.request("GET", "/")
    assert conn.getresponse().status == 200


class Client:
    """A viser client on the wire: msgpack messages out, frames in (not decoded)."""

    def __init__(self, port: int) -> None:
        self.ws = _connect(port, f"http://127.0.0.1:{port}")
        self.send(
            type="ViewerCameraMessage",
            wxyz=[1, 0, 0, 0],
            position=[0, 0, -1.0],
            fov=1.0,
            near=0.01,
            far=1000.0,
            image_height=600,
            image_width=800,
            look_at=[0, 0, 0],
            up_direction=[0, -1, 0],
        )

    def send(self, **msg) -> None:
        self.ws.send(msgspec.msgpack.encode(msg))

    def close(self) -> None:
        self.ws.close()


def wait_for(cond, timeout=10.0):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if cond():
            return True
        time.sleep(0.02)
    return False


def test_share_tunnel_request_is_refused(guarded, monkeypatch):
    import viser._viser as viser_module

    opened = []
    monkeypatch.setattr(viser_module, "ViserTunnel", lambda *a, **k: opened.append(a))
    client = Client(guarded.get_port())
    try:
        client.send(type="ShareUrlRequest")
        assert wait_for(lambda: guarded.share_requests_refused == 1)
    finally:
        client.close()
    assert opened == []


def _upload(client: Client, button, name: str, data: bytes, declared: int | None = None):
    part = 64 * 1024
    parts = [data[i : i + part] for i in range(0, len(data), part)]
    client.send(
        type="FileTransferStartUpload",
        source_component_uuid=button._impl.uuid,
        transfer_uuid=f"t-{name}",
        filename=name,
        mime_type="application/octet-stream",
        part_count=len(parts),
        size_bytes=len(data) if declared is None else declared,
    )
    for i, content in enumerate(parts):
        client.send(
            type="FileTransferPart",
            source_component_uuid=button._impl.uuid,
            transfer_uuid=f"t-{name}",
            part_index=i,
            content=content,
        )


def test_upload_limit_enforced_while_receiving(guarded):
    refused, received = [], []
    button = guarded.gui.add_upload_button("Upload")
    button.on_upload(lambda ev: received.append(ev.target.value.name))
    security.install_upload_limit(guarded, 100_000, lambda cid, name, size: refused.append(name))
    states = guarded.gui._current_file_upload_states
    client = Client(guarded.get_port())
    try:
        # Over the limit by its declared size: no buffer is ever made for it.
        _upload(client, button, "big.bin", b"\0" * 300_000)
        assert wait_for(lambda: refused == ["big.bin"])
        assert "t-big.bin" not in states
        # Declares a small size but sends more: cut off at the part that overruns.
        _upload(client, button, "liar.bin", b"\0" * 200_000, declared=1000)
        assert wait_for(lambda: refused == ["big.bin", "liar.bin"])
        assert "t-liar.bin" not in states
        # Within the limit: received whole.
        _upload(client, button, "ok.bin", np.arange(50_000, dtype=np.uint8).tobytes())
        assert wait_for(lambda: received == ["ok.bin"])
    finally:
        client.close()
    assert button.value.content == np.arange(50_000, dtype=np.uint8).tobytes()


def test_bound_address_names_the_wildcard():
    from app.gui.launch import bound_address

    assert bound_address("127.0.0.1", 8080) == "serving http://127.0.0.1:8080"
    text = bound_address("0.0.0.0", 8080)
    assert "0.0.0.0:8080" in text and "all interfaces" in text


def test_uploads_are_pruned_when_no_input_refers_to_them(tmp_path):
    from app.gui.project import Project

    project = Project(tmp_path / "proj")
    old = project.write_file("uploads/frames-old.mp4", b"x")
    kept = project.write_file("uploads/base-new.png", b"y")
    removed = project.prune_uploads([str(kept), "/elsewhere/frames"])
    assert removed == [old] and kept.exists() and not old.exists()
    assert Path(project.uploads_dir).is_dir()
