"""HTTPS for the dashboard (`hub.dashboard.tls`): the page, its WebSocket, the login and
`/metrics` over TLS with the site CA's hub pair; plain HTTP refused on that port; every file
problem one line at start."""

from __future__ import annotations

import asyncio
import os
import socket
import ssl
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from cryptography.hazmat.primitives import serialization
from prometheus_client.parser import text_string_to_metric_families

from fleetdaq import pki
from fleetdaq.hub.errors import SecretError
from tests.procs import REPO, free_port
from tests.web.conftest import Web

MakeWeb = Callable[..., Web]


@pytest.fixture
def site_pki(tmp_path: Path) -> Path:
    """A site CA and its hub pair for 127.0.0.1, as `fleetdaq pki init --hub-name 127.0.0.1`."""
    folder = tmp_path / "pki"
    pki.init(folder, "webtest", ["127.0.0.1"])
    return folder


def trusting(ca: Path) -> ssl.SSLContext:
    """A client that trusts the site CA only and checks the name (as a browser would)."""
    return ssl.create_default_context(cafile=str(ca))


def test_the_page_login_actions_metrics_and_live_socket_go_over_https(
    make_web: MakeWeb, site_pki: Path
):
    web = make_web(tls=(site_pki / "hub.crt", site_pki / "hub.key"))
    assert web.service.url == f"https://127.0.0.1:{web.port}/"
    client = web.client(tls=trusting(site_pki / "ca.crt"))

    status, page = client.get("/")
    assert status == 200
    assert b"<html" in page.lower()

    status, answer = client.login("alice")
    assert status == 200, answer
    assert "secure" in client.set_cookie.lower(), client.set_cookie  # never sent over plain HTTP
    status, answer = client.post("/api/alarms", {"action": "ack", "names": ["heave_high"]})
    assert (status, answer["ok"]) == (200, True)
    assert web.alarms.requests[-1]["user"] == "alice"

    status, text = client.get("/metrics")
    assert status == 200
    names = {f.name for f in text_string_to_metric_families(text.decode())}
    assert "fleetdaq_build_info" in names, names

    web.feed_batches(2)

    async def live() -> dict[str, Any]:
        async with (
            aiohttp.ClientSession() as s,
            s.ws_connect(
                f"wss://127.0.0.1:{web.port}/api/live", ssl=trusting(site_pki / "ca.crt")
            ) as ws,
        ):
            while True:
                msg = await asyncio.wait_for(ws.receive_json(), 20)
                if msg.get("type") == "state":
                    return msg

    state = asyncio.run(live())
    assert "wec/t8" in state["streams"]


