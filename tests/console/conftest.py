"""One ``hilsim run`` with its console for every test here (a subprocess: the bridge as a user runs it),
and a client of each sonar head (a head pings while a client asks: the console shows the frames the
devices serve): a DDF reader, an Oculus client firing at 5 Hz, an ARIS client at 5 frames/s."""

from __future__ import annotations

import socket
import threading

import pytest

from tests.runtime.bridge_helpers import start_bridge


def _drain(sock: socket.socket, stop: threading.Event) -> None:
    sock.settimeout(0.5)
    while not stop.is_set():
        try:
            if not sock.recv(1 << 16):
                return
        except socket.timeout:
            continue
        except OSError:
            return


@pytest.fixture(scope="package")  # stopped when tests/console ends: its bridge holds the vendor ports
def console_bridge(tmp_path_factory):
    from tests.runtime import abuse_clients as ac

    b = start_bridge(tmp_path_factory.mktemp("console"), "--console", "0", "--status-interval", "0")
    host, port = b.tcp("ddf-stream")
    sock = socket.create_connection((host, port), timeout=10)
    stop = threading.Event()
    reader = threading.Thread(target=_drain, args=(sock, stop), daemon=True)
    reader.start()
    heads = [ac.OculusFirer(b.endpoint("oculus")["address"], rate=3), ac.ArisClient(b.endpoint("aris")["address"])]
    for h in heads:
        h.start()
    yield b
    for h in heads:
        h.stop()
    stop.set()
    reader.join(5)
    sock.close()
    b.stop()


def console_url(bridge) -> str:
    return next(e for e in bridge.endpoints if e["device"] == "console")["url"]
