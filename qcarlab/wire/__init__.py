"""The wire format both ends of the car link speak: protocol v1's frames (``protocol``) and the
sensor frame types (``frames``). It sits below ``car/`` (the TCP client) and ``net/`` (the
server), so neither package imports the other's internals (docs/protocol.md)."""
