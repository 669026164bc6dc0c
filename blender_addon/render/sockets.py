"""Node sockets across Blender versions: a node group's own sockets (`has_socket`, `new_socket`:
`tree.interface` in 4.0+, the legacy `tree.inputs`/`tree.outputs` in 3.x), and a socket's
default value written only when it changes (`assign`).

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


def has_socket(tree, name, in_out):
    """Whether a node group has an input or output socket (`in_out` "INPUT" or "OUTPUT") named `name`."""
    if getattr(tree, "interface", None) is None:          # Blender < 4.0: the legacy API
        return name in (tree.inputs if in_out == "INPUT" else tree.outputs)
    return any(getattr(i, "item_type", "") == "SOCKET" and i.name == name and i.in_out == in_out
               for i in tree.interface.items_tree)


def new_socket(tree, name, in_out, kind):
    """A new input or output socket of a node group (`in_out` "INPUT" or "OUTPUT", `kind` e.g.
    "NodeSocketVector"), in Blender 4+ or the legacy API."""
    if getattr(tree, "interface", None) is None:
        return (tree.inputs if in_out == "INPUT" else tree.outputs).new(kind, name)
    return tree.interface.new_socket(name, in_out=in_out, socket_type=kind)
