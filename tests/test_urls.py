"""Link URLs (companion/link/urls.py): every form its docstring accepts, as MAVSDK, pymavlink/
MAVProxy and MAVROS users write them, parses to the expected LinkAddress; the refused forms
raise EndpointError naming the accepted ones; and a listening link opened from a pymavlink-
style URL really receives (and answers) a datagram on 127.0.0.1."""
from __future__ import annotations

import os
import select
import time

import pytest

os.environ.setdefault("MAVLINK20", "1")

from companion.link.endpoints import MavEndpoint, UdpLink, open_link  # noqa: E402
from companion.link.msgdef import swarmdrop as md  # noqa: E402
from companion.link.urls import DEFAULT_BAUD, FORMS, EndpointError, LinkAddress, parse_url  # noqa: E402
from companion.link.wire import Codec  # noqa: E402
from sim_bridge.sitl.testing import free_udp_base_port  # noqa: E402

ALL = "0.0.0.0"


def udpin(host: str, port: int, rhost: str = "", rport: int = 0) -> LinkAddress:
    return LinkAddress("udpin", host=host, port=port, remote_host=rhost, remote_port=rport)


def serial(device: str, baud: int = DEFAULT_BAUD) -> LinkAddress:
    return LinkAddress("serial", device=device, baud=baud)


ACCEPTED = {
    # MAVSDK
    "udpin://127.0.0.1:14540": udpin("127.0.0.1", 14540),
    "udpin://:14540": udpin(ALL, 14540),
    "udpin://0.0.0.0:14540": udpin(ALL, 14540),
    "udp://:14540": udpin(ALL, 14540),
    "udp://0.0.0.0:14540": udpin(ALL, 14540),
    "udpout://10.0.0.2:14540": LinkAddress("udpout", host="10.0.0.2", port=14540),
    "udpout://localhost:14540": LinkAddress("udpout", host="localhost", port=14540),
    "tcp://10.0.0.2:5760": LinkAddress("tcp", host="10.0.0.2", port=5760),
    "tcpout://10.0.0.2:5760": LinkAddress("tcp", host="10.0.0.2", port=5760),
    "serial:///dev/ttyAMA0:921600": serial("/dev/ttyAMA0", 921600),
    "serial:///dev/ttyAMA0": serial("/dev/ttyAMA0"),
    "serial:///dev/ttyUSB0,115200": serial("/dev/ttyUSB0", 115200),
    # MAVROS
    "udp://:14540@127.0.0.1:14557": udpin(ALL, 14540, "127.0.0.1", 14557),
    "udp://127.0.0.1:14540@10.0.0.2:14557": udpin("127.0.0.1", 14540, "10.0.0.2", 14557),
    "udp://:14540@": udpin(ALL, 14540),
    "/dev/ttyAMA0:921600": serial("/dev/ttyAMA0", 921600),
    "/dev/ttyACM0:57600": serial("/dev/ttyACM0", 57600),
    "/dev/ttyAMA0": serial("/dev/ttyAMA0"),
    "/dev/serial/by-id/usb-ArduPilot_fmuv3-if00:115200": serial("/dev/serial/by-id/usb-ArduPilot_fmuv3-if00", 115200),
    # pymavlink / MAVProxy
    "udpin:127.0.0.1:14550": udpin("127.0.0.1", 14550),
    "udpin:0.0.0.0:14550": udpin(ALL, 14550),
    "udpin::14550": udpin(ALL, 14550),
    "udp:127.0.0.1:14550": udpin("127.0.0.1", 14550),
    "udpout:10.0.0.2:14550": LinkAddress("udpout", host="10.0.0.2", port=14550),
    "tcp:10.0.0.2:5760": LinkAddress("tcp", host="10.0.0.2", port=5760),
    "/dev/ttyACM0,115200": serial("/dev/ttyACM0", 115200),
    "/dev/ttyACM0,": serial("/dev/ttyACM0"),
    # spelling: case of the scheme, surrounding blanks, a colon inside a device name
    "UDPIN://:14540": udpin(ALL, 14540),
    "  udpin://127.0.0.1:14540\n": udpin("127.0.0.1", 14540),
    "/dev/odd:name": serial("/dev/odd:name"),
    "udpin://127.0.0.1:1": udpin("127.0.0.1", 1),
    "udpin://127.0.0.1:65535": udpin("127.0.0.1", 65535),
}


