#!/usr/bin/env python3
"""Coverage-guided fuzzing (atheris + libFuzzer) of every decoder in tests/fuzz/targets.py.

Not part of CI (pytest never collects this file). See tests/fuzz/README.md.

    python tests/fuzz/fuzz_decoders.py --list
    python tests/fuzz/fuzz_decoders.py TARGET [libFuzzer options] [corpus dir | crash file ...]
    python tests/fuzz/fuzz_decoders.py TARGET -max_total_time=60

Each input: the first byte picks how the rest is fed (bit 0: after the
target's prefix; bit 1: as garbage in whole link units, then a valid message
that must be decoded; bit 2: whole, else in chunks of 1 + (byte >> 3) bytes,
and then again whole: the events must be the same); the rest goes to the
decoder. A crash is an exception escaping the decoder, a bound broken
(retained bytes), events that depend on how the input was cut, or a valid
message not decoded after garbage. Without a corpus directory, one is made under
$TMPDIR/hilsim-fuzz/TARGET and seeded with the target's valid messages.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from tests.fuzz.targets import Target

ROOT = Path(__file__).resolve().parents[2]
# Coverage feedback from our decoders and from the libraries that decode for them
# (VESC CAN: cantools). protobuf (ARIS) is C: not instrumented.
INSTRUMENTED = ("hilsim", "cantools")
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _usage() -> int:
    print(__doc__, file=sys.stderr)
    return 2


def _list() -> int:
    from tests.fuzz.targets import TARGETS

    for t in TARGETS.values():
        print(f"{t.name:14s} {t.summary}")
    return 0


def _seed(target: Target, directory: Path) -> None:
    """The target's messages as starting inputs, in the modes of :func:`one_input`."""
    directory.mkdir(parents=True, exist_ok=True)
    samples = target.samples()
    stream = b"".join(s.wire for s in samples)
    seeds = {"stream-whole": bytes([0b101]) + stream, "stream-bytes": bytes([0b001]) + stream}
    for i, s in enumerate(samples):
        seeds[f"sample-{i}"] = bytes([0b101]) + s.wire
        seeds[f"garbage-{i}"] = bytes([0b110 | (i << 3)]) + target.garbage(s.wire[: len(s.wire) // 2])
    for i, extra in enumerate(target.seeds() if target.seeds else []):
        seeds[f"extra-{i}"] = bytes([0b101]) + extra
    for i, (head, fill) in enumerate(target.oversize()):
        seeds[f"oversize-{i}"] = bytes([0b100]) + head + fill[:1024]
    for name, data in seeds.items():
        (directory / name).write_bytes(data)


def input_runner(target: Target) -> Callable[[bytes], None]:
    """The function libFuzzer calls with each input (also usable without atheris, to replay a corpus)."""
    n_samples = len(target.samples())

    def one_input(data: bytes) -> None:
        if not data:
            return
        mode, body = data[0], data[1:]
        chunks = [] if mode & 0b100 else [1 + (mode >> 3)]
        decoder = target.make()
        head = target.prefix if mode & 0b001 else b""
        if mode & 0b010:
            target.run(decoder, head + target.garbage(body), chunks)
            if target.no_resync is None:
                target.expect_resync(decoder, (mode >> 3) % n_samples, chunks)
                return
            target.finish(decoder)
        else:
            events = target.run(decoder, head + body, chunks) + target.finish(decoder)
            if chunks and target.chunking_matters is None:
                whole = target.make()
                if target.normalize(events) != target.normalize(target.run(whole, head + body) + target.finish(whole)):
                    raise AssertionError(f"{target.name}: fed in chunks of {chunks[0]}, the events differ from whole")
        held = target.buffered(decoder)
        if held > target.bound:
            raise AssertionError(f"{target.name}: {held} bytes retained after the end, bound {target.bound}")

    return one_input


def main(argv: list[str]) -> int:
    if len(argv) < 2 or argv[1] in ("-h", "--help"):
        return _usage()
    if argv[1] == "--list":
        return _list()
    name = argv[1]
    try:
        import atheris
    except ImportError:
        print("atheris is not installed: .venv/bin/pip install atheris (see tests/fuzz/README.md)", file=sys.stderr)
        return 2
    with atheris.instrument_imports(include=list(INSTRUMENTED)):
        from tests.fuzz import targets

        if name not in targets.TARGETS:
            print(f"unknown target {name!r}; targets: {', '.join(targets.TARGETS)}", file=sys.stderr)
            return 2
        target = targets.TARGETS[name]
        target.samples()  # builds lazily imported codecs (cantools) inside the instrumented imports
        target.oversize()
    one_input = input_runner(target)

    args = [argv[0], *argv[2:]]
    if not any(a.startswith("-max_len") for a in args):
        args.append("-max_len=8192")
    if not any(a.startswith("-rss_limit_mb") for a in args):
        args.append("-rss_limit_mb=1024")
    if not any(a.startswith("-timeout") for a in args):
        args.append("-timeout=30")
    if not [a for a in args[1:] if not a.startswith("-")]:
        corpus = Path(os.environ.get("TMPDIR", tempfile.gettempdir())) / "hilsim-fuzz" / name
        _seed(target, corpus)
        args.append(str(corpus))
    atheris.Setup(args, one_input)
    atheris.Fuzz()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
