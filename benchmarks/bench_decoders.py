"""Byte-stream decoder throughput: VESC UART, VRCSR and ARIS commands (sans-I/O, no bridge).

For each decoder, bytes/s for:

* ``valid, whole``: a stream of valid packets handed over in one chunk and drained;
* ``valid, 1 B``: the same stream one byte at a time;
* ``crafted, 1 B``: hostile input one byte at a time -- a header whose length
  claims bytes that never come (the decoder must wait for them) followed by
  near-miss headers that each need a check, repeated. A decoder that
  re-examines its whole buffer on every byte is quadratic in the claimed
  length here (VESC: up to 518 bytes, VRCSR 269, ARIS 1028).

Each case runs until ``--bytes`` were fed or ``--seconds`` passed, whichever
comes first, so a slow decoder still finishes. Prints figures, never passes
or fails.

    python benchmarks/bench_decoders.py [--bytes 200000] [--seconds 5]
    python benchmarks/bench_decoders.py --modules DIR   # vesc_uart.py, vrcsr.py, aris.py from DIR

``--modules`` measures other copies of the codec modules, e.g. those before the
linear-time framing (commit 2b24ace): ``mkdir /tmp/old && for m in vesc_uart vrcsr
aris; do git show 2b24ace:hilsim/protocols/$m.py > /tmp/old/$m.py; done``.
"""

from __future__ import annotations

import argparse
import importlib.util
import struct
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def load(name: str, folder: Path | None) -> ModuleType:
    if folder is None:
        return importlib.import_module(f"hilsim.protocols.{name}")
    path = folder / f"{name}.py"
    if not path.exists():  # a package since the split (aris/): its command channel
        path = folder / name / "commands.py"
    spec = importlib.util.spec_from_file_location(f"bench_{name}", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def repeat_to(unit: bytes, n: int) -> bytes:
    return (unit * (n // len(unit) + 1))[:n]


# ------------------------------------------------------------------ inputs


def vesc_inputs(vu: ModuleType, n: int) -> tuple[bytes, bytes]:
    cmds = [vu.SetRpm(5000), vu.SetDuty(0.25), vu.GetValues(), vu.Alive(), vu.SetCurrent(12.5)]
    valid = b"".join(vu.frame(vu.encode_command(c)) for c in cmds) + vu.frame(bytes(range(200)))
    # long form claiming 512 payload bytes (518 in all), then short-form starts whose end byte is
    # right (each needs a CRC); its own end byte is wrong, so it is dropped and the next one waits
    crafted = b"\x03\x02\x00" + b"\x02\x03" * 257 + b"\x00"
    return repeat_to(valid, n), repeat_to(crafted, n)


def vrcsr_inputs(vr: ModuleType, n: int) -> tuple[bytes, bytes]:
    valid = b"".join(vr.propulsion_request([0.1 * k, -0.2, 0.3], reply_node_id=k) for k in range(1, 6))
    header = vr.SYNC_REQUEST + bytes([0x81, 2, 0xF0, 255])
    # a header with a good CRC claiming 255 payload bytes (269 in all), then syncs every 2 bytes
    # (each a header CRC to check)
    crafted = header + struct.pack("<I", vr.crc32(header)) + vr.SYNC_REQUEST * 129 + b"\x00"
    return repeat_to(valid, n), repeat_to(crafted, n)


def aris_inputs(ar: ModuleType, n: int) -> tuple[bytes, bytes]:
    cmds = [ar.Ping(), ar.SetAcoustics(ar.AcousticSettings(cookie=3)), ar.SetSalinity(35),
            ar.SetFrameStreamReceiver(5000), ar.SetDateTime("2014-Jan-31 23:58:15")]
    valid = b"".join(ar.encode_command(c) for c in cmds)
    # out of sync (a 4 GB length), then a length of max_length (1028 bytes in all) and zeros:
    # every offset holds a complete empty frame that must be parsed (and is not a Command)
    crafted = b"\xff\xff\xff\xff" + struct.pack(">I", ar.MAX_COMMAND_LENGTH) + bytes(ar.MAX_COMMAND_LENGTH + 8)
    return repeat_to(valid, n), repeat_to(crafted, n)


# ------------------------------------------------------------------ running


def run(make: Callable[[], Any], feed: Callable[[Any, bytes], int], data: bytes, chunk: int,
        seconds: float) -> tuple[float, int, int]:
    """Feed ``data`` in ``chunk``-byte pieces until done or ``seconds`` passed: (bytes/s, bytes, events)."""
    dec = make()
    events, pos = 0, 0
    t0 = time.perf_counter()
    deadline = t0 + seconds
    step = max(1, 4096 // chunk)  # look at the clock every ~4 KiB
    while pos < len(data):
        for _ in range(step):
            if pos >= len(data):
                break
            events += feed(dec, data[pos:pos + chunk])
            pos += chunk
        if time.perf_counter() > deadline:
            break
    elapsed = time.perf_counter() - t0
    fed = min(pos, len(data))
    return fed / elapsed if elapsed > 0 else float("inf"), fed, events


def drainer(need: object) -> Callable[[Any, bytes], int]:
    """Feed, then drain until ``need`` (the module's NEED_DATA; older ARIS readers returned None)."""
    def feed(dec: Any, data: bytes) -> int:
        dec.receive_data(data)
        k = 0
        while (ev := dec.next_event()) is not need and ev is not None:
            k += 1
        return k

    return feed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bytes", type=int, default=200_000, help="bytes per case (default 200000)")
    ap.add_argument("--seconds", type=float, default=5.0, help="time limit per case [s] (default 5)")
    ap.add_argument("--modules", type=Path, default=None,
                    help="load vesc_uart.py, vrcsr.py and aris.py (or the aris/ package's commands.py) from this "
                         "folder instead of hilsim.protocols")
    args = ap.parse_args()

    vu, vr, ar = (load(m, args.modules) for m in ("vesc_uart", "vrcsr", "aris"))
    cases = [
        ("VESC UART", vu.PacketDecoder, drainer(vu.NEED_DATA), vesc_inputs(vu, args.bytes)),
        ("VRCSR", vr.PacketDecoder, drainer(vr.NEED_DATA), vrcsr_inputs(vr, args.bytes)),
        ("ARIS commands", ar.CommandReader, drainer(getattr(ar, "NEED_DATA", None)), aris_inputs(ar, args.bytes)),
    ]
    print(f"decoders from {args.modules or 'hilsim.protocols'}; up to {args.bytes} bytes or "
          f"{args.seconds:g} s per case")
    print(f"{'decoder':<15}{'input':<16}{'bytes/s':>14}{'bytes fed':>12}{'events':>9}")
    for name, make, feed, (valid, crafted) in cases:
        for label, data, chunk in (("valid, whole", valid, len(valid)), ("valid, 1 B", valid, 1),
                                   ("crafted, 1 B", crafted, 1)):
            rate, fed, events = run(make, feed, data, chunk, args.seconds)
            print(f"{name:<15}{label:<16}{rate:>14,.0f}{fed:>12}{events:>9}")


if __name__ == "__main__":
    main()