@pytest.mark.parametrize("url", list(ACCEPTED))
def test_accepted_forms_parse(url):
    assert parse_url(url) == ACCEPTED[url]


def test_default_baud_is_57600():
    assert DEFAULT_BAUD == 57600 and parse_url("/dev/ttyS0").baud == 57600


@pytest.mark.parametrize("address, text", [
    (udpin("127.0.0.1", 14540), "udpin://127.0.0.1:14540"),
    (udpin(ALL, 14540, "127.0.0.1", 14557), "udp://0.0.0.0:14540@127.0.0.1:14557"),
    (LinkAddress("udpout", host="10.0.0.2", port=14540), "udpout://10.0.0.2:14540"),
    (serial("/dev/ttyAMA0"), "serial:///dev/ttyAMA0:57600"),
])
def test_a_parsed_address_prints_as_an_accepted_url_of_itself(address, text):
    assert str(address) == text and parse_url(text) == address


REFUSED = {
    # MAVSDK 1 listened on udp://HOST:PORT, MAVSDK 2 sends to it: ambiguous
    "udp://10.0.0.1:14540": "write udpin://10.0.0.1:14540 to listen or udpout://10.0.0.1:14540 to send",
    # TCP servers
    "tcp://:5760": "swarmdrop connects to a TCP server",
    "tcp://0.0.0.0:5760": "swarmdrop connects to a TCP server",
    "tcpin:0.0.0.0:5760": "does not serve TCP itself",
    "tcpin://:5760": "does not serve TCP itself",
    "tcp-l:5760": "does not serve TCP itself",
    # broadcast, flow control
    "udpbcast:192.168.1.255:14550": "UDP broadcast is not supported",
    "udp-b://:14550": "UDP broadcast is not supported",
    "udp-pb://:14550": "UDP broadcast is not supported",
    "serial_flowcontrol:///dev/ttyACM0:57600": "hardware flow control is not supported",
    "serial-hwfc:///dev/ttyACM0:57600": "hardware flow control is not supported",
    # destinations need a host
    "udpout://:14540": "a destination needs a host",
    "udpout://0.0.0.0:14540": "a destination needs a host",
    "udpout:0.0.0.0:14540": "a destination needs a host",
    "tcp::5760": "a destination needs a host",
    "udp://:14540@:14557": "a destination needs a host",
    # ports
    "udpin://127.0.0.1:0": "PORT in 1..65535",
    "udpin://127.0.0.1:65536": "PORT in 1..65535",
    "udpin://127.0.0.1:+1": "PORT in 1..65535",
    "udpin://127.0.0.1": "PORT in 1..65535",
    "udpin://": "PORT in 1..65535",
    "udpin://:14540/": "PORT in 1..65535",
    "udpin://:\u0661\u0664\u0665\u0664\u0660": "PORT in 1..65535",  # Arabic-Indic digits: int() would take them
    "udpin://:" + "9" * 5000: "PORT in 1..65535",  # int() would raise ValueError, not EndpointError
    "udp:14550": "PORT in 1..65535",
    # IPv6 (the sockets are IPv4)
    "udpin://[::1]:14540": "IPv6 is not supported",
    "udp://[::]:14540": "IPv6 is not supported",
    "udpout://::1:14540": "IPv6 is not supported",
    # serial
    "serial:///dev/ttyAMA0:12345": "baud rate '12345' is not one of",
    "/dev/ttyAMA0,fast": "baud rate 'fast' is not one of",
    "/dev/ttyAMA0:" + "1" * 5000: "is not one of",
    "serial://dev/ttyAMA0:57600": "a serial device is a path such as /dev/ttyAMA0",
    "serial://:57600": "a serial device is a path",
    "/:57600": "a serial device is a path",
    # not a link
    "": "not a link URL",
    "14540": "not a link URL",
    "localhost:14540": "not a link URL",
    "serial:/dev/ttyAMA0:921600": "not a link URL",
    "bogus://x:1": "unknown scheme 'bogus'",
    "http://example.com:80": "unknown scheme 'http'",
}


