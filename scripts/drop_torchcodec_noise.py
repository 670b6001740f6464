"""Copy stdin to stdout as it arrives (progress bars included), minus torchcodec's start-up traceback.

Without FFmpeg's libraries (scripts/bootstrap.sh installs them where it can), LeRobot logs a ~60-line
traceback per process while probing torchcodec; it is harmless for state-only data and would bury the
training progress and the evaluation summary.
"""

import sys

BLOCK_START = "Could not load libtorchcodec"
BLOCK_END = "[end of libtorchcodec loading traceback]"
AFTERMATH = "'torchcodec' is installed but cannot be loaded"


def main() -> None:
    source, sink = sys.stdin.buffer.raw, sys.stdout.buffer
    in_block, pending = False, b""
    while chunk := source.read(65536):
        pending += chunk
        *lines, pending = pending.split(b"\n")
        for line in lines:
            text = line.decode(errors="replace")
            if BLOCK_START in text:
                in_block = True
            if not in_block and AFTERMATH not in text:
                sink.write(line + b"\n")
            if BLOCK_END in text:
                in_block = False
        if pending and not in_block and BLOCK_START.encode() not in pending:  # a progress bar redrawing with \r
            sink.write(pending)
            pending = b""
        sink.flush()
    if pending and not in_block:
        sink.write(pending)
        sink.flush()


if __name__ == "__main__":
    main()
