"""A subscriber that knows only docs/zenoh.md and docs/terrain.md decodes the map.

Nothing from the project is used on the receiving side: a plain zenoh session, ``struct``,
``zlib.crc32`` and ``json``, following the documented keys and byte layout. The sending side
is the real bus publishing tiles made by the real terrain codec.
"""

from __future__ import annotations

import json
import math
import re
import struct
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
import zenoh

from companion.config import ZenohConfig
from companion.method.terrain.codec import encode_tile
from companion.method.terrain.tile import Tile
from drivers.zenoh_bus import ZenohBus
from tests.processes import free_port

DOCS = Path(__file__).resolve().parents[1] / "docs"


# ---- the independent decoder (docs/terrain.md, "Tile format") -------------------------------


def decode_tile_bytes(data: bytes) -> dict:
    """Decode a tile payload with struct alone. Returns tx, ty, cell, T and row-major layers."""
    magic, version, mask, tx, ty, cell, t, _res, crc = struct.unpack_from("<4sHHiidHHI", data, 0)
    assert magic == b"CTTL" and version == 1
    assert mask & 0b111 == 0b111
    body = data[32:]
    assert zlib.crc32(body) == crc
    n = t * t
    layers = {}
    offset = 0
    for bit, name, fmt in ((1, "height", "f"), (2, "variance", "f"), (4, "count", "I"), (8, "disagreement", "f")):
        if mask & bit:
            layers[name] = struct.unpack_from(f"<{n}{fmt}", body, offset)
            offset += 4 * n
    assert offset == len(body)
    return {"tx": tx, "ty": ty, "cell": cell, "T": t, **layers}


def tile_key_indices(key: str, vehicle: str) -> tuple[int, int]:
    m = re.fullmatch(rf"companion/{vehicle}/terrain/tile/(-?\d+)/(-?\d+)", key)
    assert m, key
    return int(m.group(1)), int(m.group(2))


# ---- helpers ---------------------------------------------------------------------------------


def raw_peer(connect: str) -> zenoh.Session:
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("connect/endpoints", json.dumps([connect]))
    c.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(c)


def sample_tile(tx: int, ty: int, t: int = 32) -> Tile:
    rng = np.random.default_rng(abs(tx * 1000 + ty))
    h = rng.normal(50.0, 10.0, (t, t)).astype(np.float32)
    count = rng.integers(0, 5, (t, t)).astype(np.uint32)
    h[count == 0] = np.nan
    var = np.where(count > 0, rng.uniform(0.01, 2.0, (t, t)), np.inf).astype(np.float32)
    return Tile(tx, ty, h, var, count, cell_size_m=0.5)


def same_layer(decoded: tuple, expected: np.ndarray) -> bool:
    flat = expected.ravel()  # row-major, [i north][j east]
    return all((math.isnan(a) and math.isnan(b)) or a == b for a, b in zip(decoded, flat.tolist()))


# ---- the tests -------------------------------------------------------------------------------


def test_third_party_subscriber_decodes_live_tiles_and_the_whole_map():
    ep = f"tcp/127.0.0.1:{free_port()}"
    cfg = ZenohConfig(mode="peer", listen=(ep,), multicast_scouting=False, vehicle_name="uav7")
    tiles = {(tx, ty): sample_tile(tx, ty) for tx, ty in ((0, 0), (-1, 3), (2, -5))}
    with ZenohBus(cfg) as bus:
        for (tx, ty), tile in tiles.items():
            bus.publish_tile(tx, ty, encode_tile(tile))
        ground = raw_peer(ep)
        try:
            live = []
            sub = ground.declare_subscriber("companion/uav7/terrain/tile/*/*", lambda s: live.append(
                (str(s.key_expr), s.payload.to_bytes(), time.perf_counter())))
            # A late joiner asks for the whole map.
            deadline = time.monotonic() + 5
            got = {}
            while len(got) < len(tiles) and time.monotonic() < deadline:
                for reply in ground.get("companion/uav7/terrain/tile/**", timeout=2.0):
                    if reply.ok is not None:
                        got[str(reply.ok.key_expr)] = reply.ok.payload.to_bytes()
                time.sleep(0.05)
            assert len(got) == len(tiles)
            sizes = set()
            for key, payload in got.items():
                tx, ty = tile_key_indices(key, "uav7")
                d = decode_tile_bytes(payload)
                tile = tiles[(tx, ty)]
                assert (d["tx"], d["ty"], d["T"], d["cell"]) == (tx, ty, 32, 0.5)
                assert same_layer(d["height"], tile.height)
                assert same_layer(d["variance"], tile.variance)
                assert list(d["count"]) == tile.count.ravel().tolist()
                assert "disagreement" not in d  # internal state is not published
                sizes.add(len(payload))
            # A live change decodes too; measure publish -> receive.
            changed = sample_tile(7, 7)
            payload = encode_tile(changed)
            latencies = []
            for _ in range(20):
                live.clear()
                t0 = time.perf_counter()
                bus.publish_tile(7, 7, payload)
                deadline = time.monotonic() + 2
                while not live and time.monotonic() < deadline:
                    time.sleep(0.0002)
                assert live, "live tile not received"
                latencies.append(live[0][2] - t0)
            key, data, _ = live[0]
            assert tile_key_indices(key, "uav7") == (7, 7)
            assert same_layer(decode_tile_bytes(data)["height"], changed.height)
            sub.undeclare()
        finally:
            ground.close()
    latencies.sort()
    print(f"\ntile payload {sorted(sizes)} B (T=32); publish->receive loopback: median "
          f"{latencies[len(latencies) // 2] * 1e3:.2f} ms, max {latencies[-1] * 1e3:.2f} ms over {len(latencies)}")


