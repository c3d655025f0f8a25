"""The machine's floor under an agent's CPU: a bare asyncio process that a UDP datagram wakes
`rate_hz` times a second, which reads it and sends one back, and does nothing else.

An agent does that at least once per control tick (its autopilot's LOCAL_POSITION_NED in,
its setpoint out) before any of its own work; what the kernel, the hypervisor and asyncio
charge for it differs a lot between machines (a virtual machine that halts an idle CPU
charges each wake-up dearly). The fleet bench reports it beside the agent's CPU so that the
two can be read together.
"""
from __future__ import annotations

import socket
import subprocess
import sys
import time

RECEIVER = r"""
import asyncio, socket, sys, time
rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
rx.bind(("127.0.0.1", 0))
rx.setblocking(False)
tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
print(rx.getsockname()[1], flush=True)
marks = []

def on_read():
    while True:
        try:
            data, addr = rx.recvfrom(65535)
        except BlockingIOError:
            return
        if data in (b"start", b"stop"):  # the measured window, in this process's own CPU clock
            marks.append((time.process_time(), time.monotonic()))
            if data == b"stop":
                (c0, w0), (c1, w1) = marks[-2:]
                print((c1 - c0) / (w1 - w0), flush=True)
                done.set()
            continue
        tx.sendto(data, addr)

async def main():
    global done
    done = asyncio.Event()
    asyncio.get_running_loop().add_reader(rx.fileno(), on_read)
    await done.wait()

asyncio.run(main())
"""


def run(rate_hz: float = 50.0, window_s: float = 10.0, warmup_s: float = 1.0) -> dict:
    """CPU of the bare receiver over window_s of datagrams at rate_hz (after warmup_s), as a
    fraction of a core (its own process_time between two marker datagrams); the sender
    paces itself in this process.

    Raises:
        RuntimeError: the receiver did not report.
    """
    from sim_bridge.runs.procs import terminate_all

    proc = subprocess.Popen([sys.executable, "-c", RECEIVER], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        port = int(proc.stdout.readline())
        dest = ("127.0.0.1", port)
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        tx.bind(("127.0.0.1", 0))
        tx.setblocking(False)
        payload = bytes(60)  # a LOCAL_POSITION_NED frame's size
        t0 = time.monotonic()
        started = False
        k = 0
        while True:
            now = time.monotonic()
            if not started and now - t0 >= warmup_s:
                tx.sendto(b"start", dest)
                started = True
            if now - t0 >= warmup_s + window_s:
                tx.sendto(b"stop", dest)
                break
            tx.sendto(payload, dest)
            try:
                while True:
                    tx.recv(65535)  # the echoes (not counted)
            except BlockingIOError:
                pass
            k += 1
            time.sleep(max(0.0, t0 + k / rate_hz - time.monotonic()))  # pacing the sender
        line = proc.stdout.readline()
        tx.close()
        if not line:
            raise RuntimeError("the floor bench's receiver did not report")
        return {"rate_hz": rate_hz, "window_s": window_s, "cpu_fraction_of_core": float(line),
                "note": "a bare asyncio process woken by one UDP datagram per period, which it reads and "
                        "answers: the machine's floor under an agent's per-tick CPU"}
    finally:
        terminate_all((proc,), 5.0)


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2))
