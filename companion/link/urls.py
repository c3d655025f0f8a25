"""Link URLs: the forms MAVSDK, pymavlink/MAVProxy and MAVROS users bring, parsed to one `LinkAddress`.

Accepted (HOST may be a name or an IPv4 address; an empty listening HOST means every
interface, 0.0.0.0):

    udpin://HOST:PORT, udpin://:PORT      listen on HOST:PORT (MAVSDK)
    udp://:PORT, udp://0.0.0.0:PORT       the same (MAVSDK's older form)
    udp://[HOST]:PORT@RHOST:RPORT         listen on HOST:PORT, send to RHOST:RPORT until a
                                          peer is known (MAVROS; udp://:PORT@ = no RHOST)
    udpout://HOST:PORT                    send to HOST:PORT from an ephemeral port (MAVSDK)
    tcp://HOST:PORT, tcpout://HOST:PORT   connect to a TCP server (MAVSDK, MAVROS)
    udpin:HOST:PORT, udp:HOST:PORT        listen (pymavlink, MAVProxy)
    udpout:HOST:PORT                      send (pymavlink, MAVProxy)
    tcp:HOST:PORT                         connect (pymavlink, MAVProxy)
    serial:///dev/NAME[:BAUD]             a UART, 8N1 raw (MAVSDK, MAVROS)
    /dev/NAME[:BAUD]                      the same (MAVROS)
    /dev/NAME[,BAUD]                      the same (MAVProxy --master)

A serial URL without a baud rate runs at DEFAULT_BAUD (57600: the default of MAVROS and
MAVProxy, and of the PX4 and ArduPilot TELEM1 ports; pymavlink's own default is 115200,
so give it when the port runs faster).

Refused with an error that names the forms we take: `udp://HOST:PORT` with any other
HOST (MAVSDK 1 listened on HOST, MAVSDK 2 and later send to it: say udpin or udpout),
TCP servers (`tcpin`, `tcp-l`, MAVSDK's `tcp://:PORT`), broadcast (`udpbcast`, `udp-b`),
hardware flow control, IPv6 hosts (`[::1]`: the sockets are IPv4), ports and baud rates
not written in ASCII digits, and anything else (docs/companion.md, "Link URLs").
"""
from __future__ import annotations

from dataclasses import dataclass

DEFAULT_BAUD = 57600
BAUDS = frozenset({9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600, 1000000, 1500000,
                   2000000})
FORMS = ("udpin://HOST:PORT, udpin://:PORT, udpout://HOST:PORT, tcp://HOST:PORT, serial:///dev/NAME[:BAUD], "
         "/dev/NAME[:BAUD], udp://[HOST]:PORT@RHOST:RPORT, or pymavlink's udpin:HOST:PORT, udpout:HOST:PORT, "
         "tcp:HOST:PORT")
_LISTEN_ALL = "0.0.0.0"
_REFUSED = {
    "tcpin": "swarmdrop connects to a TCP server and does not serve TCP itself",
    "tcp-l": "swarmdrop connects to a TCP server and does not serve TCP itself",
    "udpbcast": "UDP broadcast is not supported",
    "udp-b": "UDP broadcast is not supported",
    "udp-pb": "UDP broadcast is not supported",
    "serial_flowcontrol": "hardware flow control is not supported",
    "serial-hwfc": "hardware flow control is not supported",
}


class EndpointError(ValueError):
    """A link URL that cannot be used; the message says why."""


@dataclass(frozen=True)
class LinkAddress:
    """A parsed link URL.

    scheme "udpin": listen on host:port (remote_host:remote_port, if set, is where to send
    until a peer is known); "udpout": send to host:port; "tcp": connect to host:port;
    "serial": device at baud.
    """

    scheme: str
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0
    remote_host: str = ""
    remote_port: int = 0

    def __str__(self) -> str:
        if self.scheme == "serial":
            return f"serial://{self.device}:{self.baud}"
        if self.remote_port:
            return f"udp://{self.host}:{self.port}@{self.remote_host}:{self.remote_port}"
        return f"{self.scheme}://{self.host}:{self.port}"


def _fail(url: str, why: str) -> EndpointError:
    return EndpointError(f"{url!r}: {why}; accepted forms: {FORMS} (docs/companion.md, 'Link URLs')")