def test_third_party_subscriber_reads_status_and_avoidance_json():
    ep = f"tcp/127.0.0.1:{free_port()}"
    cfg = ZenohConfig(mode="peer", listen=(ep,), multicast_scouting=False, vehicle_name="uav7")
    with ZenohBus(cfg) as bus:
        ground = raw_peer(ep)
        try:
            seen = {}
            sub = ground.declare_subscriber("companion/uav7/*", lambda s: seen.__setitem__(
                str(s.key_expr), (s.payload.to_bytes(), str(s.encoding))))
            deadline = time.monotonic() + 5
            while len(seen) < 2 and time.monotonic() < deadline:
                bus.publish_status({"state": "mapping", "uptime_s": 12.5})
                bus.publish_avoidance({"engaged": False, "mode": "advisory", "climb_rate_mps": 0.0,
                                       "restriction_alt_m": None, "limiting_cell": None})
                time.sleep(0.05)
            status, status_enc = seen["companion/uav7/status"]
            avoid, avoid_enc = seen["companion/uav7/avoidance"]
            s = json.loads(status.decode("utf-8"))
            a = json.loads(avoid.decode("utf-8"))
            assert s["schema"] == "companion.status/1" and s["vehicle"] == "uav7" and s["state"] == "mapping"
            assert isinstance(s["seq"], int) and isinstance(s["time_unix_s"], float)
            assert a["schema"] == "companion.avoidance/1" and a["engaged"] is False and a["limiting_cell"] is None
            assert status_enc == "application/json;companion.status/1"
            assert avoid_enc == "application/json;companion.avoidance/1"
            sub.undeclare()
        finally:
            ground.close()


def _doc_blocks(name: str, lang: str) -> list[str]:
    text = (DOCS / name).read_text()
    return re.findall(rf"```{lang}\n(.*?)```", text, flags=re.S)


def test_documented_zenoh_config_examples_are_valid():
    blocks = _doc_blocks("zenoh.md", "json5")
    assert len(blocks) >= 2  # TLS and access control
    for block in blocks:
        zenoh.Config.from_json5(block)  # raises on an invalid example


def test_documented_keys_match_the_bus():
    text = (DOCS / "zenoh.md").read_text()
    for key in ("companion/<vehicle>/terrain/tile/<tx>/<ty>", "companion/<vehicle>/status",
                "companion/<vehicle>/avoidance", "companion/<vehicle>/terrain/map",
                "companion/<vehicle>/alive", "companion.status/1", "companion.avoidance/1"):
        assert key in text, key


def test_the_decoder_snippet_in_the_docs_runs():
    """The Python snippet of docs/zenoh.md, executed as printed, decodes a real tile."""
    (snippet,) = _doc_blocks("zenoh.md", "python")
    tile = sample_tile(-4, 9, t=16)
    scope = {"data": encode_tile(tile)}
    exec(snippet, scope)  # noqa: S102 - our own documentation
    assert (scope["tx"], scope["ty"], scope["T"], scope["cell"]) == (-4, 9, 16, 0.5)
    assert same_layer(scope["height"], tile.height)
    assert same_layer(scope["variance"], tile.variance)
    assert list(scope["count"]) == tile.count.ravel().tolist()


@pytest.mark.skipif(not (DOCS / "terrain.md").exists(), reason="docs/terrain.md not written yet")
def test_docs_terrain_md_describes_the_layout_decoded_above():
    text = (DOCS / "terrain.md").read_text()
    for word in ("CTTL", "CRC", "float64", "uint16", "int32", "row-major"):
        assert word in text, word
