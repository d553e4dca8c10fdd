"""Connection strings as MAVProxy, mavlink-router and MAVSDK users write them; STATUSTEXT chunking."""

import pytest

from drivers.autopilot.connection import Endpoint, parse_connection
from drivers.autopilot.protocol import statustext_chunks


@pytest.mark.parametrize(
    "text, expected",
    [
        ("udpin:0.0.0.0:14550", Endpoint("udpin", "0.0.0.0", 14550)),
        ("udp:127.0.0.1:14550", Endpoint("udpin", "127.0.0.1", 14550)),  # MAVProxy: udp = listen
        ("udpout:192.168.1.10:14550", Endpoint("udpout", "192.168.1.10", 14550)),
        ("tcp:127.0.0.1:5760", Endpoint("tcp", "127.0.0.1", 5760)),
        ("tcpin:0.0.0.0:5760", Endpoint("tcpin", "0.0.0.0", 5760)),
        ("udp://:14540", Endpoint("udpin", "0.0.0.0", 14540)),  # MAVSDK
        ("udpin://0.0.0.0:14540", Endpoint("udpin", "0.0.0.0", 14540)),
        ("tcpout://localhost:5760", Endpoint("tcp", "localhost", 5760)),
        ("tcp://[::1]:5760", Endpoint("tcp", "::1", 5760)),
        ("udpin:127.0.0.1:0", Endpoint("udpin", "127.0.0.1", 0)),  # ephemeral port when listening
        ("/dev/ttyAMA0", Endpoint("serial", device="/dev/ttyAMA0", baud=921600)),
        ("/dev/ttyAMA0,57600", Endpoint("serial", device="/dev/ttyAMA0", baud=57600)),  # MAVProxy
        ("/dev/ttyACM0:115200", Endpoint("serial", device="/dev/ttyACM0", baud=115200)),  # MAVROS
        ("serial:///dev/ttyUSB0:57600", Endpoint("serial", device="/dev/ttyUSB0", baud=57600)),  # MAVSDK
        ("serial:/dev/serial/by-id/usb-CubePilot_CubeOrange-if00", Endpoint("serial", device="/dev/serial/by-id/usb-CubePilot_CubeOrange-if00", baud=921600)),
        ("  tcp:10.0.0.1:5762 ", Endpoint("tcp", "10.0.0.1", 5762)),
    ],
)
def test_connection_strings(text, expected):
    assert parse_connection(text, baud=921600) == expected


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("", "empty"),
        ("com3", "not understood"),
        ("udpin:14550", "HOST:PORT"),
        ("tcp:127.0.0.1", "HOST:PORT"),
        ("tcp:127.0.0.1:0", "port 0"),
        ("udpout:127.0.0.1:70000", "out of range"),
        ("udpout://:14550", "host"),
        ("http://x:80", "not understood"),
        ("/dev/ttyS0,fast", "device path"),
    ],
)
def test_bad_connection_strings_say_what_is_expected(text, fragment):
    with pytest.raises(ValueError, match=fragment) as e:
        parse_connection(text)
    assert repr(text) in str(e.value) or text == ""


def test_endpoint_prints_back_as_a_connection_string():
    for text in ("udpin:0.0.0.0:14550", "tcp:127.0.0.1:5760", "/dev/ttyAMA0,57600", "tcp:[::1]:5760"):
        assert parse_connection(str(parse_connection(text))) == parse_connection(text)


def test_statustext_chunks():
    assert statustext_chunks("terrain ahead") == [b"terrain ahead"]
    assert statustext_chunks("x" * 50) == [b"x" * 50]
    assert statustext_chunks("x" * 120) == [b"x" * 50, b"x" * 50, b"x" * 20]
    assert statustext_chunks("y" * 100) == [b"y" * 50, b"y" * 50, b""]  # a full last chunk needs a terminator
    text = "é" * 60  # 120 bytes of 2-byte characters: never split inside one
    chunks = statustext_chunks(text)
    assert all(len(c) <= 50 for c in chunks)
    assert b"".join(chunks).decode("utf-8") == text
    for c in chunks:
        c.decode("utf-8")
    long = statustext_chunks("z" * 1000)
    assert len(long) == 5 and long[-1].endswith(b"...")