def _number(text: str, digits: int) -> int | None:
    """text as a number of at most `digits` ASCII digits, else None (int() would also take
    other scripts' digits, and raise ValueError past 4300 of them)."""
    if not (0 < len(text) <= digits and text.isascii() and text.isdigit()):
        return None
    return int(text)


def _host_port(url: str, text: str, listen: bool) -> tuple[str, int]:
    """HOST:PORT; an empty HOST means every interface when listening and is an error otherwise."""
    host, sep, port_text = text.rpartition(":")
    port = _number(port_text, 5)
    if not sep or port is None or not 0 < port < 65536:
        raise _fail(url, f"expected HOST:PORT with PORT in 1..65535, got {text!r}")
    if ":" in host or "[" in host or "]" in host:
        raise _fail(url, f"HOST {host!r} is not a name or an IPv4 address (IPv6 is not supported)")
    if listen:
        return host or _LISTEN_ALL, port
    if not host or host == _LISTEN_ALL:
        raise _fail(url, "a destination needs a host (0.0.0.0 can only be listened on)")
    return host, port


def _serial(url: str, device: str, baud: str) -> LinkAddress:
    if not device.startswith("/") or device == "/":
        raise _fail(url, f"a serial device is a path such as /dev/ttyAMA0, got {device!r}")
    if not baud:
        return LinkAddress("serial", device=device, baud=DEFAULT_BAUD)
    rate = _number(baud, 7)
    if rate is None or rate not in BAUDS:
        raise _fail(url, f"baud rate {baud!r} is not one of {sorted(BAUDS)}")
    return LinkAddress("serial", device=device, baud=rate)


def _device_and_baud(url: str, text: str) -> LinkAddress:
    """/dev/NAME, /dev/NAME:BAUD or /dev/NAME,BAUD (a colon not followed by digits is part of the name)."""
    for sep in (",", ":"):
        device, found, baud = text.rpartition(sep)
        if found and ((baud.isascii() and baud.isdigit()) or sep == ","):
            return _serial(url, device, baud)
    return _serial(url, text, "")


def parse_url(url: str) -> LinkAddress:
    """Parse a link URL (module docstring).

    Raises:
        EndpointError: a form we do not take, a missing host or port, a port or baud rate
            out of range; the message names the accepted forms.
    """
    url = url.strip()
    scheme, sep, rest = url.partition("://")
    if not sep:
        if url.startswith("/"):
            return _device_and_baud(url, url)
        scheme, sep, rest = url.partition(":")  # pymavlink / MAVProxy: scheme:HOST:PORT
        if not sep or scheme.lower() not in ("udpin", "udpout", "udp", "tcp", *_REFUSED):
            raise _fail(url, "not a link URL")
    scheme = scheme.lower()
    if scheme in _REFUSED:
        raise _fail(url, _REFUSED[scheme])
    if scheme == "serial":
        return _device_and_baud(url, rest)
    if scheme in ("udpin", "udpout"):
        host, port = _host_port(url, rest, listen=scheme == "udpin")
        return LinkAddress(scheme, host=host, port=port)
    if scheme in ("tcp", "tcpout"):
        if sep == "://" and rest.rpartition(":")[0] in ("", _LISTEN_ALL):
            raise _fail(url, "MAVSDK's tcp://:PORT serves TCP; swarmdrop connects to a TCP server (tcp://HOST:PORT)")
        host, port = _host_port(url, rest, listen=False)
        return LinkAddress("tcp", host=host, port=port)
    if scheme == "udp":
        bind, at, remote = rest.partition("@")
        if at:  # MAVROS: udp://[BIND_HOST]:BIND_PORT@[REMOTE_HOST:REMOTE_PORT]
            host, port = _host_port(url, bind, listen=True)
            if not remote:
                return LinkAddress("udpin", host=host, port=port)
            rhost, rport = _host_port(url, remote, listen=False)
            return LinkAddress("udpin", host=host, port=port, remote_host=rhost, remote_port=rport)
        host, port = _host_port(url, rest, listen=True)
        if sep == "://" and rest.rpartition(":")[0] not in ("", _LISTEN_ALL):
            raise _fail(url, f"udp://{rest} means listen in MAVSDK 1 and send in MAVSDK 2 and later: write "
                             f"udpin://{rest} to listen or udpout://{rest} to send")
        return LinkAddress("udpin", host=host, port=port)
    raise _fail(url, f"unknown scheme {scheme!r}")
