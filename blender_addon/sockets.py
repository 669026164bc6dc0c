"""Writing a node socket's default value only when it changes.

Any write tags the material for an update, even of the value it holds: Cycles then compiles
its OSL shader anew (seconds per render, measured 5 s on a 16² sky scene) and the viewport
restarts, so writing every render or depsgraph update from Python floats (float64) into
float32 sockets made each one recompile. Values compare at the socket's precision."""
import struct


def _f32(x):
    return struct.unpack("f", struct.pack("f", float(x)))[0]


def _held(value, like):
    """`value` as the socket would hold it (its type is `like`'s)."""
    if isinstance(like, (str, bool, int)):
        return type(like)(value)
    if isinstance(like, float):
        return _f32(value)
    return tuple(_held(v, c) for v, c in zip(value, like))


def assign(socket, value):
    """Set socket.default_value to `value` unless it holds that value already."""
    current = socket.default_value
    if not isinstance(current, (str, bool, int, float)):
        current, value = tuple(current), tuple(value)
        if len(value) != len(current):
            socket.default_value = value
            return
    if _held(value, current) != current:
        socket.default_value = value