def test_plain_http_and_an_untrusted_ca_get_nothing(make_web: MakeWeb, site_pki: Path):
    web = make_web(tls=(site_pki / "hub.crt", site_pki / "hub.key"))
    with socket.create_connection(("127.0.0.1", web.port), timeout=10) as s:
        s.sendall(b"GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        got = b""
        try:
            while chunk := s.recv(4096):
                got += chunk
        except ConnectionResetError:
            pass
    assert b"fleetdaq_" not in got
    assert not got.startswith(b"HTTP/1.1 200")
    other = pki.init(site_pki.parent / "other", "elsewhere", ["127.0.0.1"])[0].cert
    with pytest.raises(ssl.SSLCertVerificationError):
        web.client(tls=trusting(other)).get("/")


def test_plain_http_on_the_redirect_port_is_sent_on_to_https(make_web: MakeWeb, site_pki: Path):
    """`http_redirect`: what a person types from habit reaches the page; path and query kept,
    the name they typed kept; nothing is served over plain HTTP there."""
    web = make_web(tls=(site_pki / "hub.crt", site_pki / "hub.key"), http_redirect=True)
    rport = web.service.redirect_port
    assert rport is not None
    assert rport != web.port

    async def get(url: str, **kw: Any) -> tuple[int, str, str]:
        async with (
            aiohttp.ClientSession() as s,
            s.get(url, allow_redirects=False, **kw) as r,
        ):
            return r.status, r.headers.get("Location", ""), await r.text()

    status, where, body = asyncio.run(get(f"http://127.0.0.1:{rport}/metrics?x=1"))
    assert (status, where) == (307, f"https://127.0.0.1:{web.port}/metrics?x=1")
    assert "fleetdaq_" not in body
    status, where, _ = asyncio.run(
        get(f"http://127.0.0.1:{rport}/api/alarms", headers={"Host": "hub.example:80"})
    )
    assert (status, where) == (307, f"https://hub.example:{web.port}/api/alarms")

    async def follow() -> tuple[int, str]:
        async with (
            aiohttp.ClientSession() as s,
            s.get(f"http://127.0.0.1:{rport}/", ssl=trusting(site_pki / "ca.crt")) as r,
        ):
            return r.status, str(r.url)

    assert asyncio.run(follow()) == (200, f"https://127.0.0.1:{web.port}/")
    # HTTP/1.0 with no Host header: this hub's own address.
    with socket.create_connection(("127.0.0.1", rport), timeout=10) as s:
        s.sendall(b"GET /x HTTP/1.0\r\n\r\n")
        got = b""
        while chunk := s.recv(4096):
            got += chunk
    assert got.startswith(b"HTTP/1.0 307") or got.startswith(b"HTTP/1.1 307"), got[:200]
    assert b"Location: https://" in got, got[:400]
    assert web.service.stats.redirects == 4


@pytest.mark.parametrize(
    ("extra", "why"),
    [
        (
            'http_redirect: "127.0.0.1:8080"',
            "http_redirect sends plain HTTP on to HTTPS: it needs tls",
        ),
        (
            'http_redirect: "0.0.0.0:8443"\n    tls: {cert_file: c, key_file: k}',
            "http_redirect and listen share port 8443",
        ),
    ],
)
def test_a_redirect_without_tls_or_on_the_same_port_is_one_line(
    tmp_path: Path, extra: str, why: str
) -> None:
    site = tmp_path / "site.yaml"
    site.write_text(
        "site: t\nhub:\n  dashboard:\n    enabled: true\n    listen: 0.0.0.0:8443\n"
        f"    {extra}\nnodes: {{}}\n"
    )
    r = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "check", str(site)],
        capture_output=True, text=True, cwd=REPO, check=False,
    )  # fmt: skip
    assert r.returncode == 2, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert "hub.dashboard" in lines[0]
    assert why in lines[0]


def _encrypted_copy(key: Path, out: Path) -> Path:
    k = serialization.load_pem_private_key(key.read_bytes(), None)
    out.write_bytes(
        k.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.BestAvailableEncryption(b"secret"),
        )
    )
    out.chmod(0o600)
    return out


def test_every_file_problem_is_one_line_naming_the_file(
    make_web: MakeWeb, site_pki: Path, tmp_path: Path
):
    cert, key = site_pki / "hub.crt", site_pki / "hub.key"
    other = pki.init(tmp_path / "other", "elsewhere", ["127.0.0.1"])[1]
    loose = tmp_path / "loose.key"
    loose.write_bytes(key.read_bytes())
    loose.chmod(0o644)
    no_cert, no_key = tmp_path / "none.crt", tmp_path / "none.key"
    cases = [
        ((no_cert, key), f"hub.dashboard.tls.cert_file {no_cert}: no such file"),
        ((cert, no_key), f"hub.dashboard.tls.key_file {no_key}: no such file"),
        ((cert, loose), f"chmod 600 {loose}"),
        ((cert, other.key), "cannot serve"),
        ((cert, _encrypted_copy(key, tmp_path / "enc.key")), "the key is encrypted"),
        ((key, key), "cannot serve"),
    ]  # fmt: skip
    for files, expected in cases:
        with pytest.raises(SecretError) as err:
            make_web(tls=files)
        text = str(err.value)
        assert expected in text, (files, text)
        assert "\n" not in text


def test_the_hub_refuses_to_start_on_a_world_readable_key_with_exit_2(
    site_pki: Path, tmp_path: Path
):
    key = site_pki / "hub.key"
    os.chmod(key, 0o644)
    site = tmp_path / "site.yaml"
    site.write_text(
        f"""\
site: webtls
hub:
  listen: [tcp/127.0.0.1:{free_port()}]
  dashboard:
    enabled: true
    listen: "127.0.0.1:0"
    tls: {{cert_file: {site_pki / "hub.crt"}, key_file: {key}}}
nodes:
  wec:
    streams:
      t8: {{driver: wave_sim, rate_hz: 100, channels: [{{name: heave, unit: m}}]}}
"""
    )
    r = subprocess.run(
        [sys.executable, "-m", "fleetdaq", "hub", "--config", str(site), "--data",
         str(tmp_path / "data")],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert r.returncode == 2, r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith(f"{site}: hub.dashboard.tls.key_file {key}: group or others"), last
    assert last.endswith(f"chmod 600 {key}"), last
