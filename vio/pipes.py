"""Messages between a parent and a worker interpreter over its stdin/stdout: length-prefixed pickles (the render
workers, `vio.sim.workers`, and the tracker's process, `vio.track_worker`)."""

from __future__ import annotations

import pickle
import struct
from typing import IO, Any

_LEN = struct.Struct("<Q")


def send(stream: IO[bytes], obj: Any) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_LEN.pack(len(data)) + data)
    stream.flush()


def recv(stream: IO[bytes]) -> Any:
    """The next message; EOFError when the other end closed."""
    head = stream.read(_LEN.size)
    if len(head) < _LEN.size:
        raise EOFError
    (n,) = _LEN.unpack(head)
    data = stream.read(n)
    if len(data) < n:
        raise EOFError
    return pickle.loads(data)
