"""The TLS examples of docs/zenoh.md, run as written (certificates made here with openssl)."""

from __future__ import annotations

import re
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from companion.config import ZenohConfig
from companion.method.terrain.codec import encode_tile
from companion.method.terrain.tile import Tile
from drivers.ground_station import GroundStation
from drivers.zenoh_bus import ZenohBus
from tests.processes import free_port

DOC = Path(__file__).resolve().parents[1] / "docs" / "zenoh.md"
DOC_DIR = "/etc/companion/tls/"

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")


def make_certificates(d: Path) -> None:
    """A CA, and a server certificate for 127.0.0.1 signed by it."""
    def run(*args):
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True, timeout=30)

    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    run("req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.pem", "-days", "2", "-subj", "/CN=companion-test-ca")
    run("req", *ec, "-keyout", "server.key", "-out", "server.csr", "-subj", "/CN=localhost")
    (d / "ext.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
                               "extendedKeyUsage=serverAuth\n")
    run("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
        "-out", "server.pem", "-days", "2", "-extfile", "ext.cnf")


def documented_block(needle: str, cert_dir: Path) -> str:
    blocks = re.findall(r"```json5\n(.*?)```", DOC.read_text(), flags=re.S)
    block = next(b for b in blocks if needle in b)
    assert DOC_DIR in block
    return block.replace(DOC_DIR, f"{cert_dir}/")


def cfg(**kw) -> ZenohConfig:
    return ZenohConfig(**{"mode": "peer", "multicast_scouting": False, "vehicle_name": "v1",
                          "reconnect_min_s": 0.2, "reconnect_max_s": 0.5, **kw})


def test_documented_tls_setup_carries_the_map_and_shuts_out_strangers(tmp_path):
    certs = tmp_path / "tls"
    certs.mkdir()
    make_certificates(certs)
    vehicle_file = tmp_path / "zenoh-tls.json5"
    vehicle_file.write_text(documented_block("listen_certificate", certs))
    ground_file = tmp_path / "ground-tls.json5"
    ground_file.write_text(documented_block("root_ca_certificate", certs))
    ep = f"tls/127.0.0.1:{free_port()}"
    with ZenohBus(cfg(listen=(ep,), config_file=str(vehicle_file))) as bus:
        tile = Tile(0, 0, np.full((4, 4), 3.0, np.float32), np.ones((4, 4), np.float32), np.ones((4, 4), np.uint32))
        bus.publish_tile(0, 0, encode_tile(tile))
        # A ground station with the CA gets the map over TLS ...
        with GroundStation(cfg(connect=(ep,), config_file=str(ground_file))) as station:
            deadline = time.monotonic() + 5
            links = []
            while time.monotonic() < deadline:
                links = station.links()
                if links:
                    break
                time.sleep(0.05)
            assert links and all(dst.startswith("tls/") for dst in links), links
            station.sync()
            assert list(station.map.tiles) == [(0, 0)] and station.map.tiles[(0, 0)].same_as(tile)
        # ... one without it never completes the handshake.
        with GroundStation(cfg(connect=(ep,))) as stranger:
            time.sleep(1.0)
            assert stranger.links() == []
            stranger.query_timeout_s = 0.5
            stranger.sync()
            assert not stranger.map.tiles