@pytest.mark.parametrize("url", list(REFUSED))
def test_refused_forms_say_why_and_name_the_accepted_forms(url):
    with pytest.raises(EndpointError) as e:
        parse_url(url)
    msg = str(e.value)
    assert REFUSED[url] in msg, msg
    assert f"accepted forms: {FORMS}" in msg and "docs/companion.md" in msg, msg
    for form in ("udpin://HOST:PORT", "udpout://HOST:PORT", "tcp://HOST:PORT", "serial:///dev/NAME[:BAUD]",
                 "udpin:HOST:PORT"):
        assert form in msg


def test_endpoint_error_is_a_value_error_and_open_link_raises_it_too():
    assert issubclass(EndpointError, ValueError)
    with pytest.raises(EndpointError, match="not a link URL"):
        open_link("localhost:14540")


def test_the_docs_list_every_accepted_form():
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[1] / "docs" / "companion.md").read_text()
    section = doc.split("## Link URLs", 1)[1].split("\n## ", 1)[0]
    for form in ("udpin://HOST:PORT", "udpin://:PORT", "udp://:PORT", "udp://[HOST]:PORT@RHOST:RPORT",
                 "udpout://HOST:PORT", "tcp://HOST:PORT", "tcpout://HOST:PORT", "udpin:HOST:PORT", "udp:HOST:PORT",
                 "udpout:HOST:PORT", "tcp:HOST:PORT", "serial:///dev/NAME[:BAUD]", "/dev/NAME[:BAUD]",
                 "/dev/NAME[,BAUD]"):
        assert f"`{form}`" in section, form


# ---------------------------------------------------------------------------- a real round trip
def _poll_until(ep: MavEndpoint, deadline: float) -> list:
    """Messages on ep, waiting on its socket (select) until some arrive or the deadline passes."""
    while True:
        got = ep.poll()
        if got:
            return got
        left = deadline - time.monotonic()
        if left <= 0:
            return []
        select.select([ep.link.fileno()], [], [], left)


@pytest.mark.timeout(30)
def test_a_listening_link_from_a_pymavlink_url_receives_and_answers_on_localhost():
    """The agent's autopilot link: open_link(URL) under a MavEndpoint (as companion.node.runner
    builds it). A 'vehicle' on another socket sends a HEARTBEAT to 127.0.0.1:PORT; the link
    receives it and answers the sender (udpin learns its peer)."""
    port = free_udp_base_port(1)
    codec = Codec(md)
    link = open_link(f"udpin:127.0.0.1:{port}", codec.crc_extra)
    agent = MavEndpoint(link, codec, 1, 191)
    vehicle = MavEndpoint(UdpLink(bind=("127.0.0.1", 0), remote=("127.0.0.1", port), learn_remote=False), codec, 1, 1)
    try:
        assert isinstance(link, UdpLink) and link.sock.getsockname() == ("127.0.0.1", port)
        vehicle.queue(md.MAVLink_heartbeat_message(2, 12, 0, 0, 3, 3))
        assert vehicle.flush() == 1
        got = _poll_until(agent, time.monotonic() + 10.0)
        assert len(got) == 1
        msg, addr = got[0]
        assert msg.get_type() == "HEARTBEAT" and msg.get_srcSystem() == 1 and msg.get_srcComponent() == 1
        assert msg.autopilot == 12 and addr == ("127.0.0.1", vehicle.link.local_port)
        agent.queue(md.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))  # no address: the learnt peer
        assert agent.flush() == 1
        back = _poll_until(vehicle, time.monotonic() + 10.0)
        assert [(m.get_type(), m.get_srcSystem(), m.get_srcComponent()) for m, _ in back] == [("HEARTBEAT", 1, 191)]
    finally:
        link.close()
        vehicle.link.close()


def test_a_listening_link_on_every_interface_is_parse_only_here():
    """`udpin://:PORT` binds 0.0.0.0; the tests bind 127.0.0.1 only, so this form is parsed,
    not opened."""
    a = parse_url("udpin://:14540")
    assert (a.scheme, a.host, a.port) == ("udpin", ALL, 14540)
